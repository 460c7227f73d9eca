"""Model-predictive control with an adaptive dynamics model: couple a planner to a model and a reward.

The planners of :mod:`smcd_rl.agents.planners` optimise an objective over action sequences and
never see a model. :func:`model_reward_objective` builds that objective from an adaptive dynamics
model, a batched reward function and an optional termination function: it rolls the model forward
over the horizon for all candidates at once and sums the rewards. :class:`MPCAgent` calls the
planner on that objective at every step and returns the first action of the plan.

Who adapts the model: the agent only *reads* it. Feed real transitions to ``model.observe`` (or
wrap the env in :class:`smcd_rl.integrations.gymnasium.AdaptationWrapper`, which also calls
``model.reset()`` on every env reset); the agent plans with whatever the model has adapted to.

Goal-conditioned envs (Fetch and other ``Dict``-observation envs with ``compute_reward``):
:meth:`MPCAgent.from_goal_env` plans with the env's own batched reward
(:class:`smcd_rl.integrations.gymnasium.GoalReward`); :meth:`MPCAgent.act` then takes the env's
``Dict`` observation, rolls the model from its ``observation`` entry and holds its
``desired_goal`` fixed over the plan.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Literal

import gymnasium
import numpy as np
import torch
from torch import Tensor

from smcd_rl.agents.planners import Objective, Planner
from smcd_rl.integrations.gymnasium import GoalReward
from smcd_rl.model import AdaptiveDynamicsModel

__all__ = ["MPCAgent", "RewardFn", "TerminationFn", "Ensemble", "model_reward_objective"]

RewardFn = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``reward_fn(obs, action, next_obs) -> [*batch, P]``; inputs ``[*batch, P, obs | A | obs]``."""

TerminationFn = Callable[[Tensor], Tensor]
"""``termination_fn(next_obs)``: ``[*batch, P, obs]`` -> bool ``[*batch, P]``, True where the episode ends."""

Ensemble = Literal["mmse", "particles"]
"""How candidates are evaluated: with the adapted MMSE mask, or one mask particle per candidate."""

_ENSEMBLES = ("mmse", "particles")


