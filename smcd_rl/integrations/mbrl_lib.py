"""mbrl-lib integration: an adaptive model as an mbrl-lib dynamics model, and a PETS-style loop.

* :class:`MbrlLibModel` gives an :class:`~smcd_rl.AdaptiveDynamicsModel` the model interface that
  ``mbrl.models.ModelEnv`` drives (``device``, ``reset(obs, rng)``, ``sample(act, state,
  deterministic, rng)``), so mbrl-lib's own ``ModelEnv.evaluate_action_sequences`` and
  ``mbrl.planning.TrajectoryOptimizerAgent`` (CEM, iCEM, MPPI) plan on the adapted model. Its
  ``propagation`` maps PETS's propagation methods onto the mask posterior (see below).
* :func:`make_model_env` builds that ``ModelEnv`` with a reward and termination of this library's
  batched-torch convention (``reward_fn(obs, action, next_obs)``, ``termination_fn(next_obs)``, as
  :func:`smcd_rl.envs.crippled_ant.ant_reward` and :func:`~smcd_rl.envs.crippled_ant.ant_termination`);
  :func:`make_cem_agent` builds mbrl-lib's CEM ``TrajectoryOptimizerAgent`` on it.
* :func:`pets_loop` is PETS with an adaptive model: collect random transitions, fit, plan with
  mbrl-lib's agent, adapt on every real step (mbrl-lib's own loop has no per-step hook).
* :func:`replay_buffer_to_tensordict` turns an ``mbrl.util.ReplayBuffer`` into the TensorDict
  :func:`smcd_rl.fit_dynamics` trains on.

Propagation (how each of the ``B = candidates x particles`` rows of a planning batch is predicted):

* ``"fixed_model"`` (PETS's TS-infinity, the default): at ``reset`` each row draws one mask from the
  posterior (a particle, with the filter's weights) and keeps it for the whole horizon, so the
  ``num_particles`` rows of one candidate sample the model uncertainty that is left after adapting.
* ``"random_model"`` (PETS's TS-1): each row draws a fresh mask from the posterior at every step.
* ``"expectation"``: every row uses the model's adapted prediction, the MMSE mask (the predictive
  mean with ``SMCD(prediction="predictive")``); ``num_particles=1`` suffices then. This is the only
  mode for strategies without particles (``NoAdaptation``, ``GradientDescent``).

An **ensemble** (a list of models, e.g. the members of an mbrl-lib ``GaussianMLP`` that
:func:`smcd_rl.integrations.mbrl_models.dynamics_models_from_mbrl` wraps) propagates over its
members as PETS does, each member predicting with its own adapted state: ``"fixed_model"`` gives
each row one member for the horizon (a random permutation of the rows, split evenly),
``"random_model"`` a fresh member per row at every step, ``"expectation"`` the members' mean.

``None`` (all ensemble members' outputs, mbrl-lib's training mode) is refused: this model is not
trained through mbrl-lib's ``ModelTrainer``, but with :func:`smcd_rl.fit_dynamics`. The network has no
output noise, so ``sample``'s ``deterministic`` flag changes nothing; the propagation alone says
which masks predict. The posterior is read at ``reset``, i.e. once per planning call, and the
adapter never adapts the model: call ``model.observe`` on real steps (:func:`pets_loop` and
:class:`smcd_rl.integrations.gymnasium.AdaptationWrapper` do).

mbrl-lib 0.2.0 pins gymnasium 0.26.3, so it is installed without its dependencies, together with
the few packages it needs at import (whose own dependencies this library already has):
``bash scripts/install_mbrl_lib.sh`` in a checkout, or by hand:

    pip install --no-deps mbrl==0.2.0 hydra-core==1.3.2 omegaconf==2.3.0 antlr4-python3-runtime==4.9.3 termcolor==3.3.0

This module imports without mbrl-lib; :class:`MbrlLibModel` needs only torch, and the functions that
build mbrl-lib objects raise an ``ImportError`` naming these commands when it is missing.

Example:
    >>> import numpy as np, torch, smcd_rl
    >>> from smcd_rl.integrations.mbrl_lib import MbrlLibModel
    >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(16,)), smcd_rl.SMCD(num_particles=10))
    >>> model.fitted = True  # a random stand-in for a trained network
    >>> model.reset()
    >>> adapter = MbrlLibModel(model, reward_fn=lambda obs, act, next_obs: -next_obs.square().sum(-1))
    >>> rng = torch.Generator().manual_seed(0)
    >>> state = adapter.reset(np.zeros((6, 3), dtype=np.float32), rng=rng)  # as ModelEnv.reset calls it
    >>> next_obs, reward, _, state = adapter.sample(torch.zeros(6, 1), state, rng=rng)
    >>> next_obs.shape, reward.shape, state["masks"].shape
    (torch.Size([6, 3]), torch.Size([6, 1]), torch.Size([6, 16]))
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, Literal

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from torch import Tensor

from smcd_rl.files import CheckpointMismatchError, load_file, save_file
from smcd_rl.model import AdaptiveDynamicsModel
from smcd_rl.strategies import SMCD
from smcd_rl.training import fit_dynamics

__all__ = [
    "Propagation",
    "PROPAGATIONS",
    "INSTALL_COMMANDS",
    "MbrlLibModel",
    "termination_for_mbrl",
    "make_model_env",
    "make_cem_agent",
    "replay_buffer_to_tensordict",
    "pets_loop",
]

#: How the rows of a planning batch are predicted (see the module docstring).
Propagation = Literal["fixed_model", "random_model", "expectation"]
PROPAGATIONS: tuple[str, ...] = ("fixed_model", "random_model", "expectation")

#: The commands that install mbrl-lib 0.2.0 beside this library's pinned stack.
INSTALL_COMMANDS = (
    "pip install --no-deps mbrl==0.2.0 hydra-core==1.3.2 omegaconf==2.3.0 "
    "antlr4-python3-runtime==4.9.3 termcolor==3.3.0"
)

RewardFn = Callable[[Tensor, Tensor, Tensor], Tensor]
TerminationFn = Callable[[Tensor], Tensor]


def _mbrl(submodule: str) -> ModuleType:
    """``mbrl.<submodule>``, or an ImportError that says how to install mbrl-lib."""
    try:
        return importlib.import_module(f"mbrl.{submodule}")
    except Exception as err:  # hydra-core 1.0.3 (mbrl's own pin) fails on Python 3.11 with a ValueError
        raise ImportError(
            f"this needs mbrl-lib 0.2.0, which could not be imported ({type(err).__name__}: {err}). mbrl-lib pins "
            "gymnasium 0.26.3, so install it without its dependencies: in a checkout of smcd-rl run "
            f"`bash scripts/install_mbrl_lib.sh`, or run `{INSTALL_COMMANDS}`"
        ) from err


class MbrlLibModel:
    """An adaptive dynamics model with the interface mbrl-lib's ``ModelEnv`` calls.

    ``ModelEnv`` uses only :attr:`device`, :meth:`reset` and :meth:`sample`; it never trains the
    model. The model keeps adapting through ``model.observe`` (it is shared, never copied), and
    each planning call sees the posterior at its start.

    Args:
        model: the dynamics model, reset with ``batch_shape=()`` (one env) before planning; or a
            list of them, an ensemble of one observation and action size (module docstring).
        propagation: ``"fixed_model"``, ``"random_model"`` or ``"expectation"`` (module docstring).
        reward_fn: batched torch reward ``(obs [B, O], action [B, A], next_obs [B, O]) -> [B]``
            (or ``[B, 1]``); :meth:`sample` returns it as the predicted reward, which ``ModelEnv``
            uses when built without a ``reward_fn`` of its own. ``None``: no reward (pass
            mbrl-lib's ``reward_fn(act, next_obs)`` to ``ModelEnv`` instead).

    Raises:
        TypeError: ``model`` is not an :class:`~smcd_rl.AdaptiveDynamicsModel` (or a non-empty list of them).
        ValueError: an unknown ``propagation``; a sampling one for one model whose strategy keeps no
            particles; an ensemble whose members differ in sizes.
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel | Sequence[AdaptiveDynamicsModel],
        *,
        propagation: Propagation = "fixed_model",
        reward_fn: RewardFn | None = None,
    ) -> None:
        given: list[Any] = list(model) if isinstance(model, (list, tuple)) else [model]
        if not given or not all(isinstance(m, AdaptiveDynamicsModel) for m in given):
            got = type(model).__name__ if not given else sorted({type(m).__name__ for m in given})
            raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel or a non-empty list of them, got {got}")
        members: list[AdaptiveDynamicsModel] = given
        sizes = {(m.observation_dim, m.action_dim) for m in members}
        if len(sizes) > 1:
            raise ValueError(
                f"the ensemble's members differ in (observation, action) sizes {sorted(sizes)}; they must model one env"
            )
        first = members[0]
        if propagation not in PROPAGATIONS:
            raise ValueError(
                f"propagation must be one of {PROPAGATIONS}, got {propagation!r}; mbrl-lib's None (every member's "
                "output, for its ModelTrainer) does not apply: fit the model with smcd_rl.fit_dynamics"
            )
        if len(members) == 1 and propagation != "expectation" and not isinstance(first.adaptation, SMCD):
            raise ValueError(
                f"propagation={propagation!r} draws masks from the SMCD posterior, but the model adapts with "
                f"{type(first.adaptation).__name__}, which keeps no particles; use propagation='expectation'"
            )
        self.model: AdaptiveDynamicsModel = first
        #: The ensemble's members (``[model]`` for one model).
        self.members = members
        self.propagation: Propagation = propagation
        self.reward_fn = reward_fn

    @property
    def device(self) -> torch.device:
        """Where the network's weights are: ``ModelEnv`` sends actions and keeps its generator there."""
        return next(self.model.net.parameters()).device

    def reset(self, obs: np.ndarray | Tensor, rng: torch.Generator | None = None) -> dict[str, Tensor]:
        """The state of ``B`` model rollouts from ``obs [B, O]``; with mask sampling, one mask per row.

        Args:
            obs: the start observations (``ModelEnv`` tiles the current one ``B`` times).
            rng: where the masks are drawn from (``ModelEnv`` passes its own generator).

        Returns:
            ``{"obs": [B, O]}``, plus for ``"fixed_model"`` ``"masks" [B, mask_dim]`` (one model) or
            ``"members" [B]`` (an ensemble: the member each row follows).
        """
        observation = self._tensor(obs)
        if observation.dim() != 2 or observation.shape[-1] != self.model.observation_dim:
            raise ValueError(
                f"reset needs observations [B, {self.model.observation_dim}], got {list(observation.shape)}"
            )
        state = {"obs": observation}
        if self.propagation == "fixed_model" and self.ensemble:
            # PETS's TS-infinity: a random permutation of the rows, split evenly over the members.
            rows = observation.shape[0]
            state["members"] = torch.randperm(rows, generator=self._cpu(rng)).to(observation.device) % len(self.members)
        elif self.propagation == "fixed_model":
            state["masks"] = self._draw_masks(observation.shape[0], rng)
        return state

    @property
    def ensemble(self) -> bool:
        """Whether this adapter plans with several members."""
        return len(self.members) > 1

    def sample(
        self,
        act: Tensor | np.ndarray,
        model_state: dict[str, Tensor],
        deterministic: bool = False,
        rng: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor | None, None, dict[str, Tensor]]:
        """One model step of every row: ``(next_obs [B, O], reward [B, 1] or None, None, next state)``.

        ``deterministic`` is accepted for ``ModelEnv`` and changes nothing (the network has no
        output noise; see the module docstring). The third element, terminals, is always
        ``None``: ``ModelEnv`` computes termination with its ``termination_fn``.
        """
        del deterministic  # no output noise: the propagation alone decides the masks
        obs, fixed_masks = self._checked_state(model_state)
        action = self._tensor(act)
        if action.shape != (obs.shape[0], self.model.action_dim):
            raise ValueError(
                f"sample needs actions [{obs.shape[0]}, {self.model.action_dim}], got {list(action.shape)}"
            )
        if self.ensemble:
            next_obs = self._ensemble_step(obs, action, model_state, rng)
            return next_obs, self._reward(obs, action, next_obs), None, {**model_state, "obs": next_obs}
        if self.propagation == "fixed_model":
            masks: Tensor | None = fixed_masks
        elif self.propagation == "random_model":
            masks = self._draw_masks(obs.shape[0], rng)
        else:
            masks = None
        with torch.no_grad():
            next_obs = self.model.step(obs, action, mask=masks)
        return next_obs, self._reward(obs, action, next_obs), None, {**model_state, "obs": next_obs}

    def _ensemble_step(
        self, obs: Tensor, action: Tensor, model_state: dict[str, Tensor], rng: torch.Generator | None
    ) -> Tensor:
        """Each row's next observation from its member (``"expectation"``: the members' mean)."""
        with torch.no_grad():
            if self.propagation == "expectation":
                return torch.stack([m.step(obs, action) for m in self.members]).mean(0)
            if self.propagation == "fixed_model":
                rows = model_state["members"]
            else:
                drawn = torch.randint(len(self.members), (obs.shape[0],), generator=self._cpu(rng))
                rows = drawn.to(obs.device)
            next_obs = torch.empty_like(obs)
            for index, member in enumerate(self.members):
                mine = rows == index
                if bool(mine.any()):
                    next_obs[mine] = member.step(obs[mine], action[mine])
            return next_obs

    def _reward(self, obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor | None:
        if self.reward_fn is None:
            return None
        with torch.no_grad():
            reward = self.reward_fn(obs, action, next_obs)
        if reward.shape not in ((obs.shape[0],), (obs.shape[0], 1)):
            raise ValueError(
                f"reward_fn returned shape {list(reward.shape)} for {obs.shape[0]} rows; it must return [B] or [B, 1]"
            )
        return reward.reshape(-1, 1).to(torch.float32)

    @staticmethod
    def _cpu(rng: torch.Generator | None) -> torch.Generator | None:
        """``rng`` where it draws on the CPU (member indices are drawn there), else none."""
        return rng if rng is not None and rng.device.type == "cpu" else None

    def _checked_state(self, model_state: Any) -> tuple[Tensor, Tensor | None]:
        """The rows' observations and (``"fixed_model"``) masks, after checking the state is one :meth:`reset` made."""
        fix = f"pass the state that this adapter's reset (propagation={self.propagation!r}) returned, as ModelEnv does"
        fixed = "members" if self.ensemble else "masks"
        expected = ["obs", fixed] if self.propagation == "fixed_model" else ["obs"]
        if not isinstance(model_state, dict) or any(key not in model_state for key in expected):
            got = sorted(model_state) if isinstance(model_state, dict) else type(model_state).__name__
            raise ValueError(
                f"sample got a model state {got} that is not from this model's reset: it needs the keys {expected}; {fix}"
            )
        obs = model_state["obs"]
        if not isinstance(obs, Tensor) or obs.dim() != 2 or obs.shape[-1] != self.model.observation_dim:
            shape = list(obs.shape) if isinstance(obs, Tensor) else type(obs).__name__
            raise ValueError(
                f"the model state's obs must be a tensor [B, {self.model.observation_dim}], got {shape}: "
                f"the state is not from this model's reset; {fix}"
            )
        if self.propagation != "fixed_model":
            return obs, None
        if self.ensemble:
            members = model_state["members"]
            if (
                not isinstance(members, Tensor)
                or members.shape != (obs.shape[0],)
                or members.dtype != torch.long
                or bool(((members < 0) | (members >= len(self.members))).any())
            ):
                raise ValueError(
                    f"the model state's members must be a long tensor [{obs.shape[0]}] of indices in "
                    f"[0, {len(self.members)}) (one member per row of obs); {fix}"
                )
            return obs, None
        masks = model_state["masks"]
        mask_dim = self.model.net.mask_dim
        if not isinstance(masks, Tensor) or masks.shape != (obs.shape[0], mask_dim):
            shape = list(masks.shape) if isinstance(masks, Tensor) else type(masks).__name__
            raise ValueError(
                f"the model state's masks must be a tensor [{obs.shape[0]}, {mask_dim}] (one mask per row of obs), "
                f"got {shape}: the state is not from this model's reset; {fix}"
            )
        binary = (masks == 0) | (masks == 1)
        if not bool(binary.all()):
            bad = masks[~binary][0].item()
            raise ValueError(
                f"the model state's masks must hold only 0 and 1 (dropout masks drawn from the posterior), got {bad}; "
                f"{fix}, or masks of 0s and 1s"
            )
        return obs, masks

    def _draw_masks(self, rows: int, rng: torch.Generator | None) -> Tensor:
        """``rows`` masks drawn from the posterior (particles with the filter's weights), as floats."""
        if self.model.batch_shape != ():
            raise ValueError(
                f"plan with a model reset for one env (batch_shape=()), not {self.model.batch_shape}: "
                "mbrl-lib's ModelEnv plans for one observation"
            )
        adaptation = self.model.adaptation
        assert isinstance(adaptation, SMCD) and adaptation.filter is not None  # checked in __init__; reset since
        weights = adaptation.filter.weights  # [N]
        if rng is not None and rng.device != weights.device:
            rng = None  # a generator on another device cannot draw for these weights
        index = torch.multinomial(weights, rows, replacement=True, generator=rng)
        # Float masks: the masked matmul costs about 2.5x more with bool ones.
        return adaptation.particles.index_select(0, index).to(next(self.model.net.parameters()).dtype)

    def _tensor(self, value: Tensor | np.ndarray) -> Tensor:
        param = next(self.model.net.parameters())
        return torch.as_tensor(value).to(device=param.device, dtype=param.dtype)


def termination_for_mbrl(termination_fn: TerminationFn | None) -> Callable[[Tensor, Tensor], Tensor]:
    """A termination of this library's convention in mbrl-lib's: ``(act, next_obs) -> bool [B, 1]``.

    Args:
        termination_fn: ``next_obs [B, O] -> bool [B]`` (or ``[B, 1]``); ``None``: never terminates.

    Example:
        >>> import torch
        >>> from smcd_rl.integrations.mbrl_lib import termination_for_mbrl
        >>> done = termination_for_mbrl(lambda next_obs: next_obs[:, 0].abs() > 1.0)
        >>> done(torch.zeros(2, 1), torch.tensor([[0.5], [2.0]]))
        tensor([[False],
                [ True]])
    """

    def terminated(act: Tensor, next_obs: Tensor) -> Tensor:
        if termination_fn is None:
            return torch.zeros(next_obs.shape[0], 1, dtype=torch.bool, device=next_obs.device)
        flags = termination_fn(next_obs)
        if flags.shape not in ((next_obs.shape[0],), (next_obs.shape[0], 1)):
            raise ValueError(
                f"termination_fn returned shape {list(flags.shape)} for {next_obs.shape[0]} rows; it must return [B] or [B, 1]"
            )
        return flags.reshape(-1, 1).to(torch.bool)

    return terminated


def make_model_env(
    env: gymnasium.Env[Any, Any],
    model: AdaptiveDynamicsModel | Sequence[AdaptiveDynamicsModel],
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None = None,
    *,
    propagation: Propagation = "fixed_model",
    seed: int | None = None,
) -> Any:
    """mbrl-lib's ``ModelEnv`` on the adaptive model, with this library's reward and termination.

    Args:
        env: the real env (``ModelEnv`` reads its observation and action spaces).
        model: the dynamics model, or an ensemble of them (see :class:`MbrlLibModel`).
        reward_fn: batched torch reward ``(obs, action, next_obs) -> [B]``, e.g.
            :func:`smcd_rl.envs.crippled_ant.ant_reward`.
        termination_fn: batched torch termination ``next_obs -> bool [B]``; ``None``: never.
        propagation: see :class:`MbrlLibModel`.
        seed: seeds the generator ``ModelEnv`` draws masks with (``None``: torch's default seed).

    Returns:
        An ``mbrl.models.ModelEnv``; its ``dynamics_model`` is the :class:`MbrlLibModel`.

    Raises:
        ImportError: mbrl-lib is not installed (the message names the install commands).
        ValueError: the env's observation or action size is not the model's.
    """
    models = _mbrl("models")
    adapter = MbrlLibModel(model, propagation=propagation, reward_fn=reward_fn)
    _check_spaces(env, adapter.model)
    generator = torch.Generator(device=adapter.device)
    if seed is not None:
        generator.manual_seed(int(seed))
    return models.ModelEnv(env, adapter, termination_for_mbrl(termination_fn), None, generator=generator)


def _check_spaces(env: gymnasium.Env[Any, Any], model: AdaptiveDynamicsModel) -> None:
    """Refuse an env whose flat Box observations or actions are not of the model's sizes."""
    for what, space, size in (
        ("observation", env.observation_space, model.observation_dim),
        ("action", env.action_space, model.action_dim),
    ):
        shape = getattr(space, "shape", None)
        if not isinstance(space, gymnasium.spaces.Box) or shape != (size,):
            raise ValueError(
                f"the env's {what} space is {space}, but the model's {what}s have size {size}: mbrl-lib's ModelEnv "
                f"needs a flat Box of that size; build the model for this env ({what} size "
                f"{shape[-1] if isinstance(space, gymnasium.spaces.Box) and shape else '?'}), or pass the env it was made for"
            )


def _check_int(name: str, value: Any, low: int, why: str = "") -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}{why}")


