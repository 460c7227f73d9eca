"""``report.md``: an experiment's tables, plots, settings (with their fingerprint), machine and wall time."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from smcd_rl.experiments.shared.config import OUTPUT_ONLY
from smcd_rl.experiments.shared.outputs import settings_fingerprint, write_text
from smcd_rl.experiments.shared.stages import duration

__all__ = ["write_report"]


def write_report(path: Path, result: Mapping[str, Any], tables: Mapping[str, str], plots: Sequence[str]) -> None:
    """``report.md``: an experiment's tables, plot, settings (with their fingerprint), machine and wall time.

    The fingerprint is that of the settings that determine the numbers, so a reader (or a test)
    can tell whether a committed report is what the current settings produce.
    """
    config = dict(result["config"])
    settings = {k: v for k, v in config.items() if k not in OUTPUT_ONLY}
    machine = result["machine"]
    lines = [f"# {result['experiment']}", ""]
    for caption, text in tables.items():
        lines += [f"**{caption}**", "", text, ""]
    for plot in plots:
        lines += [f"![{plot}]({plot})", ""]
    seconds = result["seconds"]["total"]
    lines += [
        f"Wall time {duration(seconds)} on {machine['processor']} "
        f"({machine['cpus']} CPUs, {_count(machine['torch_threads'], 'torch thread')}, torch {machine['torch']}"
        + (f", {machine['gpu']}" if "gpu" in machine else "")
        + ").",
        "",
        f"Settings (fingerprint `{settings_fingerprint(settings)[:12]}`):",
        "",
        "```json",
        json.dumps(config, indent=2, ensure_ascii=False),
        "```",
        "",
    ]
    write_text(path, "\n".join(lines), what="report")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")
