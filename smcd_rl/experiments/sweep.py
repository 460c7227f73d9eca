"""Hyper-parameter ablations (paper appendices A.1, A.2 and B.2; Figs. 5, 6 and 12): ``smcd-rl sweep``.

Three studies, chosen with ``--study``:

* ``training`` (Fig. 5): training loss of the two-link forward-kinematics model by latent
  dimension, dropout p, learning rate, batch size and epochs;
* ``smcd`` (Fig. 6): SMCD look-ahead MSE on held-out two-link arms by latent dimension, dropout p,
  bit-flip probability, likelihood noise and particle count, at every (burn-in T, horizon H) pair;
* ``drone`` (Fig. 12): training loss of the drone behaviour-cloning model (state -> operator's
  velocity command) by latent dimension, dropout p, learning rate, batch size and epochs, on
  simulated operators (:func:`smcd_rl.envs.drone_operators.simulate_operators`) or ``--dataset``.

The grid is full factorial, as in the paper's figures: each panel shows, for every value of one
parameter, the spread over all combinations of the others. ``--design one-at-a-time`` instead varies
one parameter at a time around the base values (the options of the same names), for a quick look
at large grids; its spread then says nothing about interactions.

Reads top to bottom: resolve the grid and list its points (:mod:`.sweep_grid`), run what the
result store does not hold yet as Ray tasks (:mod:`.sweep_work`; a local Ray by default,
``--address`` for an existing cluster), then the results (:mod:`.sweep_results`): ``results.csv``
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

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from smcd_rl.experiments.common import resolve_device, write_csv
from smcd_rl.experiments.harness import Experiment, ExperimentConfig, setting
from smcd_rl.experiments.result_store import ResultStore
from smcd_rl.experiments.sweep_grid import (
    DESIGNS,
    FULL_GRIDS,
    GRIDS,
    PARAMETERS,
    STUDIES,
    resolve_grid,
    trial_configs,
)
from smcd_rl.experiments.sweep_results import (
    FIGURES,
    MODEL_PARAMETERS,
    headline,
    plot,
    reference_table,
    smcd_statistics,
    summarise,
    table,
    verdict_counts,
)
from smcd_rl.experiments.sweep_trials import REFERENCES, evaluate, train, training_data, trial
from smcd_rl.experiments.sweep_work import SweepWork, ray_session

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


@dataclass
class SweepConfig(ExperimentConfig):
    """Settings of ``smcd-rl sweep``; each study's default grid finishes in minutes on 2 CPU cores."""

    out: str = setting("runs/sweep", "output directory (results, summary, plot, report, stored trials)")
    threads: int = setting(
        1, "torch CPU threads of this process (the statistics); each trial runs --cpus-per-trial", low=0
    )
    device: str = setting(
        "cpu", "torch device of each trial: cpu, cuda, cuda:1 or auto (cuda needs --gpus-per-trial > 0)"
    )
    study: str = setting("training", "training (Fig. 5), smcd (Fig. 6) or drone (Fig. 12)", choices=STUDIES)
    grid: tuple[str, ...] = setting(
        (),
        "replace a parameter's values, NAME=V1,V2,... (e.g. hidden=64,256 dropout=0.5); the others keep the study's "
        "grid. Names: training and drone: hidden dropout lr batch_size epochs; smcd: hidden dropout flip_prob "
        "noise_std particles",
    )
    design: str = setting(
        "factorial", "factorial (every combination, as the paper's figures) or one-at-a-time", choices=DESIGNS
    )
    # Base values: a parameter's value when it is not swept, and the centre of --design one-at-a-time.
    hidden: int = setting(256, "latent dimension (width of each hidden layer)", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(0.5, "dropout probability p in training", low=0.0, below=1.0)
    lr: float = setting(1e-3, "Adam learning rate", above=0.0, below=math.inf)
    batch_size: int = setting(256, "training batch size", low=1)
    epochs: int = setting(20, "training epochs", low=1)
    flip_prob: float = setting(0.01, "SMCD bit-flip probability per step", low=0.0, high=1.0)
    noise_std: float = setting(0.05, "SMCD likelihood noise std (m)", above=0.0, below=math.inf)
    particles: int = setting(500, "SMCD mask particles", low=1)
    # The smcd study's reference M+G on each trained network (not swept).
    gd_lr: float = setting(
        0.01, "smcd study: M+G's online gradient-descent learning rate (normalised units)", above=0.0
    )
    gd_steps: int = setting(5, "smcd study: M+G's gradient steps per observation", low=1)
    gd_window: int = setting(10, "smcd study: recent transitions in M+G's loss", low=1)
    # Two-link data and held-out arms (training and smcd studies).
    tasks: int = setting(100, "two-link training arms (link-length draws)", low=1)
    episodes: int = setting(30, "motor-babbling episodes per training arm", low=1)
    steps: int = setting(10, "steps per motor-babbling episode", low=1)
    measurement_noise: float = setting(
        0.01, "std of the end-effector measurement noise (m), data and held-out arms", low=0.0
    )
    arms: int = setting(100, "held-out arms each SMCD setting is evaluated on (smcd study)", low=2)
    chunk: int = setting(100, "held-out arms filtered at once (bounds memory: chunk x particles x latent)", low=1)
    burn_in: tuple[int, ...] = setting((1, 10), "burn-in (adaptation) steps T (smcd study)", low=1)
    horizons: tuple[int, ...] = setting((10,), "look-ahead horizons H (smcd study); one MSE per (T, H) pair", low=1)
    # Drone data (drone study).
    dataset: str = setting(
        "", "drone study: a trajectory dataset (.npz, smcd_rl.envs.drone_operators format); empty: simulate"
    )
    operators: int = setting(33, "drone study: simulated operators (the paper had 33)", low=1)
    trajectories_per_operator: int = setting(
        16, "drone study: landings per simulated operator (the paper had 16)", low=1
    )
    subset: int = setting(
        192, "drone study: training trajectories used, drawn at random (the paper used 192; 0: all)", low=0
    )
    # Ray.
    address: str = setting(
        "", "address of an existing Ray cluster (e.g. auto or ray://host:10001); empty: start a local Ray"
    )
    cpus: int = setting(0, "CPUs of the local Ray (0: all of this machine's); ignored with --address", low=0)
    cpus_per_trial: int = setting(1, "CPUs reserved per Ray task, and its torch threads", low=1)
    gpus_per_trial: float = setting(0.0, "GPUs reserved per Ray task (needs --device cuda)", low=0.0)
    full: bool = setting(
        False, "the paper's scale: the full factorial grids, 1000 arms x 150 episodes, 1000 held-out arms"
    )

    NON_EMPTY = ("burn_in", "horizons")

    def validate(self) -> None:
        """The declared bounds, then the grid and the checks that involve several options."""
        super().validate()
        resolve_grid(self)
        local_cpus = self.cpus or os.cpu_count() or 1
        if not self.address and self.cpus_per_trial > local_cpus:
            raise ValueError(
                f"--cpus-per-trial {self.cpus_per_trial} exceeds the local Ray's {local_cpus} CPUs; "
                "no trial could ever be scheduled"
            )
        if torch.device(resolve_device(self.device)).type != "cpu" and self.gpus_per_trial <= 0:
            raise ValueError(
                f"--device {self.device} needs --gpus-per-trial > 0: Ray hides GPUs from tasks that reserve none"
            )
        gpus = torch.cuda.device_count()
        if not self.address and self.gpus_per_trial > gpus:
            raise ValueError(
                f"--gpus-per-trial {self.gpus_per_trial:g} exceeds the local Ray's {gpus} GPUs; no trial could ever "
                "be scheduled (use --gpus-per-trial 0 on a machine without a GPU)"
            )
        if self.study == "drone" and self.dataset and not Path(self.dataset).is_file():
            raise FileNotFoundError(f"--dataset {self.dataset}: no such file; give a .npz dataset or leave it empty")


#: What ``--full`` changes besides the grid (options given explicitly still win).
FULL = {
    "tasks": 1000,
    "episodes": 150,
    "hidden": 1024,
    "lr": 1e-4,
    "batch_size": 64,
    "epochs": 200,
    "particles": 1000,
    "arms": 1000,
    "chunk": 25,
    "burn_in": (1, 5, 10, 20),
    "horizons": (1, 5, 10, 20),
    "subset": 192,
}


def run(config: SweepConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the sweep (on Ray, skipping what the result store already holds) and write its files."""
    with Experiment(config, progress=progress) as ex:
        # --- the grid, and what is left of it --------------------------------------------------
        grid = resolve_grid(config)
        points = trial_configs(config, grid)
        parameters = list(grid)
        work = SweepWork(config, points, ResultStore(ex.out / "partial", what="sweep result"))
        if not work.finished and config.study == "drone":  # a bad --subset fails here, not in every Ray task
            training_data(points[0], ex.generator)

        # --- the trials, on Ray -----------------------------------------------------------------
        if not work.finished:
            with ray_session(config) as ray:
                work.run(ray, progress=progress)

        # --- results: the summary per parameter value; in the smcd study, CIs and paired verdicts ---
        rows = [{**{p: point[p] for p in parameters}, **work.results[i]["metrics"]} for i, point in enumerate(points)]
        metrics = list(work.results[0]["metrics"])
        # A parameter with one value is a fixed setting here: it has no panel (unless nothing varies).
        varied = [p for p in parameters if len(grid[p]) > 1 or config.design == "one-at-a-time"] or parameters
        summary = summarise(rows, varied, metrics)
        what = "Look-ahead MSE (m^2)" if config.study == "smcd" else "Last epoch's training loss (normalised MSE)"
        tables = {
            f"{what} per parameter value: mean, std and min over the other parameters' grid points": table(summary)
        }
        trials: list[dict[str, Any]] = []
        comparisons: list[dict[str, Any]] = []
        extra: dict[str, Any] = {}
        if config.study == "smcd":
            references = {
                tuple(work.run_configs[key][p] for p in MODEL_PARAMETERS): {
                    m: work.references[key, m]["arms"] for m in REFERENCES
                }
                for key in work.groups
            }
            arms = [work.results[i]["arms"] for i in range(len(points))]
            pairs = [(t, h) for t in config.burn_in for h in config.horizons]
            extra["references"], comparisons = smcd_statistics(
                rows, arms, references, parameters, pairs, seed=config.seed
            )
            trials = _trial_rows(rows, arms, references, parameters)
            tables |= _smcd_tables(config, parameters, comparisons, extra["references"], len(points))
        write_csv(ex.out / "summary.csv", summary)
        ex.write(
            experiment=f"hyper-parameter sweep, study {config.study} (paper Fig. {FIGURES[config.study]})",
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
            plots={"sweep.png": lambda path: plot(rows, summary, varied, metrics, config.study, path)},
            files=["summary.csv"],
        )
        print(f"{len(points)} grid points ({len(points) - work.reused} computed, {work.reused} from the cache)")
    return ex.result


def _smcd_tables(
    config: SweepConfig,
    parameters: list[str],
    comparisons: list[dict[str, Any]],
    references: list[dict[str, Any]],
    points: int,
) -> dict[str, str]:
    base = {p: getattr(config, p) for p in parameters}
    tables = {
        f"SMCD (M+S) paired with M+N and M+G over the same arms: verdicts (95% CI of the difference) over the {points} grid points": verdict_counts(
            comparisons
        )
    }
    at_base = headline(comparisons, base)
    if at_base is not None:
        setting_text = ", ".join(f"{k}={v}" for k, v in base.items())
        tables[f"SMCD at the base setting ({setting_text}) minus M+N and M+G (negative: SMCD's error is lower)"] = (
            at_base
        )
    tables["The references on each trained network: look-ahead MSE (m^2), mean [95% CI] over the arms"] = (
        reference_table(references, [p for p in parameters if p in MODEL_PARAMETERS])
    )
    return tables


def _trial_rows(
    rows: list[dict[str, Any]],
    arms: list[dict[str, torch.Tensor]],
    references: dict[tuple[Any, ...], dict[str, dict[str, torch.Tensor]]],
    parameters: list[str],
) -> list[dict[str, Any]]:
    """One row per held-out arm of every grid point (M+S) and every reference on every trained network."""
    model = [p for p in parameters if p in MODEL_PARAMETERS]
    scored = [({p: row[p] for p in parameters}, "M+S", scores) for row, scores in zip(rows, arms, strict=True)]
    filters = {p: None for p in parameters if p not in model}
    for values, by_method in references.items():
        scored += [({**dict(zip(model, values, strict=True)), **filters}, m, s) for m, s in by_method.items()]
    return [
        {**where, "method": method, "arm": k, **{name: float(v[k]) for name, v in scores.items()}}
        for where, method, scores in scored
        for k in range(len(next(iter(scores.values()))))
    ]
