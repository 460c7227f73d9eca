"""T for ``smcd-rl fetch``: a second dynamics network whose dropout masks were trained to identify the draw.

Trained like the multi-task network M on the same transitions, except that every epoch after
the first infers each draw's mask posterior with the filter and trains ``--task-share`` of the
samples through a mask of their draw's posterior (:func:`smcd_rl.fit` with
``mask_training="task"``; the concepts page "Mask training"), with ``--mask-groups`` bits per
layer. Its methods are named ``T+<adaptation>`` (``--task-adaptations``).

Example:
    >>> from smcd_rl.experiments.fetch.config import FetchConfig
    >>> task_network(FetchConfig(hidden=32), 10, 4, "cpu").net.mask_dim  # 16 bits in each of 2 layers
    32
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

import smcd_rl

if TYPE_CHECKING:
    from smcd_rl.experiments.fetch.config import FetchConfig

__all__ = ["task_network", "task_method"]


def task_network(
    config: FetchConfig, obs_dim: int, action_dim: int, device: torch.device | str
) -> smcd_rl.AdaptiveDynamicsModel:
    """The untrained T network: M's architecture with ``--mask-groups`` bits per layer, from M's seed."""
    torch.manual_seed(config.seed)
    net = smcd_rl.MaskedMLP(
        obs_dim + action_dim,
        obs_dim,
        hidden=(config.hidden,) * config.depth,
        dropout=config.dropout,
        mask_groups=config.mask_groups or None,
        device=device,
    )
    return smcd_rl.AdaptiveDynamicsModel(net)


def task_method(variant: str) -> str:
    """The method label of T with ``variant``: ``T+S``."""
    return f"T+{variant}"
