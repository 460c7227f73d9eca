"""The adaptation strategies the experiments compare, built in one place from a config's settings.

Every experiment names its methods by the paper's letters: ``N`` (no adaptation), ``G`` (online
gradient descent) and ``S`` (SMCD). :class:`AdaptationConfig` declares their settings once, and
:func:`make_adaptation` builds the strategy for a letter (from one :class:`StrategySettings`) through
the strategies' registry (:mod:`smcd_rl.strategies.registry`), so every experiment adapts the same way.

Example:
    >>> settings = StrategySettings(particles=50, noise_std=0.05, flip_prob=0.01, gd_lr=0.03, gd_steps=1, gd_window=5)
    >>> settings.strategy("S", seed=0)
    SMCD(num_particles=50, flip_prob=0.01, noise_std=0.05, ...)
    >>> settings.strategy("G", seed=0).lr
    0.03
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch

import smcd_rl
from smcd_rl.experiments.shared.adaptation_config import AdaptationConfig, TuningConfig
from smcd_rl.experiments.shared.tuning_record import TUNED
from smcd_rl.strategies.registry import build

__all__ = ["TuningConfig", "AdaptationConfig", "AdaptationSettings", "StrategySettings", "make_adaptation", "LETTERS"]

#: The paper's letters for the strategies: none, gradient descent, SMCD.
LETTERS = ("N", "G", "S")


class AdaptationSettings(Protocol):
    """What :func:`make_adaptation` reads from a config (a :class:`StrategySettings` has it all)."""

    @property
    def flip_prob(self) -> float: ...
    @property
    def gd_lr(self) -> float: ...
    @property
    def gd_steps(self) -> int: ...
    @property
    def gd_window(self) -> int: ...


@dataclass(frozen=True)
class StrategySettings:
    """One setting of every strategy: what :func:`make_adaptation` builds a variant from."""

    particles: int
    noise_std: float | tuple[float, ...]
    flip_prob: float
    gd_lr: float
    gd_steps: int
    gd_window: int

    def strategy(self, letter: str, *, seed: int, device: torch.device | str = "cpu") -> smcd_rl.Adaptation:
        """The strategy ``N``, ``G`` or ``S`` with these settings."""
        noise = list(self.noise_std) if isinstance(self.noise_std, tuple) else self.noise_std
        return make_adaptation(letter, self, particles=self.particles, noise_std=noise, seed=seed, device=device)


def make_adaptation(
    letter: str,
    config: AdaptationSettings,
    *,
    particles: int,
    noise_std: float | Sequence[float],
    seed: int,
    device: torch.device | str = "cpu",
) -> smcd_rl.Adaptation:
    """The strategy for ``letter`` (``N``, ``G`` or ``S``) with ``config``'s settings.

    Args:
        letter: ``"N"``, ``"G"`` or ``"S"``.
        config: the gradient-descent settings and SMCD's flip probability.
        particles: SMCD's particle count.
        noise_std: SMCD's likelihood noise (a scalar or one value per observation dimension).
        seed: seed of SMCD's generator (on ``device``).
        device: where SMCD's generator draws.
    """
    settings: dict[str, dict[str, Any]] = {
        "N": {},
        "G": {"lr": config.gd_lr, "steps": config.gd_steps, "window": config.gd_window},
        "S": {
            "num_particles": particles,
            "flip_prob": config.flip_prob,
            "noise_std": noise_std,
            "seed": seed,
            "device": str(device),
        },
    }
    if letter in settings:
        return build(TUNED[letter], settings[letter])
    raise ValueError(f"unknown adaptation {letter!r}; choose from {list(LETTERS)}")
