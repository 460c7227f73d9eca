"""Closed-loop tracking with a telescoping link (paper appendix A.4, Fig. 8): ``smcd-rl telescoping``.

Reads top to bottom: seed, make motor-babbling data, train a multi-task (M), a Reptile (R) and a
task-mask (T: masks trained to identify the arm) dropout model, then for every method run all trials at once: at each of the 100 steps the
method observes the joint angles and the measured end effector, and the paper's PD law
``u = -K1 J^+ (x - x_g) - K2 q_dot`` (``K1 = 20, K2 = 5``) drives the arm toward a target moving
on a circle, with ``J`` the Jacobian of the method's adapted kinematics at the current angles.
``x`` is the method's own prediction (``--feedback predicted``, the default: model-reference
control, so the adapted model sets both the position and the direction of every correction;
the model still observes a measurement at every step) or the measured end effector
(``--feedback measured``: the model then only sets the direction, through ``J``). A.4 does not
say which; its Fig. 8 differences (an oracle that struggles) appear only with ``predicted``. The
second link telescopes, ``l2 = 1 + 0.25 sin(pi k / 20)``, so the kinematics keep changing.

Writes ``results.csv`` (the table: mean error and 95 % CI over the episodes at the report steps
and over the whole episode, and each adapted method's median ms per observation on the tuning
episodes), ``trials.csv`` (every episode's errors), ``comparisons.csv`` (every
adaptive method paired with M+N and with the others over the same episodes), ``curves.csv``
(mean and std of the error at every step), ``results.json``, ``tracking.png`` and ``report.md``.
Finished methods are kept in ``partial/``, keyed by the digest of the model they use, so a rerun
skips them and a new ``--model`` file is never mistaken for the old one.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.envs.two_link_telescoping import circle_target, telescoping_frame
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table, save_figure, write_csv
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stages import estimate, mlp_flops, tuning_cost, update_cost
from smcd_rl.experiments.shared.stats import cell_statistics, verdict_table
from smcd_rl.experiments.shared.task_family import task_verdict_table
from smcd_rl.experiments.shared.tuned_methods import ms_column, tuned_variants
from smcd_rl.experiments.shared.tuning import TuneJob, tune_all
from smcd_rl.experiments.shared.two_link_family import (
    babbling_data,
    fit_settings,
    network,
    task_fit_settings,
    task_model,
    train_reptile,
    tuning_episodes,
)
from smcd_rl.experiments.shared.video import video_name, write_gif
from smcd_rl.experiments.telescoping.config import DEFAULT_METHODS, FULL, METHODS, TelescopingConfig
from smcd_rl.experiments.telescoping.tracking import make_method, sample_episodes, track_recorded

__all__ = ["TelescopingConfig", "FULL", "METHODS", "DEFAULT_METHODS", "run", "table"]

#: Steps of each tuning episode (babbling of a fresh arm): twice the training episodes' 10.
TUNING_STEPS = 20

#: The adaptive methods, each compared (paired over the same episodes) with M+N and with each other
#: (each as the method against those after it: T+S first, so its pairs read T+S minus the other).
ADAPTIVE = (
    "T+S",
    "T+SL",
    *(
        f"{network}+{variant}"
        for network in ("M", "R")
        for variant in ("S", "SL", "L", "S(evidence)", "S(paper)", "C", "G")
    ),
    "T+L",
    "T+G",
    "T+N",
    "R+N",
    "O+P",
    "true",
)


def run(config: TelescopingConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        # --- seed, data, models -------------------------------------------------------------------
        families = {_family(name) for name in config.methods} - {""}
        trains = families - ({"M"} if config.model else set())
        data = babbling_data(config, ex) if trains else None
        models: dict[str, smcd_rl.AdaptiveModel] = {}
        losses: dict[str, list[float]] = {}
        if "M" in families and config.model:
            models["M"] = _load_model(config.model, ex.device)
        elif "M" in families:
            assert data is not None
            models["M"], losses["M"] = _train_m(ex, config, data)
        if "R" in families:
            assert data is not None
            models["R"], losses["R"] = train_reptile(ex, config, data, init_seed=config.seed + 1)
            models["R"].save(ex.out / "reptile.pt")
        if "T" in families:
            assert data is not None
            models["T"] = task_model(config, ex.device, init_seed=config.seed + 29)
            losses["T"] = ex.train("task", smcd_rl.fit, models["T"], data, **task_fit_settings(config))
            models["T"].save(ex.out / "task_model.pt")

        # --- the fair protocol: SMCD and GD tuned on babbling of fresh training arms (never telescoping)
        held_out = tuning_episodes(config, ex.device, steps=TUNING_STEPS)
        jobs = {
            family: TuneJob(models[family], held_out, variants=variants)
            for family in sorted(families)
            if (variants := tuned_variants(family, config.methods))
        }
        tunings = tune_all(ex, jobs, config)  # independent: side by side with --workers

        # --- every method on the same episodes, cached by the digest of the model it adapts ---------
        episodes, noise = sample_episodes(config, ex.device)
        record = min(config.video, config.trials)  # --video: the first episodes keep their joint angles

        def content(name: str) -> dict[str, Any]:
            # "": the true kinematics and the oracle, which use no trained model; recorded videos key their results too
            family = {_family(name): model_digest(models[_family(name)])} if _family(name) else {}
            return family | ({"video": record} if record else {})

        done = ex.evaluate(
            {name: functools.partial(make_method, name, models, tunings, config, ex.device) for name in config.methods},
            functools.partial(_evaluate, episodes, noise, config, progress, record),
            content=content,
        )
        errors = {name: done[name]["errors"] for name in config.methods}
        videos = _write_videos({name: done[name] for name in config.methods}, episodes, config, ex.out)

        # --- results: per-episode error at each report step and over the episode, CIs, verdicts -----
        scores: dict[tuple[Any, ...], dict[str, Tensor]] = {
            (k,): {name: e[:, k] for name, e in errors.items()} for k in config.report_steps
        }
        scores[("episode",)] = {name: e[:, 1:].mean(1) for name, e in errors.items()}  # k = 0: the common start
        cells, comparisons = cell_statistics(
            scores, cell=("k",), baseline="M+N", adaptive=ADAPTIVE, metric="error", seed=config.seed
        )
        ms = ms_column(config.methods, tunings)
        rows = [_row(name, cells, config, ms.get(name)) for name in config.methods]
        curves = [
            {"method": name, "k": k, "error_mean": float(e[:, k].mean()), "error_std": float(e[:, k].std())}
            for name, e in errors.items()
            for k in range(config.horizon + 1)
        ]
        write_csv(ex.out / "curves.csv", curves)
        headline = [
            c
            for c in comparisons
            if c["method"] == "M+S" and c["against"] in ("M+N", "M+G", "M+S(evidence)", "M+S(paper)")
        ]
        ex.write(
            experiment="two-link tracking with a telescoping link (paper appendix A.4, Fig. 8)",
            tables={
                f"Distance end effector - target (m), mean [95% CI] over {config.trials} episodes, "
                f"x {config.feedback}; std over episodes; median ms per observation": table(rows, config),
                "M+S paired with M+N, M+G, M+S(evidence) and M+S(paper) over the same episodes "
                "(negative: M+S's error is lower)": verdict_table(headline, cell=("k",)),
                **task_verdict_table(comparisons, cell=("k",), over="episodes"),
                **{caption: text for t in tunings.values() for caption, text in t.tables().items()},
            },
            rows=rows,
            trials=_trial_rows(scores),
            comparisons=comparisons,
            payload={
                "train_loss": losses,
                "curves": curves,
                "tuning": {name: t.payload() for name, t in tunings.items()},
                "scoreboard": scoreboard_entry(
                    f"telescoping tracking ({config.feedback})",
                    cells,
                    comparisons,
                    cell={"k": "episode"},
                    metric="error",
                    unit="m",
                    ms=ms,
                ),
            },
            plots={
                "tracking.png": lambda path: _plot(errors, config, path),
                **{f"tuning-{name}.png": t.plot for name, t in tunings.items()},
            },
            files=videos,
        )
    return ex.result


def _evaluate(
    episodes: Any, noise: Tensor, config: TelescopingConfig, progress: bool, record: int, name: str, method: Any
) -> dict[str, Tensor]:
    """One method's tracking errors on the episodes (a function, so a worker process can run it)."""
    errors, trajectory = track_recorded(name, method, episodes, noise, config, progress=progress, record=record)
    return {"errors": errors, **({"video_q": trajectory} if record else {})}


