"""The tables of ``smcd-rl panda``: success per method and measurement interval, and the rows behind them.

Example:
    >>> from smcd_rl.experiments.panda.config import PandaConfig
    >>> row = {"method": "T+S", "interval": 5, "success_mean": 1.0, "success_low": 1.0, "success_high": 1.0}
    >>> print(table([row], PandaConfig(intervals=(5,))))
    | method | n=5               | ms / observation |
    |--------|-------------------|------------------|
    | T+S    | 1.00 [1.00, 1.00] | -                |
"""

from __future__ import annotations

from typing import Any

from smcd_rl.experiments.panda.config import PandaConfig
from smcd_rl.experiments.shared.outputs import format_table

__all__ = ["describe", "trial_rows", "table"]


def describe(
    row: dict[str, Any], results: dict[tuple[str, int], dict[str, Any]], config: PandaConfig, ms: dict[str, float]
) -> dict:
    """A table row with what the success rate leaves out: spread over seeds, steps, final distance, and time.

    ``ms`` maps a method to its median ms per observation on the tuning episodes; a method
    without one (FK, or M+N of a run that tuned nothing) has no ``ms_per_observation``.
    """
    r = results[(row["method"], row["interval"])]
    rates, reached = r["reached"].double().mean(1), r["reached"].reshape(-1)
    steps = r["steps"].reshape(-1).double()
    return {
        **row,
        "success_seed_std": float(rates.std()) if len(rates) > 1 else 0.0,
        "steps_mean": float(steps[reached].mean()) if bool(reached.any()) else None,
        "final_distance_median": float(r["final_distance"].median()),
        "seeds": config.seeds,
        "tasks": config.tasks,
        "seconds": r["seconds"],
        **({"ms_per_observation": ms[row["method"]]} if row["method"] in ms else {}),
    }


def trial_rows(results: dict[tuple[str, int], dict[str, Any]], config: PandaConfig) -> list[dict[str, Any]]:
    return [
        {
            "method": label,
            "interval": n,
            "seed": s,
            "task": k,
            "reached": bool(r["reached"][s, k]),
            "steps": int(r["steps"][s, k]),
            "final_distance": float(r["final_distance"][s, k]),
            "tool_length": float(r["tools"][s, k]),
        }
        for (label, n), r in results.items()
        for s in range(config.seeds)
        for k in range(config.tasks)
    ]


def table(rows: list[dict[str, Any]], config: PandaConfig) -> str:
    """Success rate (mean [95% CI] over all arms), method down and measurement interval n across.

    The last column is the method's median milliseconds per observation on the tuning episodes
    (its rows' ``ms_per_observation``; "-" for a method without one, such as FK).

    Example:
        >>> row = {"method": "M+S", "interval": 5, "success_mean": 0.5, "success_low": 0.4, "success_high": 0.6}
        >>> print(table([{**row, "ms_per_observation": 2.345}, {**row, "method": "FK"}], PandaConfig(intervals=(5,))))
        | method | n=5               | ms / observation |
        |--------|-------------------|------------------|
        | M+S    | 0.50 [0.40, 0.60] | 2.35             |
        | FK     | 0.50 [0.40, 0.60] | -                |
    """
    intervals = sorted(set(config.intervals))
    lookup = {(r["method"], r["interval"]): r for r in rows}
    ms = {r["method"]: r["ms_per_observation"] for r in rows if r.get("ms_per_observation") is not None}
    body = []
    for label in dict.fromkeys(r["method"] for r in rows):
        cells = []
        for n in intervals:
            r = lookup.get((label, n))
            cells.append(
                "-" if r is None else f"{r['success_mean']:.2f} [{r['success_low']:.2f}, {r['success_high']:.2f}]"
            )
        body.append([label, *cells, f"{ms[label]:.3g}" if label in ms else "-"])
    return format_table(body, ["method", *[f"n={n}" for n in intervals], "ms / observation"])
