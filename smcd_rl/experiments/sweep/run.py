"""Hyper-parameter ablations (paper appendices A.1, A.2 and B.2; Figs. 5, 6 and 12): ``smcd-rl sweep``.

Four studies, chosen with ``--study``:

* ``training`` (Fig. 5): training loss of the two-link forward-kinematics model by latent
  dimension, dropout p, learning rate, batch size and epochs;
* ``smcd`` (Fig. 6): SMCD look-ahead MSE on held-out two-link arms by latent dimension, dropout p,
  bit-flip probability, likelihood noise and particle count, at every (burn-in T, horizon H) pair;
* ``drone`` (Fig. 12): training loss of the drone behaviour-cloning model (state -> operator's
  velocity command) by latent dimension, dropout p, learning rate, batch size and epochs, on
  simulated operators (:func:`smcd_rl.envs.drone_operators.simulate_operators`) or ``--dataset``;
* ``masks``: networks trained for mask adaptation (``smcd_rl.fit(mask_training="task")``), by the
  share of samples trained through their arm's mask posterior (0: random dropout, the control),
  mask bits per layer (groups of units, or one per unit), training arms and particles. Each is
  scored as the smcd study scores SMCD (T+S against T+N and T+G on the same network), and reports
  how concentrated its posteriors are (:mod:`.posteriors`): per epoch on the training arms
  (``posteriors.csv``, ``posteriors.png``) and after ``max(burn_in)`` observations of a held-out arm.

The grid is full factorial, as in the paper's figures: each panel shows, for every value of one
parameter, the spread over all combinations of the others. ``--design one-at-a-time`` instead varies
one parameter at a time around the base values (the options of the same names), for a quick look
at large grids; its spread then says nothing about interactions.

Reads top to bottom: resolve the grid and list its points (:mod:`.grid`), run what the
result store does not hold yet as Ray tasks (:mod:`.work`; a local Ray by default,
``--address`` for an existing cluster), then the results (:mod:`.results`): ``results.csv``
(every grid point), ``summary.csv`` (per parameter value: mean, std and min over the other
parameters), ``results.json``, ``sweep.png`` (one panel per parameter) and ``report.md``, and the
printed summary. In the smcd study every grid point's MSE also gets a 95 % bootstrap interval over
the held-out arms, and SMCD is compared, paired over the same arms, with the same trained network
without adaptation (M+N) and with online gradient descent (M+G): ``trials.csv`` (every arm's
MSE), ``comparisons.csv`` and the verdicts, counted over the grid and at the base setting.

On a cluster every node needs ``smcd-rl`` installed (and, with Ray's token authentication, the
cluster's token, e.g. in ``RAY_AUTH_TOKEN``); a ``--dataset`` path must exist on every node.

A trial is a pure function of its configuration (:func:`trial`, which seeds itself), so a grid
point computed on Ray equals the same call in-process. Every grid point uses the same seed: same
data, same initial weights, same held-out arms, so differences come from the hyper-parameters alone.

Example:
    >>> points = trial_configs(SweepConfig(study="smcd", grid=("particles=10,20",)))
    >>> len(points), sorted({point["particles"] for point in points})
    (162, [10, 20])
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch

import smcd_rl
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import write_csv
from smcd_rl.experiments.shared.result_store import ResultStore
from smcd_rl.experiments.shared.stages import estimate, mlp_flops
from smcd_rl.experiments.sweep import posteriors
from smcd_rl.experiments.sweep.config import (
    FILTER_STUDIES,
    FULL,
    FULL_GRIDS,
    GRIDS,
    PARAMETERS,
    STUDIES,
    SweepConfig,
    resolve_grid,
)
from smcd_rl.experiments.sweep.grid import trial_configs
from smcd_rl.experiments.sweep.posteriors import POSTERIOR_METRICS
from smcd_rl.experiments.sweep.results import (
    FIGURES,
    headline,
    method,
    model_parameters,
    plot,
    reference_table,
    smcd_statistics,
    summarise,
    table,
    verdict_counts,
)
from smcd_rl.experiments.sweep.trials import REFERENCES, evaluate, train, training_data, trial
from smcd_rl.experiments.sweep.work import SweepWork, ray_session

__all__ = [
    "SweepConfig",
    "FULL",
    "STUDIES",
    "PARAMETERS",
    "GRIDS",
    "FULL_GRIDS",
    "run",
    "trial",
    "train",
    "evaluate",
    "trial_configs",
    "resolve_grid",
    "summarise",
    "table",
]


def run(config: SweepConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the sweep (on Ray, skipping what the result store already holds) and write its files."""
    with Experiment(config, progress=progress) as ex:
        # --- the grid, and what is left of it --------------------------------------------------
        grid = resolve_grid(config)
        points = trial_configs(config, grid)
        parameters = list(grid)
        work = SweepWork(config, points, ResultStore(ex.out / "partial", what="sweep result"))
        ex.plan(stage_costs(config, points, work.groups))
        if not work.finished and config.study == "drone":  # a bad --subset fails here, not in every Ray task
            training_data(points[0], ex.generator)

        # --- the trials, on Ray -----------------------------------------------------------------
        with ex.stage("trials"):
            if not work.finished:
                with ray_session(config) as ray:
                    work.run(ray, progress=progress)

        # --- results: the summary per parameter value; in the filter studies, CIs and paired verdicts ---
        with ex.stage("statistics"):
            metrics = [m for m in work.results[0]["metrics"] if m not in POSTERIOR_METRICS]
            rows = [
                {**{p: point[p] for p in parameters}, **{m: work.results[i]["metrics"][m] for m in metrics}}
                for i, point in enumerate(points)
            ]
            # A parameter with one value is a fixed setting here: it has no panel (unless nothing varies).
            varied = [p for p in parameters if len(grid[p]) > 1 or config.design == "one-at-a-time"] or parameters
            summary = summarise(rows, varied, metrics)
            filtering = config.study in FILTER_STUDIES
            what = "Look-ahead MSE (m^2)" if filtering else "Last epoch's training loss (normalised MSE)"
            tables = {
                f"{what} per parameter value: mean, std and min over the other parameters' grid points": table(summary)
            }
            trials: list[dict[str, Any]] = []
            comparisons: list[dict[str, Any]] = []
            extra: dict[str, Any] = {}
            plots = {"sweep.png": lambda path: plot(rows, summary, varied, metrics, config.study, path)}
            files = ["summary.csv"]
            if filtering:
                model = model_parameters(parameters, config.study)
                references = {
                    tuple(work.run_configs[key][p] for p in model): {
                        method(config.study, m.split("+")[1]): work.references[key, m]["arms"] for m in REFERENCES
                    }
                    for key in work.groups
                }
                arms = [work.results[i]["arms"] for i in range(len(points))]
                pairs = [(t, h) for t in config.burn_in for h in config.horizons]
                extra["references"], comparisons = smcd_statistics(
                    rows, arms, references, parameters, pairs, seed=config.seed, study=config.study
                )
                trials = _trial_rows(rows, arms, references, parameters, config.study)
                tables |= _smcd_tables(config, parameters, comparisons, extra["references"], len(points))
            if config.study == "masks":
                runs = [({p: work.run_configs[key][p] for p in model}, work.posteriors[key]) for key in work.groups]
                tables |= _posterior_tables(config, runs, rows, arms, parameters)
                extra["posteriors"] = [{**where, **epoch} for where, epochs in runs for epoch in epochs]
                write_csv(ex.out / "posteriors.csv", extra["posteriors"])
                plots["posteriors.png"] = lambda path: posteriors.plot(runs, path)
                files.append("posteriors.csv")
        write_csv(ex.out / "summary.csv", summary)
        ex.write(
            experiment=f"hyper-parameter sweep, {_what(config.study)}",
            tables=tables,
            rows=rows,
            trials=trials,
            comparisons=comparisons,
            payload={
                "design": config.design,
                "grid": {name: list(values) for name, values in grid.items()},
                "metrics": metrics,
                "grid_points": len(points),
                "computed": len(points) - work.reused,
                "reused": work.reused,
                "train_seconds": work.train_seconds,
                "evaluate_seconds": work.evaluate_seconds,
                "summary": summary,
                **extra,
            },
            plots=plots,
            files=files,
        )
        print(f"{len(points)} grid points ({len(points) - work.reused} computed, {work.reused} from the cache)")
    return ex.result