def _write_videos(
    done: dict[str, dict[str, Any]], episodes: dict[str, Tensor], config: TelescopingConfig, out: Path
) -> list[str]:
    """``videos/<method>-<k>.gif``: each method's first ``--video`` episodes, the arm, its target and the circle."""
    names = []
    step_angle = config.angular_speed * config.dt
    for name, result in done.items():
        for k, trajectory in enumerate(result.get("video_q", ())):
            l1, radius = float(episodes["l1"][k]), float(episodes["radius"][k])
            targets = circle_target(
                torch.arange(config.horizon + 1), radius, float(episodes["start_angle"][k]), step_angle=step_angle
            )
            frames = [
                telescoping_frame(trajectory[t].numpy(), l1, t, targets[t].numpy(), radius)
                for t in range(config.horizon + 1)
            ]
            names.append(video_name(name, k))
            write_gif(frames, out / names[-1], fps=1 / config.dt)
    return names


def table(rows: list[dict[str, Any]], config: TelescopingConfig) -> str:
    """Mean distance (m) from end effector to target [95% CI] at the report steps and over the episode.

    The last column is the method's median milliseconds per observation on the tuning episodes
    (a row's ``ms_per_observation``; "-" for a method without one: the true kinematics, the
    oracle, an untuned network's N).

    Example:
        >>> row = {"method": "M+S", "error_k10": 0.2, "error_k10_low": 0.15, "error_k10_high": 0.25,
        ...        "episode_mean": 0.15, "episode_low": 0.14, "episode_high": 0.16, "episode_std": 0.05,
        ...        "ms_per_observation": 1.234}
        >>> rows = [row, {**row, "method": "true", "ms_per_observation": None}]
        >>> print(table(rows, TelescopingConfig(report_steps=(10,))))
        | method | k=10                 | episode mean         | std   | ms / observation |
        |--------|----------------------|----------------------|-------|------------------|
        | M+S    | 0.200 [0.150, 0.250] | 0.150 [0.140, 0.160] | 0.050 | 1.23             |
        | true   | 0.200 [0.150, 0.250] | 0.150 [0.140, 0.160] | 0.050 | -                |
    """

    def cell(row: dict[str, Any], name: str, mean: str) -> str:
        return f"{row[mean]:.3f} [{row[name + '_low']:.3f}, {row[name + '_high']:.3f}]"

    header = ["method", *[f"k={k}" for k in config.report_steps], "episode mean", "std", "ms / observation"]
    body = [
        [
            r["method"],
            *[cell(r, f"error_k{k}", f"error_k{k}") for k in config.report_steps],
            cell(r, "episode", "episode_mean"),
            r["episode_std"],
            "-" if r.get("ms_per_observation") is None else f"{r['ms_per_observation']:.3g}",
        ]
        for r in rows
    ]
    return format_table(body, header)


