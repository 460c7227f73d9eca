"""torchrl integration: plan on an adaptive world model, adapt on every real step, fit from a replay buffer.

* :class:`AdaptiveWorldModelEnv` turns an :class:`~smcd_rl.AdaptiveDynamicsModel` and a pure batched
  reward function into a torchrl model-based env, so torchrl's own ``CEMPlanner`` and
  ``MPPIPlanner`` plan on the adapted model unchanged. :class:`RewardToGo` is the advantage
  module ``MPPIPlanner`` needs.
* :class:`AdaptationTransform` is the environment-step hook: appended to a ``TransformedEnv`` it
  calls ``model.observe`` on every real transition and writes the filter's summary (ESS, log
  evidence) into the step's tensordict.
* :func:`fit_from_replay_buffer` fits the model on a torchrl ``ReplayBuffer``; :func:`mbrl_loop`
  is the whole recipe: collect, fit, plan, adapt.

The model is shared: the transform adapts it from real steps and the world-model env predicts
with its adapted (MMSE) mask, so the planner always sees the latest posterior. Call planners under
``torch.no_grad()`` (torchrl 0.14 does not disable gradients; the env never builds autograd graphs
itself). ``torch.inference_mode()`` works too, but its tensors cannot be updated in place outside
it: a replay buffer whose lazy storage is first filled under it fails on the next ``extend``.

Example:
    >>> import torch, smcd_rl
    >>> from torchrl.modules import CEMPlanner
    >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
    >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
    <torch._C.Generator object at ...>
    >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3, 2, hidden=(32,)), smcd_rl.SMCD(num_particles=10))
    >>> model.reset()
    >>> world = AdaptiveWorldModelEnv(
    ...     model, lambda obs, act, next_obs: -next_obs.square().sum(-1), action_low=-1.0, action_high=1.0)
    >>> planner = CEMPlanner(world, planning_horizon=5, optim_steps=3, num_candidates=20, top_k=5)
    >>> with torch.no_grad():
    ...     td = planner(world.reset())
    >>> td["action"].shape
    torch.Size([1])
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Literal

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.collectors import Collector
from torchrl.data import Bounded, Composite, LazyTensorStorage, ReplayBuffer, TensorSpec, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.transforms import Transform
from torchrl.modules import CEMPlanner, MPPIPlanner

from smcd_rl.adaptation import SMCD
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel
from smcd_rl.training import fit

__all__ = [
    "RewardFn",
    "TerminationFn",
    "AdaptiveWorldModelEnv",
    "RewardToGo",
    "AdaptationTransform",
    "fit_from_replay_buffer",
    "mbrl_loop",
]

#: ``reward_fn(obs, action, next_obs) -> reward``: pure and batched, ``[..., O], [..., A], [..., O] -> [...]``
#: (``[..., 1]`` is accepted too).
RewardFn = Callable[[Tensor, Tensor, Tensor], Tensor]
#: ``termination_fn(next_obs) -> terminated``: pure and batched, ``[..., O] -> bool [...]`` (or ``[..., 1]``).
TerminationFn = Callable[[Tensor], Tensor]

_Bound = float | Sequence[float] | Tensor | np.ndarray


# ---------------------------------------------------------------------- world-model env
class _WorldModel(TensorDictModuleBase):
    """(observation, action) -> (observation, reward[, terminated, done]) through the adapted model.

    ``ModelBasedEnvBase._step`` keeps only the observation, reward and done keys of what this
    module writes, so the next observation overwrites the observation key itself.
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        reward_fn: RewardFn,
        termination_fn: TerminationFn | None,
        *,
        observation_key: str,
        observation_dtype: torch.dtype,
    ) -> None:
        super().__init__()
        self.model = model
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.observation_key = observation_key
        self.observation_dtype = observation_dtype
        self.in_keys = [observation_key, "action"]
        self.out_keys = [observation_key, "reward"] + (["terminated", "done"] if termination_fn else [])

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        key = self.observation_key
        obs = td.get(key).to(self.observation_dtype)
        action = td.get("action")
        # Planning never needs gradients through the model, and graphs over thousands of
        # candidates cost memory and time.
        with torch.no_grad():
            query = TensorDict({key: obs, "action": action}, batch_size=td.batch_size, device=td.device)
            next_obs = self.model(query).get(("next", key)).to(self.observation_dtype)
            reward = _checked_reward(self.reward_fn(obs, action, next_obs), obs)
            td.set(key, next_obs)
            td.set("reward", reward.to(torch.float32).unsqueeze(-1))
            if self.termination_fn is not None:
                terminated = _checked_termination(self.termination_fn(next_obs), obs).unsqueeze(-1)
                td.set("terminated", terminated)
                td.set("done", terminated)
        return td


