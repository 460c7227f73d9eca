"""Fitting from a torchrl replay buffer, and the whole model-based RL recipe: collect, fit, plan, adapt."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.modules import CEMPlanner, MPPIPlanner

from smcd_rl.integrations.torchrl.envs import AdaptiveWorldModelEnv
from smcd_rl.integrations.torchrl.modules import RewardFn, RewardToGo, TerminationFn
from smcd_rl.integrations.torchrl.transforms import AdaptationTransform
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel
from smcd_rl.training import fit

__all__ = ["fit_from_replay_buffer", "mbrl_loop"]


def fit_from_replay_buffer(
    model: AdaptiveModel,
    buffer: ReplayBuffer,
    *,
    epochs: int = 100,
    batch_size: int = 64,
    lr: float = 1e-4,
    num_samples: int | None = None,
    weight_decay: float = 0.0,
    seed: int = 0,
    progress: bool = False,
    callback: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Fit ``model`` with :func:`smcd_rl.fit` on the transitions of a torchrl ``ReplayBuffer``.

    Args:
        model: the model to train; the buffer must hold its keys (for a dynamics model
            ``observation``, ``action`` and ``("next", "observation")``, as a torchrl collector writes).
        buffer: the replay buffer, e.g. filled with ``buffer.extend(batch)`` from a torchrl ``Collector``.
        epochs: passes over the data.
        batch_size: transitions per gradient step.
        lr: Adam learning rate.
        num_samples: train on ``buffer.sample(num_samples)`` (the buffer's own sampler) instead
            of every stored transition.
        weight_decay: Adam weight decay.
        seed: seed of shuffling and dropout masks.
        progress: show a progress bar.
        callback: called as ``callback(epoch, mean_loss)`` after each epoch.

    Returns:
        The mean training loss of every epoch.

    Raises:
        ValueError: the buffer is empty.
        KeyError: the buffer lacks a key the model needs.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> from smcd_rl.integrations.torchrl import fit_from_replay_buffer
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(1000))
        >>> obs, act = torch.randn(64, 3), torch.randn(64, 1)
        >>> _ = buffer.extend(TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + act}, [64]))
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4, 3, hidden=(32,)))
        >>> len(fit_from_replay_buffer(model, buffer, epochs=2, batch_size=16, lr=1e-3))
        2
    """
    if len(buffer) == 0:
        raise ValueError("the replay buffer is empty; extend it with collected transitions before fitting")
    data = buffer.sample(num_samples) if num_samples is not None else buffer[: len(buffer)]
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"the replay buffer must store TensorDicts, got {type(data).__name__}")
    keys = [*model.in_keys, model.target_key]
    missing = [key for key in keys if key not in data.keys(True, True)]
    if missing:
        raise KeyError(f"the replay buffer has no {missing} that the model needs; it has {list(data.keys(True, True))}")
    return fit(
        model,
        data.select(*keys).reshape(-1),
        epochs=epochs,
        batch_size=batch_size,
        lr=lr,
        weight_decay=weight_decay,
        seed=seed,
        progress=progress,
        callback=callback,
    )


