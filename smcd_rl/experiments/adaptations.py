"""The adaptation strategies the experiments compare, built in one place from a config's settings.

Every experiment names its methods by the paper's letters: ``N`` (no adaptation), ``G`` (online
gradient descent) and ``S`` (SMCD). :class:`AdaptationConfig` declares their settings once, and
:func:`make_adaptation` builds the strategy for a letter, so every experiment adapts the same way.

Example:
    >>> config = AdaptationConfig(particles=50)
    >>> make_adaptation("S", config, particles=config.particles, noise_std=config.noise_std, seed=0)
    SMCD(num_particles=50, flip_prob=0.01, noise_std=0.05, ...)
    >>> make_adaptation("G", config, particles=config.particles, noise_std=config.noise_std, seed=0).lr
    0.01
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch

import smcd_rl
from smcd_rl.experiments.harness import ExperimentConfig, setting

__all__ = ["AdaptationConfig", "AdaptationSettings", "make_adaptation", "LETTERS"]

#: The paper's letters for the strategies: none, gradient descent, SMCD.
LETTERS = ("N", "G", "S")


class AdaptationSettings(Protocol):
    """What :func:`make_adaptation` reads from a config (an :class:`AdaptationConfig` has it all)."""

    @property
    def flip_prob(self) -> float: ...
    @property
    def gd_lr(self) -> float: ...
    @property
    def gd_steps(self) -> int: ...
    @property
    def gd_window(self) -> int: ...


@dataclass
class AdaptationConfig(ExperimentConfig):
    """The settings of SMCD and of online gradient descent, shared by every experiment that adapts."""

    particles: int = setting(1000, "SMCD mask particles", low=1)
    flip_prob: float = setting(0.01, "SMCD bit-flip probability per step", low=0.0, high=1.0)
    noise_std: float = setting(0.05, "SMCD likelihood noise std, in the observation's units", above=0.0)
    gd_lr: float = setting(0.01, "online gradient-descent learning rate (normalised units)", above=0.0)
    gd_steps: int = setting(5, "gradient steps per observation", low=1)
    gd_window: int = setting(10, "recent transitions in the gradient-descent loss", low=1)


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