def model_reward_objective(
    model: AdaptiveDynamicsModel,
    observation: Tensor,
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None = None,
    *,
    ensemble: Ensemble = "mmse",
) -> Objective:
    """The planning objective: predicted return of each action sequence from ``observation``.

    The returned function maps actions ``[*batch, P, H, A]`` to returns ``[*batch, P]``, where
    ``*batch`` is ``observation``'s batch shape. It rolls ``model`` forward ``H`` steps for all
    ``P`` candidates at once (:meth:`~smcd_rl.AdaptiveDynamicsModel.step` on a batch ``[*batch, P]``;
    a model reset with ``batch_shape=()`` broadcasts over ``*batch``, one reset with ``batch_shape=batch`` keeps one
    adaptation state per row) and sums ``reward_fn(obs, action, next_obs)``. After
    ``termination_fn(next_obs)`` is true a candidate earns nothing more; the reward of the
    terminating step itself counts, as in gymnasium. A candidate whose predicted state becomes
    NaN or infinite while still alive scores NaN, which the planners rank last.

    ``ensemble="mmse"`` predicts with the adapted (MMSE) mask, ``model.step(obs, action)``.
    ``ensemble="particles"`` gives candidate ``p`` the mask particle ``p % N`` of
    ``model.particles`` (read once, when the objective is built) for the whole horizon:
    trajectory sampling over the mask posterior. The particles are used as equally weighted,
    which they are after each resampling (``SMCD(ess_threshold=1.0)``, the default, resamples
    after every observation).

    Args:
        model: an adaptive dynamics model, already reset (and adapted, if you like).
        observation: the current observation ``[*batch, obs]``.
        reward_fn: batched reward, see :data:`RewardFn`.
        termination_fn: batched termination, see :data:`TerminationFn`; ``None``: never terminates.
        ensemble: ``"mmse"`` or ``"particles"``.

    Returns:
        The objective for :meth:`smcd_rl.agents.planners.Planner.plan`.

    Raises:
        ValueError: ``observation`` does not have the model's observation size, or (when the
            objective runs) the actions have the wrong size or ``reward_fn`` / ``termination_fn``
            return the wrong shape.

    Example:
        >>> import torch, smcd_rl
        >>> from smcd_rl.agents.mpc import model_reward_objective
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(2 + 1, 2, hidden=(16,)))
        >>> model.fitted = True  # a random stand-in for a trained network
        >>> model.reset()
        >>> objective = model_reward_objective(model, torch.zeros(2), lambda o, a, n: -n.square().sum(-1))
        >>> objective(torch.zeros(8, 5, 1)).shape  # 8 candidates, horizon 5
        torch.Size([8])
    """
    _check_dynamics_model(model)
    obs_dim, action_dim = model.observation_dim, model.action_dim
    if observation.shape[-1:] != (obs_dim,):
        raise ValueError(
            f"observation has shape {list(observation.shape)} but the model predicts observations of size "
            f"{obs_dim}; pass [*batch, {obs_dim}]"
        )
    if ensemble not in _ENSEMBLES:
        raise ValueError(f"ensemble must be one of {_ENSEMBLES}, got {ensemble!r}")
    param = next(model.net.parameters())
    observation = observation.to(device=param.device, dtype=param.dtype)
    batch = tuple(observation.shape[:-1])
    particles = model.particles if ensemble == "particles" else None  # [*M, N, D]

    def objective(actions: Tensor) -> Tensor:
        if actions.dim() != len(batch) + 3 or tuple(actions.shape[: len(batch)]) != batch:
            raise ValueError(
                f"actions must have shape [*batch, P, H, A] with batch {list(batch)}, got {list(actions.shape)}"
            )
        if actions.shape[-1] != action_dim:
            raise ValueError(f"actions have size {actions.shape[-1]} but the model takes actions of size {action_dim}")
        num, horizon = actions.shape[-3], actions.shape[-2]
        out_device, out_dtype = actions.device, actions.dtype
        actions = actions.to(device=param.device, dtype=param.dtype)
        mask = None
        if particles is not None:
            index = torch.arange(num, device=particles.device) % particles.shape[-2]
            mask = particles.index_select(-2, index)  # [*M, P, D]: candidate p gets particle p % N
        shape = (*batch, num)
        state = observation.unsqueeze(-2).expand(*shape, obs_dim)
        total = torch.zeros(shape, device=param.device, dtype=param.dtype)
        alive = torch.ones(shape, device=param.device, dtype=torch.bool)
        diverged = torch.zeros_like(alive)
        with torch.no_grad():
            for t in range(horizon):
                action = actions[..., t, :]
                next_state = model.step(state, action, mask=mask)
                finite = torch.isfinite(next_state).all(dim=-1)
                if not bool(finite.all()):
                    # Keep rolling the others; a diverged candidate is ranked last through NaN.
                    diverged |= alive & ~finite
                    next_state = torch.where(finite.unsqueeze(-1), next_state, torch.zeros_like(next_state))
                reward = reward_fn(state, action, next_state)
                if t == 0:  # the functions are pure: one check of their shapes is enough
                    _check_shape(reward, shape, "reward_fn(obs, action, next_obs)")
                if termination_fn is None:
                    total += reward
                else:
                    total += torch.where(alive, reward.to(total.dtype), torch.zeros_like(total))
                    done = termination_fn(next_state)
                    if t == 0:
                        _check_shape(done, shape, "termination_fn(next_obs)")
                    alive = alive & ~done.bool()
                state = next_state
        total = torch.where(diverged, torch.full_like(total, float("nan")), total)
        return total.to(device=out_device, dtype=out_dtype)

    return objective