def _checked_reward(reward: Tensor, obs: Tensor) -> Tensor:
    batch = obs.shape[:-1]
    if not isinstance(reward, Tensor):
        raise TypeError(f"reward_fn must return a Tensor, got {type(reward).__name__}")
    if reward.shape == (*batch, 1):
        reward = reward.squeeze(-1)
    if reward.shape != batch:
        raise ValueError(
            f"reward_fn returned shape {list(reward.shape)} for observations of shape {list(obs.shape)}; "
            f"it must return one reward per transition, shape {list(batch)} (or {[*batch, 1]})"
        )
    return reward


def _checked_termination(terminated: Tensor, obs: Tensor) -> Tensor:
    batch = obs.shape[:-1]
    if not isinstance(terminated, Tensor):
        raise TypeError(f"termination_fn must return a Tensor, got {type(terminated).__name__}")
    if terminated.shape == (*batch, 1):
        terminated = terminated.squeeze(-1)
    if terminated.shape != batch:
        raise ValueError(
            f"termination_fn returned shape {list(terminated.shape)} for observations of shape "
            f"{list(obs.shape)}; it must return one flag per transition, shape {list(batch)} (or {[*batch, 1]})"
        )
    return terminated.to(torch.bool)


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


class RewardToGo(TensorDictModuleBase):
    """Discounted reward-to-go along a rollout's time dim, the advantage module ``MPPIPlanner`` needs.

    Writes ``advantage[..., t, :] = sum_{k >= t} gamma ** (k - t) * reward[..., k, :]``, minus (with
    ``subtract_max``) the best return among the candidates. torchrl's ``MPPIPlanner`` ranks
    candidates by the advantage at t = 0, the discounted return of the whole planned sequence,
    after zeroing rewards that follow a ``done``. It weights the top candidates by
    ``exp(temperature * advantage)`` without subtracting the maximum (torchrl 0.14.1), so returns of
    a few hundred underflow every weight to 0 and the plan becomes NaN; the update is invariant to
    a shift of all candidates' advantages, so ``subtract_max`` shifts the best to 0.

    Args:
        gamma: discount factor in ``(0, 1]``.
        reward_key: where the rewards are, ``[..., K, T, 1]`` in a planner's rollout.
        advantage_key: where the reward-to-go is written (same shape).
        time_dim: the (negative) time dim of the reward tensor; candidates are the dim before it.
        subtract_max: subtract, per planning problem, the largest t = 0 return over the candidates.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from smcd_rl.integrations.torchrl import RewardToGo
        >>> td = TensorDict({("next", "reward"): torch.ones(2, 3, 1)}, [2, 3])
        >>> RewardToGo(gamma=0.5, subtract_max=False)(td)["advantage"][0, :, 0]
        tensor([1.7500, 1.5000, 1.0000])
        >>> RewardToGo(gamma=0.5)(td)["advantage"][0, :, 0]
        tensor([ 0.0000, -0.2500, -0.7500])
    """

    def __init__(
        self,
        gamma: float = 1.0,
        *,
        reward_key: NestedKey = ("next", "reward"),
        advantage_key: NestedKey = "advantage",
        time_dim: int = -2,
        subtract_max: bool = True,
    ) -> None:
        super().__init__()
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        if time_dim >= 0:
            raise ValueError(f"time_dim must be negative (counted from the last dim), got {time_dim}")
        self.gamma = float(gamma)
        self.time_dim = int(time_dim)
        self.subtract_max = bool(subtract_max)
        self.in_keys = [reward_key]
        self.out_keys = [advantage_key]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        reward = td.get(self.in_keys[0])
        r = reward.movedim(self.time_dim, -1)  # [..., T]
        steps = torch.arange(r.shape[-1], device=r.device)
        lag = steps.unsqueeze(0) - steps.unsqueeze(1)  # lag[t, k] = k - t
        discount = torch.where(lag >= 0, self.gamma ** lag.clamp(min=0).to(r.dtype), torch.zeros((), dtype=r.dtype))
        advantage = (r @ discount.T).movedim(-1, self.time_dim)
        candidate_dim = self.time_dim - 1
        if self.subtract_max and advantage.dim() >= -candidate_dim:
            best = advantage.narrow(self.time_dim, 0, 1).amax(dim=candidate_dim, keepdim=True)
            advantage = advantage - best
        td.set(self.out_keys[0], advantage)
        return td


