"""The stage plan of ``smcd-rl ant``: each stage's rough cost from the settings, for the progress line."""

from __future__ import annotations

import math

from smcd_rl.experiments.ant.config import CELLS, PREDICTED, AntConfig
from smcd_rl.experiments.ant.episodes import ACTION_DIM, OBS_DIM
from smcd_rl.experiments.shared.stages import estimate, mlp_flops, tuning_cost, update_cost

__all__ = ["stage_costs", "predictions"]


def predictions(variant: str) -> float:
    """Network forwards of one prediction by adaptation ``variant``: the combination ``C`` predicts with each member.

    Inside the planner's rollouts and the open-loop predictions, ``C`` runs N's, G's and S's
    predictions (SMCD's from its MMSE mask) and mixes them, so it costs about three strategies' worth.

    Example:
        >>> predictions("C"), predictions("S(evidence)")
        (3.0, 1.0)
    """
    return 3.0 if variant == "C" else 1.0


def stage_costs(config: AntConfig) -> dict[str, float]:
    """Each stage's rough seconds at ``config`` (see :func:`~smcd_rl.experiments.shared.stages.estimate`), in run order.

    Collecting counts a third of a step's overhead per simulated transition, 300 for making the
    environment (and, with ``--data-policy sac``, three per SAC step); training its optimiser steps and a forward and
    backward (3 forwards) per training transition and epoch; the tuning its filter runs
    (:func:`~smcd_rl.experiments.shared.stages.tuning_cost`); each prediction stage ``prediction_steps``
    steps of every episode, each an update (:func:`~smcd_rl.experiments.shared.stages.update_cost`) and an
    open-loop prediction of ``prediction_horizon`` forwards (the rollouts batched); each MPC cell
    ``episodes x episode_steps`` steps, each an update and a plan of ``candidates x iterations x
    horizon`` forwards in ``iterations x horizon`` rollout steps, a tenth of a step's overhead each
    (measured on a 4000-transition run).

    Example:
        >>> costs = stage_costs(AntConfig())
        >>> list(costs)[:7], costs["evaluate cem/S/crippled"] > costs["evaluate cem/N/crippled"]
        (['collect', 'train', 'tune M', 'collect T', 'train T', 'tune T', 'prediction-healthy N'], True)
        >>> costs["evaluate cem/C/crippled"] > 2 * costs["evaluate cem/S/crippled"]
        True
    """
    flops = mlp_flops(OBS_DIM + ACTION_DIM, (config.hidden,) * config.depth, OBS_DIM)
    samples = config.transitions * (1 - config.validation)
    sac = 3 * config.sac_steps if config.data_policy == "sac" else 0
    costs = {
        "collect": estimate(steps=300 + config.transitions / 3 + sac),
        "train": estimate(
            steps=config.epochs * math.ceil(samples / config.batch_size),
            forwards=3 * config.epochs * samples,
            flops=flops,
        ),
        "tune M": tuning_cost(config, episodes=config.tuning_episodes, steps=config.tuning_steps, flops=flops),
    }
    task = [f"T+{v}" for v in config.task_adaptations]
    if task:  # T: as many transitions as M, its training with each condition's posterior every epoch
        costs["collect T"] = estimate(steps=300 + config.transitions / 3)
        costs["train T"] = 1.5 * costs["train"]
        costs["tune T"] = costs["tune M"]
    horizon = config.prediction_horizon
    for condition in config.conditions:
        for name in [*PREDICTED, *task]:
            variant = name.removeprefix("T+")
            overhead, update = update_cost(variant, config)
            rollout = predictions(variant) * horizon
            forwards = config.prediction_episodes * config.prediction_steps * (update + rollout)
            steps = config.prediction_steps * (1 + overhead) + rollout  # the open-loop rollouts run batched
            costs[f"prediction-{condition} {name}"] = estimate(steps=steps, forwards=forwards, flops=flops)
    plan = config.candidates * config.iterations * config.horizon
    for cell in CELLS:
        if cell[0] in config.planners and cell[1] in config.adaptations and cell[2] in config.conditions:
            overhead, update = update_cost(cell[1], config)
            steps = config.episodes * config.episode_steps
            each = predictions(cell[1])
            costs[f"evaluate {'/'.join(cell)}"] = estimate(
                steps=steps * (1 + overhead + each * config.iterations * config.horizon / 10),
                forwards=steps * (update + each * plan),
                flops=flops,
            )
    return costs
