"""The crippled-leg Ant's primary metric: prediction error of the adapted model on logged episodes.

:mod:`smcd_rl.experiments.ant.run` calls these. :func:`random_episodes` logs episodes of the Ant under
a fixed behaviour policy (uniform random actions, the default data-collection policy), as a
TensorDict of batch ``[E, T]`` in the dynamics model's keys; it makes both the fair protocol's
tuning episodes (healthy Ant, seeds of their own) and the test episodes (healthy, and one leg
crippled per episode). :func:`prediction_errors` filters one strategy along every episode at
once and scores each episode by

* ``one_step``: the RMSE of the prediction of transition ``t`` from the transitions before it,
  made before observing it (``t = 1..T-1``, as :func:`smcd_rl.tuning.diagnostics.trace` scores it);
* ``open_loop``: from each step ``t = 1..T-H``, after observing the transitions before ``t``, the
  adapted model rolled ``H`` steps ahead on the logged actions from the logged state at ``t``, its
  RMSE against the logged states ``t+1..t+H`` (pooled over the ``H`` steps).

Both are in observation units, pooled over the 41 dimensions, one number per episode, so that
strategies are compared paired over the same episodes.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(8,)))
    >>> model.fitted = True  # a toy network: declare it trained
    >>> td = TensorDict({"observation": torch.rand(4, 6, 3), "action": torch.rand(4, 6, 1),
    ...                  "next": {"observation": torch.rand(4, 6, 3)}}, [4, 6])
    >>> errors = prediction_errors(model, smcd_rl.NoAdaptation(), td, horizon=2)
    >>> errors["one_step"].shape, errors["open_loop"].shape, errors["refused"]
    (torch.Size([4]), torch.Size([4]), 0)
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.digests import content_digest
from smcd_rl.experiments.ant.config import TASKS

if TYPE_CHECKING:
    from smcd_rl.experiments.ant.config import AntConfig
    from smcd_rl.experiments.shared.harness import Experiment

__all__ = ["PREDICTION_SEED", "random_episodes", "prediction_errors", "evaluate_predictions"]

#: Offset of the prediction episodes' env seeds from ``--seed`` (neither training nor tuning data).
PREDICTION_SEED = 3_000_003


def random_episodes(
    task_env: dict[str, Any], legs: Sequence[int] | None, *, count: int, steps: int, seed: int
) -> tuple[TensorDict, list[int]]:
    """``count`` episodes of ``steps`` uniform random actions: batch ``[count, steps]``, and each one's leg.

    Episode ``k`` resets with env seed ``seed + k`` (its start state and, crippled, its leg drawn
    from ``legs``; ``None``: healthy) and draws its actions from a generator of the same seed, so
    the episodes depend on nothing else. The Ant never ends an episode early here (only the
    dynamics matter), whatever the task's termination.

    Args:
        task_env: the task's :class:`~smcd_rl.envs.crippled_ant.CrippledAntEnv` arguments.
        legs: legs the crippled leg is drawn from, or ``None`` for the healthy Ant.
        count: episodes.
        steps: transitions per episode.
        seed: the first episode's seed.
    """
    from smcd_rl.envs.crippled_ant import CrippledAntEnv

    env = CrippledAntEnv(crippled_legs=legs, **{**task_env, "terminate_when_unhealthy": False})
    observations, actions, nexts, chosen = [], [], [], []
    for k in range(count):
        obs, info = env.reset(seed=seed + k)
        chosen.append(int(info["crippled_leg"]))
        rng = np.random.default_rng(seed + k)
        episode_obs, episode_actions = [obs], []
        for _ in range(steps):
            action = rng.uniform(-1.0, 1.0, size=env.action_space.shape).astype(np.float32)
            obs, *_ = env.step(action)
            episode_obs.append(obs)
            episode_actions.append(action)
        states = torch.as_tensor(np.stack(episode_obs))
        observations.append(states[:-1])
        nexts.append(states[1:])
        actions.append(torch.as_tensor(np.stack(episode_actions)))
    env.close()
    td = TensorDict(
        {
            "observation": torch.stack(observations),
            "action": torch.stack(actions),
            "next": {"observation": torch.stack(nexts)},
        },
        batch_size=[count, steps],
    )
    return td, chosen


@torch.no_grad()
def prediction_errors(
    model: smcd_rl.AdaptiveDynamicsModel, strategy: smcd_rl.Adaptation, episodes: TensorDict, *, horizon: int
) -> dict[str, Any]:
    """Per-episode one-step and ``horizon``-step open-loop RMSE of ``strategy`` (see the module doc).

    Args:
        model: the trained model; ``strategy`` adapts a copy of it (``model.with_adaptation``).
        strategy: a fresh strategy.
        episodes: batch ``[E, T]`` with ``observation``, ``action`` and ``("next", "observation")``;
            ``T > horizon``.
        horizon: the open-loop look-ahead ``H`` (steps).

    Returns:
        ``{"one_step": [E], "open_loop": [E]}`` (float64, observation units) and ``"refused"``: the
        steps whose observation the strategy refused (skipped: it keeps its state and goes on).
    """
    count, steps = episodes.batch_size
    if steps <= horizon:
        raise ValueError(f"episodes of {steps} steps are too short for a {horizon}-step open-loop error")
    adapted = model.with_adaptation(strategy)
    assert isinstance(adapted, smcd_rl.AdaptiveDynamicsModel)
    adapted.reset(batch_shape=(count,))
    obs, act = episodes.get("observation"), episodes.get("action")
    target = episodes.get(("next", "observation")).to(torch.float64)
    one_step = torch.zeros(count, dtype=torch.float64)
    open_loop = torch.zeros(count, dtype=torch.float64)
    starts, refused = 0, 0
    for t in range(steps):
        if t > 0:
            predicted = adapted.step(obs[:, t], act[:, t]).to(torch.float64)
            one_step += (predicted - target[:, t]).square().mean(-1).cpu()
            if t + horizon <= steps:
                state = obs[:, t]
                for k in range(horizon):
                    state = adapted.step(state, act[:, t + k])
                    open_loop += (state.to(torch.float64) - target[:, t + k]).square().mean(-1).cpu()
                starts += 1
        try:
            adapted.observe(episodes[:, t])
        except ValueError:
            refused += 1
    return {
        "one_step": (one_step / (steps - 1)).sqrt(),
        "open_loop": (open_loop / (starts * horizon)).sqrt(),
        "refused": refused,
    }


def evaluate_predictions(
    ex: Experiment,
    config: AntConfig,
    networks: Mapping[str, tuple[Any, Callable[[str], Any], dict[str, Any], Sequence[str]]],
) -> tuple[dict[str, dict[str, dict[str, Any]]], dict[str, list[int]]]:
    """Per condition: every method's per-episode errors on that condition's logged episodes, and their legs.

    ``networks`` maps a network's prefix (``"M"``, ``"T"``) to its model, its strategy factory
    (variant -> a fresh strategy), what keys its results (its digest and tuned settings) and its
    variants; the results are keyed by method label (``"M+S"``, ``"T+S"``). Every network is
    scored on the same episodes (env seeds ``--seed + PREDICTION_SEED + k``).
    """
    results: dict[str, dict[str, dict[str, Any]]] = {}
    legs: dict[str, list[int]] = {}
    for condition in config.conditions:
        episodes, legs[condition] = random_episodes(
            TASKS[config.task][0],
            config.crippled_legs if condition == "crippled" else None,
            count=config.prediction_episodes,
            steps=config.prediction_steps,
            seed=config.seed + PREDICTION_SEED,
        )
        episodes = episodes.to(ex.device)
        results[condition] = {}
        for prefix, (model, strategy, content, variants) in networks.items():
            # M's results are stored under their variant names (a rerun reuses them), another network's as labelled.
            stored = {variant: variant if prefix == "M" else f"{prefix}+{variant}" for variant in variants}
            done = ex.evaluate(
                {stored[variant]: functools.partial(strategy, variant) for variant in variants},
                functools.partial(_errors, model, episodes, config.prediction_horizon),
                content={**content, "episodes": content_digest(episodes)},
                kind=f"prediction-{condition}",
            )
            results[condition].update({f"{prefix}+{variant}": done[stored[variant]] for variant in variants})
    return results, legs


def _errors(
    model: smcd_rl.AdaptiveDynamicsModel, episodes: Any, horizon: int, name: str, strategy: smcd_rl.Adaptation
) -> dict[str, Any]:
    """One strategy's errors on one condition's episodes (``name``, the method, keys the cache only)."""
    return prediction_errors(model, strategy, episodes, horizon=horizon)