def mbrl_loop(
    env: EnvBase,
    model: AdaptiveDynamicsModel,
    reward_fn: RewardFn,
    *,
    termination_fn: TerminationFn | None = None,
    iterations: int = 10,
    initial_frames: int = 1000,
    episode_steps: int = 200,
    fit_epochs: int = 20,
    fit_batch_size: int = 64,
    lr: float = 1e-3,
    planner: Literal["cem", "mppi"] = "cem",
    planning_horizon: int = 15,
    optim_steps: int = 5,
    num_candidates: int = 200,
    top_k: int = 20,
    temperature: float = 1.0,
    gamma: float = 1.0,
    buffer_size: int = 100_000,
    seed: int = 0,
) -> list[float]:
    """Model-based RL with an adaptive model: collect, fit, plan, adapt.

    1. A torchrl ``Collector`` with random actions fills a ``ReplayBuffer`` with ``initial_frames``.
    2. Each iteration fits the model on the whole buffer (:func:`fit_from_replay_buffer`), then runs
       one episode of up to ``episode_steps`` on ``TransformedEnv(env, AdaptationTransform(model))``
       with torchrl's ``CEMPlanner`` or ``MPPIPlanner`` (with :class:`RewardToGo`) on an
       :class:`AdaptiveWorldModelEnv`: the model adapts on every real step and the next plan uses
       it. The episode's transitions join the buffer.

    Args:
        env: the real env, a torchrl env of batch size ``()`` (e.g. ``GymEnv``); it is not closed.
        model: the dynamics model, trained further in place.
        reward_fn: pure batched reward of the planners (see :data:`RewardFn`).
        termination_fn: pure batched termination of the planners (see :data:`TerminationFn`).
        iterations: fit-plan-adapt rounds.
        initial_frames: random transitions collected first.
        episode_steps: most steps of each planned episode.
        fit_epochs: epochs of each fit.
        fit_batch_size: batch size of each fit.
        lr: learning rate of each fit.
        planner: ``"cem"`` or ``"mppi"``.
        planning_horizon: steps each plan looks ahead.
        optim_steps: planner iterations per action.
        num_candidates: action sequences per planner iteration.
        top_k: elite sequences per planner iteration.
        temperature: MPPI temperature.
        gamma: MPPI discount of the reward-to-go.
        buffer_size: replay buffer capacity.
        seed: seeds torch, the env and the collector.

    Returns:
        The real return (sum of the env's rewards) of each iteration's planned episode.

    Example:
        >>> import torch, smcd_rl
        >>> from torchrl.envs import GymEnv
        >>> from smcd_rl.integrations.torchrl import mbrl_loop
        >>> def reward(obs, action, next_obs):  # Pendulum-v1: upright and still
        ...     angle = torch.atan2(obs[..., 1], obs[..., 0])
        ...     return -(angle**2 + 0.1 * obs[..., 2] ** 2 + 0.001 * action[..., 0] ** 2)
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4, 3, hidden=(32,)), smcd_rl.SMCD(num_particles=10))
        >>> returns = mbrl_loop(GymEnv("Pendulum-v1"), model, reward, iterations=1, initial_frames=50, episode_steps=3,
        ...                     fit_epochs=1, planning_horizon=3, optim_steps=2, num_candidates=10, top_k=3)
        >>> len(returns)
        1
    """
    if env.batch_size != ():
        raise ValueError(f"mbrl_loop needs an env of batch size (), got {tuple(env.batch_size)}")
    if planner not in ("cem", "mppi"):
        raise ValueError(f"planner must be 'cem' or 'mppi', got {planner!r}")
    torch.manual_seed(seed)
    env.set_seed(seed)
    keys = [*model.in_keys, model.target_key]
    buffer = ReplayBuffer(storage=LazyTensorStorage(buffer_size))

    # total_frames=-1 (endless) and one batch: a Collector that reaches total_frames closes the env.
    collector = Collector(env, None, frames_per_batch=initial_frames, total_frames=-1)
    buffer.extend(next(iter(collector)).select(*keys).reshape(-1))
    collector.shutdown(close_env=False)

    world = AdaptiveWorldModelEnv.from_env(model, env, reward_fn, termination_fn=termination_fn)
    policy: TensorDictModuleBase
    if planner == "cem":
        policy = CEMPlanner(world, planning_horizon, optim_steps, num_candidates, top_k)
    else:
        policy = MPPIPlanner(
            world, RewardToGo(gamma), temperature, planning_horizon, optim_steps, num_candidates, top_k
        )
    adaptive_env = TransformedEnv(env, AdaptationTransform(model))

    returns: list[float] = []
    for iteration in range(iterations):
        fit_from_replay_buffer(
            model, buffer, epochs=fit_epochs, batch_size=fit_batch_size, lr=lr, seed=seed + iteration
        )
        with torch.no_grad():  # not inference_mode: the episode's tensors go into the replay buffer
            episode = adaptive_env.rollout(episode_steps, policy, break_when_any_done=True)
        returns.append(float(episode["next", "reward"].sum()))
        buffer.extend(episode.select(*keys).reshape(-1))
    return returns
