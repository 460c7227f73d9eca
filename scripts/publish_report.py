"""Copy a run's report.md and the pictures it shows into an experiment's docs page directory.

    python scripts/publish_report.py runs/two-link docs/experiments/two-link

The docs include the report as the command wrote it; tests/test_docs_reports.py checks that its
settings are the command's current defaults.
"""

from __future__ import annotations

import argparse
import re
import shutil
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="the run's output directory (with report.md)")
    parser.add_argument("page", type=Path, help="the docs directory of the experiment's page")
    args = parser.parse_args()
    report = args.run / "report.md"
    if not report.is_file():
        parser.error(f"{report} does not exist: run the experiment with --out {args.run} first")
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report.read_text())
    args.page.mkdir(parents=True, exist_ok=True)
    for name in ["report.md", *pictures]:
        shutil.copyfile(args.run / name, args.page / name)
    print(f"{args.page}: report.md and {len(pictures)} pictures from {args.run}")


if __name__ == "__main__":
    main()
