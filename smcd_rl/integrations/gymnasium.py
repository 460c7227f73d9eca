"""Gymnasium and stable-baselines3 integration: the environment-step hook and data collection.

* :class:`AdaptationWrapper` wraps any gymnasium env whose observations and actions are flat
  boxes: ``reset`` starts a new adaptation episode (``model.reset()``), every ``step`` feeds the
  real transition to ``model.observe``, ``info`` carries the adapted model's summary, and an
  optional context vector appended to the observation lets a policy (e.g. stable-baselines3's
  ``"MlpPolicy"``) condition on what the model has inferred.
* :class:`AdaptationVectorWrapper` does the same for a ``gymnasium.vector.VectorEnv``, with one
  adaptation state (particle set) per sub-env, honouring the vector env's autoreset mode.
* :func:`collect_transitions` records transitions with random actions, an SB3 model or any
  callable policy, in the TensorDict layout that :func:`smcd_rl.fit_dynamics` takes.
* :class:`GoalReward` is the batched torch reward of a goal-conditioned env (gymnasium-robotics'
  Fetch, or any env with ``Dict`` observations and ``compute_reward``), for the planners.

Goal-conditioned envs (``Dict`` observations ``{"observation", "achieved_goal", "desired_goal"}``):
the dynamics model learns the ``observation`` entry only (the ``Dict`` entry named by the model's
observation key), :func:`collect_transitions` records every entry under its own key, the wrappers
feed ``model.observe`` that entry and add the context as a new ``Dict`` entry
(``context_key="smcd_context"``) instead of concatenating it, so SB3's ``"MultiInputPolicy"`` and
``HerReplayBuffer`` work unchanged. :class:`GoalReward` maps a predicted observation to the
achieved goal (``achieved_goal_fn``, derived for Fetch) and scores it with the env's own
``compute_reward`` towards the ``desired_goal``, a constant of the plan.

The context vector (``context=k``) is ``k + 1`` numbers appended to the observation:

* ``W @ z``: a fixed random projection of the standardised MMSE mask ``z = (m - p) / sqrt(p (1 - p))``,
  where ``m`` is :attr:`smcd_rl.AdaptiveModel.mask` and ``p`` the network's ``keep_prob``, so an
  unadapted (prior-mean) mask projects to about zero. ``W`` is ``[k, mask_dim]`` with i.i.d.
  ``N(0, 1 / mask_dim)`` entries drawn from ``torch.Generator().manual_seed(context_seed)``: the
  same seed and network size always give the same projection (``wrapper.context_projection``).
* ``ess / N``: the filter's effective sample size as a fraction of its particles, in ``(0, 1]``.

Strategies without a mask (``NoAdaptation``, ``GradientDescent``) give a zero projection and
``ess / N = 1``. The box bounds of the context are exact: ``|(W z)_i| <= sum_j |W_ij| max|z|``.

Stable-baselines3: SB3 vectorises single gymnasium envs itself, so wrap each env with its own
:class:`AdaptationWrapper` and its own model (``model.with_adaptation(smcd_rl.SMCD(...))`` shares the
trained network), e.g. ``make_vec_env(lambda: AdaptationWrapper(gymnasium.make(...), make_model()), n_envs=4)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, Protocol, SupportsFloat, runtime_checkable

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space
from tensordict import TensorDict
from torch import Tensor

from smcd_rl.filter import ParticleFilter
from smcd_rl.model import AdaptiveDynamicsModel

__all__ = [
    "AdaptationWrapper",
    "AdaptationVectorWrapper",
    "collect_transitions",
    "GoalReward",
    "fetch_achieved_goal",
    "SupportsPredict",
    "CONTEXT_KEY",
]

#: The ``Dict`` entry where the wrappers put the context of a goal-conditioned (``Dict``) env.
CONTEXT_KEY = "smcd_context"


@runtime_checkable
class SupportsPredict(Protocol):
    """Anything with stable-baselines3's ``predict`` (``BaseAlgorithm`` and ``BasePolicy`` both have it)."""

    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> Any: ...


