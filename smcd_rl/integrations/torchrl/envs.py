"""The world-model env: an adaptive dynamics model and a reward function as a torchrl model-based env."""

from __future__ import annotations

import math
from collections.abc import Sequence

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase

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

    Args:
        model: the dynamics model, with keys ``observation``, ``action`` and
            ``("next", "observation")`` (the observation key may be renamed; the action key may not,
            torchrl's planners write ``"action"``). It must be reset before stepping.
        reward_fn: pure batched reward, ``(obs [..., O], action [..., A], next_obs [..., O]) -> [...]``.
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
        reward_fn: RewardFn,
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
        self.observation_spec = Composite({obs_key: obs_spec}, device=self.device)
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
        obs_dim, action_dim = model.observation_dim, model.action_dim
        obs_box = _check_box(obs_space, obs_dim, "observation", model)
        action_box = _check_box(action_space, action_dim, "action", model)
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
        return TensorDict(
            {self.observation_key: obs.to(self._initial_observation.dtype), "done": done, "terminated": done.clone()},
            batch_size=batch_size,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        """Nothing to seed: steps are deterministic given the model's adaptation state."""


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
