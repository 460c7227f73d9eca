"""The tables and the figure of ``smcd-rl task-masks``.

Example:
    >>> label((1.0, 16))
    'share 1, 16 groups'
    >>> estimate(0.01234, 0.011, 0.0139)
    '0.01234 [0.011, 0.0139]'
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from torch import Tensor

from smcd_rl.experiments.shared.outputs import format_table, save_figure

__all__ = ["label", "estimate", "tables", "plot"]


def label(point: tuple[float, int]) -> str:
    """A grid point's name: ``share 1, 16 groups``."""
    return f"share {point[0]:g}, {point[1]} groups"


def estimate(mean: float, low: float, high: float) -> str:
    """``mean [low, high]`` to four significant digits (errors span 1e-3 to 1 across the families)."""
    return f"{mean:.4g} [{low:.4g}, {high:.4g}]"


def tables(
    rows: Sequence[Mapping[str, Any]],
    comparisons: Sequence[Mapping[str, Any]],
    summary: Mapping[str, Any],
    points: Sequence[tuple[float, int]],
) -> dict[str, str]:
    """Caption -> Markdown: the choice, then every grid point's T+S and T+N with its pairing against the experiment's setting."""
    by_method = {row["method"]: row for row in rows}
    paired = {c["method"]: c for c in comparisons}
    current = tuple(summary["current"])
    body = []
    for point in sorted(points):
        name = label(point)
        smcd, none = by_method[f"{name} T+S"], by_method[f"{name} T+N"]
        c = paired.get(f"{name} T+S")
        against = "(the experiment's)" if point == current else "-"
        if c is not None:
            against = f"{estimate(c['difference'], c['low'], c['high'])} {c['verdict']}"
        noise = summary["smcd"][name]["noise_std"]
        noise_text = f"{noise if isinstance(noise, float) else statistics.median(noise):.3g}"
        body.append(
            [
                f"{point[0]:g}",
                point[1],
                estimate(smcd["error_mean"], smcd["error_low"], smcd["error_high"]),
                estimate(none["error_mean"], none["error_low"], none["error_high"]),
                against,
                f"{noise_text} / {summary['smcd'][name]['flip_prob']:g}",
            ]
        )
    best = tuple(summary["best"])
    choice = format_table(
        [
            [
                summary["family"],
                summary["experiment"],
                summary["criterion"],
                label(current),
                label(best),
                "yes" if best == current else "no",
            ]
        ],
        ["family", "experiment", "criterion", "experiment's setting", "lowest mean T+S", "the same"],
    )
    grid_caption = (
        f"{summary['criterion']} error of T on {summary['scored_on']} held-out training-task episodes "
        f"({summary['task']}; SMCD calibrated on {summary['calibrated_on']} others): mean [95% CI]; "
        "T+S paired with the experiment's setting over the same episodes (negative: lower error)"
    )
    if summary["extended"]:  # the lowest mean lay on the grid's edge
        past = ", ".join(label((share, groups)) for share, groups in summary["extended"])
        grid_caption += f"; past the grid's edge, where its lowest mean lay: {past}"
    grid_table = format_table(
        body,
        [
            "share",
            "groups",
            "T+S",
            "T+N",
            "T+S minus the experiment's setting [95% CI]",
            "SMCD noise (median over dimensions) / flip",
        ],
    )
    return {"The choice (lowest mean T+S error)": choice, grid_caption: grid_table}


def plot(
    scores: Mapping[str, Tensor], points: Sequence[tuple[float, int]], summary: Mapping[str, Any], path: Path
) -> None:
    """T+S and T+N error against the mask groups, one line per share (means with 95 % CIs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from smcd_rl.experiments.shared.stats import mean_ci

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    current = tuple(summary["current"])
    for ax, method in zip(axes, ("T+S", "T+N"), strict=True):
        for share in sorted({p[0] for p in points}):
            groups = sorted(g for s, g in points if s == share)
            found = [mean_ci(scores[f"{label((share, g))} {method}"]) for g in groups]
            means = [e.mean for e in found]
            errors = [[e.mean - e.low for e in found], [e.high - e.mean for e in found]]
            ax.errorbar(groups, means, yerr=errors, marker="o", capsize=3, label=f"share {share:g}")
        ax.plot(
            [current[1]], [mean_ci(scores[f"{label(current)} {method}"]).mean], "k*", ms=11, label="the experiment's"
        )
        ax.set_xscale("log", base=2)
        ticks = sorted({g for _, g in points})
        ax.set_xticks(ticks, [str(g) for g in ticks])
        ax.minorticks_off()
        ax.set_xlabel("mask groups per layer")
        ax.set_ylabel(f"{summary['criterion']} error")
        ax.set_title(f"{method} ({summary['family']})")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
