"""The scoreboard's docs page: its report is what its committed entries draw, and it fits a page."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

from PIL import Image

from smcd_rl.experiments.scoreboard import run as scoreboard
from smcd_rl.experiments.scoreboard.plot import draw

PAGE = Path(__file__).resolve().parents[2] / "docs" / "experiments" / "scoreboard"


def _body(report: str) -> list[str]:
    """The report less what depends on where and when it was drawn (wall time, machine, --out)."""
    return [line for line in report.splitlines() if not line.startswith(("Wall time", '  "out"'))]


def test_the_committed_report_is_what_the_committed_scoreboard_json_draws(tmp_path: Path, capsys) -> None:
    """The docs page shows runs that are not in the repository: its numbers must come from its entries."""
    scoreboard.render(PAGE / "scoreboard.json", out=tmp_path / "board", progress=False)
    capsys.readouterr()
    assert _body((tmp_path / "board" / "report.md").read_text()) == _body((PAGE / "report.md").read_text())
    assert (
        json.loads((PAGE / "scoreboard.json").read_text())["runs"]
        == json.loads((tmp_path / "board" / "scoreboard.json").read_text())["runs"]
    )


def test_the_report_tables_are_narrow_enough_for_a_page() -> None:
    """One table of ten columns of intervals overflowed the docs page; tables of at most five fit it.

    The table of times per observation has eight columns of short numbers: it fits by its width.
    """
    lines = (PAGE / "report.md").read_text().splitlines()
    tables = [
        (line, below)
        for line, below in itertools.pairwise(lines)
        if line.startswith("| task ") and below.startswith("|-")
    ]
    # the summary, metric and cell, means, verdicts, one-step SMCD and combination, the last layer,
    # SMCD with a Bayesian readout, SMCD on task masks, T's other strategies, the notes (the Ant's T), times
    assert len(tables) == 11, tables
    for header, rule in tables:
        assert header.count("|") - 1 <= 5 or len(rule) <= 120, header


def test_each_panel_of_the_plot_is_readable_at_page_width(tmp_path: Path) -> None:
    """Seven panels in one row were squeezed to ~100 px each on the page; two to a row they keep ~half its width."""
    entries = scoreboard.read_entries(PAGE / "scoreboard.json")[1]
    path = tmp_path / "board.png"
    draw(scoreboard._rows(entries), path)
    with Image.open(path) as image:
        width, height = image.size
    assert width <= 1100 and width / 2 >= 480 and height > width  # two columns, rows of panels below each other
    with Image.open(PAGE / "scoreboard.png") as committed:
        assert committed.size == (width, height)  # the committed picture is drawn this way
