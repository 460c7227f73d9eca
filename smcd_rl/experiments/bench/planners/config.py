"""The config of ``smcd-rl bench planners`` (:mod:`smcd_rl.experiments.bench.planners.run`): its settings and ``--full`` preset.

Example:
    >>> BenchPlannersConfig().top_k, FULL
    (50, {'repeats': 100, 'warmup': 5})
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.bench.config import BenchConfig
from smcd_rl.experiments.shared.config import setting

__all__ = ["BenchPlannersConfig", "FULL"]


@dataclass
class BenchPlannersConfig(BenchConfig):
    """Settings of ``smcd-rl bench planners``; the defaults are the reference setting (Ant-v5 sizes)."""

    out: str = setting("runs/bench-planners", "output directory (results.json, results.csv)")
    observation: int = setting(27, "observation size (Ant-v5 without contact forces: 27)", low=1)
    action: int = setting(8, "action size (Ant: 8)", low=1)
    hidden: tuple[int, ...] = setting((256, 256), "hidden layer widths of the model", low=1, repeats=True)
    horizon: int = setting(15, "planning horizon H", low=1)
    candidates: int = setting(500, "action sequences per iteration", low=2)
    top_k: int = setting(50, "elites per iteration (2 to --candidates)", low=2)
    steps: int = setting(5, "optimisation steps (iterations) per plan", low=1)
    adaptation: str = setting(
        "none", "strategy the model plans with: none, or smcd (MMSE mask)", choices=("none", "smcd")
    )
    particles: int = setting(100, "SMCD particles (--adaptation smcd)", low=1)
    repeats: int = setting(20, "timed plans per planner (medians are reported)", low=1)
    warmup: int = setting(2, "untimed plans per planner first", low=0)
    full: bool = setting(False, "more repeats for steadier medians")

    NON_EMPTY = ("hidden",)

    def validate(self) -> None:
        super().validate()
        if self.top_k > self.candidates:
            raise ValueError(f"--top-k must be at most --candidates ({self.candidates}), got {self.top_k}")


#: What ``--full`` changes (options given explicitly still win).
FULL = {"repeats": 100, "warmup": 5}
