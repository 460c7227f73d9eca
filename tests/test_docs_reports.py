"""The run reports committed under docs/experiments/ are what the current code's default settings produce.

Each experiment page includes the ``report.md`` its command wrote. A report names its settings
and their fingerprint; this test rebuilds the command's config from the current code, with only
the options that select the run (a sweep's study, the scoreboard's run directories), and checks
that it has exactly the report's settings. A changed default, a renamed or new setting, or a
report from a run with other options fails here until the run is repeated and its report
committed. The pictures a report shows are committed beside it.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from smcd_rl.cli import make_config
from smcd_rl.experiments.shared.config import OUTPUT_ONLY, config_dict
from smcd_rl.experiments.shared.outputs import settings_fingerprint

DOCS = Path(__file__).resolve().parents[1] / "docs" / "experiments"

#: report (relative to docs/experiments) -> (command, the options that select that default run)
REPORTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "two-link/report.md": ("two-link", ()),
    "panda/report.md": ("panda", ()),
    "telescoping/report.md": ("telescoping", ()),
    "telescoping/measured/report.md": ("telescoping", ("feedback",)),
    "interpret/report.md": ("interpret", ()),
    "ant/report.md": ("ant", ()),
    "fetch/report.md": ("fetch", ()),
    "regimes/report.md": ("regimes", ()),
    "sweep/training/report.md": ("sweep", ()),
    "sweep/smcd/report.md": ("sweep", ("study",)),
    "sweep/drone/report.md": ("sweep", ("study",)),
    "sweep/masks/report.md": ("sweep", ("study",)),
    **{
        f"task-masks/{f}/report.md": ("task-masks", ("family",))
        for f in ("pendulum", "telescoping", "ant", "panda", "fetch", "drone")
    },
    "scoreboard/report.md": ("scoreboard", ("runs",)),
}


def _settings_and_fingerprint(text: str) -> tuple[dict, str]:
    found = re.search(r"Settings \(fingerprint `([0-9a-f]{12})`\):\s*```json\n(.*?)```", text, re.S)
    assert found, "the report has no settings block with a fingerprint"
    config = json.loads(found.group(2))
    return {k: v for k, v in config.items() if k not in OUTPUT_ONLY}, found.group(1)


def test_every_committed_report_is_checked() -> None:
    assert {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("report.md")} == set(REPORTS)


@pytest.mark.parametrize("name", sorted(REPORTS))
def test_report_matches_the_current_default_settings(name: str) -> None:
    command, selecting = REPORTS[name]
    text = (DOCS / name).read_text()
    settings, fingerprint = _settings_and_fingerprint(text)
    assert settings_fingerprint(settings)[:12] == fingerprint, f"{name}: its settings were edited by hand"
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items() if k in selecting}
    current = {k: v for k, v in config_dict(make_config(command, given)).items() if k not in OUTPUT_ONLY}
    changed = sorted(k for k in {*current, *settings} if current.get(k, "missing") != settings.get(k, "missing"))
    assert not changed, (
        f"docs/experiments/{name} was made with other settings than `smcd-rl {command}`'s current defaults "
        f"(differ: {changed}); run the command again and commit its report.md and pictures"
    )


@pytest.mark.parametrize("name", sorted(REPORTS))
def test_the_pictures_a_report_shows_are_committed(name: str) -> None:
    report = DOCS / name
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report.read_text())
    assert all((report.parent / p).is_file() for p in pictures), pictures


def _table(text: str, first_column: str) -> list[dict[str, str]]:
    """The rows of the first Markdown table in ``text`` whose header starts with ``first_column``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_column} "))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, (c.strip() for c in line.strip("|").split("|")), strict=True)))
    return rows


def test_the_readme_scoreboard_quotes_the_committed_report() -> None:
    """The README's results table is the scoreboard report's first table (its summary), row for row."""
    readme = _table((DOCS.parents[1] / "README.md").read_text(), "task")
    report = _table((DOCS / "scoreboard" / "report.md").read_text(), "task")
    assert readme == report and "best mean" in readme[0]


def test_the_readme_decision_table_is_the_one_the_scoreboard_computed() -> None:
    """The README's "what to use when" is the scoreboard report's computed table, row for row."""
    readme = _table((DOCS.parents[1] / "README.md").read_text(), "your situation")
    report = _table((DOCS / "scoreboard" / "report.md").read_text(), "your situation")
    assert readme == report and len(report) >= 5
