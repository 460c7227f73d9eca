"""Each family's task-mask network T as its experiment trains it, with that experiment's held-out episodes.

A :class:`Family` holds what ``smcd-rl task-masks`` varies and what it keeps: T's training data
(with each sample's ``"task"``), its trainer and settings (the experiment's epochs, batch, rate
and seed), an untrained T of any mask groups, and twice the experiment's tuning episodes, drawn
as its fair protocol draws them: fresh tasks of the *training* distribution, never its test
tasks. SMCD is calibrated on the first half by the criterion the experiment tunes by, and the
grid points are scored on the second half by the same criterion.

Example:
    >>> family = load("panda", seed=0, device="cpu", generator=torch.Generator().manual_seed(0))
    >>> family.experiment, family.criterion, family.current
    ('panda', 'one-step', (1.0, 16))
    >>> family.build(8).net.mask_dim  # 8 bits in each of 3 hidden layers
    24
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.experiments.shared.task_family import task_mask_settings
from smcd_rl.experiments.task_masks.config import experiment_config

__all__ = ["Family", "load"]


@dataclass
class Family:
    """One family's T: how to build and train it, and the held-out episodes it is scored on."""

    #: The command whose T network this is.
    experiment: str
    #: What one task of the family is (what T's masks are trained to identify).
    task: str
    #: The experiment's own (share, groups): the grid's reference point.
    current: tuple[float, int]
    #: Width of T's hidden layers (mask groups must divide it).
    width: int
    #: SMCD's particles in the experiment.
    particles: int
    #: Flip probabilities the experiment's calibration tries.
    flips: tuple[float, ...]
    #: What the experiment tunes by: ``"one-step"`` or ``"lookahead"`` (``horizon`` steps ahead).
    criterion: str
    horizon: int | None
    #: T's training data, with each sample's ``"task"``.
    data: TensorDictBase
    #: ``2 x`` the experiment's tuning episodes ``[E, T]``: calibrate on the first half, score on the second.
    episodes: TensorDictBase
    #: ``groups -> untrained T`` (the experiment's architecture and initial-weight seed).
    build: Callable[[int], smcd_rl.AdaptiveModel]
    #: ``smcd_rl.fit`` or ``smcd_rl.fit_dynamics``.
    trainer: Callable[..., Any]
    #: The trainer's settings but the share.
    settings: dict[str, Any]

    def fit_settings(self, share: float) -> dict[str, Any]:
        """The trainer's settings with masks tied to the task, ``share`` of the samples through them."""
        return {**self.settings, **task_mask_settings(SimpleNamespace(task_share=share))}


def _family(config: Any, **fields: Any) -> Family:
    """A :class:`Family` with what every experiment's config holds (its T setting, width, particles, flips
    and fit settings) and the one-step criterion; ``fields`` give the rest and may replace any of these."""
    common = {
        "criterion": "one-step",
        "horizon": None,
        "current": (config.task_share, config.mask_groups),
        "width": config.hidden,
        "particles": config.particles,
        "flips": config.calibrate_flips,
        "settings": {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed},
    }
    return Family(**{**common, **fields})


def load(name: str, *, seed: int, device: torch.device | str, generator: torch.Generator) -> Family:
    """The family ``name`` of :data:`~smcd_rl.experiments.task_masks.config.FAMILIES` at its experiment's defaults."""
    return _LOADERS[name](experiment_config(name, seed), torch.device(device), generator)