# ---------------------------------------------------------------------- the step hook
class AdaptationTransform(Transform):
    """The environment-step hook: adapt a model on every real step of a torchrl env.

    On each step it calls ``model.observe`` on the transition, read from the step's tensordict
    (keys without ``"next"`` from the state before the step, ``("next", ...)`` keys from the new
    one), and writes the model's summary, one value per env with a trailing dim of 1, to
    ``prefix + name``: for :class:`~smcd_rl.SMCD` ``smcd_ess`` (effective sample size, in
    ``[1, N]``) and ``smcd_log_evidence`` (log p(z_1..t), reset to 0). These keys are added to
    the observation spec. On reset it calls ``model.reset(batch_shape=env.batch_size)``, so a
    batched env (``SerialEnv``, ``ParallelEnv``, a vectorised ``GymEnv``) keeps one particle set
    per sub-env; a partial reset (``"_reset"`` mask) restarts only the particle sets of the
    sub-envs that reset. Append the transform to the batched env, not inside its workers, so
    that there is one model.

    Args:
        model: the adaptive model; its keys must be in the env's tensordicts.
        prefix: prepended to each summary name to form its key.
        summary_keys: which entries of ``model.summary()`` to write (default: all an
            :class:`~smcd_rl.SMCD` model reports, none for other strategies).

    Example:
        >>> import torch, smcd_rl
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from smcd_rl.integrations.torchrl import AdaptationTransform
        >>> net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32,))
        >>> model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.SMCD(num_particles=10))
        >>> env = TransformedEnv(GymEnv("smcd_rl/TwoLinkArm-v0"), AdaptationTransform(model))
        >>> td = env.rollout(3)
        >>> td["next", "smcd_ess"].shape, td["smcd_log_evidence"][0].item()
        (torch.Size([3, 1]), 0.0)
    """

    def __init__(
        self, model: AdaptiveModel, *, prefix: str = "smcd_", summary_keys: Sequence[str] | None = None
    ) -> None:
        if not isinstance(model, AdaptiveModel):
            raise TypeError(f"model must be a smcd_rl.AdaptiveModel, got {type(model).__name__}")
        if summary_keys is None:
            summary_keys = ("ess", "log_evidence") if isinstance(model.adaptation, SMCD) else ()
        self.summary_keys = tuple(summary_keys)
        super().__init__(in_keys=[], out_keys=[prefix + name for name in self.summary_keys])
        self.model = model

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        transition = TensorDict(batch_size=next_tensordict.batch_size, device=next_tensordict.device)
        for key in [*self.model.in_keys, self.model.target_key]:
            if isinstance(key, tuple) and key[0] == "next":
                value = next_tensordict.get(key[1:], None)
            else:
                value = tensordict.get(key, None)
            if value is not None:  # a missing key is reported by model.observe, with the keys there are
                transition.set(key, value)
        step_mask = tensordict.get("_step", None)
        self._where(step_mask, lambda: self.model.observe(transition), batch_shape=tuple(next_tensordict.batch_size))
        return self._write_summary(next_tensordict)

    def _reset(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_shape = tuple(tensordict_reset.batch_size)
        reset_mask = tensordict.get("_reset", None) if tensordict is not None else None
        try:
            same_batch = self.model.batch_shape == batch_shape
        except RuntimeError:  # never reset yet
            same_batch = False
        if not same_batch:
            reset_mask = None
        self.model.reset(batch_shape=batch_shape, where=reset_mask)
        return self._write_summary(tensordict_reset)

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Outside an env (e.g. the transform applied to stored data) there is no transition to observe.
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for key in self.out_keys:
            observation_spec[key] = Unbounded(
                shape=(*observation_spec.shape, 1), device=observation_spec.device, dtype=torch.float32
            )
        return observation_spec

    def _write_summary(self, td: TensorDictBase) -> TensorDictBase:
        if not self.summary_keys:
            return td
        summary = self.model.summary()
        for name, key in zip(self.summary_keys, self.out_keys, strict=True):
            if name not in summary:
                raise KeyError(f"the model's summary has no {name!r}; it has {sorted(summary)}")
            td.set(key, summary[name].detach().to(torch.float32).reshape(*td.batch_size, 1).to(td.device))
        return td

    def _where(self, mask: Tensor | None, update: Callable[[], None], *, batch_shape: tuple[int, ...]) -> None:
        """Run ``update`` for the batch elements where ``mask`` is True (all when it is None)."""
        if mask is None or bool(mask.all()):
            update()
            return
        if not bool(mask.any()):
            return
        mask = mask.reshape(batch_shape)
        # The core resets and updates every batch element at once: act on all, then put back
        # the old state where the mask is not set.
        adaptation = self.model.adaptation
        old = adaptation.state_dict()
        update()
        adaptation.restore_rows(old, ~mask)


# ---------------------------------------------------------------------- fitting and the MBRL loop
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
