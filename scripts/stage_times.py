"""Where an experiment's time went: each stage's seconds from its ``results.json``, as a Markdown table.

Every experiment records the wall seconds of each stage it ran (``seconds``: trainings, tunings,
each method's evaluation) and of the whole run (``total``). With worker processes stages run side
by side, so their sum exceeds the run's wall time. The main job's table on the performance page
is this script's output for a ``smcd-rl two-link`` run:

    python scripts/stage_times.py runs/two-link --out docs/benchmarks/main-job.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from smcd_rl.files import write_text

#: The first word of a stage's name -> the group it is listed under, in this order.
GROUPS = {"train": "training", "tune": "tuning", "evaluate": "evaluation"}


def report(payload: dict[str, Any], command: str) -> str:
    """The table of ``payload["seconds"]``: each stage in run order under its group, each group's sum, the wall time."""
    seconds: dict[str, float] = payload.get("seconds") or {}
    if "total" not in seconds:
        raise ValueError("the results.json has no 'seconds' with a 'total': run the experiment with this version")
    machine = payload.get("machine", {})
    lines = [
        f"`{command}` on {machine.get('processor', 'an unnamed CPU')} ({machine.get('cpus', '?')} CPUs, "
        f"{machine.get('torch_threads', '?')} torch thread per process, torch {machine.get('torch', '?')})",
        "",
        "| stage | seconds |",
        "|---|---|",
    ]
    for word, group in GROUPS.items():
        stages = {name: value for name, value in seconds.items() if name.split(" ")[0] == word}
        for name, value in stages.items():
            lines.append(f"| {name} | {value:.1f} |")
        lines.append(f"| **{group}, summed** | **{sum(stages.values()):.1f}** |")
    total = seconds["total"]
    lines.append(f"| **wall time of the run** | **{total:.1f}** ({int(total // 60)} min {round(total % 60)} s) |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="the experiment's output directory (its results.json)")
    parser.add_argument("--command", default="smcd-rl two-link", help="the command that wrote the run, for the caption")
    parser.add_argument("--out", help="also write the table to this Markdown file")
    args = parser.parse_args()
    text = report(json.loads((args.run / "results.json").read_text()), args.command)
    print(text, end="")
    if args.out:
        write_text(args.out, text, what="report")


if __name__ == "__main__":
    main()
