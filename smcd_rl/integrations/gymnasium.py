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
from collections.abc import Callable
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

__all__ = ["AdaptationWrapper", "AdaptationVectorWrapper", "collect_transitions", "SupportsPredict"]


@runtime_checkable
class SupportsPredict(Protocol):
    """Anything with stable-baselines3's ``predict`` (``BaseAlgorithm`` and ``BasePolicy`` both have it)."""

    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> Any: ...


class _Hook:
    """What both wrappers share: checks, tensors, the context vector, the summary and per-element state."""

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        observation_space: spaces.Space[Any],
        action_space: spaces.Space[Any],
        *,
        context: int | None,
        context_seed: int,
    ) -> None:
        if not isinstance(model, AdaptiveDynamicsModel):
            raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel, got {type(model).__name__}")
        net = model.net
        obs_dim = net.out_features
        action_dim = net.in_features - obs_dim
        sizes = f"(network {net.in_features} inputs = observation {obs_dim} + action {action_dim})"
        if not isinstance(observation_space, spaces.Box) or observation_space.shape != (obs_dim,):
            raise ValueError(
                f"the env's observation space {observation_space} does not match the model, which predicts "
                f"observations of shape ({obs_dim},) {sizes}"
            )
        if not np.issubdtype(observation_space.dtype, np.floating):
            raise ValueError(f"the env's observation space must be a floating Box, got {observation_space}")
        if not isinstance(action_space, spaces.Box) or action_space.shape != (action_dim,):
            raise ValueError(
                f"the env's action space {action_space} does not match the model, which takes actions of shape "
                f"({action_dim},) {sizes}"
            )
        if context is not None and (isinstance(context, bool) or not isinstance(context, int) or context < 1):
            raise ValueError(f"context must be None or a positive int (projection size), got {context!r}")
        self.model = model
        self.obs_key, self.action_key = model.in_keys[0], model.in_keys[1]
        self.next_key = model.out_key
        self.obs_dim = obs_dim
        self.obs_dtype = observation_space.dtype
        self.context = context
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

    def extend(self, space: spaces.Box) -> spaces.Box:
        """``space`` with the context's bounds appended."""
        if self.context is None:
            return space
        low = np.concatenate([space.low, self.context_low]).astype(self.obs_dtype)
        high = np.concatenate([space.high, self.context_high]).astype(self.obs_dtype)
        return spaces.Box(low, high, dtype=self.obs_dtype)

    def tensor(self, value: Any) -> Tensor:
        param = next(self.model.net.parameters())
        return torch.as_tensor(np.asarray(value), dtype=param.dtype, device=param.device)

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

    def augment(self, obs: np.ndarray) -> np.ndarray:
        if self.context is None:
            return obs
        return np.concatenate([np.asarray(obs), self.context_vector().numpy()], axis=-1).astype(self.obs_dtype)


