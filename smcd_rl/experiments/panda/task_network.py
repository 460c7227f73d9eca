"""T for ``smcd-rl panda``: a network whose dropout masks were trained to identify the tool.

M trains on samples that each carry a tool of their own, so no mask can stand for a tool. T
trains on as many samples in ``--task-tools`` groups, each group one tool (the joint angles
uniform within the limits, as M's), every epoch after the first through a mask of its tool's
filter posterior (:func:`smcd_rl.fit` with ``mask_training="task"``; the concepts page "Mask
training"), with ``--mask-groups`` bits per layer. Its data come from a generator of their own,
so M's data, training and results are the same with or without T.

Example:
    >>> from smcd_rl.experiments.panda.config import PandaConfig
    >>> data = task_data(PandaConfig(samples=40, task_tools=4))
    >>> data["task"].unique().tolist(), bool((data["tool_length"][:10] == data["tool_length"][0]).all())
    ([0, 1, 2, 3], True)
    >>> task_network(PandaConfig(hidden=32, depth=2), "cpu").net.mask_dim  # 16 bits in each of 2 layers
    32
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.envs.panda_reach import panda_fk, panda_kinematics_data

if TYPE_CHECKING:
    from smcd_rl.experiments.panda.config import PandaConfig

__all__ = ["TASK_DATA_SEED", "task_data", "task_network"]

#: Offset of T's data seed from ``--seed`` (a stream of its own: M's data and the test tasks are untouched).
TASK_DATA_SEED = 7919


def task_data(config: PandaConfig) -> TensorDict:
    """``--samples`` samples in ``--task-tools`` equal groups of one tool each; ``"task"`` numbers the tool."""
    generator = torch.Generator().manual_seed(config.seed + TASK_DATA_SEED)
    data = panda_kinematics_data(config.samples, tool_range=config.tool_range, generator=generator)
    task = torch.arange(config.samples) * config.task_tools // config.samples  # equal groups, in order
    tools = (torch.rand(config.task_tools, generator=generator) * 2 - 1) * config.tool_range
    data["tool_length"] = tools[task].to(data["tool_length"].dtype)
    data["ee"] = panda_fk(data["q"], data["tool_length"])
    data["task"] = task
    return data


def task_network(config: PandaConfig, device: torch.device | str) -> smcd_rl.AdaptiveModel:
    """The untrained T network: M's architecture with ``--mask-groups`` bits per layer, from a seed of its own."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed + TASK_DATA_SEED)
        net = smcd_rl.MaskedMLP(
            7,
            3,
            hidden=(config.hidden,) * config.depth,
            dropout=config.dropout,
            mask_groups=config.mask_groups or None,
            device=device,
        )
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
