"""What to use when, computed from the scoreboard's rows by written rules, never typed.

Each :class:`Situation` names the rows it cites (by their regime, or by task) and the strategies a
user in that situation can run (a network trained as usual: M's strategies; one trained with each
sample's task labelled: T+S too). A strategy is **recommended** for a situation where, on every row
it cites, the rule holds:

1. it ran on the row;
2. its mean is the best of the situation's strategies there, or tied with the best: their paired
   verdict over the same trials is a tie, or, where the experiment did not pair the two, their 95 %
   intervals overlap;
3. it is never significantly worse than another of the situation's strategies there (by every
   paired verdict the row holds);
4. for a budget (``max_ms``), its median time per observation is within the budget on the row.

A situation where no strategy holds on every row it cites says so, with each row's best.
:func:`decision_table` writes the table; :func:`contradictions` checks a table (the README's, a
page's) against the rows: every strategy it recommends must hold on every row it cites.

Example:
    >>> rows = [{"task": "x T=3", "cell": "regime=T=3", "lower_is_better": True, "ms": {},
    ...          **{c: m for c, m in (("GD", 0.3), ("SMCD (one-step)", 0.2))}}]
    >>> holds(rows[0], "SMCD (one-step)", ("GD", "SMCD (one-step)"))
    True
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from smcd_rl.experiments.scoreboard.summary import SHORT, best_of, pair_word
from smcd_rl.experiments.shared.outputs import format_table
from smcd_rl.experiments.shared.scoreboard_entry import TASK_MASKS

__all__ = ["Situation", "SITUATIONS", "holds", "recommend", "decision_table", "contradictions", "parse_table"]

Row = Mapping[str, Any]

#: The strategies on a network trained as usual (M), in the order a tie is listed.
USUAL = ("SMCD (one-step)", "SMCD + last layer", "GD", "last layer", "combination")
#: ... and with the task-mask network's strategies for a user who can train it.
EITHER = (TASK_MASKS, "T+SL", "T+G", "T+L", *USUAL)


@dataclass(frozen=True)
class Situation:
    """A user's situation: the rows that speak to it and the strategies that user can run."""

    #: What the table's first column says.
    text: str
    #: How the cited rows are described.
    rows_text: str
    #: Which rows it cites.
    cites: Callable[[Row], bool]
    #: The strategies (scoreboard columns) the user can run there.
    strategies: tuple[str, ...]
    #: A budget: only strategies timed under this many ms per observation on the row.
    max_ms: float | None = None


def _regime(name: str) -> Callable[[Row], bool]:
    return lambda row: f"regime={name}" in str(row.get("cell", "")).split(", ")


def _task(prefix: str) -> Callable[[Row], bool]:
    return lambda row: str(row.get("task", "")).startswith(prefix)


#: The situations of the table, each with its rows and strategies.
SITUATIONS: tuple[Situation, ...] = (
    Situation("you can train the network with each sample's task labelled", "every row", lambda row: True, EITHER),
    Situation("a network trained as usual, 1-3 observations of a new task", "every T=3 row", _regime("T=3"), USUAL),
    Situation("a network trained as usual, many observations of one task", "every T=30 row", _regime("T=30"), USUAL),
    Situation(
        "a network trained as usual, the task switches while you run",
        "every switch row",
        _regime("switch: new task"),
        USUAL,
    ),
    Situation("a network trained as usual, corrupted readings", "every outlier row", _regime("outlier"), USUAL),
    Situation(
        "a network trained as usual, under 1 ms per observation", "every timed row", lambda row: True, USUAL, 1.0
    ),
    Situation(
        "control through a linear change of the output (a rotation, a gain)", "Fetch reach", _task("Fetch"), EITHER
    ),
    Situation(
        "a condition none of the training tasks had (a crippled leg)",
        "crippled Ant",
        _task("Ant one-step prediction (crippled)"),
        USUAL,
    ),
)


def holds(row: Row, strategy: str, strategies: Sequence[str], max_ms: float | None = None) -> bool:
    """Whether ``strategy`` is best or tied with the best of ``strategies`` on ``row``, and never
    significantly worse than one of them (the module's rule)."""
    ran = _open(row, strategies, max_ms)
    if strategy not in ran:
        return False
    best = best_of(row, ran)
    assert best is not None  # ``strategy`` ran
    if strategy != best and _compare(row, strategy, best) != "tie":
        return False
    return all(_compare(row, strategy, other) != "worse" for other in ran if other != strategy)


