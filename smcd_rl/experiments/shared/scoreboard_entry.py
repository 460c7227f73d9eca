"""The scoreboard's entry of one experiment: the cell of its table that stands for its task.

Each experiment writes it into its ``results.json`` (:func:`scoreboard_entry`): the estimates of
its methods for "none", "GD", "SMCD (paper)" and "SMCD (calibrated)" (and, where it ran them,
"SMCD (one-step)", "combination" and "SMCD (task masks)") and their paired verdicts;
``smcd-rl scoreboard`` reads the entries of many runs into one table.

Example:
    >>> rows = [{"T": 10, "method": "M+N", "rmse_mean": 0.2, "rmse_low": 0.1, "rmse_high": 0.3, "trials": 9}]
    >>> entry = scoreboard_entry("two-link", rows, [], cell={"T": 10}, metric="rmse", unit="m")
    >>> entry["estimates"]["none"]["mean"], entry["verdicts"]["SMCD (calibrated) vs none"]
    (0.2, 'not compared')
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from smcd_rl.experiments.shared.stats import Estimate

__all__ = [
    "scoreboard_entry",
    "COLUMNS",
    "CORE_COLUMNS",
    "HEADLINE",
    "TASK_MASKS",
    "TASK_MASKS_METHOD",
    "VERDICTS",
    "CORE_VERDICTS",
    "VERDICT_LABELS",
    "HEADERS",
    "paired_verdict",
    "T_COLUMNS",
]

#: The scoreboard's strategies, in order: "SMCD (calibrated)" is SMCD calibrated by its evidence,
#: "SMCD (one-step)" SMCD tuned like GD, by the same criterion (:func:`smcd_rl.tune`), "combination"
#: the tuned combination of the others, "last layer" the Bayesian last layer, "SMCD + last layer"
#: SMCD with a Bayesian readout, "SMCD (task masks)" one-step SMCD on a network whose masks were
#: trained to identify the task, and "T+N", "T+G", "T+L", "T+SL" the other strategies on that
#: network; an experiment that did not run one reads "not run".
COLUMNS = (
    "none",
    "GD",
    "SMCD (paper)",
    "SMCD (calibrated)",
    "SMCD (one-step)",
    "combination",
    "last layer",
    "SMCD + last layer",
    "SMCD (task masks)",
    "T+N",
    "T+G",
    "T+L",
    "T+SL",
)
#: The task-mask network's strategies besides T+S: each column is its method's label.
T_COLUMNS = ("T+N", "T+G", "T+L", "T+SL")
#: The column of SMCD on the task-mask network (``fit(mask_training="task")``), and its method label.
TASK_MASKS, TASK_MASKS_METHOD = "SMCD (task masks)", "T+S"
#: The columns every experiment's entry has.
CORE_COLUMNS = COLUMNS[:4]
#: Strategy -> the method suffix the experiments use for it (after ``M+``).
HEADLINE = {
    "none": "N",
    "GD": "G",
    "SMCD (paper)": "S(paper)",
    "SMCD (calibrated)": "S(evidence)",
    "SMCD (one-step)": "S",
    "combination": "C",
    "last layer": "L",
    "SMCD + last layer": "SL",
}
#: The paired verdicts shown: (method, against); those after the first four where those strategies ran.
VERDICTS = (
    ("SMCD (calibrated)", "none"),
    ("SMCD (calibrated)", "GD"),
    ("SMCD (paper)", "none"),
    ("SMCD (paper)", "GD"),
    ("SMCD (one-step)", "GD"),
    ("combination", "GD"),
    ("last layer", "GD"),
    ("last layer", "SMCD (one-step)"),
    ("SMCD + last layer", "GD"),
    ("SMCD + last layer", "SMCD (one-step)"),
    (TASK_MASKS, "GD"),
    (TASK_MASKS, "SMCD (one-step)"),
)
#: The verdicts every experiment's entry has.
CORE_VERDICTS = VERDICTS[:4]
#: How a table heads a column: SMCD tuned by each task's criterion (look-ahead where the task scores
#: one, else one-step error) is "SMCD (tuned)"; its key stays "SMCD (one-step)" in the entries.
HEADERS = {"SMCD (one-step)": "SMCD (tuned)"}
#: The verdicts' column headers.
VERDICT_LABELS = {
    (m, a): " vs ".join(
        name.removeprefix("SMCD (").removesuffix(")") if name.startswith("SMCD (") else name
        for name in (HEADERS.get(m, m), HEADERS.get(a, a))
    )
    for m, a in VERDICTS
}


def scoreboard_entry(
    task: str,
    rows: Sequence[Mapping[str, Any]],
    comparisons: Sequence[Mapping[str, Any]],
    *,
    cell: Mapping[str, Any],
    metric: str,
    unit: str,
    methods: Mapping[str, str] | None = None,
    prefix: str = "M+",
    lower_is_better: bool = True,
    ms: Mapping[str, float] | None = None,
    note: str | None = None,
) -> dict[str, Any]:
    """The ``results.json`` entry that stands for ``task`` in the scoreboard: its estimates and verdicts.

    Args:
        task: the task's name in the scoreboard.
        rows: the table rows of :func:`~smcd_rl.experiments.shared.stats.cell_statistics`.
        comparisons: its paired comparisons.
        cell: the headline cell, field -> value (if it did not run, e.g. other burn-in steps were
            asked for, the first row's cell is used).
        metric: the rows' score name (``rmse`` reads ``rmse_mean``, ``rmse_low``, ``rmse_high``).
        unit: the metric's unit, for the table.
        methods: strategy (a :data:`COLUMNS` name) -> method suffix; default :data:`HEADLINE`.
        prefix: what the suffixes follow (``"M+"``).
        lower_is_better: ``False`` for success rates and returns.
        ms: method label -> its median milliseconds per observation (``ms_per_observation`` of
            the entry, by strategy; only the strategies found in the cell).
        note: what a reader must know to compare the row's strategies (e.g. a network that saw
            the test condition in training); the scoreboard lists it under its tables.
    """
    chosen = dict(cell)
    if rows and not any(_in_cell(r, chosen) for r in rows):
        chosen = {k: rows[0][k] for k in chosen}
    labels = {column: prefix + suffix for column, suffix in (HEADLINE if methods is None else methods).items()}
    found = {r["method"]: r for r in rows if _in_cell(r, chosen)}
    if TASK_MASKS_METHOD in found:  # the task-mask network's strategies, where the experiment ran them
        labels[TASK_MASKS] = TASK_MASKS_METHOD
        labels.update({column: column for column in T_COLUMNS})
    estimates = {
        column: {
            "method": label,
            "mean": found[label][f"{metric}_mean"],
            "low": found[label][f"{metric}_low"],
            "high": found[label][f"{metric}_high"],
            "trials": found[label]["trials"],
        }
        for column, label in labels.items()
        if label in found
    }
    pairs = {(c["method"], c["against"]): c for c in comparisons if _in_cell(c, chosen)}
    verdicts = {  # the pairs of strategies this experiment has (the core four always)
        f"{method} vs {against}": paired_verdict(pairs, labels.get(method, ""), labels.get(against, ""))
        for method, against in VERDICTS
        if (method, against) in CORE_VERDICTS or (method in labels and against in labels)
    }
    ran = [column for column in COLUMNS if column in estimates]
    entry = {
        "task": task,
        "cell": chosen,
        "metric": metric,
        "unit": unit,
        "lower_is_better": lower_is_better,
        "estimates": estimates,
        "verdicts": verdicts,
        # Every pair of the strategies that ran, paired over the same trials: what the scoreboard's
        # verdicts by network choose from.
        "pairs": {
            f"{a} vs {b}": verdict
            for i, a in enumerate(ran)
            for b in ran[i + 1 :]
            if (verdict := paired_verdict(pairs, labels[a], labels[b])) != "not compared"
        },
    }
    if ms:
        timed = {column: ms[e["method"]] for column, e in estimates.items() if e["method"] in ms}
        entry["ms_per_observation"] = timed
    if note:
        entry["note"] = note
    return entry


def _in_cell(row: Mapping[str, Any], cell: Mapping[str, Any]) -> bool:
    return all(row.get(k) == v for k, v in cell.items())


def paired_verdict(pairs: Mapping[tuple[str, str], Mapping[str, Any]], a: str, b: str) -> str:
    """``a`` against ``b``: "better -0.020 [-0.030, -0.010]", from either orientation of the stored pair.

    ``pairs`` maps (method, against) to a comparison row of one cell; "not compared" if neither
    orientation is there.
    """
    flip = {"better": "worse", "worse": "better"}
    if (a, b) in pairs:
        c = pairs[(a, b)]
        return f"{c['verdict']} {Estimate(c['difference'], c['low'], c['high'], 0)}"
    if (b, a) in pairs:
        c = pairs[(b, a)]
        verdict = flip.get(c["verdict"], c["verdict"])
        return f"{verdict} {Estimate(-c['difference'], -c['high'], -c['low'], 0)}"
    return "not compared"