class _Hook:
    """What both wrappers share: checks, tensors, the context vector, the summary and per-element state.

    With a ``Dict`` observation space the model reads the entry named by its observation key
    (``state_key``) and the context becomes the new entry ``context_key``. The spaces are those of
    one env: a vector env's single (per sub-env) spaces.
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        env: gymnasium.Env[Any, Any] | VectorEnv,
        *,
        context: int | None,
        context_seed: int,
        context_key: str = CONTEXT_KEY,
    ) -> None:
        if isinstance(env, VectorEnv):
            observation_space, action_space = env.single_observation_space, env.single_action_space
        else:
            observation_space, action_space = env.observation_space, env.action_space
        if not isinstance(model, AdaptiveDynamicsModel):
            raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel, got {type(model).__name__}")
        net = model.net
        obs_dim = net.out_features
        action_dim = net.in_features - obs_dim
        sizes = f"(network {net.in_features} inputs = observation {obs_dim} + action {action_dim})"
        self.obs_key, self.action_key = model.in_keys[0], model.in_keys[1]
        self.state_key: str | None = None
        state_space = observation_space
        if isinstance(observation_space, spaces.Dict):
            self.state_key = _dict_entry(observation_space, self.obs_key)
            state_space = observation_space[self.state_key]
            if not isinstance(context_key, str) or context_key in observation_space.spaces:
                raise ValueError(
                    f"context_key must be a str that is not already an entry of the env's Dict observations "
                    f"{list(observation_space.keys())}, got {context_key!r}"
                )
        where = "" if self.state_key is None else f"'s entry {self.state_key!r}"
        if not isinstance(state_space, spaces.Box) or state_space.shape != (obs_dim,):
            raise ValueError(
                f"the env's observation space{where} {state_space} does not match the model, which predicts "
                f"observations of shape ({obs_dim},) {sizes}"
            )
        if not np.issubdtype(state_space.dtype, np.floating):
            raise ValueError(f"the env's observation space{where} must be a floating Box, got {state_space}")
        if not isinstance(action_space, spaces.Box) or action_space.shape != (action_dim,):
            raise ValueError(
                f"the env's action space {action_space} does not match the model, which takes actions of shape "
                f"({action_dim},) {sizes}"
            )
        if context is not None and (isinstance(context, bool) or not isinstance(context, int) or context < 1):
            raise ValueError(f"context must be None or a positive int (projection size), got {context!r}")
        self.model = model
        self.next_key = model.out_key
        self.obs_dim = obs_dim
        # A Dict env's context is an entry of its own: float32, whatever the other entries' dtypes.
        self.obs_dtype = np.dtype(np.float32) if self.state_key is not None else state_space.dtype
        self.context = context
        self.context_key = context_key
        self.projection: Tensor | None = None
        self._seeds: np.random.Generator | None = None
        if context is not None:
            generator = torch.Generator().manual_seed(int(context_seed))
            self.projection = torch.randn(context, net.mask_dim, generator=generator) / math.sqrt(net.mask_dim)
            p = net.keep_prob
            self._scale = math.sqrt(p * (1.0 - p)) or 1.0
            z_max = max(p, 1.0 - p) / self._scale if 0.0 < p < 1.0 else 0.0
            # Exact bound of W @ z over z in the box, widened a hair against float32 rounding.
            bound = self.projection.double().abs().sum(-1).numpy() * z_max * (1 + 1e-5) + 1e-6
            self.context_low = np.concatenate([-bound, [0.0]]).astype(self.obs_dtype)
            self.context_high = np.concatenate([bound, [1.0]]).astype(self.obs_dtype)

    @property
    def context_dim(self) -> int:
        return 0 if self.context is None else self.context + 1

    def extend(self, space: spaces.Space[Any]) -> spaces.Space[Any]:
        """``space`` with the context's bounds appended (a ``Box``) or added as an entry (a ``Dict``)."""
        if self.context is None:
            return space
        if isinstance(space, spaces.Dict):
            box = spaces.Box(self.context_low, self.context_high, dtype=self.obs_dtype)
            return spaces.Dict({**space.spaces, self.context_key: box})
        assert isinstance(space, spaces.Box)
        low = np.concatenate([space.low, self.context_low]).astype(self.obs_dtype)
        high = np.concatenate([space.high, self.context_high]).astype(self.obs_dtype)
        return spaces.Box(low, high, dtype=self.obs_dtype)

    def tensor(self, value: Any) -> Tensor:
        param = next(self.model.net.parameters())
        return torch.as_tensor(np.asarray(value), dtype=param.dtype, device=param.device)

    def state(self, obs: Any) -> Tensor:
        """The part of an env observation the model sees, as a tensor in the model's dtype."""
        return self.tensor(obs if self.state_key is None else obs[self.state_key])

    def filter(self) -> ParticleFilter | None:
        found = getattr(self.model.adaptation, "filter", None)
        return found if isinstance(found, ParticleFilter) else None

    # ------------------------------------------------------------------ adaptation state
    def reset(self, batch_shape: tuple[int, ...], seed: int | None) -> None:
        self.model.reset(batch_shape=batch_shape)
        if seed is not None:
            self._seeds = np.random.default_rng(int(seed))
        particle_filter = self.filter()
        if self._seeds is not None and particle_filter is not None:
            # Reseed the filter from the wrapper's own seed stream (never the env's np_random), so
            # seeded episodes and the unseeded resets after them are repeatable, prior draw included.
            particle_filter.generator.manual_seed(int(self._seeds.integers(2**62)))
            particle_filter.reset(batch_shape)

    def reset_elements(self, where: np.ndarray) -> None:
        """Start a new adaptation episode for the batch elements where ``where`` is True."""
        self.model.reset(batch_shape=self.model.batch_shape, where=torch.as_tensor(where))

    def observe(self, obs: Tensor, action: Any, next_obs: Tensor, valid: np.ndarray | None = None) -> None:
        """Feed one transition per batch element; rows where ``valid`` is False carry no information.

        An invalid row's target is replaced by the model's own prediction, a transition without
        error signal, and the caller resets that row's state right after.
        """
        batch = tuple(obs.shape[:-1])
        td = TensorDict({self.obs_key: obs, self.action_key: self.tensor(action)}, batch_size=batch)
        if valid is not None and not valid.all():
            predicted = self.model(td.clone()).get(self.next_key)
            keep = torch.as_tensor(valid, device=next_obs.device).unsqueeze(-1)
            next_obs = torch.where(keep, next_obs, predicted)
        td.set(self.next_key, next_obs)
        self.model.observe(td)

    # ------------------------------------------------------------------ outputs
    def summary(self) -> dict[str, Tensor]:
        return {k: v.detach() for k, v in self.model.summary().items()}

    def context_vector(self) -> Tensor:
        """``[*batch, context + 1]``: the projected standardised MMSE mask and ``ess / N``."""
        assert self.projection is not None and self.context is not None
        batch = self.model.batch_shape
        mask = self.model.mask
        if mask is None:
            projected = torch.zeros(*batch, self.context)
        else:
            z = (mask.float().cpu() - self.model.net.keep_prob) / self._scale
            projected = z @ self.projection.T
        particle_filter = self.filter()
        ess = self.model.summary().get("ess")
        if ess is None or particle_filter is None:
            fraction = torch.ones(*batch, 1)
        else:
            fraction = (ess.float().cpu() / particle_filter.num_particles).reshape(*batch, 1)
        vector = torch.cat([projected, fraction], dim=-1).numpy()
        return torch.as_tensor(np.clip(vector, self.context_low, self.context_high))

    def augment(self, obs: Any) -> Any:
        if self.context is None:
            return obs
        vector = self.context_vector().numpy().astype(self.obs_dtype)
        if self.state_key is not None:
            return {**obs, self.context_key: vector}
        return np.concatenate([np.asarray(obs), vector], axis=-1).astype(self.obs_dtype)


