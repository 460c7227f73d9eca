"""The tracking loop of ``smcd-rl telescoping``: PD control of two-link arms whose second link telescopes.

:func:`sample_episodes` draws the arms, targets and measurement noise every method faces,
:func:`make_method` builds a method by its label (``true``, ``O+P``, ``M+N``, ``M+G``, ``M+S``,
``M+S(evidence)``, ``M+S(paper)``, ``M+C``, and the same on the Reptile model R), and :func:`track`
runs one method over all episodes at once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from torch import Tensor
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.pd import JacobianPD
from smcd_rl.baselines import OracleModel
from smcd_rl.envs.two_link_arm import two_link_fk
from smcd_rl.envs.two_link_telescoping import (
    circle_target,
    integrate_acceleration,
    sample_initial_state,
    telescoping_link_lengths,
)
from smcd_rl.experiments.shared.tuned_methods import method_variant, strategy_for
from smcd_rl.experiments.shared.tuning import Tuning
from smcd_rl.experiments.shared.two_link_family import oracle

if TYPE_CHECKING:
    from smcd_rl.experiments.telescoping.config import TelescopingConfig

__all__ = ["sample_episodes", "make_method", "track", "track_recorded"]


def sample_episodes(config: TelescopingConfig, device: torch.device) -> tuple[dict[str, Tensor], Tensor]:
    """The episodes every method faces (same arms, targets and measurement noise for all).

    Example:
        >>> from smcd_rl.experiments.telescoping.config import TelescopingConfig
        >>> episodes, noise = sample_episodes(TelescopingConfig(trials=3, horizon=5), torch.device("cpu"))
        >>> episodes["q"].shape, noise.shape
        (torch.Size([3, 2]), torch.Size([3, 5, 2]))
    """
    generator = torch.Generator().manual_seed(config.seed + 1_000_003)  # disjoint from training data
    episodes = sample_initial_state((config.trials,), generator=generator)
    noise = config.measurement_noise * torch.randn(config.trials, config.horizon, 2, generator=generator)
    return {key: value.to(device) for key, value in episodes.items()}, noise.to(device)


def make_method(
    name: str,
    models: Mapping[str, smcd_rl.AdaptiveModel],
    tunings: Mapping[str, Tuning],
    config: TelescopingConfig,
    device: torch.device,
) -> Any:
    """The method ``name``: ``None`` for the true kinematics, the oracle, or a model with its (tuned) adaptation."""
    if name == "true":
        return None
    if name == "O+P":
        return oracle(config, device)
    strategy = strategy_for(name, tunings, seed=config.seed + 11, device=device)
    return models[method_variant(name)[0]].with_adaptation(strategy)


def _kinematics(method: Any, k: int, l1: Tensor) -> Callable[[Tensor], Tensor]:
    """The method's current kinematics ``q [B, 2] -> ee [B, 2]``, differentiable in ``q``."""
    if method is None:
        lengths = telescoping_link_lengths(k, l1)
        return lambda q: two_link_fk(q, lengths)
    if isinstance(method, OracleModel):
        # The posterior predictive mean, as OracleModel.forward computes it, but on a plain tensor.
        particles, weights = method.filter.particles, method.filter.weights
        assert particles is not None, "the oracle observes before the controller asks for its kinematics"
        return lambda q: (weights.unsqueeze(-1) * two_link_fk(q.unsqueeze(-2), particles)).sum(-2)
    return method.predict


def track(
    name: str, method: Any, episodes: dict[str, Tensor], noise: Tensor, config: TelescopingConfig, *, progress: bool
) -> Tensor:
    """Distances end effector - target ``[trials, horizon + 1]`` (k = 0 is the start) of one method."""
    return track_recorded(name, method, episodes, noise, config, progress=progress, record=0)[0]


def track_recorded(
    name: str,
    method: Any,
    episodes: dict[str, Tensor],
    noise: Tensor,
    config: TelescopingConfig,
    *,
    progress: bool,
    record: int,
) -> tuple[Tensor, Tensor]:
    """:func:`track`, also keeping the joint angles of the first ``record`` episodes (for videos).

    Returns:
        The distances ``[trials, horizon + 1]`` (the very numbers of :func:`track`) and the joint
        angles ``[record, horizon + 1, 2]`` at every step ``k``.
    """
    l1, radius, start_angle = episodes["l1"], episodes["radius"], episodes["start_angle"]
    q = episodes["q"].clone()
    q_dot = torch.zeros_like(q)
    batch = q.shape[0]
    if method is not None:
        method.reset(batch_shape=(batch,))
    step_angle = config.angular_speed * config.dt
    errors = torch.empty(batch, config.horizon + 1)
    trajectory = []
    for k in tqdm(range(config.horizon + 1), desc=name, unit="step", disable=not progress):
        if record:  # (a copy to the CPU syncs a GPU: only when recording)
            trajectory.append(q[:record].cpu())
        ee_true = two_link_fk(q, telescoping_link_lengths(k, l1))
        target = circle_target(k, radius, start_angle, step_angle=step_angle)
        errors[:, k] = (ee_true - target).norm(dim=-1).cpu()
        if k == config.horizon:
            break
        ee = ee_true + noise[:, k]
        with torch.no_grad():
            if method is not None:
                method.observe(TensorDict({"q": q, "ee": ee}, [batch]))
        controller = JacobianPD(_kinematics(method, k, l1), k1=config.k1, k2=config.k2, damping=config.damping)
        position = ee if config.feedback == "measured" else None
        with torch.no_grad():
            u = controller(q, q_dot, target, position=position).clamp(-config.max_acceleration, config.max_acceleration)
        q, q_dot = integrate_acceleration(q, q_dot, u, config.dt)
    return errors, torch.stack(trajectory, dim=1) if record else torch.empty(0, config.horizon + 1, 2)
