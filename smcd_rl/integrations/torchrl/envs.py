"""The world-model env: an adaptive dynamics model and a reward function as a torchrl model-based env."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase

from smcd_rl.integrations.gymnasium import GoalReward
from smcd_rl.integrations.torchrl.modules import (
    RewardFn,
    TerminationFn,
    _checked_reward,
    _checked_termination,
    _WorldModel,
)
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel

__all__ = ["AdaptiveWorldModelEnv"]

_Bound = float | Sequence[float] | Tensor | np.ndarray


class AdaptiveWorldModelEnv(ModelBasedEnvBase):
    """A torchrl model-based env that steps an adaptive dynamics model with its adapted (MMSE) mask.

    One step maps ``(observation, action)`` to the model's predicted next observation, the reward
    ``reward_fn(obs, action, next_obs)`` (written with shape ``[..., 1]``) and, with
    ``termination_fn``, ``terminated``/``done`` flags; without it episodes never end. The env is
    not batch-locked: any batch of states steps at once, which is what torchrl's ``CEMPlanner``
    and ``MPPIPlanner`` need. It keeps a reference to ``model`` (never a copy), so adaptation
    from real steps (:class:`AdaptationTransform`) is seen by the next plan. The model's batch
    shape must lead the planning batch: ``()`` to plan for one env, ``(B,)`` for a batch of B
    envs each with its own particle set.

    Observation and action sizes come from the model (``net.out_features`` observations,
    ``net.in_features - net.out_features`` actions); bounds and dtype from the arguments or,
    with :meth:`from_gym` / :meth:`from_env`, from an env, which must match the model.

    Goal-conditioned envs (:meth:`from_goal_env`, or a
    :class:`~smcd_rl.integrations.gymnasium.GoalReward` as ``reward_fn``): the observation spec
    holds ``observation``, ``achieved_goal`` and ``desired_goal``, the keys torchrl's ``GymEnv``
    gives a Fetch env. A step predicts ``observation``, writes its ``achieved_goal`` and carries
    ``desired_goal`` over unchanged (a constant of the plan); the reward is the env's own
    ``compute_reward``.

    Args:
        model: the dynamics model, with keys ``observation``, ``action`` and
            ``("next", "observation")`` (the observation key may be renamed; the action key may not,
            torchrl's planners write ``"action"``). It must be reset before stepping.
        reward_fn: pure batched reward, ``(obs [..., O], action [..., A], next_obs [..., O]) -> [...]``,
            or a :class:`~smcd_rl.integrations.gymnasium.GoalReward` (goal-conditioned).
        action_low: lower action bound, a scalar or ``A`` values.
        action_high: upper action bound, a scalar or ``A`` values.
        observation_low: lower observation bound (default unbounded); informative only, the
            planners never clip observations.
        observation_high: upper observation bound (default unbounded).
        termination_fn: pure batched termination, ``next_obs [..., O] -> bool [...]``.
        observation_dtype: dtype of the observations the env reads and writes.
        initial_observation: the observation :meth:`reset` returns when the tensordict passed to it
            holds none (default zeros, clipped into the bounds); planning never resets.
        device: where the env's tensors live (the model is moved there).

    Raises:
        TypeError: ``model`` is not an :class:`~smcd_rl.AdaptiveDynamicsModel`.
        ValueError: a bound, ``initial_observation`` or the output of ``reward_fn`` /
            ``termination_fn`` on a test batch does not fit the model's sizes.

    Example:
        >>> import torch, smcd_rl
        >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
        >>> net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=(32,))
        >>> model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.SMCD(num_particles=10))
        >>> model.fitted = True  # a random stand-in for a trained network
        >>> model.reset()
        >>> world = AdaptiveWorldModelEnv(
        ...     model, lambda obs, act, next_obs: -next_obs.square().sum(-1), action_low=-2.0, action_high=2.0)
        >>> td = world.reset()
        >>> td["action"] = torch.ones(1)
        >>> world.step(td)["next", "reward"].shape
        torch.Size([1])
        >>> world.rollout(4, auto_reset=False, tensordict=world.reset().expand(8).clone())["next", "observation"].shape
        torch.Size([8, 4, 3])
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        reward_fn: RewardFn | GoalReward,
        *,
        action_low: _Bound,
        action_high: _Bound,
        observation_low: _Bound | None = None,
        observation_high: _Bound | None = None,
        termination_fn: TerminationFn | None = None,
        observation_dtype: torch.dtype = torch.float32,
        initial_observation: Tensor | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        _check_model(model)
        obs_key, action_key = model.in_keys
        if action_key != "action" or not isinstance(obs_key, str):
            raise ValueError(
                f"the model reads {model.in_keys}; torchrl's planners need a top-level observation key "
                "and the action key 'action'"
            )
        obs_dim, action_dim = model.observation_dim, model.action_dim
        world_model = _WorldModel(
            model, reward_fn, termination_fn, observation_key=obs_key, observation_dtype=observation_dtype
        )
        super().__init__(world_model, device=device)
        self.model = model
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.observation_key = obs_key

        low = _bound(action_low, action_dim, "action_low", -math.inf)
        high = _bound(action_high, action_dim, "action_high", math.inf)
        if not bool((low <= high).all()) or not bool(torch.isfinite(low).all() & torch.isfinite(high).all()):
            raise ValueError(f"action bounds must be finite with low <= high, got {low.tolist()} and {high.tolist()}")
        self.action_spec = Bounded(low=low, high=high, shape=(action_dim,), device=self.device)
        obs_low = _bound(observation_low, obs_dim, "observation_low", -math.inf).to(observation_dtype)
        obs_high = _bound(observation_high, obs_dim, "observation_high", math.inf).to(observation_dtype)
        obs_spec: TensorSpec
        if bool(torch.isinf(obs_low).all() & torch.isinf(obs_high).all()):
            obs_spec = Unbounded(shape=(obs_dim,), device=self.device, dtype=observation_dtype)
        else:
            obs_spec = Bounded(
                low=obs_low, high=obs_high, shape=(obs_dim,), device=self.device, dtype=observation_dtype
            )
        specs: dict[str, TensorSpec] = {obs_key: obs_spec}
        self.goal = reward_fn if isinstance(reward_fn, GoalReward) else None
        if self.goal is not None:
            if self.goal.observation_dim != obs_dim:
                raise ValueError(
                    f"the goal env's {self.goal.observation_key!r} has {self.goal.observation_dim} values but the "
                    f"model predicts {obs_dim} observations"
                )
            goal_box = self.goal.goal_space
            goal_dtype = torch.from_numpy(np.zeros(0, dtype=goal_box.dtype)).dtype
            goal_low = torch.as_tensor(goal_box.low, dtype=goal_dtype)
            goal_high = torch.as_tensor(goal_box.high, dtype=goal_dtype)
            specs[self.goal.desired_goal_key] = _box_spec(goal_low, goal_high, goal_dtype, self.device)
            # Unbounded: the achieved goal of a predicted observation may leave the goal's box.
            specs["achieved_goal"] = Unbounded(shape=goal_low.shape, device=self.device, dtype=goal_dtype)
            self._initial_goal = torch.zeros(self.goal.goal_dim, dtype=goal_dtype).clamp(goal_low, goal_high)
        self.observation_spec = Composite(specs, device=self.device)
        self.reward_spec = Unbounded(shape=(1,), device=self.device)

        if initial_observation is None:
            initial = torch.zeros(obs_dim, dtype=observation_dtype).clamp(obs_low, obs_high)
        else:
            initial = torch.as_tensor(initial_observation, dtype=observation_dtype)
            if initial.shape != (obs_dim,):
                raise ValueError(
                    f"initial_observation has shape {list(initial.shape)} but the model predicts {obs_dim} observations"
                )
        self._initial_observation = initial.to(self.device)

        # Fail now, not in the middle of a plan, if the functions do not return one value per transition.
        probe_obs = torch.zeros(2, obs_dim, dtype=observation_dtype, device=self.device)
        probe_action = ((low + high) / 2).to(self.device).expand(2, action_dim)
        with torch.no_grad():
            if isinstance(reward_fn, GoalReward):
                _checked_reward(reward_fn(probe_obs, self._initial_goal.to(self.device)), probe_obs)
            else:
                _checked_reward(reward_fn(probe_obs, probe_action, probe_obs), probe_obs)
            if termination_fn is not None:
                _checked_termination(termination_fn(probe_obs), probe_obs)

    @classmethod
    def from_gym(
        cls,
        model: AdaptiveDynamicsModel,
        env: gymnasium.Env | gymnasium.vector.VectorEnv,
        reward_fn: RewardFn,
        *,
        termination_fn: TerminationFn | None = None,
        initial_observation: Tensor | None = None,
        device: torch.device | str = "cpu",
    ) -> AdaptiveWorldModelEnv:
        """Build the env with the bounds and dtype of a gymnasium env's ``Box`` spaces.

        Vector envs use their single-env spaces.

        Raises:
            ValueError: a space is not a 1-d ``Box``, or its size differs from the model's.

        Example:
            >>> import gymnasium, torch, smcd_rl
            >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
            >>> env = gymnasium.make("Pendulum-v1")
            >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(32,)))
            >>> world = AdaptiveWorldModelEnv.from_gym(model, env, lambda o, a, n: -n[..., 2].abs())
            >>> world.action_spec.space.high
            tensor([2.])
        """
        _check_model(model)
        obs_space = getattr(env, "single_observation_space", env.observation_space)
        action_space = getattr(env, "single_action_space", env.action_space)
        if isinstance(obs_space, gymnasium.spaces.Dict):
            raise ValueError(
                f"the env's observations are a Dict with entries {list(obs_space.keys())}; for a goal-conditioned "
                "env use AdaptiveWorldModelEnv.from_goal_env(model, env), which plans with its compute_reward"
            )
        return cls._from_spaces(model, reward_fn, obs_space, action_space, termination_fn, initial_observation, device)

    @classmethod
    def from_goal_env(
        cls,
        model: AdaptiveDynamicsModel,
        env: gymnasium.Env[Any, Any],
        *,
        achieved_goal_fn: Callable[[Tensor], Tensor] | slice | None = None,
        termination_fn: TerminationFn | None = None,
        initial_observation: Tensor | None = None,
        device: torch.device | str = "cpu",
    ) -> AdaptiveWorldModelEnv:
        """The world model of a goal-conditioned gymnasium env, rewarded by the env's own ``compute_reward``.

        Bounds and dtypes come from the env's action space and its ``Dict`` entries
        ``observation`` and ``desired_goal``; the reward of a step is
        ``compute_reward(achieved_goal_fn(next_obs), desired_goal, {})``
        (:class:`~smcd_rl.integrations.gymnasium.GoalReward`). A tensordict from torchrl's
        ``GymEnv`` on the same env (keys ``observation``, ``achieved_goal``, ``desired_goal``)
        plans as it is.

        Args:
            model: the dynamics model of the env's ``observation`` entry.
            env: a single goal-conditioned gymnasium env (Fetch, or any env with ``Dict``
                observations and a batched ``compute_reward``).
            achieved_goal_fn: ``observation [..., O] -> achieved_goal [..., G]`` in torch, or a
                ``slice`` of columns; derived for gymnasium-robotics Fetch envs when ``None``.
            termination_fn: as in the constructor.
            initial_observation: as in the constructor.
            device: as in the constructor.

        Raises:
            ValueError: the env is not goal-conditioned (what is missing is named), a space does
                not fit the model, or ``achieved_goal_fn`` is needed and missing.

        Example:
            >>> import gymnasium, numpy as np, torch, smcd_rl
            >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
            >>> class Point(gymnasium.Env):  # a goal env reduced to its spaces and reward
            ...     box = gymnasium.spaces.Box(-1.0, 1.0, (2,))
            ...     observation_space = gymnasium.spaces.Dict(observation=box, achieved_goal=box, desired_goal=box)
            ...     action_space = box
            ...     def compute_reward(self, achieved_goal, desired_goal, info):
            ...         return -np.linalg.norm(achieved_goal - desired_goal, axis=-1)
            >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(2 + 2, 2, hidden=(16,)))
            >>> model.fitted = True  # a random stand-in for a trained network
            >>> model.reset()
            >>> world = AdaptiveWorldModelEnv.from_goal_env(model, Point(), achieved_goal_fn=slice(0, 2))
            >>> sorted(world.observation_spec.keys())
            ['achieved_goal', 'desired_goal', 'observation']
            >>> td = world.reset()
            >>> td["desired_goal"] = torch.tensor([0.5, 0.5])
            >>> world.rollout(3, auto_reset=False, tensordict=td)["next", "desired_goal"][-1]
            tensor([0.5000, 0.5000])
        """
        _check_model(model)
        if isinstance(env, gymnasium.vector.VectorEnv):
            raise TypeError("from_goal_env takes a single gymnasium env; pass one sub-env (gymnasium.make(id))")
        goal = GoalReward(env, achieved_goal_fn=achieved_goal_fn, observation_key=_observation_key(model))
        return cls._from_spaces(
            model, goal, goal.observation_space, env.action_space, termination_fn, initial_observation, device
        )

    @classmethod
    def _from_spaces(
        cls,
        model: AdaptiveDynamicsModel,
        reward_fn: RewardFn | GoalReward,
        obs_space: gymnasium.Space,
        action_space: gymnasium.Space,
        termination_fn: TerminationFn | None,
        initial_observation: Tensor | None,
        device: torch.device | str,
    ) -> AdaptiveWorldModelEnv:
        """The env with the bounds and dtype of the observation and action ``Box`` spaces (checked against the model)."""
        obs_box = _check_box(obs_space, model.observation_dim, "observation", model)
        action_box = _check_box(action_space, model.action_dim, "action", model)
        return cls(
            model,
            reward_fn,
            action_low=torch.as_tensor(action_box.low, dtype=torch.float32),
            action_high=torch.as_tensor(action_box.high, dtype=torch.float32),
            observation_low=torch.as_tensor(obs_box.low, dtype=torch.float64),
            observation_high=torch.as_tensor(obs_box.high, dtype=torch.float64),
            termination_fn=termination_fn,
            observation_dtype=torch.from_numpy(np.zeros(0, dtype=obs_box.dtype)).dtype,
            initial_observation=initial_observation,
            device=device,
        )

    @classmethod
    def from_env(
        cls,
        model: AdaptiveDynamicsModel,
        env: EnvBase,
        reward_fn: RewardFn,
        *,
        termination_fn: TerminationFn | None = None,
        initial_observation: Tensor | None = None,
    ) -> AdaptiveWorldModelEnv:
        """Build the env with the bounds and dtype of a torchrl env's specs (e.g. ``GymEnv``, batched or not).

        Raises:
            ValueError: the env's observation or action spec is not a vector of the model's size.

        Example:
            >>> import torch, smcd_rl
            >>> from torchrl.envs import GymEnv
            >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
            >>> env = GymEnv("smcd_rl/TwoLinkArm-v0")
            >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32,)))
            >>> world = AdaptiveWorldModelEnv.from_env(model, env, lambda o, a, n: -n[..., 2:].square().sum(-1))
            >>> world.action_spec.space.low
            tensor([-3., -3.])
        """
        _check_model(model)
        obs_dim, action_dim = model.observation_dim, model.action_dim
        obs_spec = env.observation_spec_unbatched.get(model.in_keys[0], None)
        if obs_spec is None:
            raise ValueError(
                f"the env has no observation {model.in_keys[0]!r}; it has {list(env.observation_spec.keys(True, True))}"
            )
        action_spec = env.action_spec_unbatched
        _check_spec(obs_spec, obs_dim, "observation", model)
        _check_spec(action_spec, action_dim, "action", model)
        if not isinstance(action_spec, Bounded):
            raise ValueError(f"the env's action spec must be Bounded for planning, got {type(action_spec).__name__}")
        obs_bounds: tuple[Tensor | None, Tensor | None] = (None, None)
        if isinstance(obs_spec, Bounded):
            obs_bounds = (obs_spec.space.low, obs_spec.space.high)
        return cls(
            model,
            reward_fn,
            action_low=action_spec.space.low,
            action_high=action_spec.space.high,
            observation_low=obs_bounds[0],
            observation_high=obs_bounds[1],
            termination_fn=termination_fn,
            observation_dtype=obs_spec.dtype,
            initial_observation=initial_observation,
            device=env.device if env.device is not None else "cpu",
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: object) -> TensorDictBase:
        batch_size = tensordict.batch_size if tensordict is not None else self.batch_size
        obs = tensordict.get(self.observation_key, None) if tensordict is not None else None
        if obs is None:
            obs = self._initial_observation.expand(*batch_size, -1).clone()
        done = torch.zeros(*batch_size, 1, dtype=torch.bool, device=self.device)
        obs = obs.to(self._initial_observation.dtype)
        out = TensorDict(
            {self.observation_key: obs, "done": done, "terminated": done.clone()},
            batch_size=batch_size,
            device=self.device,
        )
        if self.goal is not None:
            key = self.goal.desired_goal_key
            desired = tensordict.get(key, None) if tensordict is not None else None
            if desired is None:
                desired = self._initial_goal.to(self.device).expand(*batch_size, -1).clone()
            out.set(key, desired.to(self._initial_goal.dtype))
            out.set("achieved_goal", self.goal.achieved_goal(obs).to(self._initial_goal.dtype))
        return out

    def _set_seed(self, seed: int | None) -> None:
        """Nothing to seed: steps are deterministic given the model's adaptation state."""