class AdaptationWrapper(gymnasium.Wrapper[Any, np.ndarray, Any, np.ndarray], gymnasium.utils.RecordConstructorArgs):
    """The environment-step hook: adapts a dynamics model to every real step of a gymnasium env.

    * ``reset``: ``model.reset()`` (one adaptation state, ``batch_shape=()``); no transition is
      observed. With ``seed``, the model's filter is reseeded too, so a seeded episode, context
      included, is repeatable (gymnasium's determinism checks rely on it).
    * ``step(action)``: ``model.observe`` of the TensorDict ``{observation, action, ("next",
      "observation")}`` (the model's own keys) built from the previous and the new *original*
      observation and the action as passed to ``step``. The transition into a terminal state is
      observed like any other; the next one only follows a ``reset``.
    * ``info[info_key]``: the model's summary after the call, as floats (SMCD:
      ``{"ess": ..., "log_evidence": ...}``; ``{}`` for strategies without diagnostics).
    * ``context=k``: ``k + 1`` numbers appended to the observation (see the module docstring:
      a fixed random projection of the MMSE mask, then ``ess / N``) and to ``observation_space``.
      The model itself always sees the original observation.

    The env must have a flat ``Box`` action space and a flat ``Box`` observation space of the
    model's sizes, or a ``Dict`` observation space (a goal-conditioned env such as Fetch) whose
    entry named by the model's observation key (``"observation"`` by default) is that ``Box``.
    With a ``Dict`` the model observes that entry only, and the context is the new entry
    ``context_key`` (the other entries pass through), so SB3's ``"MultiInputPolicy"`` and
    ``HerReplayBuffer`` see it like any other entry. One wrapper owns its model's adaptation
    state: give every wrapped env its own model.

    Args:
        env: the env to wrap.
        model: the adaptive dynamics model, ``observation + action -> ("next", "observation")``.
        context: size of the mask projection to append to observations (``None``: no context).
        context_seed: seed of the fixed projection matrix.
        info_key: key of the summary in ``info``.
        context_key: the ``Dict`` entry of the context, for ``Dict`` observation spaces.

    Raises:
        ValueError: the env's spaces do not match the model's sizes (both are named), a ``Dict``
            space has no entry for the model or already has ``context_key``, or ``context`` is
            not a positive int.

    Example:
        >>> import gymnasium, torch, smcd_rl, warnings
        >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
        >>> from smcd_rl.integrations.gymnasium import AdaptationWrapper
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4 + 2, 4, hidden=(16,)),
        ...                                       adaptation=smcd_rl.SMCD(num_particles=20))
        >>> env = AdaptationWrapper(gymnasium.make("smcd_rl/TwoLinkArm-v0"), model, context=3)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, sorted(info["smcd"])
        ((8,), ['ess', 'log_evidence'])
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> env.observation_space.shape, info["smcd"]["log_evidence"] != 0.0
        ((8,), True)
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, np.ndarray],
        model: AdaptiveDynamicsModel,
        *,
        context: int | None = None,
        context_seed: int = 0,
        info_key: str = "smcd",
        context_key: str = CONTEXT_KEY,
    ) -> None:
        # Recorded (not copied) for env.spec; the spec deep-copies them once, so spec.make() gets its own model.
        gymnasium.utils.RecordConstructorArgs.__init__(
            self,
            model=model,
            context=context,
            context_seed=context_seed,
            info_key=info_key,
            context_key=context_key,
            _disable_deepcopy=True,
        )
        gymnasium.Wrapper.__init__(self, env)
        self._hook = _Hook(model, env, context=context, context_seed=context_seed, context_key=context_key)
        self.model = model
        self.info_key = info_key
        self.context_key = context_key
        if context is not None:
            self.observation_space = self._hook.extend(env.observation_space)
        self._last_obs: Tensor | None = None

    @property
    def context_dim(self) -> int:
        """How many numbers the context holds (``context + 1``, or 0)."""
        return self._hook.context_dim

    @property
    def context_projection(self) -> Tensor | None:
        """The fixed projection ``W [context, mask_dim]`` (``None`` without context)."""
        return self._hook.projection

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._hook.reset((), seed)
        self._last_obs = self._hook.state(obs)
        return self._hook.augment(obs), self._with_summary(info)

    def step(self, action: np.ndarray) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        if self._last_obs is None:
            raise RuntimeError("call reset() before step(): the wrapper needs the first observation")
        obs, reward, terminated, truncated, info = self.env.step(action)
        next_obs = self._hook.state(obs)
        self._hook.observe(self._last_obs, action, next_obs)
        self._last_obs = next_obs
        return self._hook.augment(obs), reward, terminated, truncated, self._with_summary(info)

    def _with_summary(self, info: dict[str, Any]) -> dict[str, Any]:
        info = dict(info)
        info[self.info_key] = {k: float(v) for k, v in self._hook.summary().items()}
        return info

    def compute_reward(self, achieved_goal: Any, desired_goal: Any, info: Any) -> Any:
        """The wrapped goal-conditioned env's ``compute_reward``: the wrapper changes no reward.

        So that the wrapper is a goal env like the one it wraps, for SB3's ``HerReplayBuffer`` and
        ``check_env`` (which call ``compute_reward`` on the outermost env).

        Raises:
            AttributeError: the wrapped env has no ``compute_reward`` (it is not goal-conditioned).
        """
        compute: Callable[[Any, Any, Any], Any] = self.env.get_wrapper_attr("compute_reward")
        return compute(achieved_goal, desired_goal, info)


class AdaptationVectorWrapper(VectorWrapper):
    """:class:`AdaptationWrapper` for a gymnasium vector env: one adaptation state per sub-env.

    The model is reset with ``batch_shape=(num_envs,)`` and observes one transition per sub-env
    and step. Episode boundaries follow ``env.metadata["autoreset_mode"]``:

    * ``NEXT_STEP`` (gymnasium's default): the step after a sub-env finished is its reset step;
      that step is not observed as a transition and only that sub-env's state starts afresh.
    * ``SAME_STEP``: the transition into ``info["final_obs"]`` is observed, then that sub-env's
      state starts afresh from the reset observation.
    * ``DISABLED``: ``reset(options={"reset_mask": m})`` starts afresh the sub-envs in ``m`` only.

    A sub-env's reset restarts only its own adaptation state (``model.reset(where=...)``: a fresh
    prior draw for :class:`smcd_rl.SMCD`, the trained weights and an empty window for
    :class:`smcd_rl.GradientDescent`). A full ``reset()`` resets all.

    ``info[info_key]`` holds the summary as arrays ``[num_envs]`` with gymnasium's ``"_key"``
    masks; ``context`` appends ``context + 1`` numbers to each sub-env's observation, or, for a
    ``Dict`` observation space, adds them as the entry ``context_key`` (``[num_envs, context + 1]``).

    Args:
        env: the vector env (flat ``Box`` single action space; a flat ``Box`` single observation
            space, or a ``Dict`` one with the model's entry, as for :class:`AdaptationWrapper`).
        model: the adaptive dynamics model.
        context: size of the mask projection to append (``None``: no context).
        context_seed: seed of the fixed projection matrix.
        info_key: key of the summary in ``info``.
        context_key: the ``Dict`` entry of the context, for ``Dict`` observation spaces.

    Example:
        >>> import gymnasium, smcd_rl, warnings
        >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
        >>> from smcd_rl.integrations.gymnasium import AdaptationVectorWrapper
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4 + 2, 4, hidden=(16,)),
        ...                                       adaptation=smcd_rl.SMCD(num_particles=20))
        >>> envs = AdaptationVectorWrapper(gymnasium.make_vec("smcd_rl/TwoLinkArm-v0", num_envs=2), model, context=3)
        >>> obs, info = envs.reset(seed=0)
        >>> obs, *_, info = envs.step(envs.action_space.sample())
        >>> obs.shape, model.particles.shape[0], info["smcd"]["ess"].shape
        ((2, 8), 2, (2,))
    """

    def __init__(
        self,
        env: VectorEnv,
        model: AdaptiveDynamicsModel,
        *,
        context: int | None = None,
        context_seed: int = 0,
        info_key: str = "smcd",
        context_key: str = CONTEXT_KEY,
    ) -> None:
        super().__init__(env)
        self._hook = _Hook(model, env, context=context, context_seed=context_seed, context_key=context_key)
        self.model = model
        self.info_key = info_key
        self.context_key = context_key
        mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self.autoreset_mode = mode if isinstance(mode, AutoresetMode) else AutoresetMode(mode)
        if context is not None:
            single = self._hook.extend(env.single_observation_space)
            self.single_observation_space = single
            self.observation_space = batch_space(single, env.num_envs)
        self._last_obs: Tensor | None = None
        self._autoreset = np.zeros(env.num_envs, dtype=np.bool_)

    @property
    def context_dim(self) -> int:
        """How many numbers each sub-env's context holds (``context + 1``, or 0)."""
        return self._hook.context_dim

    @property
    def context_projection(self) -> Tensor | None:
        """The fixed projection ``W [context, mask_dim]`` (``None`` without context)."""
        return self._hook.projection

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        options = dict(options) if options is not None else None  # the vector env pops "reset_mask"
        partial = None if options is None else options.get("reset_mask")
        # Sync and async vector envs take one seed per sub-env, though VectorEnv.reset's hint says int only.
        reset: Callable[..., tuple[Any, dict[str, Any]]] = self.env.reset
        obs, info = reset(seed=seed, options=options)
        next_obs = self._hook.state(obs)
        if partial is None or self._last_obs is None:
            first_seed = seed[0] if isinstance(seed, list) else seed
            self._hook.reset((self.num_envs,), first_seed)
            self._last_obs = next_obs
            self._autoreset[:] = False
        else:
            where = np.asarray(partial, dtype=np.bool_)
            self._hook.reset_elements(where)
            rows = torch.as_tensor(where, device=next_obs.device).unsqueeze(-1)
            self._last_obs = torch.where(rows, next_obs, self._last_obs)
            self._autoreset[where] = False
        return self._hook.augment(obs), self._with_summary(info)

    def step(self, actions: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._last_obs is None:
            raise RuntimeError("call reset() before step(): the wrapper needs the first observations")
        obs, rewards, terminations, truncations, info = self.env.step(actions)
        next_obs = self._hook.state(obs)
        done = np.logical_or(terminations, truncations)
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            # Sub-envs that finished last step were reset by this step: no transition, fresh state.
            starting = self._autoreset.copy()
            self._hook.observe(self._last_obs, actions, next_obs, valid=~starting)
            self._hook.reset_elements(starting)
            self._autoreset = done
        elif self.autoreset_mode == AutoresetMode.SAME_STEP:
            target = next_obs
            if done.any():
                final = info["final_obs"]
                key = self._hook.state_key
                rows = [
                    (final[i] if key is None else final[i][key]) if done[i] else (obs if key is None else obs[key])[i]
                    for i in range(self.num_envs)
                ]
                target = self._hook.tensor(np.stack(rows))
            self._hook.observe(self._last_obs, actions, target)
            self._hook.reset_elements(done)
        else:
            self._hook.observe(self._last_obs, actions, next_obs)
        self._last_obs = next_obs
        return self._hook.augment(obs), rewards, terminations, truncations, self._with_summary(info)

    def _with_summary(self, info: dict[str, Any]) -> dict[str, Any]:
        info = dict(info)
        everywhere = np.ones(self.num_envs, dtype=np.bool_)
        summary: dict[str, np.ndarray] = {}
        for key, value in self._hook.summary().items():
            summary[key] = value.cpu().numpy().reshape(self.num_envs)
            summary[f"_{key}"] = everywhere.copy()
        info[self.info_key] = summary
        info[f"_{self.info_key}"] = everywhere
        return info


def collect_transitions(
    env: gymnasium.Env[Any, Any],
    policy: SupportsPredict | Callable[[Any], Any] | None = None,
    steps: int = 1000,
    *,
    seed: int | None = None,
    deterministic: bool = False,
) -> TensorDict:
    """Run ``policy`` in ``env`` for ``steps`` steps and return the transitions for fitting.

    Episodes restart automatically; the transition into a terminal state is kept. Actions are
    clipped to a ``Box`` action space before the env sees them, and recorded as clipped.

    If ``env`` is (or wraps, through plain ``gymnasium.Wrapper`` layers) an
    :class:`AdaptationWrapper` with a context, the policy sees the observation with context and the
    recorded ``observation`` is the original one, the context columns (or ``Dict`` entry) dropped.

    ``Dict`` observations (goal-conditioned envs such as Fetch) are recorded entry by entry, each
    under its own key: ``"observation"``, ``"achieved_goal"``, ``"desired_goal"`` and
    ``("next", "observation")``, ... (the keys torchrl's ``GymEnv`` uses), so
    :func:`smcd_rl.fit_dynamics` learns the ``observation`` entry as it is.

    Args:
        env: a single (not vector) gymnasium env.
        policy: ``None`` for uniform random actions (``env.action_space.sample()``); an object
            with stable-baselines3's ``predict`` (an SB3 model or policy); or a callable mapping
            an observation to an action (e.g. :meth:`smcd_rl.agents.mpc.MPCAgent.act`).
        steps: number of transitions.
        seed: seeds the first ``reset`` and the action space's sampler.
        deterministic: passed to ``predict`` of an SB3 policy.

    Returns:
        TensorDict of batch ``[steps]`` with ``"observation"``, ``"action"`` and ``"next"``:
        ``{"observation", "reward" [steps, 1], "terminated", "truncated", "done" [steps, 1] (bool)}``
        (torchrl's layout), ready for :func:`smcd_rl.fit_dynamics`; with ``Dict`` observations,
        one key per entry in place of ``"observation"``, at the top level and under ``"next"``.

    Raises:
        ValueError: ``steps`` is not a positive int, or a ``Dict`` observation has nested or
            non-numeric entries, or entries named like a key of the layout (``"action"``,
            ``"next"``, ``"reward"``, ``"terminated"``, ``"truncated"``, ``"done"``).

    Example:
        >>> import gymnasium, smcd_rl
        >>> from smcd_rl.integrations.gymnasium import collect_transitions
        >>> data = collect_transitions(gymnasium.make("smcd_rl/TwoLinkArm-v0"), None, 50, seed=0)
        >>> data.batch_size, data["next", "observation"].shape, data["next", "reward"].shape
        (torch.Size([50]), torch.Size([50, 4]), torch.Size([50, 1]))
    """
    if isinstance(env, VectorEnv):
        raise TypeError("collect_transitions takes a single gymnasium.Env; collect per sub-env or use make(...)")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    wrapper = _adaptation_wrapper(env)
    strip = 0 if wrapper is None else wrapper.context_dim
    drop = None if wrapper is None or not strip else wrapper.context_key
    if policy is None:
        if seed is not None:
            env.action_space.seed(seed)
        act: Callable[[Any], Any] = lambda _obs: env.action_space.sample()  # noqa: E731
    elif isinstance(policy, SupportsPredict):
        act = lambda obs: policy.predict(obs, deterministic=deterministic)[0]  # noqa: E731
    elif callable(policy):
        act = policy
    else:
        raise TypeError(
            f"policy must be None, have an SB3-style predict(), or be callable; got {type(policy).__name__}"
        )
    space = env.action_space
    rows: dict[str, list[Any]] = {k: [] for k in ("obs", "action", "next", "reward", "term", "trunc")}
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        action = np.asarray(act(obs))
        if isinstance(space, spaces.Box):
            action = np.clip(action, space.low, space.high).astype(space.dtype)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        rows["obs"].append(_original(obs, strip, drop))
        rows["action"].append(np.asarray(action, dtype=np.float32))
        rows["next"].append(_original(next_obs, strip, drop))
        rows["reward"].append(np.asarray(reward, dtype=np.float32))
        rows["term"].append(np.asarray(terminated, dtype=np.bool_))
        rows["trunc"].append(np.asarray(truncated, dtype=np.bool_))
        obs = env.reset()[0] if terminated or truncated else next_obs
    term = torch.as_tensor(np.stack(rows["term"])).unsqueeze(-1)
    trunc = torch.as_tensor(np.stack(rows["trunc"])).unsqueeze(-1)
    return TensorDict(
        {
            **_stacked(rows["obs"]),
            "action": torch.as_tensor(np.stack(rows["action"])).reshape(steps, -1),
            "next": {
                **_stacked(rows["next"]),
                "reward": torch.as_tensor(np.stack(rows["reward"])).unsqueeze(-1),
                "terminated": term,
                "truncated": trunc,
                "done": term | trunc,
            },
        },
        batch_size=[steps],
    )


def _adaptation_wrapper(env: gymnasium.Env[Any, Any]) -> AdaptationWrapper | None:
    """The outermost AdaptationWrapper in ``env``'s wrapper chain, if any."""
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, AdaptationWrapper):
            return env
        env = env.env
    return None


