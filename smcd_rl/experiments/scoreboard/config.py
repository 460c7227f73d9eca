"""The config of ``smcd-rl scoreboard`` (:mod:`smcd_rl.experiments.scoreboard.run`).

Example:
    >>> ScoreboardConfig(runs=("runs/two-link",)).out
    'runs/scoreboard'
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.config import ExperimentConfig, setting

__all__ = ["ScoreboardConfig"]


@dataclass
class ScoreboardConfig(ExperimentConfig):
    """Settings of ``smcd-rl scoreboard``."""

    runs: tuple[str, ...] = setting(
        (),
        "run directories of experiments (each with its results.json), e.g. runs/two-link runs/panda",
        positional=True,
    )
    out: str = setting("runs/scoreboard", "output directory (scoreboard table, plot, report)")

    NON_EMPTY = ("runs",)