class MPCAgent:
    """Model-predictive control through an adaptive dynamics model.

    At every :meth:`act` the planner optimises :func:`model_reward_objective` from the current
    observation (warm-started from the previous plan) and the first action is returned.

    The agent never changes the model: adapting it (``model.observe``) and starting a new
    adaptation episode (``model.reset()``) are the caller's job, or that of
    :class:`smcd_rl.integrations.gymnasium.AdaptationWrapper`, which does both on the env's
    ``step`` and ``reset``. :meth:`reset` only forgets the planner's warm start.

    Batches: a single observation ``[obs]`` gives an action ``[A]``; observations ``[B, obs]``
    (a vector env) give actions ``[B, A]``, planned as ``B`` independent problems. The model may
    be reset with ``batch_shape=()`` (one adaptation state shared by all rows) or
    ``batch_shape=(B,)`` (one per sub-env).

    Goal-conditioned envs: with a :class:`~smcd_rl.integrations.gymnasium.GoalReward` as
    ``reward_fn`` (what :meth:`from_goal_env` builds), :meth:`act` and :meth:`plan` take the
    env's ``Dict`` observation (single or batched; other entries, such as the wrapper's
    context, are ignored): the model rolls forward from its ``observation`` entry and every
    candidate is scored by the env's ``compute_reward`` towards its ``desired_goal``.

    Args:
        model: the adaptive dynamics model to plan with.
        planner: a :class:`~smcd_rl.agents.planners.Planner` whose action size is the model's.
        reward_fn: batched reward ``reward_fn(obs, action, next_obs) -> [*batch, P]``, or a
            :class:`~smcd_rl.integrations.gymnasium.GoalReward` (goal-conditioned).
        termination_fn: batched termination ``termination_fn(next_obs) -> bool [*batch, P]``.
        ensemble: ``"mmse"`` (default) evaluates every candidate with the adapted MMSE mask;
            ``"particles"`` gives candidate ``p`` the mask particle ``p % N`` (trajectory
            sampling over the mask posterior; needs :class:`smcd_rl.SMCD`).
        device: where the rollouts run; must be the model's device (the default).

    Raises:
        TypeError: ``model`` is not an :class:`smcd_rl.AdaptiveDynamicsModel`.
        ValueError: the planner's action size differs from the model's, ``ensemble`` is unknown,
            ``"particles"`` is asked of a strategy without particles, or a ``GoalReward``'s
            observation size is not the model's.

    Example:
        >>> import torch, smcd_rl
        >>> from smcd_rl.agents.mpc import MPCAgent
        >>> from smcd_rl.agents.planners import CEM
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(2 + 1, 2, hidden=(16,)),
        ...                                       adaptation=smcd_rl.SMCD(num_particles=10))
        >>> model.fitted = True  # a random stand-in for a trained network
        >>> model.reset()
        >>> planner = CEM(action_low=-1.0, action_high=1.0, horizon=5, num_candidates=20, num_elites=4)
        >>> agent = MPCAgent(model, planner, lambda o, a, n: -n[..., 0].abs(), ensemble="particles")
        >>> agent.act(torch.zeros(2)).shape, agent.act(torch.zeros(3, 2)).shape
        ((1,), (3, 1))
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        planner: Planner,
        reward_fn: RewardFn | GoalReward,
        termination_fn: TerminationFn | None = None,
        *,
        ensemble: Ensemble = "mmse",
        device: torch.device | str | None = None,
    ) -> None:
        _check_dynamics_model(model)
        obs_dim, action_dim = model.observation_dim, model.action_dim
        if not isinstance(planner, Planner):
            raise TypeError(f"planner must be a smcd_rl.agents.planners.Planner, got {type(planner).__name__}")
        if planner.action_dim != action_dim:
            raise ValueError(
                f"the planner plans actions of size {planner.action_dim} but the model takes actions of size "
                f"{action_dim} (network input {model.net.in_features} = observation {obs_dim} + action)"
            )
        if ensemble not in _ENSEMBLES:
            raise ValueError(f"ensemble must be one of {_ENSEMBLES}, got {ensemble!r}")
        if ensemble == "particles" and getattr(type(model.adaptation), "particles", None) is None:
            raise ValueError(
                f"ensemble='particles' needs a strategy with mask particles (smcd_rl.SMCD), but the model uses "
                f"{type(model.adaptation).__name__}; use ensemble='mmse'"
            )
        self.goal_reward = reward_fn if isinstance(reward_fn, GoalReward) else None
        if self.goal_reward is not None and self.goal_reward.observation_dim != obs_dim:
            raise ValueError(
                f"the env's {self.goal_reward.observation_key!r} has {self.goal_reward.observation_dim} values but "
                f"the model predicts observations of size {obs_dim}"
            )
        self.model = model
        self.planner = planner
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.ensemble: Ensemble = ensemble
        model_device = next(model.net.parameters()).device
        wanted = model_device if device is None else torch.device(device)
        self.device = model_device
        if wanted.type != model_device.type or wanted.index not in (None, model_device.index):
            raise ValueError(
                f"device={wanted} but the model lives on {model_device}; move it first "
                "(model.to(device), then model.reset()) so its adaptation state follows"
            )
        self.observation_dim = obs_dim
        self.action_dim = action_dim

    @classmethod
    def from_goal_env(
        cls,
        model: AdaptiveDynamicsModel,
        planner: Planner,
        env: gymnasium.Env[Any, Any],
        *,
        achieved_goal_fn: Callable[[Tensor], Tensor] | slice | None = None,
        termination_fn: TerminationFn | None = None,
        ensemble: Ensemble = "mmse",
        device: torch.device | str | None = None,
    ) -> MPCAgent:
        """An agent that plans with a goal-conditioned env's own batched ``compute_reward``.

        The reward of a planned step is ``env.compute_reward(achieved_goal_fn(next_obs),
        desired_goal, {})`` (:class:`~smcd_rl.integrations.gymnasium.GoalReward`), with the
        ``desired_goal`` of the observation passed to :meth:`act` held fixed over the plan.

        Args:
            model: the dynamics model of the env's ``observation`` entry.
            planner: the planner.
            env: a single goal-conditioned env (``Dict`` observations with ``observation`` and
                ``desired_goal``, and ``compute_reward``); wrappers allowed.
            achieved_goal_fn: ``observation [..., O] -> achieved_goal [..., G]`` in torch, or a
                ``slice`` of columns; derived for gymnasium-robotics Fetch envs when ``None``.
            termination_fn: as in the constructor.
            ensemble: as in the constructor.
            device: as in the constructor.

        Raises:
            ValueError: the env is not goal-conditioned (which part is missing is named), or
                ``achieved_goal_fn`` is needed and missing.

        Example:
            >>> import gymnasium, numpy as np, torch, smcd_rl
            >>> from smcd_rl.agents.mpc import MPCAgent
            >>> from smcd_rl.agents.planners import CEM
            >>> class Point(gymnasium.Env):  # a goal env reduced to its spaces and reward
            ...     box = gymnasium.spaces.Box(-1.0, 1.0, (2,))
            ...     observation_space = gymnasium.spaces.Dict(observation=box, achieved_goal=box, desired_goal=box)
            ...     action_space = box
            ...     def compute_reward(self, achieved_goal, desired_goal, info):
            ...         return -np.linalg.norm(achieved_goal - desired_goal, axis=-1)
            >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(2 + 2, 2, hidden=(16,)))
            >>> model.fitted = True  # a random stand-in for a trained network
            >>> model.reset()
            >>> planner = CEM(action_low=[-1.0, -1.0], action_high=[1.0, 1.0], horizon=3, num_candidates=20, num_elites=4)
            >>> agent = MPCAgent.from_goal_env(model, planner, Point(), achieved_goal_fn=slice(0, 2))
            >>> obs = {"observation": np.zeros(2), "achieved_goal": np.zeros(2), "desired_goal": np.ones(2)}
            >>> agent.act(obs).shape
            (2,)
        """
        reward = GoalReward(env, achieved_goal_fn=achieved_goal_fn)
        return cls(model, planner, reward, termination_fn, ensemble=ensemble, device=device)

    def reset(self) -> None:
        """Forget the planner's warm start (call at the start of an episode); the model is untouched."""
        self.planner.reset()

    def plan(self, observation: np.ndarray | Tensor | Mapping[str, Any]) -> Tensor:
        """The whole optimised plan ``[*batch, H, A]`` from ``observation [*batch, obs]``.

        A goal-conditioned agent takes the env's ``Dict`` observation instead (entries
        ``[*batch, ...]``).

        Raises:
            ValueError: the observation size is not the model's, or its batch does not match the
                batch shape the model was reset with; a ``Dict`` observation for an agent without
                a ``GoalReward``, or the other way round.
        """
        reward_fn: RewardFn
        if self.goal_reward is not None:
            goal = self.goal_reward
            if not isinstance(observation, Mapping):
                raise ValueError(
                    "this agent plans towards a goal (its reward_fn is a GoalReward): pass the env's Dict "
                    f"observation with entries {goal.observation_key!r} and {goal.desired_goal_key!r}, "
                    f"got a {type(observation).__name__}"
                )
            missing = [k for k in (goal.observation_key, goal.desired_goal_key) if k not in observation]
            if missing:
                raise ValueError(f"the Dict observation has no {missing}; it has {list(observation)}")
            desired = observation[goal.desired_goal_key]
            observation = observation[goal.observation_key]
            desired = torch.as_tensor(np.asarray(desired) if not isinstance(desired, Tensor) else desired)
            reward_fn = goal.towards(desired.to(device=self.device, dtype=next(self.model.net.parameters()).dtype))
        else:
            if isinstance(observation, Mapping):
                raise ValueError(
                    f"got a Dict observation with entries {list(observation)}; for a goal-conditioned env build the "
                    "agent with MPCAgent.from_goal_env(model, planner, env), else pass the observation array"
                )
            assert not isinstance(self.reward_fn, GoalReward)
            reward_fn = self.reward_fn
        obs = torch.as_tensor(np.asarray(observation) if not isinstance(observation, Tensor) else observation)
        obs = obs.to(device=self.device, dtype=next(self.model.net.parameters()).dtype)
        if obs.dim() == 0 or obs.shape[-1] != self.observation_dim:
            raise ValueError(
                f"observation has shape {list(obs.shape)} but the model predicts observations of size "
                f"{self.observation_dim}; pass [{self.observation_dim}] or [B, {self.observation_dim}]"
            )
        batch = tuple(obs.shape[:-1])
        model_batch = self.model.batch_shape
        if model_batch != () and model_batch != batch:
            raise ValueError(
                f"observation batch {list(batch)} does not match the model's batch_shape {list(model_batch)}; "
                f"pass one observation per adaptation state, or reset the model with batch_shape={list(batch)}"
            )
        if self.goal_reward is not None and tuple(desired.shape[:-1]) != batch:
            raise ValueError(
                f"desired_goal {list(desired.shape)} and observation {list(obs.shape)} have different batch dims"
            )
        objective = model_reward_objective(self.model, obs, reward_fn, self.termination_fn, ensemble=self.ensemble)
        return self.planner.plan(objective, batch_shape=batch)

    def act(self, observation: np.ndarray | Tensor | Mapping[str, Any]) -> np.ndarray:
        """The first action of the plan: ``[A]`` for one observation, ``[B, A]`` for ``[B, obs]``."""
        return self.plan(observation)[..., 0, :].detach().cpu().numpy()

    def __repr__(self) -> str:
        return (
            f"MPCAgent(planner={type(self.planner).__name__}(horizon={self.planner.horizon}), "
            f"adaptation={type(self.model.adaptation).__name__}, ensemble={self.ensemble!r}"
            + ("" if self.goal_reward is None else f", reward={self.goal_reward!r}")
            + ")"
        )


def _check_shape(value: Tensor, expected: tuple[int, ...], what: str) -> None:
    if not isinstance(value, Tensor):
        raise TypeError(f"{what} must return a torch.Tensor of shape {list(expected)}, got {type(value).__name__}")
    if tuple(value.shape) != expected:
        raise ValueError(
            f"{what} returned shape {list(value.shape)}, expected [*batch, P] = {list(expected)}: one value per "
            "candidate, without a trailing dimension (reduce with .sum(-1) or index [..., 0])"
        )


def _check_dynamics_model(model: object) -> None:
    if not isinstance(model, AdaptiveDynamicsModel):
        raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel, got {type(model).__name__}")