def stage_costs(config: TelescopingConfig) -> dict[str, float]:
    """Each stage's rough seconds at ``config`` (see :func:`~smcd_rl.experiments.shared.stages.estimate`), in run order.

    Training M counts its optimiser steps and a forward and backward (3 forwards) per babbling
    sample and epoch; Reptile the same per inner epoch, with one inner step per batch of each task;
    the tuning its filter runs on ``tuning_episodes x 20`` steps
    (:func:`~smcd_rl.experiments.shared.stages.tuning_cost`); each method ``horizon`` control steps of
    ``trials`` arms, each a Jacobian of the model (about 3 forwards) and an update
    (:func:`~smcd_rl.experiments.shared.stages.update_cost`), or ``oracle_particles`` analytic kinematics
    (about 200 operations each) for O+P.

    Example:
        >>> costs = stage_costs(TelescopingConfig())
        >>> list(costs)[:4], costs["evaluate M+S"] > costs["evaluate M+N"]
        (['train', 'train reptile', 'train task', 'tune M'], True)
    """
    flops = mlp_flops(2, (config.hidden,) * config.depth, 2)
    samples = config.tasks * config.episodes * config.steps
    families = {_family(name) for name in config.methods} - {""}
    costs: dict[str, float] = {}
    if "M" in families and not config.model:
        steps = config.epochs * -(-samples // config.batch_size)
        costs["train"] = estimate(steps=steps, forwards=3 * config.epochs * samples, flops=flops)
    if "R" in families:
        inner = config.reptile_epochs * config.reptile_inner_epochs
        steps = inner * config.tasks * -(-config.episodes * config.steps // config.reptile_batch_size)
        costs["train reptile"] = estimate(steps=steps, forwards=3 * inner * samples, flops=flops)
    if "T" in families:  # M's training, and from the second epoch each arm's mask posterior (16 x 100 forwards)
        steps = config.epochs * -(-samples // config.batch_size)
        posteriors = (config.epochs - 1) * config.tasks * 16 * 100
        costs["train task"] = estimate(steps=steps, forwards=3 * config.epochs * samples + posteriors, flops=flops)
    for family in sorted(families):
        if tuned_variants(family, config.methods):
            tuning = tuning_cost(config, episodes=config.tuning_episodes, steps=TUNING_STEPS, flops=flops)
            costs[f"tune {family}"] = tuning
    for name in config.methods:
        overhead, update = update_cost(name.partition("+")[2], config) if _family(name) else (0.0, 0.0)
        per_arm = {"true": 0.0, "O+P": config.oracle_particles * 200 / flops}.get(name, 3 + update)
        forwards = config.horizon * config.trials * per_arm
        costs[f"evaluate {name}"] = estimate(steps=config.horizon * (1 + overhead), forwards=forwards, flops=flops)
    return costs


def _family(name: str) -> str:
    """The trained model a method adapts: ``"M"``, ``"R"``, ``"T"``, or ``""`` (true kinematics, oracle)."""
    return name[0] if name[0] in "MRT" and name[1:2] == "+" else ""


def _train_m(
    ex: Experiment, config: TelescopingConfig, data: TensorDictBase
) -> tuple[smcd_rl.AdaptiveModel, list[float]]:
    """Train (or resume) the M (multi-task, :func:`smcd_rl.fit`) network from initial weights of its own."""
    with torch.random.fork_rng(devices=[]):  # a run that trains only M trains the same M; the global RNG is kept
        torch.manual_seed(config.seed)
        model = smcd_rl.AdaptiveModel(network(config, ex.device), in_keys=["q"], out_key="ee")
    losses = ex.train("train", smcd_rl.fit, model, data, **fit_settings(config))
    model.save(ex.out / "model.pt")
    return model, losses


def _load_model(path: str, device: torch.device) -> smcd_rl.AdaptiveModel:
    model = smcd_rl.load(path).to(device)  # an unreadable file raises an error naming it and the fix
    if model.in_keys != ["q"] or model.out_keys != ["ee"] or model.net.in_features != 2:
        raise ValueError(
            f"--model {path} maps {model.in_keys} ({model.net.in_features} inputs) -> {model.out_keys}; this "
            "experiment needs a two-link forward-kinematics model q (2) -> ee, e.g. the model.pt of `smcd-rl two-link`"
        )
    return model


def _row(name: str, cells: list[dict[str, Any]], config: TelescopingConfig, ms: float | None) -> dict[str, Any]:
    """One method's row of ``results.csv``: the table's cells with their CIs and spreads, and its ms per observation.

    ``ms`` is ``None`` for a method without a time (the true kinematics, the oracle, an untuned
    network's N): its row has no ``ms_per_observation``.
    """
    by_cell = {c["k"]: c for c in cells if c["method"] == name}
    row: dict[str, Any] = {"method": name}
    for k in config.report_steps:
        c = by_cell[k]
        row |= {
            f"error_k{k}": c["error_mean"],
            f"error_k{k}_low": c["error_low"],
            f"error_k{k}_high": c["error_high"],
            f"std_k{k}": c["error_std"],
        }
    c = by_cell["episode"]
    row |= {
        "episode_mean": c["error_mean"],
        "episode_low": c["error_low"],
        "episode_high": c["error_high"],
        "episode_std": c["error_std"],
        "episode_sem": c["error_std"] / math.sqrt(c["trials"]),
        "trials": c["trials"],
    }
    if ms is not None:
        row["ms_per_observation"] = ms
    return row


def _trial_rows(scores: dict[tuple[Any, ...], dict[str, Tensor]]) -> list[dict[str, Any]]:
    """One row per method and episode: its error at each report step and its episode mean."""
    names = next(iter(scores.values()))
    return [
        {
            "method": name,
            "trial": i,
            **{
                ("episode_mean" if k == "episode" else f"error_k{k}"): float(by[name][i]) for (k,), by in scores.items()
            },
        }
        for name in names
        for i in range(len(names[name]))
    ]


def _plot(errors: dict[str, Tensor], config: TelescopingConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    steps = torch.arange(config.horizon + 1)
    for name, e in errors.items():
        mean, std = e.mean(0), e.std(0)
        if name == "true":
            (line,) = ax.plot(steps, mean, label="true kinematics", color="black", linestyle="--")
        else:
            (line,) = ax.plot(steps, mean, label=name)
        ax.fill_between(steps, (mean - std).clamp_min(0), mean + std, color=line.get_color(), alpha=0.1)
    ax.set_xlabel("step k")
    ax.set_ylabel("distance end effector - target (m)")
    ax.set_title(f"PD tracking with a telescoping link ({config.trials} trials, 1-sigma bands, x {config.feedback})")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
