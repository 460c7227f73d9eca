"""The scoreboard in one compact table: per task, the best mean, the SMCD family against tuned GD, the cost.

Each row says which strategy has the best mean on the task's headline metric; how each member of
the SMCD family (SMCD tuned like GD, SMCD on task-trained masks, the combination, SMCD
with a Bayesian readout) and the Bayesian last layer fares
against tuned gradient descent, by the experiment's own paired verdict over the same trials
(``better``, ``worse`` or ``tie`` where the difference's 95 % interval holds zero; ``-`` where it
did not run); and each one's median time per observation. The scoreboard's other tables hold
the means, intervals and differences behind every cell.

Example:
    >>> verdict_word("better -0.067 [-0.091, -0.046]"), verdict_word("no significant difference 0.001 [-0.001, 0.003]")
    ('better', 'tie')
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from smcd_rl.experiments.shared.outputs import format_table
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, TASK_MASKS

__all__ = ["FAMILY", "SHORT", "summary_table", "verdict_word", "milliseconds"]

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
}


def verdict_word(verdict: str) -> str:
    """The first word of a paired verdict: ``better``, ``worse``, ``tie`` (no significant difference) or ``-``."""
    if verdict.startswith("better"):
        return "better"
    if verdict.startswith("worse"):
        return "worse"
    if verdict.startswith("no significant difference"):
        return "tie"
    return "-"


def summary_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The compact table of scoreboard rows (as the scoreboard builds them, one per task).

    A member of :data:`FAMILY` that no task ran has no column.
    """
    family = [member for member in FAMILY if any(math.isfinite(row[member]) for row in rows)]
    body = []
    for row in rows:
        present = [c for c in COLUMNS if math.isfinite(row[c])]
        pick = min if row["lower_is_better"] else max
        best = pick(present, key=lambda c: row[c])
        unit = row["metric"].split("(", 1)[1].rstrip(")") if "(" in row["metric"] else ""
        verdicts = " · ".join(verdict_word(row.get(f"{member} vs GD", "")) for member in family)
        times = " · ".join(milliseconds(row["ms"].get(c)) for c in ("GD", *family))
        body.append([row["task"], f"{SHORT[best]} {row[best]:.3f} {unit}".rstrip(), verdicts, times])
    header = [
        "task",
        "best mean",
        "against tuned GD: " + " · ".join(SHORT[c] for c in family),
        "ms / observation: " + " · ".join(SHORT[c] for c in ("GD", *family)),
    ]
    return format_table(body, header)


def milliseconds(value: float | None) -> str:
    """A time per observation as the tables show it: three significant digits, ``-`` where none was measured."""
    return "-" if value is None else f"{value:.3g}"