#: Keys of collect_transitions' layout that a Dict observation entry must not take.
_LAYOUT_KEYS = ("action", "next", "reward", "terminated", "truncated", "done")


def _original(obs: Any, strip: int, drop: str | None) -> np.ndarray | dict[str, np.ndarray]:
    """The observation as the env below the wrapper made it: context columns or entry removed, float32."""
    if isinstance(obs, Mapping):
        entries = {}
        for key, value in obs.items():
            if key == drop:
                continue
            if not isinstance(key, str) or key in _LAYOUT_KEYS or isinstance(value, Mapping):
                raise ValueError(
                    f"collect_transitions records each Dict observation entry under its own key; entry {key!r} "
                    f"is nested or named like a key of the layout {_LAYOUT_KEYS}: flatten or rename it"
                )
            array = np.asarray(value)
            if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
                raise ValueError(f"Dict observation entry {key!r} is not numeric ({array.dtype})")
            entries[key] = array.astype(np.float32)
        return entries
    array = np.asarray(obs, dtype=np.float32)
    return array[..., : array.shape[-1] - strip] if strip else array


def _stacked(rows: list[Any]) -> dict[str, Tensor]:
    """``{"observation": [T, ...]}`` for array rows, one key per entry for Dict rows."""
    if isinstance(rows[0], dict):
        return {key: torch.as_tensor(np.stack([row[key] for row in rows])) for key in rows[0]}
    return {"observation": torch.as_tensor(np.stack(rows))}


