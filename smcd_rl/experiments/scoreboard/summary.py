"""The scoreboard in one compact table: per task, the best mean of either network, the SMCD family by network, the cost.

Each row says which strategy, on either network, has the best mean on the task's headline
metric, and answers two questions by the experiment's own paired verdicts over the same trials
(``better``, ``worse`` or ``tie`` where the difference's 95 % interval holds zero; ``-`` where a
side did not run or the pair was not compared):

* **on the same network**, is the SMCD family better than the best of gradient descent and the
  last layer? On the usual network (M) the family is SMCD and SMCD with a Bayesian readout; on the
  task-mask network (T), T+S and T+SL against T+G and T+L. Each side is its best mean there.
* **for a user who can train either network**, is the best SMCD-family strategy of both networks
  better than the best other strategy of both (gradient descent, the last layer and the
  combination on M; T+G and T+L)?

And each strategy's median time per observation. The scoreboard's other tables hold the means,
intervals and differences behind every cell.

Example:
    >>> verdict_word("better -0.067 [-0.091, -0.046]"), verdict_word("no significant difference 0.001 [-0.001, 0.003]")
    ('better', 'tie')
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from smcd_rl.experiments.shared.outputs import format_table
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, T_COLUMNS, TASK_MASKS

__all__ = [
    "FAMILY",
    "SHORT",
    "NETWORKS",
    "EITHER",
    "best_of",
    "summary_table",
    "verdict_word",
    "pair_word",
    "milliseconds",
]

#: The SMCD family and the Bayesian last layer, in the order the table lists them.
FAMILY = ("SMCD (one-step)", TASK_MASKS, "combination", "SMCD + last layer", "last layer")
#: Each strategy's short name in the table.
SHORT = {
    "none": "none",
    "GD": "GD",
    "SMCD (paper)": "SMCD (paper)",
    "SMCD (calibrated)": "SMCD (evidence)",
    "SMCD (one-step)": "SMCD",
    "combination": "combination",
    "last layer": "last layer",
    "SMCD + last layer": "SMCD+L",
    TASK_MASKS: "T+S",
    **{column: column for column in T_COLUMNS},
}
#: Per network: its SMCD family and the strategies it is held against there.
NETWORKS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "M": (("SMCD (one-step)", "SMCD + last layer"), ("GD", "last layer")),
    "T": ((TASK_MASKS, "T+SL"), ("T+G", "T+L")),
}
#: Either network: the SMCD family of both against every other strategy of both.
EITHER: tuple[tuple[str, ...], tuple[str, ...]] = (
    ("SMCD (one-step)", "SMCD + last layer", TASK_MASKS, "T+SL"),
    ("GD", "last layer", "combination", "T+G", "T+L"),
)


def verdict_word(verdict: str) -> str:
    """The first word of a paired verdict: ``better``, ``worse``, ``tie`` (no significant difference) or ``-``."""
    if verdict.startswith("better"):
        return "better"
    if verdict.startswith("worse"):
        return "worse"
    if verdict.startswith("no significant difference"):
        return "tie"
    return "-"


def pair_word(row: Mapping[str, Any], a: str, b: str) -> str:
    """``a`` against ``b`` on ``row`` as one word (``better``, ``worse``, ``tie``; ``-``: not compared),
    from the entry's pairs, else from its verdicts, in either orientation."""
    flip = {"better": "worse", "worse": "better", "tie": "tie", "-": "-"}
    pairs = row.get("pairs", {})
    for key, flipped in ((f"{a} vs {b}", False), (f"{b} vs {a}", True)):
        verdict = pairs.get(key, row.get(key, ""))
        word = verdict_word(str(verdict))
        if word != "-":
            return flip[word] if flipped else word
    return "-"


def best_of(row: Mapping[str, Any], columns: Sequence[str]) -> str | None:
    """The column of ``columns`` with the best mean on ``row`` (``None`` where none ran)."""
    present = [c for c in columns if math.isfinite(row[c])]
    if not present:
        return None
    return (min if row["lower_is_better"] else max)(present, key=lambda c: row[c])


def _side_verdict(row: Mapping[str, Any], family: Sequence[str], others: Sequence[str], *, named: bool = False) -> str:
    """The best of ``family`` against the best of ``others`` on ``row`` (``-`` where a side did not run)."""
    ours, theirs = best_of(row, family), best_of(row, others)
    if ours is None or theirs is None:
        return "-"
    word = pair_word(row, ours, theirs)
    return f"{SHORT[ours]} vs {SHORT[theirs]}: {word}" if named else word


def summary_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The compact table of scoreboard rows (as the scoreboard builds them, one per task)."""
    family = [member for member in FAMILY if any(math.isfinite(row[member]) for row in rows)]
    body = []
    for row in rows:
        best = best_of(row, COLUMNS)
        assert best is not None  # every entry has an estimate (checked when read)
        unit = row["metric"].split("(", 1)[1].rstrip(")") if "(" in row["metric"] else ""
        same = " · ".join(_side_verdict(row, *NETWORKS[net]) for net in NETWORKS)
        either = _side_verdict(row, *EITHER, named=True)
        times = " · ".join(milliseconds(row["ms"].get(c)) for c in ("GD", *family))
        body.append([row["task"], f"{SHORT[best]} {row[best]:.3f} {unit}".rstrip(), same, either, times])
    header = [
        "task",
        "best mean",
        "SMCD family vs best of GD, last layer: M · T",
        "best SMCD vs best other, either network",
        "ms / observation: " + " · ".join(SHORT[c] for c in ("GD", *family)),
    ]
    return format_table(body, header)


def milliseconds(value: float | None) -> str:
    """A time per observation as the tables show it: three significant digits, ``-`` where none was measured."""
    return "-" if value is None else f"{value:.3g}"
