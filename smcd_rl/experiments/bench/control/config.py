"""The config of ``smcd-rl bench control`` (:mod:`smcd_rl.experiments.bench.control.run`): its settings and ``--full`` preset.

Example:
    >>> BenchControlConfig().hidden, FULL
    ((1024, 1024, 1024), {'steps': 200, 'warmup': 10})
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from smcd_rl.experiments.bench.config import BenchConfig
from smcd_rl.experiments.shared.config import setting

__all__ = ["BenchControlConfig", "FULL"]


@dataclass
class BenchControlConfig(BenchConfig):
    """Settings of ``smcd-rl bench control``; the defaults are the paper's Panda network and SMCD at N = 1000.

    One torch thread, the harness's default, is also this benchmark's measured best (module docstring).
    """

    out: str = setting("runs/bench-control", "output directory (results.json, results.csv)")
    model: str = setting("", "a trained model.pt to time (e.g. runs/panda/model.pt); empty: random weights of --hidden")
    hidden: tuple[int, ...] = setting(
        (1024, 1024, 1024), "hidden widths of the random network (every layer masked)", low=1, repeats=True
    )
    dropout: float = setting(0.5, "dropout probability of the random network", low=0.0, below=1.0)
    batch: int = setting(1, "arms controlled at once by each contender", low=1)
    particles: int = setting(1000, "SMCD particles", low=1)
    flip_prob: float = setting(0.01, "SMCD bit-flip probability per step", low=0.0, high=1.0)
    noise_std: float = setting(0.05, "SMCD likelihood noise std (m)", above=0.0)
    gd_lr: float = setting(0.01, "online gradient-descent learning rate (normalised units)", above=0.0)
    gd_steps: int = setting(5, "gradient steps per observation", low=1)
    gd_window: int = setting(10, "recent transitions in the gradient-descent loss", low=1)
    steps: int = setting(50, "timed control steps per contender", low=1)
    warmup: int = setting(3, "untimed control steps per contender first", low=0)
    full: bool = setting(False, "more timed steps for steadier means")

    NON_EMPTY = ("hidden",)

    def validate(self) -> None:
        super().validate()
        if self.model and not Path(self.model).is_file():
            raise FileNotFoundError(
                f"--model {self.model}: no such file; train one with `smcd-rl panda` or leave it empty"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {"steps": 200, "warmup": 10}