def recommend(situation: Situation, rows: Sequence[Row]) -> tuple[list[str], list[Row]]:
    """The strategies that hold on every row ``situation`` cites, and those rows."""
    cited = [row for row in rows if situation.cites(row) and _timed(row, situation)]
    if not cited:
        return [], []
    chosen = [
        s for s in situation.strategies if all(holds(r, s, situation.strategies, situation.max_ms) for r in cited)
    ]
    return chosen, cited


def decision_table(rows: Sequence[Row]) -> str:
    """The Markdown table of :data:`SITUATIONS`: each one's recommendation and the rows behind it."""
    body = []
    for situation in SITUATIONS:
        chosen, cited = recommend(situation, rows)
        if not cited:
            continue
        bests = [_best(row, situation) for row in cited]
        if len(cited) <= 4:
            behind = " · ".join(f"{row['task']}: {best}" for row, best in zip(cited, bests, strict=True))
        else:  # how often each strategy is best
            counts = Counter(best.rsplit(" ", 1)[0] for best in bests)
            behind = ", ".join(f"{name} on {n}" for name, n in counts.most_common())
            behind = f"best: {behind}"
        if chosen:
            use = " or ".join(SHORT[s] for s in chosen)
        else:
            name, n = Counter(best.rsplit(" ", 1)[0] for best in bests).most_common(1)[0]
            use = f"no one strategy ({name} best on {n} of {len(cited)})"
        body.append([situation.text, use, f"{situation.rows_text} ({len(cited)}): {behind}"])
    return format_table(body, ["your situation", "use", "rows behind it"])


def parse_table(text: str) -> dict[str, list[str]]:
    """A decision table's recommendations, situation -> strategies (scoreboard columns), from its Markdown."""
    columns = {short: column for column, short in SHORT.items()}
    found: dict[str, list[str]] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or cells[0] in ("your situation", "") or set(cells[0]) <= {"-"}:
            continue
        use = cells[1]
        found[cells[0]] = [] if use.startswith("no one strategy") else [columns[n] for n in use.split(" or ")]
    return found


def contradictions(table: Mapping[str, Sequence[str]], rows: Sequence[Row]) -> list[str]:
    """Every (situation, strategy, row) where a recommendation of ``table`` breaks the rule."""
    situations = {s.text: s for s in SITUATIONS}
    found = []
    for text, strategies in table.items():
        situation = situations.get(text)
        if situation is None:
            found.append(f"{text!r}: no such situation (the situations are {sorted(situations)})")
            continue
        cited = [row for row in rows if situation.cites(row) and _timed(row, situation)]
        for strategy in strategies:
            for row in cited:
                if not holds(row, strategy, situation.strategies, situation.max_ms):
                    found.append(
                        f"{text!r}: {SHORT[strategy]} does not hold on {row['task']} ({_best(row, situation)})"
                    )
    return found


def _ran(row: Row, strategy: str) -> bool:
    value = row.get(strategy)
    return isinstance(value, (int, float)) and math.isfinite(value)


def _in_budget(row: Row, strategy: str, max_ms: float | None) -> bool:
    if max_ms is None:
        return True
    ms = row.get("ms", {}).get(strategy)
    return ms is not None and ms <= max_ms


def _timed(row: Row, situation: Situation) -> bool:
    return situation.max_ms is None or bool(row.get("ms"))


def _compare(row: Row, strategy: str, other: str) -> str:
    """``strategy`` against ``other`` on ``row``: ``better``, ``worse`` or ``tie``, by their paired
    verdict where the row holds one (its pairs, or its verdicts), else by whether their intervals overlap."""
    word = pair_word(row, strategy, other)
    if word != "-":
        return word
    low, high = row.get(f"{strategy} low", row[strategy]), row.get(f"{strategy} high", row[strategy])
    other_low, other_high = row.get(f"{other} low", row[other]), row.get(f"{other} high", row[other])
    if low <= other_high and other_low <= high:
        return "tie"
    ahead = row[strategy] < row[other] if row["lower_is_better"] else row[strategy] > row[other]
    return "better" if ahead else "worse"


def _best(row: Row, situation: Situation) -> str:
    best = best_of(row, _open(row, situation.strategies, situation.max_ms))
    return "none ran" if best is None else f"{SHORT[best]} {row[best]:.3g}"


def _open(row: Row, strategies: Sequence[str], max_ms: float | None) -> list[str]:
    """The ``strategies`` that ran on ``row``, within the budget where there is one."""
    return [s for s in strategies if _ran(row, s) and _in_budget(row, s, max_ms)]