#: Mean steps of a simulated drone landing (as ``smcd-rl interpret`` counts them).
LANDING_STEPS = 60
#: The observations and particles per arm of ``fit(mask_training="task")``'s task posteriors (its defaults).
TASK_OBSERVATIONS, TASK_PARTICLES = (
    inspect.signature(smcd_rl.fit).parameters[name].default for name in ("mask_observations", "mask_particles")
)


def stage_costs(
    config: SweepConfig, points: Sequence[Mapping[str, Any]], groups: Mapping[str, Sequence[int]]
) -> dict[str, float]:
    """The two stages' rough seconds (see :func:`~smcd_rl.experiments.shared.stages.estimate`): the trials on Ray, the statistics.

    The trials count starting Ray, and for each training run (``groups``: its grid points) a Ray
    task's overhead per task, its optimiser steps and
    a forward and backward (3 forwards) per sample and epoch (the most its points need), and in the
    smcd study each point's and each reference's filtering of ``arms`` held-out arms (``particles``
    forwards per arm and burn-in step), all shared among the Ray workers (``--cpus`` over
    ``--cpus-per-trial``); work already stored counts all the same, as a rerun's trials stage ends
    at once and so does not count towards the speed. The statistics count a bootstrap per point and
    (T, H) pair in the smcd study, and the summary and plot (about a second) in every study.

    Example:
        >>> from smcd_rl.experiments.sweep.grid import trial_configs
        >>> config = SweepConfig(grid=("hidden=8,16", "epochs=2"))
        >>> points = trial_configs(config)
        >>> list(stage_costs(config, points, {"a": [0], "b": [1]}))
        ['trials', 'statistics']
    """
    trials = 0.0
    for indices in groups.values():
        trials += estimate(steps=30 * (1 + len(indices)))  # a Ray task's own overhead, about 0.1 s
        point = points[indices[0]]
        epochs = max(int(points[i]["epochs"]) for i in indices)
        drone = point["study"] == "drone"
        dims = (7, 3) if drone else (2, 2)
        flops = mlp_flops(dims[0], (int(point["hidden"]),) * int(point["depth"]), dims[1])
        if drone:
            samples = int(point["subset"] or point["operators"] * point["trajectories_per_operator"]) * LANDING_STEPS
        else:
            samples = int(point["tasks"]) * int(point["episodes"]) * int(point["steps"])
        steps = epochs * -(-samples // int(point["batch_size"]))
        trials += estimate(steps=steps, forwards=3 * epochs * samples, flops=flops)
        if point["study"] == "masks":  # each later epoch's task posteriors, on the arm's and on dealt samples
            inference = 2 * int(point["tasks"]) * TASK_OBSERVATIONS * TASK_PARTICLES
            trials += estimate(
                steps=2 * (epochs - 1) * TASK_OBSERVATIONS, forwards=(epochs - 1) * inference, flops=flops
            )
            for i in indices:  # the held-out arms' posteriors, then every arm's future under every arm's mask
                forwards = int(point["arms"]) * max(point["burn_in"]) * int(points[i]["particles"])
                forwards += int(point["arms"]) ** 2 * max(point["horizons"])
                trials += estimate(steps=max(point["burn_in"]) + int(point["arms"]), forwards=forwards, flops=flops)
        if point["study"] in FILTER_STUDIES:
            runs = [int(points[i]["particles"]) for i in indices] + [1, 3 * config.gd_steps * config.gd_window]
            burn = max(point["burn_in"]) + max(point["horizons"])
            chunks = -(-int(point["arms"]) // int(point["chunk"]))
            for per_arm in runs:
                trials += estimate(steps=chunks * burn, forwards=int(point["arms"]) * burn * per_arm, flops=flops)
    workers = max(1, (config.cpus or os.cpu_count() or 1) // config.cpus_per_trial)
    pairs = len(config.burn_in) * len(config.horizons) if config.study in FILTER_STUDIES else 0
    ray_start = 30.0  # starting Ray and its workers (each imports torch): about half a minute on 2 CPUs
    return {"trials": ray_start + trials / workers, "statistics": estimate(steps=300 + 30 * pairs * len(points))}


def _what(study: str) -> str:
    """The study as the report's title names it."""
    if study in FIGURES:
        return f"study {study} (paper Fig. {FIGURES[study]})"
    return f"study {study} (networks trained for mask adaptation, fit(mask_training='task'))"


def _smcd_tables(
    config: SweepConfig,
    parameters: list[str],
    comparisons: list[dict[str, Any]],
    references: list[dict[str, Any]],
    points: int,
) -> dict[str, str]:
    smcd, none, gd = (method(config.study, kind) for kind in "SNG")
    base = {p: getattr(config, p) for p in parameters}
    tables = {
        f"SMCD ({smcd}) paired with {none} and {gd} over the same arms: verdicts (95% CI of the difference) over the {points} grid points": verdict_counts(
            comparisons, smcd
        )
    }
    at_base = headline(comparisons, base, smcd)
    if at_base is not None:
        setting_text = ", ".join(f"{k}={v}" for k, v in base.items())
        tables[f"SMCD at the base setting ({setting_text}) minus {none} and {gd} (negative: SMCD's error is lower)"] = (
            at_base
        )
    tables["The references on each trained network: look-ahead MSE (m^2), mean [95% CI] over the arms"] = (
        reference_table(references, model_parameters(parameters, config.study))
    )
    return tables


def _posterior_tables(
    config: SweepConfig,
    runs: list[tuple[dict[str, Any], list[dict[str, float]]]],
    rows: list[dict[str, Any]],
    arms: list[dict[str, torch.Tensor]],
    parameters: list[str],
) -> dict[str, str]:
    steps = max(config.burn_in)
    return {
        "Training arms' mask posteriors, mean over the arms, at the first and last epoch that infers them (identity "
        "gap: log evidence per observation of one arm's samples minus that of samples dealt at random; about 0 "
        "when masks do not carry the arm)": posteriors.training_table(runs),
        f"Held-out arms' SMCD posteriors after {steps} observations: how much worse the other arms' MMSE masks "
        f"predict an arm's next {max(config.horizons)} positions than its own (mask specificity; about 0 when every "
        "arm gets the same sub-network) and the ESS share, mean [95% CI] over the arms": posteriors.held_out_table(
            rows, arms, parameters
        ),
    }


def _trial_rows(
    rows: list[dict[str, Any]],
    arms: list[dict[str, torch.Tensor]],
    references: dict[tuple[Any, ...], dict[str, dict[str, torch.Tensor]]],
    parameters: list[str],
    study: str,
) -> list[dict[str, Any]]:
    """One row per held-out arm of every grid point (SMCD) and every reference on every trained network."""
    model = model_parameters(parameters, study)
    scored = [
        ({p: row[p] for p in parameters}, method(study, "S"), scores) for row, scores in zip(rows, arms, strict=True)
    ]
    filters = {p: None for p in parameters if p not in model}
    for values, by_method in references.items():
        scored += [({**dict(zip(model, values, strict=True)), **filters}, m, s) for m, s in by_method.items()]
    return [
        {**where, "method": label, "arm": k, **{name: float(v[k]) for name, v in scores.items()}}
        for where, label, scores in scored
        for k in range(len(next(iter(scores.values()))))
    ]