def _check_cem_settings(
    *,
    planning_horizon: int,
    num_iterations: int,
    population_size: int,
    elite_ratio: float,
    alpha: float,
    num_particles: int,
    replan_freq: int,
) -> None:
    """The CEM agent's settings, checked before mbrl-lib fails deep inside or plans nonsense with them."""
    _check_int("planning_horizon", planning_horizon, 1)
    _check_int("num_iterations", num_iterations, 1, " (with 0, mbrl-lib's CEM never samples and returns action 0)")
    _check_int("population_size", population_size, 1)
    _check_int("num_particles", num_particles, 1)
    _check_int("replan_freq", replan_freq, 1)
    if replan_freq > planning_horizon:
        raise ValueError(
            f"replan_freq must be in [1, planning_horizon={planning_horizon}] (a plan has only planning_horizon "
            f"actions), got {replan_freq}"
        )
    for name, value, ok, valid in (
        ("elite_ratio", elite_ratio, lambda v: 0 < v <= 1, "in (0, 1]"),
        ("alpha", alpha, lambda v: 0 <= v < 1, "in [0, 1) (with 1 the CEM mean never moves from action 0)"),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or not ok(value):
            raise ValueError(f"{name} must be {valid}, got {value!r}")
    elites = math.ceil(population_size * elite_ratio)  # as mbrl-lib's CEMOptimizer counts them
    if num_iterations > 1 and elites < 2:
        least_population = math.floor(1 / elite_ratio) + 1
        while math.ceil(least_population * elite_ratio) < 2:  # float rounding of 1 / elite_ratio
            least_population += 1
        raise ValueError(
            f"population_size={population_size} with elite_ratio={elite_ratio} keeps {elites} elite, but CEM with "
            f"num_iterations={num_iterations} needs at least 2 (the variance of one elite is NaN, and so are the "
            f"actions): use population_size >= {least_population}, elite_ratio > {1 / population_size:.3g}, "
            "or num_iterations=1"
        )


def make_cem_agent(
    model_env: Any,
    *,
    planning_horizon: int = 15,
    num_iterations: int = 5,
    population_size: int = 350,
    elite_ratio: float = 0.1,
    alpha: float = 0.1,
    num_particles: int = 20,
    replan_freq: int = 1,
    clipped_normal: bool = False,
) -> Any:
    """mbrl-lib's ``TrajectoryOptimizerAgent`` with its ``CEMOptimizer``, planning on ``model_env``.

    The same agent as ``mbrl.planning.create_trajectory_optim_agent_for_model`` with mbrl-lib's
    PETS configuration (``_recursive_: False``, which hydra-core 1.3 needs for the nested
    optimizer config). Objective: ``model_env.evaluate_action_sequences`` with
    ``num_particles`` rows per candidate, the mean predicted return.

    Args:
        model_env: an ``mbrl.models.ModelEnv`` (e.g. from :func:`make_model_env`).
        planning_horizon: steps of each action sequence, >= 1.
        num_iterations: CEM iterations per plan, >= 1.
        population_size: candidates per iteration, >= 1.
        elite_ratio: fraction of candidates kept as elites, in (0, 1]; with ``num_iterations > 1``
            the ``ceil(population_size * elite_ratio)`` elites must be at least 2.
        alpha: momentum of the CEM mean and variance, in [0, 1).
        num_particles: rows per candidate (masks with ``"fixed_model"`` / ``"random_model"``), >= 1.
        replan_freq: plan every ``replan_freq`` steps, in [1, planning_horizon].
        clipped_normal: clipped instead of truncated normal samples.

    Returns:
        The agent: ``agent.act(obs)`` plans and returns the first action; ``agent.reset()`` at
        each episode start clears its warm start.

    Raises:
        ImportError: mbrl-lib is not installed.
        ValueError: a setting is out of its range (the message names it and the range).
    """
    _check_cem_settings(
        planning_horizon=planning_horizon,
        num_iterations=num_iterations,
        population_size=population_size,
        elite_ratio=elite_ratio,
        alpha=alpha,
        num_particles=num_particles,
        replan_freq=replan_freq,
    )
    planning = _mbrl("planning")
    omegaconf = importlib.import_module("omegaconf")
    action_space = model_env.action_space
    device = str(model_env.device)
    config = omegaconf.OmegaConf.create(
        {
            "_target_": "mbrl.planning.TrajectoryOptimizerAgent",
            "_recursive_": False,
            "action_lb": action_space.low.tolist(),
            "action_ub": action_space.high.tolist(),
            "planning_horizon": int(planning_horizon),
            "replan_freq": int(replan_freq),
            "verbose": False,
            "optimizer_cfg": {
                "_target_": "mbrl.planning.CEMOptimizer",
                "num_iterations": int(num_iterations),
                "elite_ratio": float(elite_ratio),
                "population_size": int(population_size),
                "alpha": float(alpha),
                "device": device,
                "lower_bound": "???",
                "upper_bound": "???",
                "return_mean_elites": True,
                "clipped_normal": bool(clipped_normal),
            },
        }
    )
    return planning.create_trajectory_optim_agent_for_model(model_env, config, num_particles=int(num_particles))


def replay_buffer_to_tensordict(buffer: Any) -> TensorDict:
    """The transitions of an ``mbrl.util.ReplayBuffer`` as the TensorDict :func:`smcd_rl.fit_dynamics` takes.

    Args:
        buffer: anything with mbrl-lib's ``get_all()`` returning a ``TransitionBatch``.

    Returns:
        Batch ``[n]`` with ``observation``, ``action`` and ``next``: ``observation``, ``reward``,
        ``terminated``, ``truncated``, ``done`` (the last four ``[n, 1]``), torchrl's layout.
    """
    batch = buffer.get_all()
    n = len(batch)
    if n == 0:
        raise ValueError("the replay buffer is empty; add transitions before fitting")

    def column(value: Any, dtype: torch.dtype) -> Tensor:
        return torch.as_tensor(np.asarray(value)).to(dtype).reshape(n, -1)

    terminated = column(batch.terminateds, torch.bool)
    truncated = column(batch.truncateds, torch.bool)
    return TensorDict(
        {
            "observation": column(batch.obs, torch.float32),
            "action": column(batch.act, torch.float32),
            "next": {
                "observation": column(batch.next_obs, torch.float32),
                "reward": column(batch.rewards, torch.float32),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[n],
    )


#: The ``"format"`` entry of :func:`pets_loop` checkpoints.
_PETS_FORMAT = "smcd_rl/pets_loop/1"
_BUFFER_FIELDS = ("obs", "next_obs", "action", "reward", "terminated", "truncated")


def pets_loop(
    env: gymnasium.Env[Any, Any],
    model: AdaptiveDynamicsModel,
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None = None,
    *,
    num_steps: int = 2000,
    initial_steps: int = 500,
    freq_train_model: int = 250,
    fit_epochs: int = 20,
    fit_batch_size: int = 64,
    lr: float = 1e-3,
    propagation: Propagation = "fixed_model",
    planning_horizon: int = 15,
    num_iterations: int = 5,
    population_size: int = 350,
    elite_ratio: float = 0.1,
    alpha: float = 0.1,
    num_particles: int = 20,
    seed: int = 0,
    on_episode: Callable[[int, float, int], None] | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
) -> list[float]:
    """PETS (mbrl-lib's ``mbrl.algorithms.pets.train`` loop) with an adaptive model that adapts on every step.

    1. ``initial_steps`` random transitions (mbrl-lib's ``RandomAgent`` and
       ``rollout_agent_trajectories``) fill an ``mbrl.util.ReplayBuffer``.
    2. Then, step by step for ``num_steps`` real steps: every ``freq_train_model`` steps the model
       is fitted further on the whole buffer (:func:`smcd_rl.fit_dynamics`), and its filter
       restarts and re-reads the current episode, so the posterior belongs to the new weights;
       mbrl-lib's CEM agent (:func:`make_cem_agent`) plans the action on :func:`make_model_env`;
       the real transition goes into the buffer and into ``model.observe``. Each episode starts
       with ``model.reset()`` and ``agent.reset()``.

    With ``checkpoint``, the run is saved after the random transitions and after every planned
    episode (the model, its filter, the buffer, every random generator, the returns), and a later
    call with the same path and settings resumes after the last saved episode: its result (returns,
    model, filter) is bit for bit that of an uninterrupted run. An interruption loses at most the
    episode that was running. A call with other settings raises
    :class:`smcd_rl.CheckpointMismatchError` naming them; a finished run's checkpoint returns its
    results at once.

    Args:
        env: the real gymnasium env (flat Box spaces of the model's sizes); it is not closed.
        model: the dynamics model, trained in place (an unfitted one is fine: it is fitted first).
        reward_fn: batched torch reward of the planner, ``(obs, action, next_obs) -> [B]``.
        termination_fn: batched torch termination of the planner, ``next_obs -> bool [B]``.
        num_steps: real steps planned by the agent (after the random ones), >= 1.
        initial_steps: random exploration steps first, >= 1.
        freq_train_model: fit every this many planned steps (the first before step 0), >= 1.
        fit_epochs: epochs of each fit, >= 1.
        fit_batch_size: batch size of each fit, >= 1.
        lr: Adam learning rate of each fit, > 0.
        propagation: see :class:`MbrlLibModel`.
        planning_horizon: CEM horizon (the CEM settings' ranges are those of :func:`make_cem_agent`).
        num_iterations: CEM iterations per action.
        population_size: CEM candidates per iteration.
        elite_ratio: CEM elite fraction.
        alpha: CEM momentum.
        num_particles: rows per candidate.
        seed: seeds torch, numpy's buffer generator, the env, its action space and the planner; >= 0.
        on_episode: called as ``on_episode(env_steps, episode_return, episode_length)`` after
            each planned episode (also the last, unfinished one, cut at ``num_steps``). A resumed
            run first calls it for each episode the checkpoint holds, in order, so a log started
            afresh is complete.
        checkpoint: file to save the run to and to resume it from (``None``: no checkpoint).

    Returns:
        The real return of each planned episode, the last one possibly cut short.

    Raises:
        ValueError: a setting is out of its range, or the env's sizes are not the model's; raised
            before any step.
        smcd_rl.CheckpointMismatchError: ``checkpoint`` was written with other settings.
        ImportError: mbrl-lib is not installed.
    """
    for name, value in (
        ("num_steps", num_steps),
        ("initial_steps", initial_steps),
        ("freq_train_model", freq_train_model),
        ("fit_epochs", fit_epochs),
        ("fit_batch_size", fit_batch_size),
    ):
        _check_int(name, value, 1)
    _check_int("seed", seed, 0, " (numpy and gymnasium take only non-negative seeds)")
    if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not math.isfinite(lr) or lr <= 0:
        raise ValueError(f"lr must be a finite number > 0, got {lr!r}")
    # The agent's settings, named once: checked here, before any step, then given to the agent and recorded.
    cem: dict[str, Any] = {
        "planning_horizon": planning_horizon,
        "num_iterations": num_iterations,
        "population_size": population_size,
        "elite_ratio": elite_ratio,
        "alpha": alpha,
        "num_particles": num_particles,
    }
    _check_cem_settings(**cem, replan_freq=1)
    planning, util_common, util = _mbrl("planning"), _mbrl("util.common"), _mbrl("util")
    # Both check the env's sizes and the propagation before any step; neither draws a random number.
    model_env = make_model_env(env, model, reward_fn, termination_fn, propagation=propagation, seed=seed)
    agent = make_cem_agent(model_env, **cem)
    settings = {
        "env": None if env.spec is None else env.spec.id,
        "num_steps": num_steps,
        "initial_steps": initial_steps,
        "freq_train_model": freq_train_model,
        "fit_epochs": fit_epochs,
        "fit_batch_size": fit_batch_size,
        "lr": lr,
        "propagation": propagation,
        **cem,
        "seed": seed,
        "net": model.net.config,
        "adaptation": {"name": model.adaptation.name, **model.adaptation.config()},
    }
    torch.manual_seed(seed)
    obs_shape, act_shape = env.observation_space.shape, env.action_space.shape
    assert obs_shape is not None and act_shape is not None
    buffer = util.ReplayBuffer(initial_steps + num_steps, obs_shape, act_shape, rng=np.random.default_rng(seed))
    param = next(model.net.parameters())
    obs_key, action_key, next_key = model.in_keys[0], model.in_keys[1], model.out_key

    def tensor(value: Any) -> Tensor:
        return torch.as_tensor(np.asarray(value)).to(device=param.device, dtype=param.dtype)

    def transitions(rows: list[tuple[Tensor, Tensor, Tensor]]) -> TensorDict:
        o, a, n = (torch.stack(column) for column in zip(*rows, strict=True))
        return TensorDict({obs_key: o, action_key: a, next_key: n}, [len(rows)])

    episodes: list[tuple[int, float, int]] = []  # (env_steps, return, length) of each planned episode
    env_steps, fits = 0, 0
    path = Path(checkpoint) if checkpoint is not None else None

    def save() -> None:
        assert path is not None
        try:
            adaptation = model.adaptation.state_dict() if model.batch_shape == () else None
        except RuntimeError:  # never reset yet (before the first fit): nothing adapted to keep
            adaptation = None
        n = buffer.num_stored
        state = {
            "format": _PETS_FORMAT,
            "settings": settings,
            "env_steps": env_steps,
            "fits": fits,
            "episodes": episodes,
            "model": model.checkpoint(),
            "adaptation": adaptation,
            "buffer": {name: getattr(buffer, name)[:n].copy() for name in _BUFFER_FIELDS},
            "buffer_rng": buffer._rng,
            # At an episode's end the env's next reset draws from its generator alone (mbrl-lib's
            # RandomAgent, the only user of the action space's generator, is done by then).
            "env_rng": env.np_random,
            "planner_rng": model_env._rng.get_state(),  # ModelEnv's generator (mbrl-lib 0.2.0 keeps it as _rng)
            "torch_rng": torch.get_rng_state(),  # mbrl-lib's CEM samples from torch's global generator
            "cuda_rng": torch.cuda.get_rng_state(param.device) if param.device.type == "cuda" else None,
        }
        save_file(state, path, what="pets_loop checkpoint")

    if path is not None and path.is_file():
        state = load_file(
            path,
            what="pets_loop checkpoint",
            expect_format=_PETS_FORMAT,
            expect_keys=("settings", "env_steps", "fits", "episodes", "model", "buffer", "env_rng", "torch_rng"),
            fix="delete it to start afresh, or pass another checkpoint path",
        )
        if state["settings"] != settings:
            differ = [
                f"{key}={state['settings'].get(key)!r} (this call: {settings.get(key)!r})"
                for key in sorted(set(settings) | set(state["settings"]))
                if state["settings"].get(key) != settings.get(key)
            ]
            raise CheckpointMismatchError(
                f"{path} was written by a run with other settings: {', '.join(differ)}; pass the same settings "
                "to resume it, or delete it or pass another checkpoint path to start afresh"
            )
        env_steps, fits, episodes = int(state["env_steps"]), int(state["fits"]), list(state["episodes"])
        model.load_checkpoint(state["model"])
        if state["adaptation"] is not None:
            model.reset()
            model.adaptation.load_state_dict(state["adaptation"])
        n = len(state["buffer"]["obs"])
        for name in _BUFFER_FIELDS:
            getattr(buffer, name)[:n] = state["buffer"][name]
        buffer.num_stored, buffer.cur_idx, buffer._rng = n, n % buffer.capacity, state["buffer_rng"]
        env.np_random = state["env_rng"]
        model_env._rng.set_state(state["planner_rng"])
        torch.set_rng_state(state["torch_rng"])
        if state.get("cuda_rng") is not None:
            torch.cuda.set_rng_state(state["cuda_rng"], param.device)
        if on_episode is not None:
            for row in episodes:
                on_episode(*row)
    else:
        env.reset(seed=seed)
        env.action_space.seed(seed)
        util_common.rollout_agent_trajectories(env, initial_steps, planning.RandomAgent(env), {}, replay_buffer=buffer)
        if path is not None:
            save()

    while env_steps < num_steps:
        obs, _ = env.reset()
        agent.reset()
        episode: list[tuple[Tensor, Tensor, Tensor]] = []
        total, done = 0.0, False
        while not done and env_steps < num_steps:
            if env_steps % freq_train_model == 0:
                data = replay_buffer_to_tensordict(buffer)
                fit_dynamics(
                    model, data, epochs=fit_epochs, batch_size=fit_batch_size, lr=lr, seed=seed + fits, progress=False
                )
                fits += 1
                model.reset()  # the posterior of the old weights does not hold for the new ones
                if episode:
                    model.observe(transitions(episode))
            elif not episode:
                model.reset()
            action = agent.act(obs)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            buffer.add(obs, action, next_obs, reward, terminated, truncated)
            episode.append((tensor(obs), tensor(action).reshape(-1), tensor(next_obs)))
            model.observe(transitions(episode[-1:])[0])
            obs, total, done = next_obs, total + float(reward), bool(terminated or truncated)
            env_steps += 1
        episodes.append((env_steps, total, len(episode)))
        if path is not None:
            save()
        if on_episode is not None:
            on_episode(*episodes[-1])
    return [total for _, total, _ in episodes]
