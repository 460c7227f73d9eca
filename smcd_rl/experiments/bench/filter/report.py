"""The goals and the printed report of ``smcd-rl bench filter`` (the timing itself is in :mod:`.run`).

Example:
    >>> row = {"N": 1000, "regime": "realistic", "schedule": "interleaved", "ours_over_matmul": 0.2, "naive_over_ours": 8.0}
    >>> goals([row], None)["interleaved"]["at_least_10x_faster_than_naive"]
    False
"""

from __future__ import annotations

from typing import Any

from smcd_rl.experiments.bench.tools import machine_line
from smcd_rl.experiments.shared.outputs import format_table

__all__ = ["GOALS", "GOAL_PARTICLES", "SCHEDULES", "goals", "report"]

#: Goals of issue 4 at N = 1000 (and the memory goal at ``memory_particles``).
GOALS = {"realistic_over_matmul": 1.0, "worst_over_matmul": 1.5, "naive_over_ours": 10.0, "peak_extra_mb": 200.0}
GOAL_PARTICLES = 1000
#: How the contenders' updates are ordered; both are timed in the same run (see ``_time_regime``).
SCHEDULES = ("interleaved", "back to back")


def goals(rows: list[dict[str, Any]], memory: dict[str, Any] | None) -> dict[str, dict[str, bool | None]]:
    """Issue 4's goals per schedule (the memory goal does not depend on it)."""
    verdicts: dict[str, dict[str, bool | None]] = {}
    for schedule in SCHEDULES:
        at = {row["regime"]: row for row in rows if row["N"] == GOAL_PARTICLES and row["schedule"] == schedule}
        realistic, worst = at.get("realistic"), at.get("worst")
        verdicts[schedule] = {
            "realistic_at_most_1.0x_matmul": None
            if realistic is None
            else realistic["ours_over_matmul"] <= GOALS["realistic_over_matmul"],
            "worst_at_most_1.5x_matmul": None
            if worst is None
            else worst["ours_over_matmul"] <= GOALS["worst_over_matmul"],
            "at_least_10x_faster_than_naive": None
            if realistic is None
            else realistic["naive_over_ours"] >= GOALS["naive_over_ours"],
            "peak_extra_under_200_mb": None
            if memory is None
            else memory["ours_peak_extra_mb"] < GOALS["peak_extra_mb"],
        }
    return verdicts


def report(payload: dict[str, Any]) -> str:
    """The printed report: machine, network, the timing table, peak memory and a verdict per goal and schedule."""
    net = payload["network"]
    lines = [machine_line(payload)]
    lines.append(
        f"network: MaskedMLP {net['in']} -> {' -> '.join(map(str, net['hidden']))} -> {net['out']}, "
        f"{net['mask_dim']} mask bits, dropout {net['dropout']}; flip prob {payload['config']['flip_prob']}"
    )
    lines.append(
        "ms per update: mean over the run (ours median in brackets); matmul: median of one (N x 1024) @ (1024 x 1024)"
    )
    lines.append(
        "schedule: interleaved = every contender once per step (caches filled by the others), "
        "back to back = each contender's whole run in a block (its own data in cache)"
    )
    lines.append("")
    body = [
        [
            r["N"],
            r["regime"],
            r["schedule"],
            f"{r['mean_distinct_parents']:.0f}",
            f"{r['ours_ms']:.2f} ({r['ours_median_ms']:.2f})",
            f"{r['dense_path_ms']:.2f}",
            f"{r['naive_ms']:.2f}",
            f"{r['matmul_ms']:.2f}",
            f"{r['ours_over_matmul']:.2f}x",
            f"{r['naive_over_ours']:.1f}x",
        ]
        for r in payload["results"]
    ]
    header = [
        "N",
        "regime",
        "schedule",
        "distinct parents",
        "ours ms",
        "dense path ms",
        "naive ms",
        "matmul ms",
        "ours / matmul",
        "naive / ours",
    ]
    lines.append(format_table(body, header))
    memory = payload["memory"]
    if memory is not None:
        lines.append("")
        lines.append(
            f"extra peak memory of an update, N={memory['particles']}, hidden {memory['hidden']}: "
            f"ours {memory['ours_peak_extra_mb']:.0f} MB, naive {memory['naive_peak_extra_mb']:.0f} MB"
        )
    lines.append("")
    verdict = {True: "met", False: "NOT met", None: "not measured"}
    at = f"N={GOAL_PARTICLES}"
    targets = {
        "realistic_at_most_1.0x_matmul": (
            f"goal {at}, realistic: ours <= {GOALS['realistic_over_matmul']}x matmul",
            "realistic",
            "ours_over_matmul",
        ),
        "worst_at_most_1.5x_matmul": (
            f"goal {at}, worst case: ours <= {GOALS['worst_over_matmul']}x matmul",
            "worst",
            "ours_over_matmul",
        ),
        "at_least_10x_faster_than_naive": (
            f"goal {at}, realistic: ours >= {GOALS['naive_over_ours']:.0f}x faster than naive",
            "realistic",
            "naive_over_ours",
        ),
    }
    for goal, (text, regime, ratio) in targets.items():
        verdicts = []
        for schedule in SCHEDULES:
            row = [
                r
                for r in payload["results"]
                if r["N"] == GOAL_PARTICLES and r["regime"] == regime and r["schedule"] == schedule
            ]
            value = f" ({row[0][ratio]:.2f}x)" if row else ""
            verdicts.append(f"{verdict[payload['goals'][schedule][goal]]} {schedule}{value}")
        lines.append(f"{text}: {', '.join(verdicts)}")
    size = f"N={memory['particles']}" if memory is not None else "memory"
    lines.append(
        f"goal {size}: extra peak memory < {GOALS['peak_extra_mb']:.0f} MB: "
        f"{verdict[payload['goals'][SCHEDULES[0]]['peak_extra_under_200_mb']]}"
    )
    return "\n".join(lines)
