"""What the two-link experiments share: motor-babbling data, the M, R and T networks, and the oracle.

``smcd-rl two-link`` (Fig. 2) and ``smcd-rl telescoping`` (Fig. 8) both train a multi-task
dropout network M, a Reptile network R and a network T whose masks were trained to identify the
arm (:func:`smcd_rl.fit` with ``mask_training="task"``) on motor babbling of many two-link arms,
and compare them with an oracle particle filter over the link lengths. Their configs derive from
:class:`TwoLinkFamilyConfig`, which declares those settings once.

Example:
    >>> from smcd_rl.experiments.shared.two_link_family import TwoLinkFamilyConfig, network
    >>> network(TwoLinkFamilyConfig(hidden=8, depth=2), "cpu").mask_dim
    16
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.baselines import OracleModel
from smcd_rl.envs.two_link_arm import motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.task_family import task_mask_settings
from smcd_rl.experiments.shared.two_link_family_config import TwoLinkFamilyConfig

__all__ = [
    "TwoLinkFamilyConfig",
    "TUNING_ARMS_SEED",
    "babbling_data",
    "tuning_episodes",
    "network",
    "fit_settings",
    "train_reptile",
    "task_model",
    "task_fit_settings",
    "reptile_model",
    "reptile_settings",
    "oracle",
]

#: Offset of the tuning arms' seed from ``--seed`` (a stream of their own, disjoint from training and test).
TUNING_ARMS_SEED = 2_000_003


def babbling_data(config: TwoLinkFamilyConfig, ex: Experiment) -> TensorDictBase:
    """Motor babbling of ``config.tasks`` arms (batch ``[tasks, episodes, steps]``), from the run's generator."""
    data = motor_babbling(
        config.tasks, config.episodes, config.steps, measurement_noise=config.measurement_noise, generator=ex.generator
    )
    return data.to(ex.device)


def tuning_episodes(config: TwoLinkFamilyConfig, device: torch.device | str, *, steps: int) -> TensorDictBase:
    """The fair protocol's held-out episodes: babbling of ``tuning_episodes`` fresh training-distribution arms.

    One episode of ``steps`` steps per arm, batch ``[E, steps]``, drawn exactly as the training
    data is but from a generator of its own (seed ``config.seed + TUNING_ARMS_SEED``), so neither
    the training arms nor the test arms are among them.
    """
    generator = torch.Generator().manual_seed(config.seed + TUNING_ARMS_SEED)
    data = motor_babbling(
        config.tuning_episodes, 1, steps, measurement_noise=config.measurement_noise, generator=generator
    )
    return data.reshape(config.tuning_episodes, steps).select("q", "ee").to(device)


def network(
    config: TwoLinkFamilyConfig, device: torch.device | str, *, mask_groups: int | None = None
) -> smcd_rl.MaskedMLP:
    """An untrained ``q (2) -> ee (2)`` dropout network of the config's width and depth (``mask_groups``: T's bits)."""
    hidden = (config.hidden,) * config.depth
    return smcd_rl.MaskedMLP(2, 2, hidden=hidden, dropout=config.dropout, mask_groups=mask_groups, device=device)


def fit_settings(config: TwoLinkFamilyConfig) -> dict[str, Any]:
    """The :func:`smcd_rl.fit` settings of the M network."""
    return {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}


def reptile_model(config: TwoLinkFamilyConfig, device: torch.device | str, *, init_seed: int) -> smcd_rl.AdaptiveModel:
    """The untrained R network: initial weights from ``init_seed``, the global RNG left as it was.

    So adding or dropping R methods changes nothing for the others.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(init_seed)
        return smcd_rl.AdaptiveModel(network(config, device), in_keys=["q"], out_key="ee")


def task_model(config: TwoLinkFamilyConfig, device: torch.device | str, *, init_seed: int) -> smcd_rl.AdaptiveModel:
    """The untrained T network: M's architecture with ``config.mask_groups`` bits per layer, from ``init_seed``.

    The global RNG is left as it was, so adding or dropping T methods changes nothing for the others.

    Example:
        >>> task_model(TwoLinkFamilyConfig(hidden=32, mask_groups=4), "cpu", init_seed=0).net.mask_dim
        8
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(init_seed)
        net = network(config, device, mask_groups=config.mask_groups or None)
        return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")


def task_fit_settings(config: TwoLinkFamilyConfig) -> dict[str, Any]:
    """The :func:`smcd_rl.fit` settings of the T network: M's, with masks tied to the arm (the data's ``"task"``)."""
    return {**fit_settings(config), **task_mask_settings(config)}


def reptile_settings(config: TwoLinkFamilyConfig) -> dict[str, Any]:
    """The :func:`smcd_rl.fit_reptile` settings of the R network (it samples by task: the data's first dim is the arm)."""
    return {
        "epochs": config.reptile_epochs,
        "batch_size": config.reptile_batch_size,
        "lr": config.reptile_lr,
        "inner_lr": config.reptile_inner_lr,
        "inner_epochs": config.reptile_inner_epochs,
        "tasks_per_batch": config.reptile_tasks_per_batch,
        "seed": config.seed,
    }


def train_reptile(
    ex: Experiment, config: TwoLinkFamilyConfig, data: TensorDictBase, *, init_seed: int
) -> tuple[smcd_rl.AdaptiveModel, list[float]]:
    """The R network trained (or resumed) by :func:`smcd_rl.fit_reptile`; its losses."""
    model = reptile_model(config, ex.device, init_seed=init_seed)
    return model, ex.train("reptile", smcd_rl.fit_reptile, model, data, **reptile_settings(config))


def oracle(config: TwoLinkFamilyConfig, device: torch.device | str) -> OracleModel:
    """O+P: a particle filter over the link lengths that knows the two-link kinematics.

    The lengths follow a random walk (``oracle_jitter`` per step), the filter's usual model of
    slowly changing parameters; it does not know that a link may telescope.
    """
    return OracleModel(
        lambda lengths, q: two_link_fk(q, lengths),
        lambda shape, g: sample_link_lengths(shape, generator=g, device=g.device),
        in_keys=["q"],
        out_key="ee",
        noise_std=config.noise_std,
        num_particles=config.oracle_particles,
        jitter_std=config.oracle_jitter,
        lower=0.1,
        generator=torch.Generator(device=device).manual_seed(config.seed + 7),
    )