def _pendulum(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.experiments.regimes import families as regimes

    data = regimes.training_data("pendulum", config, generator).to(device)
    _, trainer, task_data, settings = regimes.other_network("pendulum-task", config, data, device)
    settings = {k: v for k, v in settings.items() if k not in ("mask_training", "task_share", "group_masks")}
    doubled = dataclasses.replace(config, tuning_episodes=2 * config.tuning_episodes)

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return regimes.other_network("pendulum-task", dataclasses.replace(config, mask_groups=groups), data, device)[0]

    return _family(
        config,
        experiment="regimes",
        task="pendulum (mass and length)",
        data=task_data,
        episodes=regimes.tuning_episodes("pendulum", doubled).to(device),
        build=build,
        trainer=trainer,
        settings=settings,
    )


def _telescoping(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.envs.two_link_arm import motor_babbling
    from smcd_rl.experiments.shared import two_link_family as arms
    from smcd_rl.experiments.telescoping.run import TUNING_STEPS

    data = motor_babbling(
        config.tasks, config.episodes, config.steps, measurement_noise=config.measurement_noise, generator=generator
    ).to(device)
    doubled = dataclasses.replace(config, tuning_episodes=2 * config.tuning_episodes)

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return arms.task_model(dataclasses.replace(config, mask_groups=groups), device, init_seed=config.seed + 29)

    return _family(
        config,
        experiment="telescoping",
        task="two-link arm (link lengths)",
        data=data,
        episodes=arms.tuning_episodes(doubled, device, steps=TUNING_STEPS),
        build=build,
        trainer=smcd_rl.fit,
        settings=arms.fit_settings(config),
    )


def _fetch(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.experiments.fetch.episodes import collect, tuning_episodes
    from smcd_rl.experiments.fetch.run import TUNING_SEED
    from smcd_rl.experiments.fetch.task_network import task_network

    family = config.families[0]
    data = collect(family, config, progress=False)["data"]
    n_val = max(1, int(round(config.validation * data.shape[0])))  # T trains on M's share, as in the experiment
    train = data[:-n_val].to(device)
    obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
    doubled = dataclasses.replace(config, tuning_episodes=2 * config.tuning_episodes)

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return task_network(dataclasses.replace(config, mask_groups=groups), obs_dim, action_dim, device)

    return _family(
        config,
        experiment="fetch",
        task=f"{family} draw (rotation and gain)",
        criterion="lookahead",
        horizon=config.tuning_horizon,
        data=train,
        episodes=tuning_episodes(family, doubled, seed=config.seed + TUNING_SEED).to(device),
        build=build,
        trainer=smcd_rl.fit_dynamics,
    )


def _panda(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.experiments.panda.reaching import tuning_episodes
    from smcd_rl.experiments.panda.task_network import task_data, task_network

    doubled = dataclasses.replace(config, tuning_episodes=2 * config.tuning_episodes)

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return task_network(dataclasses.replace(config, mask_groups=groups), device)

    return _family(
        config,
        experiment="panda",
        task="tool length",
        data=task_data(config).to(device),
        episodes=tuning_episodes(doubled, device),
        build=build,
        trainer=smcd_rl.fit,
    )


def _drone(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.experiments.interpret import drone, lookahead

    data, split = drone.load(config)
    doubled = dataclasses.replace(config, tuning_episodes=2 * config.tuning_episodes)
    flights, fit_ids = lookahead.tuning_flights(doubled, data, split)
    fitted = data.select(split["train"]) if fit_ids is None else data.select(fit_ids)

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return drone.make_model(config, fitted, device, mask_groups=groups)

    return _family(
        config,
        experiment="interpret",
        task="drone operator",
        criterion="lookahead",
        horizon=config.tuning_horizon,
        data=drone.steps(fitted, device),
        episodes=lookahead.tuning_episodes(flights, doubled, device),
        build=build,
        trainer=smcd_rl.fit,
    )


def _ant(config: Any, device: torch.device, generator: torch.Generator) -> Family:
    from smcd_rl.experiments.ant.config import TASKS
    from smcd_rl.experiments.ant.prediction import random_episodes
    from smcd_rl.experiments.ant.run import TUNING_SEED
    from smcd_rl.experiments.ant.task_network import (
        TASK_TUNING_SEED,
        task_data,
        task_network,
        task_tuning_episodes,
    )

    # Each half holds healthy and crippled episodes: the first is T's own tuning episodes in the experiment.
    n, steps, task_env = config.tuning_episodes, config.tuning_steps, TASKS[config.task][0]
    healthy, _ = random_episodes(task_env, None, count=n + n // 2, steps=steps, seed=config.seed + TUNING_SEED)
    crippled, _ = random_episodes(
        task_env, config.crippled_legs, count=n - n // 2, steps=steps, seed=config.seed + TASK_TUNING_SEED + n
    )
    episodes = torch.cat([task_tuning_episodes(healthy[:n], config), healthy[n:], crippled.to(healthy.device)])

    def build(groups: int) -> smcd_rl.AdaptiveModel:
        return task_network(dataclasses.replace(config, mask_groups=groups), device)

    return _family(
        config,
        experiment="ant",
        task="Ant leg (healthy or one crippled)",
        data=task_data(config).to(device),
        episodes=episodes.to(device),
        build=build,
        trainer=smcd_rl.fit_dynamics,
    )


_LOADERS: dict[str, Callable[[Any, torch.device, torch.Generator], Family]] = {
    "pendulum": _pendulum,
    "telescoping": _telescoping,
    "fetch": _fetch,
    "panda": _panda,
    "drone": _drone,
    "ant": _ant,
}
