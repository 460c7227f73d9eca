"""The tables and figure of ``smcd-rl fetch``: results per family, planner and method, and ``fetch.png``.

Example:
    >>> METRICS["success"]
    ('success rate', True)
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from smcd_rl.experiments.fetch.config import METHOD_LABELS
from smcd_rl.experiments.shared.outputs import format_table, ms_cell, save_figure

if TYPE_CHECKING:
    from smcd_rl.experiments.fetch.config import FetchConfig

__all__ = ["METRICS", "rename", "unrename", "table", "plot"]

#: Metrics: name in the rows -> (label, higher is better).
METRICS = {"success": ("success rate", True), "distance": ("final distance (m)", False)}


def rename(row: dict[str, Any], metric: str) -> dict[str, Any]:
    """A statistics row with its metric's fields under generic names (``mean``, ``low``, ``high``, ``std``)."""
    out = {k: v for k, v in row.items() if not k.startswith(f"{metric}_")}
    return out | {k.removeprefix(f"{metric}_"): v for k, v in row.items() if k.startswith(f"{metric}_")}


def unrename(row: dict[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`rename` (what :func:`scoreboard_entry` reads)."""
    metric = row["metric"]
    return {(f"{metric}_{k}" if k in ("mean", "low", "high", "std") else k): v for k, v in row.items()}


def table(rows: list[dict[str, Any]]) -> str:
    """``mean [95% CI]`` per family, planner and method (down), per metric (across), then ms per observation.

    The last column is the rows' ``ms_per_observation`` ("-" where a row has none, as random actions).

    Example:
        >>> row = {"family": "reach", "planner": "CEM", "method": "M+S", "mean": 0.5, "low": 0.25, "high": 0.75}
        >>> print(table([row | {"metric": "success", "ms_per_observation": 2.345}]))
        | family | planner | method | success rate      | final distance (m) | ms / observation |
        |--------|---------|--------|-------------------|--------------------|------------------|
        | reach  | CEM     | M+S    | 0.50 [0.25, 0.75] | -                  | 2.35             |
    """
    lookup = {(r["family"], r["planner"], r["method"], r["metric"]): r for r in rows}
    keys = list(dict.fromkeys((r["family"], r["planner"], r["method"]) for r in rows))
    times = {(r["family"], r["planner"], r["method"]): r.get("ms_per_observation") for r in rows}
    body = []
    for family, planner, method in keys:
        cells = []
        for metric in METRICS:
            r = lookup.get((family, planner, method, metric))
            digits = 2 if metric == "success" else 3
            cells.append(
                "-" if r is None else f"{r['mean']:.{digits}f} [{r['low']:.{digits}f}, {r['high']:.{digits}f}]"
            )
        body.append([family, planner, method, *cells, ms_cell(times[(family, planner, method)])])
    header = ["family", "planner", "method", *(label for label, _ in METRICS.values()), "ms / observation"]
    return format_table(body, header)


def plot(rows: list[dict[str, Any]], config: FetchConfig, path: Path) -> None:
    """``fetch.png``: one row of panels per family (success rate, final distance), bars per method grouped by planner."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = list(dict.fromkeys(r["family"] for r in rows))
    fig, axes = plt.subplots(
        len(families), len(METRICS), figsize=(5.0 * len(METRICS), 3.4 * len(families)), squeeze=False
    )
    for i, family in enumerate(families):
        for ax, (metric, (label, _)) in zip(axes[i], METRICS.items(), strict=True):
            sel = [r for r in rows if r["family"] == family and r["metric"] == metric]
            labels = [
                r["method"] if r["planner"] == "-" else f"{r['planner']}\n{r['method'].removeprefix('M+')}" for r in sel
            ]
            colors = [
                f"C{list(METHOD_LABELS.values()).index(r['method'])}"
                if r["method"] in METHOD_LABELS.values()
                else "grey"
                for r in sel
            ]
            ax.bar(
                range(len(sel)),
                [r["mean"] for r in sel],
                yerr=[[r["mean"] - r["low"] for r in sel], [r["high"] - r["mean"] for r in sel]],
                capsize=3,
                color=colors,
            )
            ax.set_xticks(range(len(sel)), labels, fontsize=7)
            ax.set_title(f"{family}: {label}", fontsize=10)
            ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"Fetch MPC, {config.episodes} test draws x {config.episode_steps} steps (95% CI)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