def _dict_entry(space: spaces.Dict, key: Any) -> str:
    """The entry of a ``Dict`` observation space that a model with observation key ``key`` reads."""
    if not isinstance(key, str) or key not in space.spaces:
        raise ValueError(
            f"the env's observations are a Dict with entries {list(space.keys())}, but the model reads {key!r}; "
            "build the model with observation_key naming the entry it predicts (e.g. 'observation')"
        )
    return key


# ---------------------------------------------------------------------------------------- goal-conditioned envs
class _Columns:
    """``obs[..., start:stop]``: the achieved goal as a slice of the observation (picklable, with a repr)."""

    def __init__(self, index: slice) -> None:
        self.index = index

    def __call__(self, observation: Tensor) -> Tensor:
        return observation[..., self.index]

    def __repr__(self) -> str:
        return f"observation[..., {self.index.start}:{self.index.stop}]"


def fetch_achieved_goal(env: gymnasium.Env[Any, Any]) -> Callable[[Tensor], Tensor] | None:
    """The achieved goal of a gymnasium-robotics Fetch env as a function of its ``observation``, or ``None``.

    Fetch builds its observation as ``[grip_pos (3), object_pos (3), ...]`` and its achieved goal
    as the gripper's position (Reach: columns 0-2) or the object's (Push, Slide, PickAndPlace:
    columns 3-5). ``None`` for any other env.

    Example:
        >>> import gymnasium, smcd_rl
        >>> from smcd_rl.integrations.gymnasium import fetch_achieved_goal
        >>> fetch_achieved_goal(gymnasium.make("Pendulum-v1")) is None
        True
    """
    unwrapped = env.unwrapped
    # A subclass of a Fetch env (the registered smcd_rl families are) keeps Fetch's observation layout.
    fetch = any(cls.__module__.startswith("gymnasium_robotics.envs.fetch") for cls in type(unwrapped).__mro__)
    if not fetch or not hasattr(unwrapped, "has_object"):
        return None
    return _Columns(slice(3, 6) if unwrapped.has_object else slice(0, 3))


