"""T for ``smcd-rl ant``: a dynamics network whose dropout masks were trained to identify the leg.

M trains on the healthy Ant only, so the crippled Ant is a condition it never saw: the
experiment asks how far adaptation carries a model to it. T asks what the task-mask network is
for. It trains on as many random-action transitions as M, in equal shares from the healthy Ant
and from each leg of ``--crippled-legs`` crippled (the condition is each sample's ``"task"``),
every epoch after the first through a mask of its condition's filter posterior
(:func:`smcd_rl.fit` with ``mask_training="task"``, ``--task-share``, ``--mask-groups``): can
SMCD tell from a few steps which leg is crippled? Its methods are tuned on held-out episodes of
its own training distribution (half healthy, half crippled, seeds of their own, neither its
data nor a test episode) and scored on the same prediction episodes as M's. The crippled Ant is
a training condition of T and not of M, so T+S is paired with T+G and T+N (the same network and
data) for what the filter adds, and with M's rows for what training on the legs buys.

Example:
    >>> from smcd_rl.experiments.ant.config import AntConfig
    >>> conditions(AntConfig(crippled_legs=(0, 2)))
    [None, 0, 2]
    >>> task_network(AntConfig(hidden=40, mask_groups=8), "cpu").net.mask_dim  # 8 bits in each of 2 layers
    16
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.experiments.ant.config import TASKS
from smcd_rl.experiments.ant.episodes import ACTION_DIM, OBS_DIM
from smcd_rl.experiments.ant.prediction import random_episodes

if TYPE_CHECKING:
    from smcd_rl.experiments.ant.config import AntConfig

__all__ = ["TASK_DATA_SEED", "TASK_TUNING_SEED", "conditions", "task_data", "task_network", "task_tuning_episodes"]

#: Offsets of T's env seeds from ``--seed``: its data (a stream per condition) and its crippled tuning episodes.
TASK_DATA_SEED, TASK_TUNING_SEED = 4_000_003, 5_000_003


def conditions(config: AntConfig) -> list[int | None]:
    """T's training conditions, in task order: the healthy Ant (``None``), then each crippled leg."""
    return [None, *config.crippled_legs]


def task_data(config: AntConfig) -> TensorDict:
    """``--transitions`` random-action transitions in equal shares per condition; ``"task"`` numbers the condition.

    Each condition's episodes of ``--data-episode-steps`` steps come from env seeds of their own
    (``--seed + TASK_DATA_SEED + 100000 c + k``), so neither M's data nor any test episode is among them.
    """
    task_env = TASKS[config.task][0]
    chunks = []
    per_condition = max(1, config.transitions // (len(conditions(config)) * config.data_episode_steps))
    for c, leg in enumerate(conditions(config)):
        episodes, _ = random_episodes(
            task_env,
            None if leg is None else (leg,),
            count=per_condition,
            steps=config.data_episode_steps,
            seed=config.seed + TASK_DATA_SEED + 100_000 * c,
        )
        flat = episodes.reshape(-1)
        flat["task"] = torch.full((flat.shape[0],), c, dtype=torch.int64)
        chunks.append(flat)
    return torch.cat(chunks)


def task_tuning_episodes(healthy: TensorDict, config: AntConfig) -> TensorDict:
    """T's tuning episodes: the first half of M's (healthy) and as many crippled ones, from seeds of their own."""
    half = config.tuning_episodes // 2
    crippled, _ = random_episodes(
        TASKS[config.task][0],
        config.crippled_legs,
        count=config.tuning_episodes - half,
        steps=config.tuning_steps,
        seed=config.seed + TASK_TUNING_SEED,
    )
    return torch.cat([healthy[:half], crippled.to(healthy.device)])


def task_network(config: AntConfig, device: torch.device | str) -> smcd_rl.AdaptiveDynamicsModel:
    """The untrained T network: M's architecture with ``--mask-groups`` bits per layer, from a seed of its own."""
    with torch.random.fork_rng(devices=[]):  # M's initial weights and the global RNG are untouched
        torch.manual_seed(config.seed + TASK_DATA_SEED)
        net = smcd_rl.MaskedMLP(
            OBS_DIM + ACTION_DIM,
            OBS_DIM,
            hidden=(config.hidden,) * config.depth,
            dropout=config.dropout,
            mask_groups=config.mask_groups or None,
            device=device,
        )
    return smcd_rl.AdaptiveDynamicsModel(net)
