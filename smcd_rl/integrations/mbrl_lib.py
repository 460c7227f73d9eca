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
from collections.abc import Callable
from types import ModuleType
from typing import Any, Literal

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from torch import Tensor

from smcd_rl.adaptation import SMCD
from smcd_rl.model import AdaptiveDynamicsModel
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
        model: the dynamics model, reset with ``batch_shape=()`` (one env) before planning.
        propagation: ``"fixed_model"``, ``"random_model"`` or ``"expectation"`` (module docstring).
        reward_fn: batched torch reward ``(obs [B, O], action [B, A], next_obs [B, O]) -> [B]``
            (or ``[B, 1]``); :meth:`sample` returns it as the predicted reward, which ``ModelEnv``
            uses when built without a ``reward_fn`` of its own. ``None``: no reward (pass
            mbrl-lib's ``reward_fn(act, next_obs)`` to ``ModelEnv`` instead).

    Raises:
        TypeError: ``model`` is not an :class:`~smcd_rl.AdaptiveDynamicsModel`.
        ValueError: an unknown ``propagation``, or a sampling one for a strategy without particles.
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        *,
        propagation: Propagation = "fixed_model",
        reward_fn: RewardFn | None = None,
    ) -> None:
        if not isinstance(model, AdaptiveDynamicsModel):
            raise TypeError(f"model must be a smcd_rl.AdaptiveDynamicsModel, got {type(model).__name__}")
        if propagation not in PROPAGATIONS:
            raise ValueError(
                f"propagation must be one of {PROPAGATIONS}, got {propagation!r}; mbrl-lib's None (every member's "
                "output, for its ModelTrainer) does not apply: fit the model with smcd_rl.fit_dynamics"
            )
        if propagation != "expectation" and not isinstance(model.adaptation, SMCD):
            raise ValueError(
                f"propagation={propagation!r} draws masks from the SMCD posterior, but the model adapts with "
                f"{type(model.adaptation).__name__}, which keeps no particles; use propagation='expectation'"
            )
        self.model = model
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
            ``{"obs": [B, O]}``, plus ``"masks" [B, mask_dim]`` for ``"fixed_model"``.
        """
        observation = self._tensor(obs)
        if observation.dim() != 2 or observation.shape[-1] != self.model.observation_dim:
            raise ValueError(
                f"reset needs observations [B, {self.model.observation_dim}], got {list(observation.shape)}"
            )
        state = {"obs": observation}
        if self.propagation == "fixed_model":
            state["masks"] = self._draw_masks(observation.shape[0], rng)
        return state

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
        obs = model_state["obs"]
        action = self._tensor(act)
        if action.shape != (obs.shape[0], self.model.action_dim):
            raise ValueError(
                f"sample needs actions [{obs.shape[0]}, {self.model.action_dim}], got {list(action.shape)}"
            )
        if self.propagation == "fixed_model":
            masks: Tensor | None = model_state["masks"]
        elif self.propagation == "random_model":
            masks = self._draw_masks(obs.shape[0], rng)
        else:
            masks = None
        with torch.no_grad():
            next_obs = self.model.step(obs, action, mask=masks)
            reward = None
            if self.reward_fn is not None:
                reward = self.reward_fn(obs, action, next_obs)
                if reward.shape not in ((obs.shape[0],), (obs.shape[0], 1)):
                    raise ValueError(
                        f"reward_fn returned shape {list(reward.shape)} for {obs.shape[0]} rows; it must return [B] or [B, 1]"
                    )
                reward = reward.reshape(-1, 1).to(torch.float32)
        return next_obs, reward, None, {**model_state, "obs": next_obs}

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
    model: AdaptiveDynamicsModel,
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None = None,
    *,
    propagation: Propagation = "fixed_model",
    seed: int | None = None,
) -> Any:
    """mbrl-lib's ``ModelEnv`` on the adaptive model, with this library's reward and termination.

    Args:
        env: the real env (``ModelEnv`` reads its observation and action spaces).
        model: the dynamics model (see :class:`MbrlLibModel`).
        reward_fn: batched torch reward ``(obs, action, next_obs) -> [B]``, e.g.
            :func:`smcd_rl.envs.crippled_ant.ant_reward`.
        termination_fn: batched torch termination ``next_obs -> bool [B]``; ``None``: never.
        propagation: see :class:`MbrlLibModel`.
        seed: seeds the generator ``ModelEnv`` draws masks with (``None``: torch's default seed).

    Returns:
        An ``mbrl.models.ModelEnv``; its ``dynamics_model`` is the :class:`MbrlLibModel`.

    Raises:
        ImportError: mbrl-lib is not installed (the message names the install commands).
    """
    models = _mbrl("models")
    adapter = MbrlLibModel(model, propagation=propagation, reward_fn=reward_fn)
    generator = torch.Generator(device=adapter.device)
    if seed is not None:
        generator.manual_seed(int(seed))
    return models.ModelEnv(env, adapter, termination_for_mbrl(termination_fn), None, generator=generator)


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
        planning_horizon: steps of each action sequence.
        num_iterations: CEM iterations per plan.
        population_size: candidates per iteration.
        elite_ratio: fraction of candidates kept as elites.
        alpha: momentum of the CEM mean and variance.
        num_particles: rows per candidate (masks with ``"fixed_model"`` / ``"random_model"``).
        replan_freq: plan every ``replan_freq`` steps.
        clipped_normal: clipped instead of truncated normal samples.

    Returns:
        The agent: ``agent.act(obs)`` plans and returns the first action; ``agent.reset()`` at
        each episode start clears its warm start.

    Raises:
        ImportError: mbrl-lib is not installed.
    """
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

    Args:
        env: the real gymnasium env (flat Box spaces of the model's sizes); it is not closed.
        model: the dynamics model, trained in place (an unfitted one is fine: it is fitted first).
        reward_fn: batched torch reward of the planner, ``(obs, action, next_obs) -> [B]``.
        termination_fn: batched torch termination of the planner, ``next_obs -> bool [B]``.
        num_steps: real steps planned by the agent (after the random ones).
        initial_steps: random exploration steps first.
        freq_train_model: fit every this many planned steps (the first before step 0).
        fit_epochs: epochs of each fit.
        fit_batch_size: batch size of each fit.
        lr: Adam learning rate of each fit.
        propagation: see :class:`MbrlLibModel`.
        planning_horizon: CEM horizon.
        num_iterations: CEM iterations per action.
        population_size: CEM candidates per iteration.
        elite_ratio: CEM elite fraction.
        alpha: CEM momentum.
        num_particles: rows per candidate.
        seed: seeds torch, numpy's buffer generator, the env, its action space and the planner.
        on_episode: called as ``on_episode(env_steps, episode_return, episode_length)`` after
            each planned episode (also the last, unfinished one, cut at ``num_steps``).

    Returns:
        The real return of each planned episode, the last one possibly cut short.

    Raises:
        ValueError: a step count is not a positive int.
        ImportError: mbrl-lib is not installed.
    """
    for name, value in (
        ("num_steps", num_steps),
        ("initial_steps", initial_steps),
        ("freq_train_model", freq_train_model),
    ):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    planning, util_common, util = _mbrl("planning"), _mbrl("util.common"), _mbrl("util")
    torch.manual_seed(seed)
    obs_shape, act_shape = env.observation_space.shape, env.action_space.shape
    assert obs_shape is not None and act_shape is not None
    buffer = util.ReplayBuffer(initial_steps + num_steps, obs_shape, act_shape, rng=np.random.default_rng(seed))
    env.reset(seed=seed)
    env.action_space.seed(seed)
    util_common.rollout_agent_trajectories(env, initial_steps, planning.RandomAgent(env), {}, replay_buffer=buffer)

    model_env = make_model_env(env, model, reward_fn, termination_fn, propagation=propagation, seed=seed)
    agent = make_cem_agent(
        model_env,
        planning_horizon=planning_horizon,
        num_iterations=num_iterations,
        population_size=population_size,
        elite_ratio=elite_ratio,
        alpha=alpha,
        num_particles=num_particles,
    )
    param = next(model.net.parameters())
    obs_key, action_key, next_key = model.in_keys[0], model.in_keys[1], model.out_key

    def tensor(value: Any) -> Tensor:
        return torch.as_tensor(np.asarray(value)).to(device=param.device, dtype=param.dtype)

    def transitions(rows: list[tuple[Tensor, Tensor, Tensor]]) -> TensorDict:
        o, a, n = (torch.stack(column) for column in zip(*rows, strict=True))
        return TensorDict({obs_key: o, action_key: a, next_key: n}, [len(rows)])

    returns: list[float] = []
    env_steps, fits = 0, 0
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
        returns.append(total)
        if on_episode is not None:
            on_episode(env_steps, total, len(episode))
    return returns
