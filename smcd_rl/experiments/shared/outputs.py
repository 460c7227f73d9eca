"""The files and tables every experiment writes: CSV, JSON, figures, Markdown tables, settings fingerprints.

Every file goes through :mod:`smcd_rl.files`'s atomic writer, so an interrupted or failed write
never leaves a truncated result behind.

Example:
    >>> print(format_table([["M+S", 0.1234]], header=["method", "rmse"]))
    | method | rmse  |
    |--------|-------|
    | M+S    | 0.123 |
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from smcd_rl.files import write_atomic, write_text

__all__ = [
    "write_csv",
    "write_json",
    "write_text",
    "save_figure",
    "format_table",
    "ms_cell",
    "settings_fingerprint",
    "Transcript",
]


class Transcript:
    """What a benchmark script prints, kept to be written as a Markdown report: its first line names
    the command and where it was measured (processor, cores, torch threads and version).

    Example:
        >>> transcript = Transcript("python scripts/bench.py")
        >>> transcript.say("| a | b |")
        | a | b |
        >>> transcript.lines[0].startswith("Measured by `python scripts/bench.py` on processor ")
        True
    """

    def __init__(self, command: str) -> None:
        from smcd_rl.experiments.shared.runtime import machine_info  # imports torch: not for every user of outputs

        info = {k: v for k, v in machine_info().items() if k in ("processor", "cpus", "torch_threads", "torch")}
        self.lines = [f"Measured by `{command}` on " + ", ".join(f"{k} {v}" for k, v in info.items()) + ".", ""]

    def say(self, line: str = "") -> None:
        """Print ``line`` now and keep it for the report."""
        print(line, flush=True)
        self.lines.append(line)

    def write(self, path: str | os.PathLike[str] | None) -> None:
        """Write the report to ``path`` (its folder made if needed); nothing where ``path`` is ``None``."""
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            write_text(path, "\n".join(self.lines) + "\n", what="report")


def settings_fingerprint(settings: Mapping[str, Any]) -> str:
    """A hex digest that changes whenever a setting does: names caches and checkpoints by their settings.

    Example:
        >>> settings_fingerprint({"seed": 0}) == settings_fingerprint({"seed": 0}) != settings_fingerprint({"seed": 1})
        True
    """
    return hashlib.sha256(json.dumps(dict(settings), sort_keys=True, default=str).encode()).hexdigest()


def write_csv(path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]]) -> None:
    """Write dict rows to a CSV file; its columns are every row's keys in order of appearance, blank where a row has none."""
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    columns = list(dict.fromkeys(key for row in rows for key in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, text.getvalue(), what="table")


def write_json(path: str | os.PathLike[str], payload: Any) -> None:
    """Write ``payload`` as indented JSON (values JSON cannot hold as their ``str``), atomically."""
    write_text(path, json.dumps(payload, indent=2, default=str) + "\n", what="JSON file")


def save_figure(fig: Any, path: str | os.PathLike[str], **options: Any) -> None:
    """Save a matplotlib figure atomically, in the format of ``path``'s suffix (``.png``): ``fig.savefig(..., **options)``.

    A full disk or an unwritable directory is a :class:`~smcd_rl.files.FileWriteError` naming the
    file (and the space it needs), and no truncated picture is left behind.
    """
    suffix = Path(path).suffix.lstrip(".").lower() or "png"
    write_atomic(path, lambda handle: fig.savefig(handle, format=suffix, **options), what="plot")


def format_table(rows: Iterable[Sequence[Any]], header: Sequence[str]) -> str:
    """A Markdown table (it reads in a terminal and pastes into the README as is)."""
    cells = [[str(h) for h in header]] + [[_cell(v) for v in row] for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |" for row in cells]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def ms_cell(value: float | None) -> str:
    """A time per observation as a table cell: three significant digits, "-" where there is none.

    Example:
        >>> ms_cell(12.345), ms_cell(None), ms_cell(float("nan"))
        ('12.3', '-', '-')
    """
    return f"{value:.3g}" if value is not None and math.isfinite(value) else "-"


def _cell(value: Any) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)
