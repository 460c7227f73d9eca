"""Model-based control of the crippled-leg Ant (paper appendix C, Fig. 15): ``smcd-rl ant``.

Reads top to bottom: seed, collect transitions from the *healthy* Ant (random actions, or a
small stable-baselines3 SAC policy), fit one dropout dynamics model, then run every combination
of planner {CEM, MPPI, RS} x adaptation {none, GD, SMCD} on the healthy Ant and on the Ant with
a crippled leg (the episodes are in :mod:`smcd_rl.experiments.ant_episodes`). All cells share
the trained network (``model.with_adaptation``).

Writes ``results.csv`` (one row per planner, adaptation and condition: mean episode return with
its 95% bootstrap interval, and its spread), ``trials.csv`` (every episode), ``comparisons.csv``
(each adaptation paired with no adaptation and with the other over the same episodes, per planner
and condition), ``results.json``, ``ant.png`` (Fig. 15: healthy and crippled panels, bars per
planner grouped by adaptation, error bars the 95% intervals) and ``report.md``. The collected
data and the finished cells (in ``partial/``, keyed by the data settings, and by the trained
model's digest and the settings) and the training (``train-<digest>.ckpt``) are reused by a rerun.

Choices the paper leaves open, made here:

* Crippled condition: each episode cripples a leg drawn uniformly from ``--crippled-legs``
  (default all four: the model never saw any crippled leg, so all are out of distribution).
  Episode ``k`` uses the same env seed in every cell, hence the same initial state and the same
  leg: cells are compared paired, on identical episodes.
* The task (``--task l2a``, default) is Learning to Adapt's, which the paper used: reward =
  forward velocity + 0.05 per step, no control or contact cost, and episodes never end early.
  ``--task ant-v5`` uses Ant-v5's reward (forward velocity + 1 while healthy - 0.5 |a|^2 -
  contact cost) and ends an episode when the Ant is unhealthy. The reported reward is the env's;
  the planners optimise :func:`~smcd_rl.envs.crippled_ant.ant_reward` with the same weights (the
  contact term, which needs contact forces, left out) and, for ant-v5,
  :func:`~smcd_rl.envs.crippled_ant.ant_termination`. On ant-v5, with a model fitted to random
  actions, the planners mostly keep the Ant standing: the control cost outweighs the forward
  velocity the model can predict.
* SMCD's likelihood noise is per observation dimension: the trained model's RMSE on held-out
  transitions times ``--noise-scale`` (default 3; at 1 the effective sample size collapses to
  about 15% of the particles after every step).
* Dropout: ``--full`` uses the paper's p = 0.5 on its 3 x 1024 network. The default network is
  five times narrower and underfits at p = 0.5 (held-out normalised MSE 0.46 on 10^5 random
  transitions, against 0.16 at the default p = 0.1), and planning on it barely moves the Ant.
* Planners get the same budget of model evaluations per step: CEM and MPPI ``iterations x
  candidates``, random shooting that many candidates in one round.

Example:
    >>> from smcd_rl.experiments.ant import AntConfig, CELLS
    >>> config = AntConfig()
    >>> len(CELLS), config.planners, config.adaptations, config.conditions
    (18, ('cem', 'mppi', 'rs'), ('none', 'gd', 'smcd'), ('healthy', 'crippled'))
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.experiments.ant_episodes import ACTION_DIM, OBS_DIM, TASKS, collect, run_cell, validation_error
from smcd_rl.experiments.common import format_table
from smcd_rl.experiments.harness import Experiment, ExperimentConfig, setting
from smcd_rl.experiments.stats import cell_statistics, verdict_table

__all__ = ["AntConfig", "FULL", "PLANNERS", "ADAPTATIONS", "CONDITIONS", "CELLS", "TASKS", "run", "table"]

#: Planner names and their labels in the table and plot.
PLANNERS: dict[str, str] = {"cem": "CEM", "mppi": "MPPI", "rs": "RS"}
#: Adaptation names and their labels.
ADAPTATIONS: dict[str, str] = {"none": "none", "gd": "GD", "smcd": "SMCD"}
#: Conditions: the Ant the model was trained on, and the Ant with one leg crippled per episode.
CONDITIONS: tuple[str, ...] = ("healthy", "crippled")
#: Every (planner, adaptation, condition) cell of Fig. 15.
CELLS: tuple[tuple[str, str, str], ...] = tuple(itertools.product(PLANNERS, ADAPTATIONS, CONDITIONS))
#: Settings that determine the collected transitions.
DATA_SETTINGS = ("seed", "task", "data_policy", "sac_steps", "transitions", "data_episode_steps")


@dataclass
class AntConfig(ExperimentConfig):
    """Settings of ``smcd-rl ant``; the defaults finish in under 20 minutes on 2 CPU cores."""

    out: str = setting("runs/ant", "output directory (results, plot, report, data, trained model)")
    task: str = setting(
        "l2a", "reward and episode end: l2a (Learning to Adapt's, the paper's) or ant-v5", choices=tuple(TASKS)
    )
    data_policy: str = setting(
        "random", "policy that collects the training data: random or sac", choices=("random", "sac")
    )
    sac_steps: int = setting(5000, "training steps of the SAC data policy (--data-policy sac)", low=1)
    transitions: int = setting(100_000, "transitions collected from the healthy Ant (see --validation)", low=3)
    data_episode_steps: int = setting(200, "steps per data-collection episode", low=1)
    hidden: int = setting(200, "width of each hidden layer", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(
        0.1, "dropout probability p (0 < p < 1) used in training (the paper's 0.5 with --full)", above=0.0
    )
    epochs: int = setting(40, "training epochs", low=1)
    batch_size: int = setting(256, "training batch size", low=1)
    lr: float = setting(1e-3, "Adam learning rate", above=0.0)
    validation: float = setting(
        0.1, "fraction (0 < f < 1) of the transitions held out (validation RMSE, SMCD noise)", above=0.0
    )
    planners: tuple[str, ...] = setting(tuple(PLANNERS), "planners to run: cem, mppi, rs", choices=tuple(PLANNERS))
    adaptations: tuple[str, ...] = setting(
        tuple(ADAPTATIONS), "adaptations to run: none, gd, smcd", choices=tuple(ADAPTATIONS)
    )
    conditions: tuple[str, ...] = setting(CONDITIONS, "conditions to run: healthy, crippled", choices=CONDITIONS)
    crippled_legs: tuple[int, ...] = setting(
        (0, 1, 2, 3), "legs the crippled leg is drawn from per episode", choices=(0, 1, 2, 3)
    )
    episodes: int = setting(
        6, "evaluation episodes per cell (at least 2: a confidence interval over one is a point)", low=2
    )
    episode_steps: int = setting(200, "steps per evaluation episode (ant-v5: a fall ends it sooner)", low=1)
    horizon: int = setting(10, "planning horizon H (steps)", low=1)
    candidates: int = setting(200, "action sequences per planner iteration (RS: times --iterations, once)", low=1)
    elites: int = setting(20, "CEM elites per iteration (at most --candidates)", low=1)
    iterations: int = setting(3, "CEM and MPPI iterations per step", low=1)
    temperature: float = setting(1.0, "MPPI temperature (units of the predicted return)", above=0.0)
    mppi_noise: float = setting(0.5, "MPPI perturbation std (actions lie in [-1, 1])", above=0.0)
    particles: int = setting(100, "SMCD mask particles", low=1)
    flip_prob: float = setting(0.01, "SMCD bit-flip probability per step", low=0.0)
    noise_scale: float = setting(3.0, "SMCD likelihood noise, in units of the held-out RMSE per dimension", above=0.0)
    gd_lr: float = setting(0.01, "online gradient-descent learning rate (normalised units)", above=0.0)
    gd_steps: int = setting(5, "gradient steps per observation", low=1)
    gd_window: int = setting(10, "recent transitions in the gradient-descent loss", low=1)
    full: bool = setting(False, "the paper's scale: 3 x 1024 model, 10^6 transitions, 110 episodes of 1000 steps")

    NON_EMPTY = ("planners", "adaptations", "conditions", "crippled_legs")
    SELECTION = ("planners", "adaptations", "conditions")  # which cells run: a subset rerun reuses cells

    def validate(self) -> None:
        """The declared bounds, then what they cannot express: upper bounds and bounds across options."""
        super().validate()
        for name in ("dropout", "validation"):
            if getattr(self, name) >= 1.0:
                raise ValueError(f"--{name} must be < 1, got {getattr(self, name)}")
        if self.elites > self.candidates:
            raise ValueError(f"--elites ({self.elites}) must be <= --candidates ({self.candidates})")
        if self.transitions * self.validation < 1 or self.transitions * (1 - self.validation) < 2:
            raise ValueError(f"{self.transitions} transitions are too few to hold out {self.validation:.0%}")
        keep = 1.0 - self.dropout  # SMCD's keep_rate transition flips a bit with up to 2 d max(k, 1 - k)
        if self.flip_prob > 1 / (2 * max(keep, 1 - keep)):
            raise ValueError(
                f"--flip-prob {self.flip_prob} is too large at dropout {self.dropout}: "
                f"use at most {1 / (2 * max(keep, 1 - keep)):.3g}"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "transitions": 1_000_000,
    "data_episode_steps": 1000,
    "hidden": 1024,
    "depth": 3,
    "dropout": 0.5,
    "epochs": 100,
    "lr": 1e-4,
    "episodes": 110,
    "episode_steps": 1000,
    "horizon": 15,
    "candidates": 500,
    "elites": 50,
    "iterations": 5,
    "particles": 1000,
    "threads": 0,
}


def run(config: AntConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        # --- seed, data from the healthy Ant ----------------------------------------------------
        data_key = {k: getattr(config, k) for k in DATA_SETTINGS}
        collected = ex.store.get("data", data_key)
        if collected is None:
            collected = collect(config, progress=progress)
            ex.store.put("data", data_key, collected)
        n_val = max(1, int(round(config.validation * config.transitions)))
        train, val = collected["data"][:-n_val].to(ex.device), collected["data"][-n_val:].to(ex.device)
        episode_seeds = [config.seed + 1_000_003 + k for k in range(config.episodes)]  # the same in every cell

        # --- one dropout dynamics model for every cell --------------------------------------------
        torch.manual_seed(config.seed)  # the same initial weights whether the data was collected or loaded
        net = smcd_rl.MaskedMLP(
            OBS_DIM + ACTION_DIM,
            OBS_DIM,
            hidden=(config.hidden,) * config.depth,
            dropout=config.dropout,
            device=ex.device,
        )
        model = smcd_rl.AdaptiveDynamicsModel(net)
        fit = {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}
        losses = ex.train("train", smcd_rl.fit_dynamics, model, train, **fit)
        model.save(ex.out / "model.pt")
        val_rmse, val_nmse = validation_error(model, val)
        noise_std = (config.noise_scale * val_rmse).clamp_min(1e-4)

        # --- every (planner, adaptation, condition) cell on the same episodes ----------------------
        cells = [
            c for c in CELLS if c[0] in config.planners and c[1] in config.adaptations and c[2] in config.conditions
        ]

        # A cell's factory runs its episodes; it is called only for cells the cache does not have.
        cell_runs = {
            "/".join(cell): functools.partial(
                run_cell,
                model,
                cell,
                config,
                noise_std,
                # One planner seed per planner, the same in every adaptation and condition.
                planner_seed=config.seed + 1000 * (1 + list(PLANNERS).index(cell[0])),
                episode_seeds=episode_seeds,
                device=ex.device,
                progress=progress,
            )
            for cell in cells
        }
        done = ex.evaluate(
            cell_runs,
            lambda name, result: result,
            content={"model": model_digest(model), "noise_std": noise_std},
        )

        # --- results: returns per episode, 95% CIs, adaptations paired over the same episodes -----
        episodes = {cell: done["/".join(cell)]["episodes"] for cell in cells}
        scores: dict[tuple[str, str], dict[str, torch.Tensor]] = {}
        for (planner, adaptation, condition), records in episodes.items():
            returns = torch.tensor([e["return"] for e in records], dtype=torch.float64)
            scores.setdefault((PLANNERS[planner], condition), {})[ADAPTATIONS[adaptation]] = returns
        stats, comparisons = cell_statistics(
            scores,
            cell=("planner", "condition"),
            baseline="none",
            adaptive=("SMCD", "GD"),
            metric="return",
            lower_is_better=False,
            seed=config.seed,
        )
        rows = _rows(stats, episodes, {cell: done["/".join(cell)]["seconds"] for cell in cells})
        trial_rows = [
            {"planner": PLANNERS[p], "adaptation": ADAPTATIONS[a], "condition": c, **e}
            for (p, a, c), records in episodes.items()
            for e in records
        ]
        headline = [c for c in comparisons if c["method"] == "SMCD"]
        tables = {
            f"Episode return (task {config.task}), mean [95% CI] over {config.episodes} episodes of up to "
            f"{config.episode_steps} steps": table(rows)
        }
        if headline:
            caption = "SMCD paired with no adaptation and GD over the same episodes (positive: SMCD's return is higher)"
            tables[caption] = verdict_table(headline, cell=("planner", "condition"))
        ex.write(
            experiment="crippled-leg Ant, model-based control with adaptation (paper appendix C, Fig. 15)",
            tables=tables,
            rows=rows,
            trials=trial_rows,
            comparisons=comparisons,
            payload={
                "data": {
                    "policy": config.data_policy,
                    "transitions": config.transitions,
                    "held_out": n_val,
                    "collect_seconds": collected["seconds"],
                    "sac_seconds": collected.get("sac_seconds"),
                },
                "training": {
                    "loss": losses,
                    "validation_nmse": val_nmse,
                    "validation_rmse": val_rmse.tolist(),
                    "smcd_noise_std": noise_std.tolist(),
                },
            },
            plots={"ant.png": lambda path: _plot(rows, config, path)},
        )
    return ex.result


def _rows(
    stats: list[dict[str, Any]],
    episodes: dict[tuple[str, str, str], list[dict[str, Any]]],
    seconds: dict[tuple[str, str, str], float],
) -> list[dict[str, Any]]:
    """One row per cell, in :data:`CELLS` order: the return's mean, 95% CI and spread, steps, distance."""
    lookup = {(r["planner"], r["method"], r["condition"]): r for r in stats}
    rows = []
    for (planner, adaptation, condition), records in episodes.items():
        r = lookup[(PLANNERS[planner], ADAPTATIONS[adaptation], condition)]
        rows.append(
            {
                "planner": PLANNERS[planner],
                "adaptation": ADAPTATIONS[adaptation],
                "condition": condition,
                "return_mean": r["return_mean"],
                "return_low": r["return_low"],
                "return_high": r["return_high"],
                "return_std": r["return_std"],
                "return_sem": r["return_std"] / math.sqrt(r["trials"]),
                "steps_mean": float(np.mean([e["steps"] for e in records])),
                "distance_mean": float(np.mean([e["distance"] for e in records])),
                "episodes": r["trials"],
                "seconds": seconds[(planner, adaptation, condition)],
            }
        )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """Episode return ``mean [95% CI]`` per planner and adaptation (down), per condition (across)."""
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    lookup = {(r["planner"], r["adaptation"], r["condition"]): r for r in rows}
    pairs = list(dict.fromkeys((r["planner"], r["adaptation"]) for r in rows))
    body = []
    for planner, adaptation in pairs:
        cells = []
        for condition in conditions:
            r = lookup.get((planner, adaptation, condition))
            cells.append(
                "-" if r is None else f"{r['return_mean']:.1f} [{r['return_low']:.1f}, {r['return_high']:.1f}]"
            )
        body.append([planner, adaptation, *cells])
    return format_table(body, ["planner", "adaptation", *conditions])


