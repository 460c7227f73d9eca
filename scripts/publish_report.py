"""Copy a run's report.md and the pictures it shows into an experiment's docs page directory.

    python scripts/publish_report.py runs/two-link docs/experiments/two-link

With ``--scoreboard``, the run's scoreboard entries also replace those of the same tasks in a
committed ``scoreboard.json``, and that scoreboard is drawn again (in ``runs/scoreboard``) and
published beside it, so a rerun of one experiment updates its rows without the other runs:

    python scripts/publish_report.py runs/two-link docs/experiments/two-link \
        --scoreboard docs/experiments/scoreboard/scoreboard.json

The docs include the report as the command wrote it; tests/test_docs_reports.py checks that its
settings are the command's current defaults. A ``scoreboard.json`` in the run (the scoreboard's
entries) is copied too, and given in place of the run it draws the scoreboard again from those
entries (in ``runs/scoreboard``, the command's default ``--out``), e.g. after a change of layout:

    python scripts/publish_report.py docs/experiments/scoreboard/scoreboard.json docs/experiments/scoreboard
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

#: Files copied beside the report when the run has them: what draws the page again.
DATA = ("scoreboard.json",)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "run", type=Path, help="the run's output directory (with report.md), or a scoreboard.json to draw again"
    )
    parser.add_argument("page", type=Path, help="the docs directory of the experiment's page")
    parser.add_argument(
        "--scoreboard", type=Path, help="a committed scoreboard.json whose entries of the run's tasks the run replaces"
    )
    args = parser.parse_args()
    if args.scoreboard is not None:
        _replace_entries(parser, args.run, args.scoreboard)
    if args.run.is_file() and args.run.name == "scoreboard.json":
        from smcd_rl.experiments.scoreboard import run as scoreboard

        out = Path(scoreboard.ScoreboardConfig().out)
        try:
            scoreboard.render(args.run, out=out, progress=False)
        except (ValueError, OSError) as err:
            parser.error(str(err))
        args.run = out
    report = args.run / "report.md"
    if not report.is_file():
        parser.error(f"{report} does not exist: run the experiment with --out {args.run} first")
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report.read_text())
    data = [name for name in DATA if (args.run / name).is_file()]
    args.page.mkdir(parents=True, exist_ok=True)
    for name in ["report.md", *pictures, *data]:
        shutil.copyfile(args.run / name, args.page / name)
    print(f"{args.page}: report.md, {len(pictures)} pictures and {len(data)} data files from {args.run}")


def _replace_entries(parser: argparse.ArgumentParser, run: Path, path: Path) -> None:
    """Put the run's scoreboard entries in place of those of the same tasks in ``path``, then redraw it there."""
    from smcd_rl.experiments.scoreboard import run as scoreboard
    from smcd_rl.experiments.scoreboard.entries import run_entries

    try:
        fresh = run_entries(run)  # checked as the scoreboard checks them
        data = json.loads(path.read_text())
        scoreboard.read_entries(path)  # the committed file is a scoreboard's
    except (ValueError, OSError) as err:
        parser.error(str(err))
    tasks = {entry["task"] for entry in fresh}
    if not any(item["entry"]["task"] in tasks for item in data["entries"]):
        parser.error(f"{path} has no entry of the run's tasks {sorted(tasks)}: nothing to replace")
    by_task = {entry["task"]: entry for entry in fresh}
    data["entries"] = [{**item, "entry": by_task.get(item["entry"]["task"], item["entry"])} for item in data["entries"]]
    path.write_text(json.dumps(data, indent=1) + "\n")
    out = Path(scoreboard.ScoreboardConfig().out)
    scoreboard.render(path, out=out, progress=False)
    for name in ("report.md", "scoreboard.png", "scoreboard.json"):
        shutil.copyfile(out / name, path.parent / name)
    print(f"{path.parent}: the entries of {sorted(tasks)} replaced and the scoreboard drawn again")


if __name__ == "__main__":
    main()
