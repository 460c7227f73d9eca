"""The tables, figures and videos of ``smcd-rl ant``: prediction errors, returns per cell, MPC episodes as GIFs."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from smcd_rl.experiments.ant.config import METHOD_LABELS, PLANNERS, AntConfig
from smcd_rl.experiments.ant.episodes import render_states
from smcd_rl.experiments.shared.outputs import format_table, ms_cell, save_figure
from smcd_rl.experiments.shared.video import video_name, write_gif

__all__ = ["write_videos", "prediction_table", "return_rows", "table", "plot_returns", "plot_prediction"]


def write_videos(done: dict[tuple[str, str, str], dict[str, Any]], config: AntConfig, out: Path) -> list[str]:
    """``videos/<planner>-<adaptation>-<condition>-<k>.gif``: each cell's first ``--video`` MPC episodes, redrawn by MuJoCo."""
    names = []
    for (planner, adaptation, condition), result in done.items():
        for k, episode in enumerate(result.get("video", ())):
            frames, fps = render_states(config.task, episode["leg"], episode["states"], max_steps=config.episode_steps)
            names.append(video_name(f"{PLANNERS[planner]}-{METHOD_LABELS[adaptation]}-{condition}", k))
            write_gif(frames, out / names[-1], fps=fps)
    return names


def prediction_table(rows: list[dict[str, Any]], ms: Mapping[str, float] | None = None) -> str:
    """Prediction RMSE ``mean [95% CI]`` per condition and strategy (down), per metric (across).

    The last column is each strategy's median milliseconds per observation on the tuning episodes
    (``ms``, method -> ms; "-" for a method without one).

    Example:
        >>> row = {"condition": "healthy", "method": "M+S", "prediction": "one-step"}
        >>> print(prediction_table([row | {"rmse_mean": 0.2, "rmse_low": 0.1, "rmse_high": 0.3}], {"M+S": 1.234}))
        | condition | method | one-step       | ms / observation |
        |-----------|--------|----------------|------------------|
        | healthy   | M+S    | 0.2 [0.1, 0.3] | 1.23             |
    """
    ms = ms or {}
    metrics = list(dict.fromkeys(r["prediction"] for r in rows))
    lookup = {(r["condition"], r["method"], r["prediction"]): r for r in rows}
    keys = list(dict.fromkeys((r["condition"], r["method"]) for r in rows))
    body = []
    for condition, method in keys:
        cells = []
        for metric in metrics:
            r = lookup.get((condition, method, metric))
            cells.append("-" if r is None else f"{r['rmse_mean']:.4g} [{r['rmse_low']:.4g}, {r['rmse_high']:.4g}]")
        body.append([condition, method, *cells, ms_cell(ms.get(method))])
    return format_table(body, ["condition", "method", *metrics, "ms / observation"])


def return_rows(
    stats: list[dict[str, Any]],
    episodes: dict[tuple[str, str, str], list[dict[str, Any]]],
    seconds: dict[tuple[str, str, str], float],
) -> list[dict[str, Any]]:
    """One row per cell, in :data:`CELLS` order: the return's mean, 95% CI and spread, steps, distance."""
    lookup = {(r["planner"], r["method"], r["condition"]): r for r in stats}
    rows = []
    for (planner, adaptation, condition), records in episodes.items():
        r = lookup[(PLANNERS[planner], METHOD_LABELS[adaptation], condition)]
        rows.append(
            {
                "planner": PLANNERS[planner],
                "method": METHOD_LABELS[adaptation],
                "condition": condition,
                "return_mean": r["return_mean"],
                "return_low": r["return_low"],
                "return_high": r["return_high"],
                "return_std": r["return_std"],
                "return_sem": r["return_std"] / math.sqrt(r["trials"]),
                "steps_mean": float(np.mean([e["steps"] for e in records])),
                "distance_mean": float(np.mean([e["distance"] for e in records])),
                "episodes": r["trials"],
                "seconds": seconds[(planner, adaptation, condition)],
            }
        )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """Episode return ``mean [95% CI]`` per planner and method (down), per condition (across)."""
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    lookup = {(r["planner"], r["method"], r["condition"]): r for r in rows}
    pairs = list(dict.fromkeys((r["planner"], r["method"]) for r in rows))
    body = []
    for planner, adaptation in pairs:
        cells = []
        for condition in conditions:
            r = lookup.get((planner, adaptation, condition))
            cells.append(
                "-" if r is None else f"{r['return_mean']:.1f} [{r['return_low']:.1f}, {r['return_high']:.1f}]"
            )
        body.append([planner, adaptation, *cells])
    return format_table(body, ["planner", "method", *conditions])


def plot_returns(rows: list[dict[str, Any]], config: AntConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    adaptations = list(dict.fromkeys(r["method"] for r in rows))
    planners = list(dict.fromkeys(r["planner"] for r in rows))
    lookup = {(r["planner"], r["method"], r["condition"]): r for r in rows}
    width = 0.8 / len(planners)
    fig, axes = plt.subplots(1, len(conditions), figsize=(4.2 * len(conditions), 3.6), sharey=True, squeeze=False)
    for ax, condition in zip(axes[0], conditions, strict=True):
        for i, planner in enumerate(planners):
            sel = [lookup.get((planner, a, condition)) for a in adaptations]
            xs = [j + (i - (len(planners) - 1) / 2) * width for j in range(len(adaptations))]
            ax.bar(
                xs,
                [r["return_mean"] if r else float("nan") for r in sel],
                width,
                yerr=[
                    [r["return_mean"] - r["return_low"] if r else 0.0 for r in sel],
                    [r["return_high"] - r["return_mean"] if r else 0.0 for r in sel],
                ],
                capsize=3,
                label=planner,
            )
        ax.set_xticks(range(len(adaptations)), adaptations)
        ax.set_title("all legs functional" if condition == "healthy" else "one leg crippled")
        ax.set_xlabel("adaptation")
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("episode return")
    axes[0][-1].legend(title="planner")
    fig.suptitle(f"Ant MPC ({config.episodes} episodes of up to {config.episode_steps} steps, 95% CI)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def plot_prediction(rows: list[dict[str, Any]], config: AntConfig, path: Path) -> None:
    """``prediction.png``: one panel per metric, bars per strategy grouped by condition, 95% CIs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = list(dict.fromkeys(r["prediction"] for r in rows))
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lookup = {(r["condition"], r["method"], r["prediction"]): r for r in rows}
    width = 0.8 / len(methods)
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.4 * len(metrics), 3.6), squeeze=False)
    for ax, metric in zip(axes[0], metrics, strict=True):
        for i, method in enumerate(methods):
            sel = [lookup[(c, method, metric)] for c in conditions]
            xs = [j + (i - (len(methods) - 1) / 2) * width for j in range(len(conditions))]
            ax.bar(
                xs,
                [r["rmse_mean"] for r in sel],
                width,
                yerr=[[r["rmse_mean"] - r["rmse_low"] for r in sel], [r["rmse_high"] - r["rmse_mean"] for r in sel]],
                capsize=3,
                label=method,
            )
        ax.set_xticks(range(len(conditions)), conditions)
        ax.set_title(f"{metric} prediction error", fontsize=10)
        ax.set_ylabel("RMSE (observation units)")
        ax.grid(axis="y", alpha=0.3)
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(
        f"Ant: adapted model on {config.prediction_episodes} random-action episodes of {config.prediction_steps} "
        "steps per condition (95% CI)"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
