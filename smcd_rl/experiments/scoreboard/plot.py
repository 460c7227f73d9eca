"""The scoreboard's picture: a panel per task, each strategy's mean with its 95 % interval.

Example:
    >>> BAR_LABELS["combination"]
    'combi-\\nnation'
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from smcd_rl.experiments.shared.outputs import save_figure
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, T_COLUMNS, TASK_MASKS

__all__ = ["draw", "BAR_LABELS"]

#: The strategies' names under the bars.
BAR_LABELS = {
    "none": "none",
    "GD": "GD",
    "SMCD (paper)": "SMCD\n(paper)",
    "SMCD (calibrated)": "SMCD\n(calibrated)",
    "SMCD (one-step)": "SMCD\n(one-step)",
    "combination": "combi-\nnation",
    "last layer": "last\nlayer",
    "SMCD + last layer": "SMCD +\nlast layer",
    TASK_MASKS: "T+S",
    **{column: column for column in T_COLUMNS},
}


def draw(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """A panel per task (its own metric and scale), two to a row: each strategy's mean with its 95 % CI.

    Two columns of panels, each about 4 inches wide, so that the picture is readable at the width
    of a docs page (about 700 pixels) with no zooming.
    """
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = 1 if len(rows) == 1 else 2
    lines = math.ceil(len(rows) / columns)
    fig, axes = plt.subplots(lines, columns, figsize=(4.2 * columns, 2.9 * lines + 0.6), squeeze=False)
    for ax, row in zip(axes.flat, rows, strict=False):
        present = [c for c in COLUMNS if math.isfinite(row[c])]  # the strategies this task ran
        for j, column in enumerate(present):
            mean = row[column]
            error = [[mean - row[f"{column} low"]], [row[f"{column} high"] - mean]]
            ax.bar(j, mean, 0.7, yerr=error, capsize=3, color=f"C{COLUMNS.index(column) % 10}")
        # Both networks' strategies do not fit side by side at a page's width: upright names then.
        crowded = len(present) > 8
        ax.set_xticks(
            range(len(present)),
            [BAR_LABELS[c].replace("\n", " ") if crowded else BAR_LABELS[c] for c in present],
            fontsize=10 if len(present) <= 4 else 8,
            rotation=90 if crowded else 0,
        )
        ax.set_xlim(-0.6, max(len(present), 1) - 0.4)
        ax.set_title("\n".join(textwrap.wrap(row["task"], 40)), fontsize=12)
        better = "lower" if row["lower_is_better"] else "higher"
        ax.set_ylabel("\n".join(textwrap.wrap(f"{row['metric']}, {better} is better", 28)), fontsize=10)
        ax.tick_params(axis="y", labelsize=10)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes.flat[len(rows) :]:
        ax.axis("off")
    fig.suptitle("Scoreboard: mean and 95% CI of each task's headline metric", fontsize=13)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