class AdaptationWrapper(
    gymnasium.Wrapper[np.ndarray, np.ndarray, np.ndarray, np.ndarray], gymnasium.utils.RecordConstructorArgs
):
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

    The env must have flat ``Box`` observation and action spaces of the model's sizes. One
    wrapper owns its model's adaptation state: give every wrapped env its own model.

    Args:
        env: the env to wrap.
        model: the adaptive dynamics model, ``observation + action -> ("next", "observation")``.
        context: size of the mask projection to append to observations (``None``: no context).
        context_seed: seed of the fixed projection matrix.
        info_key: key of the summary in ``info``.

    Raises:
        ValueError: the env's spaces do not match the model's sizes (both are named), or
            ``context`` is not a positive int.

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
        env: gymnasium.Env[np.ndarray, np.ndarray],
        model: AdaptiveDynamicsModel,
        *,
        context: int | None = None,
        context_seed: int = 0,
        info_key: str = "smcd",
    ) -> None:
        # Recorded (not copied) for env.spec; the spec deep-copies them once, so spec.make() gets its own model.
        gymnasium.utils.RecordConstructorArgs.__init__(
            self, model=model, context=context, context_seed=context_seed, info_key=info_key, _disable_deepcopy=True
        )
        gymnasium.Wrapper.__init__(self, env)
        self._hook = _Hook(model, env.observation_space, env.action_space, context=context, context_seed=context_seed)
        self.model = model
        self.info_key = info_key
        if context is not None:
            self.observation_space = self._hook.extend(env.observation_space)  # type: ignore[arg-type]
        self._last_obs: Tensor | None = None

    @property
    def context_dim(self) -> int:
        """How many numbers are appended to each observation (``context + 1``, or 0)."""
        return self._hook.context_dim

    @property
    def context_projection(self) -> Tensor | None:
        """The fixed projection ``W [context, mask_dim]`` (``None`` without context)."""
        return self._hook.projection

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._hook.reset((), seed)
        self._last_obs = self._hook.tensor(obs)
        return self._hook.augment(obs), self._with_summary(info)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        if self._last_obs is None:
            raise RuntimeError("call reset() before step(): the wrapper needs the first observation")
        obs, reward, terminated, truncated, info = self.env.step(action)
        next_obs = self._hook.tensor(obs)
        self._hook.observe(self._last_obs, action, next_obs)
        self._last_obs = next_obs
        return self._hook.augment(obs), reward, terminated, truncated, self._with_summary(info)

    def _with_summary(self, info: dict[str, Any]) -> dict[str, Any]:
        info = dict(info)
        info[self.info_key] = {k: float(v) for k, v in self._hook.summary().items()}
        return info


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
    masks; ``context`` appends ``context + 1`` numbers to each sub-env's observation.

    Args:
        env: the vector env (flat ``Box`` single observation and action spaces).
        model: the adaptive dynamics model.
        context: size of the mask projection to append (``None``: no context).
        context_seed: seed of the fixed projection matrix.
        info_key: key of the summary in ``info``.

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
    ) -> None:
        super().__init__(env)
        self._hook = _Hook(
            model, env.single_observation_space, env.single_action_space, context=context, context_seed=context_seed
        )
        self.model = model
        self.info_key = info_key
        mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self.autoreset_mode = mode if isinstance(mode, AutoresetMode) else AutoresetMode(mode)
        if context is not None:
            single = self._hook.extend(env.single_observation_space)  # type: ignore[arg-type]
            self.single_observation_space = single
            self.observation_space = batch_space(single, env.num_envs)
        self._last_obs: Tensor | None = None
        self._autoreset = np.zeros(env.num_envs, dtype=np.bool_)

    @property
    def context_dim(self) -> int:
        """How many numbers are appended to each sub-env's observation (``context + 1``, or 0)."""
        return self._hook.context_dim

    @property
    def context_projection(self) -> Tensor | None:
        """The fixed projection ``W [context, mask_dim]`` (``None`` without context)."""
        return self._hook.projection

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        options = dict(options) if options is not None else None  # the vector env pops "reset_mask"
        partial = None if options is None else options.get("reset_mask")
        # Sync and async vector envs take one seed per sub-env, though VectorEnv.reset's hint says int only.
        reset: Callable[..., tuple[np.ndarray, dict[str, Any]]] = self.env.reset
        obs, info = reset(seed=seed, options=options)
        next_obs = self._hook.tensor(obs)
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

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._last_obs is None:
            raise RuntimeError("call reset() before step(): the wrapper needs the first observations")
        obs, rewards, terminations, truncations, info = self.env.step(actions)
        next_obs = self._hook.tensor(obs)
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
                final = np.stack([info["final_obs"][i] if done[i] else obs[i] for i in range(self.num_envs)])
                target = self._hook.tensor(final)
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
    policy: SupportsPredict | Callable[[np.ndarray], Any] | None = None,
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
    recorded ``observation`` is the original one, the context columns dropped.

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
        (torchrl's layout), ready for :func:`smcd_rl.fit_dynamics`.

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
    strip = _context_dim(env)
    if policy is None:
        if seed is not None:
            env.action_space.seed(seed)
        act: Callable[[np.ndarray], Any] = lambda _obs: env.action_space.sample()  # noqa: E731
    elif isinstance(policy, SupportsPredict):
        act = lambda obs: policy.predict(obs, deterministic=deterministic)[0]  # noqa: E731
    elif callable(policy):
        act = policy
    else:
        raise TypeError(
            f"policy must be None, have an SB3-style predict(), or be callable; got {type(policy).__name__}"
        )
    space = env.action_space
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "action", "next", "reward", "term", "trunc")}
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        action = np.asarray(act(obs))
        if isinstance(space, spaces.Box):
            action = np.clip(action, space.low, space.high).astype(space.dtype)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        rows["obs"].append(_original(obs, strip))
        rows["action"].append(np.asarray(action, dtype=np.float32))
        rows["next"].append(_original(next_obs, strip))
        rows["reward"].append(np.asarray(reward, dtype=np.float32))
        rows["term"].append(np.asarray(terminated, dtype=np.bool_))
        rows["trunc"].append(np.asarray(truncated, dtype=np.bool_))
        obs = env.reset()[0] if terminated or truncated else next_obs
    term = torch.as_tensor(np.stack(rows["term"])).unsqueeze(-1)
    trunc = torch.as_tensor(np.stack(rows["trunc"])).unsqueeze(-1)
    return TensorDict(
        {
            "observation": torch.as_tensor(np.stack(rows["obs"])),
            "action": torch.as_tensor(np.stack(rows["action"])).reshape(steps, -1),
            "next": {
                "observation": torch.as_tensor(np.stack(rows["next"])),
                "reward": torch.as_tensor(np.stack(rows["reward"])).unsqueeze(-1),
                "terminated": term,
                "truncated": trunc,
                "done": term | trunc,
            },
        },
        batch_size=[steps],
    )


def _context_dim(env: gymnasium.Env[Any, Any]) -> int:
    """Context columns appended by the outermost AdaptationWrapper in ``env``'s wrapper chain."""
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, AdaptationWrapper):
            return env.context_dim
        env = env.env
    return 0


def _original(obs: Any, strip: int) -> np.ndarray:
    array = np.asarray(obs, dtype=np.float32)
    return array[..., : array.shape[-1] - strip] if strip else array
