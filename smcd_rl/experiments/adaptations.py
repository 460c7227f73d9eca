"""The adaptation strategies the experiments compare, built in one place from a config's settings.

Every experiment names its methods by the paper's letters: ``N`` (no adaptation), ``G`` (online
gradient descent) and ``S`` (SMCD). :class:`AdaptationConfig` declares their settings once, and
:func:`make_adaptation` builds the strategy for a letter (from one :class:`StrategySettings`), so every
experiment adapts the same way.

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
from typing import ClassVar, Protocol

import torch

import smcd_rl
from smcd_rl.experiments.harness import ExperimentConfig, setting

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


@dataclass
class TuningConfig(ExperimentConfig):
    """The settings of the fair protocol (:mod:`smcd_rl.experiments.tuning`), shared by every experiment that adapts.

    The calibrated SMCD (``S``) and gradient descent (``G``) are tuned on ``tuning_episodes``
    held-out training-task episodes, GD over the grid ``gd_lr x gd_steps x gd_window``. An
    experiment redeclares ``tuning_episodes`` to say what its episodes are.
    """

    tuning_episodes: int = setting(
        32, "held-out episodes of fresh training-distribution tasks that SMCD and GD are tuned on", low=2
    )
    gd_lr: tuple[float, ...] = setting(
        (0.003, 0.01, 0.03, 0.1), "gradient-descent learning rates tried in tuning (normalised units)", above=0.0
    )
    gd_steps: tuple[int, ...] = setting((1, 5), "gradient steps per observation tried in tuning", low=1)
    gd_window: tuple[int, ...] = setting((5, 10), "recent transitions in the gradient-descent loss tried", low=1)
    calibrate_flips: tuple[float, ...] = setting(
        (0.001, 0.003, 0.01, 0.03), "flip probabilities SMCD's calibration tries", low=0.0, high=1.0
    )

    NON_EMPTY: ClassVar[tuple[str, ...]] = ("gd_lr", "gd_steps", "gd_window", "calibrate_flips")


@dataclass
class AdaptationConfig(TuningConfig):
    """The settings of SMCD and of online gradient descent, shared by every experiment that adapts.

    SMCD's ``noise_std`` and ``flip_prob`` are the paper's fixed settings (variant ``S(paper)``); the
    tuned variants' settings come from :class:`TuningConfig`'s fields.
    """

    particles: int = setting(1000, "SMCD mask particles", low=1)
    flip_prob: float = setting(0.01, "bit-flip probability per step of SMCD at the paper's settings", low=0.0, high=1.0)
    noise_std: float = setting(
        0.05, "likelihood noise std of SMCD at the paper's settings (observation units)", above=0.0
    )


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
    if letter == "N":
        return smcd_rl.NoAdaptation()
    if letter == "G":
        return smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window)
    if letter == "S":
        return smcd_rl.SMCD(
            num_particles=particles,
            flip_prob=config.flip_prob,
            noise_std=noise_std,
            generator=torch.Generator(device=device).manual_seed(seed),
        )
    raise ValueError(f"unknown adaptation {letter!r}; choose from {list(LETTERS)}")