def _box_spec(low: Tensor, high: Tensor, dtype: torch.dtype, device: torch.device | None) -> TensorSpec:
    """``Unbounded`` when every bound is infinite, else ``Bounded``."""
    if bool(torch.isinf(low).all() & torch.isinf(high).all()):
        return Unbounded(shape=low.shape, device=device, dtype=dtype)
    return Bounded(low=low, high=high, shape=low.shape, device=device, dtype=dtype)


def _observation_key(model: AdaptiveDynamicsModel) -> str:
    key = model.in_keys[0]
    if not isinstance(key, str):
        raise ValueError(f"a goal-conditioned model reads a top-level Dict entry, but its observation key is {key!r}")
    return key


def _check_model(model: object) -> None:
    if not isinstance(model, AdaptiveDynamicsModel):
        raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel, got {type(model).__name__}")


def _bound(value: _Bound | None, size: int, name: str, default: float) -> Tensor:
    if value is None:
        return torch.full((size,), default)
    bound = torch.as_tensor(value, dtype=torch.float32).detach().cpu()
    if bound.dim() == 0:
        return bound.expand(size).clone()
    if bound.shape != (size,):
        raise ValueError(f"{name} has shape {list(bound.shape)} but the model has {size} such features")
    return bound


def _size_error(what: str, kind: str, shape: object, size: int, model: AdaptiveModel) -> ValueError:
    obs_dim, action_dim = model.net.out_features, model.net.in_features - model.net.out_features
    return ValueError(
        f"the env's {what} {kind} has shape {shape} but the model expects {size} {what} features "
        f"(network {model.net.in_features} inputs = {obs_dim} observation + {action_dim} action, "
        f"{obs_dim} outputs)"
    )


def _check_box(space: gymnasium.Space, size: int, what: str, model: AdaptiveModel) -> gymnasium.spaces.Box:
    """``space`` itself, once it is known to be a Box of ``size`` values."""
    if not isinstance(space, gymnasium.spaces.Box) or len(space.shape) != 1:
        raise ValueError(f"the env's {what} space must be a 1-d gymnasium Box, got {space}")
    if space.shape != (size,):
        raise _size_error(what, "space", tuple(space.shape), size, model)
    return space


def _check_spec(spec: TensorSpec, size: int, what: str, model: AdaptiveModel) -> None:
    if len(spec.shape) != 1 or not spec.dtype.is_floating_point:
        raise ValueError(f"the env's {what} spec must be a float vector, got shape {list(spec.shape)} {spec.dtype}")
    if spec.shape != (size,):
        raise _size_error(what, "spec", tuple(spec.shape), size, model)