def _plot(rows: list[dict[str, Any]], config: AntConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    adaptations = list(dict.fromkeys(r["adaptation"] for r in rows))
    planners = list(dict.fromkeys(r["planner"] for r in rows))
    lookup = {(r["planner"], r["adaptation"], r["condition"]): r for r in rows}
    width = 0.8 / len(planners)
    fig, axes = plt.subplots(1, len(conditions), figsize=(4.2 * len(conditions), 3.6), sharey=True, squeeze=False)
    for ax, condition in zip(axes[0], conditions, strict=True):
        for i, planner in enumerate(planners):
            sel = [lookup.get((planner, a, condition)) for a in adaptations]
            xs = [j + (i - (len(planners) - 1) / 2) * width for j in range(len(adaptations))]
            ax.bar(
                xs,
                [r["return_mean"] if r else float("nan") for r in sel],
                width,
                yerr=[
                    [r["return_mean"] - r["return_low"] if r else 0.0 for r in sel],
                    [r["return_high"] - r["return_mean"] if r else 0.0 for r in sel],
                ],
                capsize=3,
                label=planner,
            )
        ax.set_xticks(range(len(adaptations)), adaptations)
        ax.set_title("all legs functional" if condition == "healthy" else "one leg crippled")
        ax.set_xlabel("adaptation")
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("episode return")
    axes[0][-1].legend(title="planner")
    fig.suptitle(f"Ant MPC ({config.episodes} episodes of up to {config.episode_steps} steps, 95% CI)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
