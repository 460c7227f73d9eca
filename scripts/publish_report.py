"""Copy a run's report.md and the pictures it shows into an experiment's docs page directory.

    python scripts/publish_report.py runs/two-link docs/experiments/two-link

The docs include the report as the command wrote it; tests/test_docs_reports.py checks that its
settings are the command's current defaults. A ``scoreboard.json`` in the run (the scoreboard's
entries) is copied too, and given in place of the run it draws the scoreboard again from those
entries (in ``runs/scoreboard``, the command's default ``--out``), e.g. after a change of layout:

    python scripts/publish_report.py docs/experiments/scoreboard/scoreboard.json docs/experiments/scoreboard
"""

from __future__ import annotations

import argparse
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
    args = parser.parse_args()
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


if __name__ == "__main__":
    main()
