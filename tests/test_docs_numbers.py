"""No hand-typed result on a results page: every decimal figure in its prose is in one of its reports.

A page describes and its report states: an experiment page includes its ``report.md`` and may
quote it, and the README's results section quotes the scoreboard. A figure typed by hand drifts
from the report the next time the command runs. This test finds every decimal figure in each
page's prose (not in code, links or the included report) and looks for it among the numbers of
the page's reports and data files, as printed or rounded to the figure's digits. A number that
is not a result (a family's parameter range) is on :data:`NOT_RESULTS` with its reason, and a
section whose figures no command can rerun is on :data:`NOT_CHECKED` with its reason.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "docs" / "experiments"

#: page -> {figure: why it is not a result}. Short on purpose: a result belongs in a report.
NOT_RESULTS: dict[str, dict[str, str]] = {
    "docs/experiments/regimes/index.md": {"1.5": "the pendulum family's length prior, U(0.5, 1.5)"},
    "docs/concepts/strategies.md": {"4.685": "Tukey's biweight cut, in residuals"},
    "docs/concepts/mask-training.md": {
        "1.6": "forward passes of mask training at the defaults (millions), computed from the sizes",
        "4.5": "forward passes of the gradient steps at the defaults (millions), computed from the sizes",
    },
}

#: page -> (a section's heading, why its figures are not checked against a report).
NOT_CHECKED: dict[str, tuple[str, str]] = {
    "docs/performance.md": (
        "## Across CPU models",
        "how far one example's printed numbers move across CPU models and kernel settings, measured on two "
        "machines: no single machine can rerun it, and it sets the doc tests' tolerances, not a product result",
    ),
}

#: Concept pages with a section on what the experiments measured: each quotes the experiment pages it links.
CONCEPTS = ("docs/concepts/strategies.md", "docs/concepts/mask-training.md")

#: A decimal figure of prose: digits, a point, digits (not part of a version, a path or a longer number).
FIGURE = re.compile(r"(?<![\w.\-/])(\d+\.\d+)(?![\w.]*\d)")
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def prose(text: str) -> str:
    """The page's own words: without code blocks, inline code, link targets, comments and includes."""
    kept, fenced = [], False
    for line in text.splitlines():
        if line.strip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or "--8<--" in line:
            continue
        line = re.sub(r"`[^`]*`", "", line)
        line = re.sub(r"\]\([^)]*\)", "]", line)
        kept.append(re.sub(r"<!--.*?-->", "", line))
    return "\n".join(kept)


def unquoted(page_text: str, sources: list[str], allowed: dict[str, str] | None = None) -> list[str]:
    """The page's decimal figures found in none of ``sources``, as printed or rounded to the figure's digits."""
    values = {float(n) for text in sources for n in NUMBER.findall(text)}
    missing = []
    for figure in FIGURE.findall(prose(page_text)):
        digits = len(figure.split(".")[1])
        if figure in (allowed or {}):
            continue
        if not any(abs(v) == float(figure) or f"{abs(v):.{digits}f}" == figure for v in values):
            missing.append(figure)
    return missing


def _pages() -> dict[str, list[Path]]:
    """Each results page -> the reports and data files it may quote."""
    pages = {}
    for page in sorted(EXPERIMENTS.rglob("index.md")):
        pages[page.relative_to(ROOT).as_posix()] = _sources(page.parent)
    board = EXPERIMENTS / "scoreboard"
    pages["README.md#results"] = [board / "report.md", board / "scoreboard.json"]
    # The performance page includes the benchmarks' reports, each written by the command it names.
    pages["docs/performance.md"] = sorted((ROOT / "docs" / "benchmarks").glob("*.md"))
    # A concept page that states what the experiments measured quotes the reports of the pages it links.
    for page in CONCEPTS:
        linked = sorted(set(re.findall(r"\(\.\./experiments/([\w/-]+?)/index\.md", (ROOT / page).read_text())))
        pages[page] = [source for name in linked for source in _sources(EXPERIMENTS / name)]
    return pages


def _sources(directory: Path) -> list[Path]:
    """The reports and data files under an experiment page's directory."""
    return sorted(directory.rglob("report.md")) + sorted(directory.glob("*.json"))


def _text(name: str) -> str:
    if name == "README.md#results":
        readme = (ROOT / "README.md").read_text()
        return readme[readme.index("## Results") : readme.index("## Citing")]
    text = (ROOT / name).read_text()
    if name in NOT_CHECKED:  # from its heading to the next one
        heading = NOT_CHECKED[name][0]
        start = text.index(heading)
        following = text.find("\n## ", start + len(heading))
        text = text[:start] + (text[following:] if following >= 0 else "")
    return text


@pytest.mark.parametrize("name", sorted(_pages()))
def test_every_figure_on_a_results_page_is_in_its_reports(name: str) -> None:
    sources = [path.read_text() for path in _pages()[name]]
    missing = unquoted(_text(name), sources, NOT_RESULTS.get(name))
    assert not missing, (
        f"{name} types figures that none of its reports holds: {missing}; quote the report (or include it), "
        "or, for a number that is not a result, add it to NOT_RESULTS with its reason"
    )


def test_the_check_catches_a_hand_typed_figure_and_a_stale_one() -> None:
    report = "| M+G | 0.1446 [0.13, 0.16] |\nWall time 6 min 41 s"
    assert unquoted("GD reaches 0.145 m (0.14 rounded).", [report]) == []
    assert unquoted("GD reaches 0.152 m.", [report]) == ["0.152"]  # a figure from an older run
    assert unquoted("`--gd-lr 0.003` and [a link](x/0.5.md)\n```text\n0.9\n```\n", [report]) == []
    assert unquoted("a prior U(0.5, 1.5)", [report], {"0.5": "prior", "1.5": "prior"}) == []