class GoalReward:
    """The planning reward of a goal-conditioned env: its own batched ``compute_reward``, in torch.

    A goal-conditioned env (gymnasium-robotics' Fetch, PointMaze, ...) has ``Dict`` observations
    ``{"observation", "achieved_goal", "desired_goal"}`` and a batched
    ``compute_reward(achieved_goal, desired_goal, info)`` (the outermost one of ``env`` and its
    wrappers, as ``env.get_wrapper_attr`` finds it, usually ``env.unwrapped``'s). The dynamics model
    predicts the ``observation`` entry; ``achieved_goal_fn`` maps a (predicted) observation to the
    goal it achieves, and the reward of a planned step is::

        reward(next_obs, desired_goal) = compute_reward(achieved_goal_fn(next_obs), desired_goal, {})

    computed in numpy on all candidates at once and returned as a tensor. ``info`` is ``{}``: a
    planned step has no info, so the env's reward must not depend on it (Fetch's and PointMaze's
    do not). Planners hold ``desired_goal`` fixed over a plan (:meth:`towards`).

    Why ``observation`` plus a function and not a model of the concatenation with the achieved
    goal: in Fetch the achieved goal *is* a slice of the observation, so predicting both would
    make the network predict the same quantity twice (and the filter count its errors twice), and
    the model's keys stay those of the real env, for gymnasium and torchrl alike.

    Args:
        env: a single goal-conditioned gymnasium env (wrappers allowed).
        achieved_goal_fn: pure batched ``observation [..., O] -> achieved_goal [..., G]`` in torch,
            or a ``slice`` of observation columns. ``None``: derived for gymnasium-robotics Fetch
            envs (:func:`fetch_achieved_goal`); any other env must pass it.
        observation_key: the ``Dict`` entry the model predicts.
        desired_goal_key: the ``Dict`` entry of the goal.

    Raises:
        TypeError: ``env`` is a vector env (pass one of its sub-envs: ``compute_reward`` is the same).
        ValueError: the env's observations are not a ``Dict`` with these entries (as ``Box``),
            it has no ``compute_reward``, ``achieved_goal_fn`` is missing and cannot be derived, or
            either function does not return one value per batch element on a test batch.

    Example:
        >>> import gymnasium, torch
        >>> from smcd_rl.integrations.gymnasium import GoalReward
        >>> class Point(gymnasium.Env):  # a goal env reduced to its spaces and reward
        ...     box = gymnasium.spaces.Box(-1.0, 1.0, (2,))
        ...     observation_space = gymnasium.spaces.Dict(observation=box, achieved_goal=box, desired_goal=box)
        ...     action_space = box
        ...     def compute_reward(self, achieved_goal, desired_goal, info):
        ...         return -((achieved_goal - desired_goal) ** 2).sum(-1) ** 0.5
        >>> reward = GoalReward(Point(), achieved_goal_fn=slice(0, 2))
        >>> reward(torch.zeros(5, 2), torch.tensor([3.0, 4.0])).tolist()
        [-5.0, -5.0, -5.0, -5.0, -5.0]
        >>> reward.towards(torch.tensor([0.0, 1.0]))(None, None, torch.zeros(3, 2)).shape  # a plan's RewardFn
        torch.Size([3])
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        *,
        achieved_goal_fn: Callable[[Tensor], Tensor] | slice | None = None,
        observation_key: str = "observation",
        desired_goal_key: str = "desired_goal",
    ) -> None:
        if isinstance(env, VectorEnv):
            raise TypeError(
                "GoalReward takes a single goal-conditioned env, not a vector env; pass one sub-env "
                "(gymnasium.make(id)): its compute_reward is the same batched function"
            )
        name = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        space = env.observation_space
        wanted = (observation_key, desired_goal_key)
        if not isinstance(space, spaces.Dict) or any(k not in space.spaces for k in wanted):
            entries = list(space.keys()) if isinstance(space, spaces.Dict) else None
            raise ValueError(
                f"a goal-conditioned env has Dict observations with entries {list(wanted)}; {name}'s observation "
                f"space is {space if entries is None else f'a Dict with entries {entries}'}"
            )
        boxes = {k: space[k] for k in wanted}
        for key, box in boxes.items():
            if not isinstance(box, spaces.Box) or len(box.shape) != 1:
                raise ValueError(f"{name}'s observation entry {key!r} must be a 1-d Box, got {box}")
        try:  # the outermost definition: a wrapper may define its own (this module's wrappers forward)
            compute = env.get_wrapper_attr("compute_reward")
        except AttributeError:
            compute = None
        if not callable(compute):
            raise ValueError(
                f"{name} has no compute_reward(achieved_goal, desired_goal, info), which a goal-conditioned env "
                "provides (gymnasium-robotics' GoalEnv); pass your own reward_fn instead"
            )
        if isinstance(achieved_goal_fn, slice):
            achieved_goal_fn = _Columns(achieved_goal_fn)
        if achieved_goal_fn is None:
            achieved_goal_fn = fetch_achieved_goal(env)
            if achieved_goal_fn is None:
                raise ValueError(
                    f"achieved_goal_fn is needed for {name}: a pure batched function mapping its "
                    f"{observation_key!r} [..., O] to the achieved goal [..., G] (e.g. slice(0, 3) for the "
                    "first three columns); it is derived only for gymnasium-robotics Fetch envs"
                )
        if not callable(achieved_goal_fn):
            raise TypeError(f"achieved_goal_fn must be callable or a slice, got {type(achieved_goal_fn).__name__}")
        self.env = env
        self.compute_reward: Callable[..., Any] = compute
        self.achieved_goal_fn: Callable[[Tensor], Tensor] = achieved_goal_fn
        self.observation_key = observation_key
        self.desired_goal_key = desired_goal_key
        self.observation_space: spaces.Box = boxes[observation_key]  # type: ignore[assignment]
        self.goal_space: spaces.Box = boxes[desired_goal_key]  # type: ignore[assignment]
        self.observation_dim = int(self.observation_space.shape[0])
        self.goal_dim = int(self.goal_space.shape[0])
        # Fail now, not in the middle of a plan, on functions that do not fit the env's sizes.
        probe = torch.zeros(2, self.observation_dim)
        achieved = self.achieved_goal(probe)
        if tuple(achieved.shape) != (2, self.goal_dim):
            raise ValueError(
                f"achieved_goal_fn maps observations [2, {self.observation_dim}] to shape {list(achieved.shape)}, "
                f"expected [2, {self.goal_dim}] (the size of {name}'s {desired_goal_key!r})"
            )
        self(probe, torch.zeros(self.goal_dim))

    def achieved_goal(self, observation: Tensor) -> Tensor:
        """``achieved_goal_fn(observation)``: ``[..., O] -> [..., G]``."""
        return self.achieved_goal_fn(observation)

    def __call__(self, next_observation: Tensor, desired_goal: Tensor) -> Tensor:
        """The env's reward for reaching ``next_observation [..., O]`` with goal ``desired_goal`` (broadcast), ``[...]``."""
        achieved = self.achieved_goal(next_observation)
        goal = torch.as_tensor(desired_goal, device=achieved.device, dtype=achieved.dtype).expand_as(achieved)
        batch = tuple(achieved.shape[:-1])
        flat_achieved = achieved.detach().reshape(-1, self.goal_dim).cpu().double().numpy()
        flat_goal = goal.detach().reshape(-1, self.goal_dim).cpu().double().numpy()
        reward = np.asarray(self.compute_reward(flat_achieved, flat_goal, {}), dtype=np.float64)
        if reward.size != flat_goal.shape[0]:
            raise ValueError(
                f"compute_reward returned shape {list(reward.shape)} for a batch of {flat_goal.shape[0]} goals; "
                "planning needs a batched compute_reward, one reward per row"
            )
        dtype = next_observation.dtype if next_observation.dtype.is_floating_point else torch.float32
        return torch.as_tensor(reward.reshape(batch), dtype=dtype, device=next_observation.device)

    def towards(self, desired_goal: Tensor | np.ndarray) -> Callable[[Any, Any, Tensor], Tensor]:
        """A :data:`smcd_rl.agents.mpc.RewardFn` ``(obs, action, next_obs) -> [...]`` for a fixed goal.

        ``desired_goal [*batch, G]`` is the goal of each planning problem; the reward function's
        ``next_obs [*batch, *extra, O]`` (e.g. ``extra = (P,)`` candidates) is scored towards it.
        """
        goal = torch.as_tensor(np.asarray(desired_goal) if not isinstance(desired_goal, Tensor) else desired_goal)
        if goal.dim() == 0 or goal.shape[-1] != self.goal_dim:
            raise ValueError(f"desired_goal must have shape [..., {self.goal_dim}], got {list(goal.shape)}")

        def reward_fn(obs: Any, action: Any, next_obs: Tensor) -> Tensor:
            extra = next_obs.dim() - goal.dim()
            if extra < 0 or tuple(next_obs.shape[: goal.dim() - 1]) != tuple(goal.shape[:-1]):
                raise ValueError(
                    f"next_obs {list(next_obs.shape)} does not start with the goal's batch {list(goal.shape[:-1])}"
                )
            shaped = goal.reshape(*goal.shape[:-1], *([1] * extra), self.goal_dim)
            return self(next_obs, shaped)

        return reward_fn

    def __repr__(self) -> str:
        name = self.env.spec.id if self.env.spec is not None else type(self.env.unwrapped).__name__
        return f"GoalReward({name}, achieved_goal_fn={self.achieved_goal_fn!r})"
