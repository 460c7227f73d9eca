"""7-DOF Panda reaching with an unknown tool and sparse measurements (paper sec. 4.2, Fig. 3): ``smcd-rl panda``.

Reads top to bottom: seed, sample joint configurations with random tools, train one dropout
forward-kinematics network ``q (7) -> x (3)``, tune its adaptation strategies by the fair protocol,
then for every method, measurement interval ``n`` and seed drive ``tasks`` arms at once from the
ready pose towards random feasible goals with :class:`~smcd_rl.agents.pd.JacobianPD` through the
method's kinematics, and count the arms whose true end effector gets within 5 cm of the goal
within ``steps`` control steps.

Methods (Fig. 3): ``FK``, the analytic chain that does not know the tool (assumes ``l = 0``);
``M+N``, the trained network with no adaptation; ``M+G``, online gradient descent (tuned);
``M+S``, SMCD tuned by one-step error; ``M+S(evidence)``, SMCD calibrated by its evidence;
``M+S(paper)``, SMCD at the paper's settings (``--noise-std`` 0.02 m, ``--flip-prob`` 0.05);
``M+C``, the combination of N, G and S (:class:`smcd_rl.Combination`). At every n-th step (0, n,
2n, ...) the true end effector is measured: the adaptive model observes ``(q, measured x)`` and the
controller corrects the measured error. In between, nothing is observed and the controller
corrects the error of its own kinematics' prediction (model-reference control). ``FK`` at
``n = 1`` is the reference line of Fig. 3.

The fair protocol (:mod:`smcd_rl.experiments.shared.tuning`): before any test task is seen,
``--tuning-episodes`` episodes are drawn from the *training* distribution (each a fresh tool from
``U(-tool_range, tool_range)`` observed at ``--tuning-steps`` states of a reach towards a fresh goal,
from a generator of its own, so neither training samples nor test tasks are among them). On them
:func:`smcd_rl.tune` tunes every method by one-step error: SMCD's likelihood noise and flip
probability (``M+S``), gradient descent's learning rate, steps, window and loss from the grid
``--gd-lr x --gd-steps x --gd-window`` (``M+G``; one value each makes a one-point grid, extended
past an edge while the best point lies there) and the combination's weights (``M+C``).
``M+S(evidence)`` is SMCD calibrated by its log evidence instead; ``M+S(paper)`` is not tuned. The
report's tuning tables and ``tuning-M.png`` show the chosen settings, each method's median time
per observation (also the results table's last column) and each strategy's diagnosis on those
episodes; ``results.json`` holds them under ``"tuning"``.

Writes ``results.csv`` (success rate per method and n: mean and 95 % CI over all arms, std over
seeds), ``trials.csv`` (every arm: reached, steps, final distance, tool), ``comparisons.csv``
(every adaptive method paired with M+N and the others over the same arms), ``results.json`` (with
the ``"tuning"`` entry and the ``"scoreboard"`` entry, success rate at n = 20, for ``smcd-rl
scoreboard``), ``panda.png`` (success rate against n), ``tuning-M.png`` and ``report.md``.
Finished (method, n) runs are kept in ``partial/`` and skipped by a rerun with the same network and
settings (methods and intervals aside).

Choices the paper leaves open, made here:

* Control: ``u`` is a joint acceleration (``q_dot += dt u; q += dt q_dot``, dt = 0.05 s) with the
  Panda's acceleration, velocity and position limits, and the gains of the paper's two-link
  controller (K1 = 20, K2 = 5). With the true kinematics this reaches every one of 300 random
  goals, median 23 steps (``tests/envs/test_panda_reach.py`` checks >= 95 % of 50).
* Seeds: one trained network and one tuning; each seed draws its own ``tasks`` test tools and goals
  (the same for every method and n, so the methods are compared on identical tasks) and its own
  filter noise.
* Trials: 3 seeds x 100 tasks = 300 arms by default, enough for a paired comparison to detect a
  success-rate difference of 0.1 between two methods (see the note above :class:`PandaConfig`).
* Measurements are exact unless ``--measurement-noise`` is set (then the tuning episodes carry the
  same noise); SMCD's likelihood noise stands for the network's own error.

Example:
    >>> from smcd_rl.experiments.panda.run import PandaConfig, method_labels
    >>> config = PandaConfig()
    >>> method_labels(config)
    ['FK', 'M+N', 'M+G', 'M+S', 'M+S(evidence)', 'M+S(paper)', 'M+C', 'M+L', 'M+SL', 'T+N', 'T+G', 'T+S', 'T+L', 'T+SL']
    >>> config.tasks * config.seeds, config.gd_lr, PandaConfig(gd_lr=(0.01,)).gd_lr
    (300, (0.003, 0.01, 0.03, 0.1), (0.01,))
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.envs.panda_reach import panda_frame, panda_kinematics_data
from smcd_rl.experiments.panda.config import DEFAULT_INTERVALS, FULL, METHODS, PandaConfig
from smcd_rl.experiments.panda.figure import plot
from smcd_rl.experiments.panda.reaching import method_kinematics, reach, sample_tasks, tuning_episodes
from smcd_rl.experiments.panda.tables import describe, table, trial_rows
from smcd_rl.experiments.panda.task_network import task_data, task_network
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stages import estimate, mlp_flops, tuning_cost
from smcd_rl.experiments.shared.stats import cell_statistics, verdict_table
from smcd_rl.experiments.shared.task_family import task_mask_settings, task_verdict_table
from smcd_rl.experiments.shared.tuned_methods import ms_column, tuned_variants
from smcd_rl.experiments.shared.tuning import Tuning, tune
from smcd_rl.experiments.shared.video import video_name, write_gif

__all__ = [
    "PandaConfig",
    "FULL",
    "METHODS",
    "DEFAULT_INTERVALS",
    "HEADLINE_INTERVAL",
    "method_labels",
    "reach",
    "run",
    "table",
]

#: The scoreboard's cell: the sparsest default measurements, where Fig. 3's methods differ most
#: (a run without it reports its largest n instead).
HEADLINE_INTERVAL = 20


def method_labels(config: PandaConfig) -> list[str]:
    """The table's method rows, in the order of :data:`METHODS`."""
    return [name for name in METHODS if name in config.methods]


def run(config: PandaConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        # --- seed, data, model --------------------------------------------------------------------
        data = panda_kinematics_data(config.samples, tool_range=config.tool_range, generator=ex.generator)
        held_out = panda_kinematics_data(2000, tool_range=config.tool_range, generator=ex.generator)
        net = smcd_rl.MaskedMLP(7, 3, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=ex.device)
        model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
        fit = {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}
        losses = ex.train("train", smcd_rl.fit, model, data.to(ex.device), **fit)
        model.save(ex.out / "model.pt")
        held_out_rmse = _held_out_rmse(model, held_out.to(ex.device))
        models = {"M": model}
        if any(m.startswith("T+") for m in config.methods):  # T: masks trained to identify the tool
            models["T"] = task_network(config, ex.device)
            samples = task_data(config).to(ex.device)
            losses_t = ex.train("train T", smcd_rl.fit, models["T"], samples, **fit, **task_mask_settings(config))
            models["T"].save(ex.out / "task_model.pt")

        # --- the fair protocol: every network's methods tuned on held-out episodes of fresh tools ---
        episodes = tuning_episodes(config, ex.device) if _adapts(config) else None
        tunings = {
            net: tune(ex, models[net], episodes, config, name=net, variants=variants)
            for net in models
            if episodes is not None and (variants := tuned_variants(net, config.methods))
        }

        # --- every (method, n) on the same arms: each seed's tasks run as one batch -----------------
        labels = method_labels(config)
        runs = {f"{label} n={n}": (label, n) for label in labels for n in _intervals(label, config)}
        video_n = _video_interval(config)

        units = {name: functools.partial(_unit, *unit) for name, unit in runs.items()}
        digests = {net: model_digest(m) for net, m in models.items()}
        done = ex.evaluate(
            units,
            functools.partial(_evaluate, models, tunings, config, video_n, ex.device, progress),
            # The recorded videos are part of those results, so their count keys them (only where recorded).
            content=lambda name: {
                "model": digests[runs[name][0].partition("+")[0] if "+" in runs[name][0] else "M"],
                **({"video": config.video} if runs[name][1] == video_n else {}),
            },
        )
        videos = _write_videos({unit: done[name] for name, unit in runs.items()}, video_n, config, ex.out)

        # --- results: success over all arms per (n, method), CIs, paired verdicts -------------------
        results = {unit: done[name] for name, unit in runs.items()}
        intervals = sorted({n for _, n in results})
        scores = {
            (n,): {label: r["reached"].reshape(-1).double() for (label, m), r in results.items() if m == n}
            for n in intervals
        }
        # T+S first: its pairs read T+S minus the other.
        order = (
            "T+S",
            "T+SL",
            "M+S",
            "M+SL",
            "M+L",
            "M+S(evidence)",
            "M+S(paper)",
            "M+C",
            "M+G",
            "T+L",
            "T+G",
            "T+N",
            "FK",
        )
        adaptive = [m for m in order if m in labels]
        rows, comparisons = cell_statistics(
            scores,
            cell=("interval",),
            baseline="M+N",
            adaptive=adaptive,
            metric="success",
            lower_is_better=False,
            seed=config.seed,
        )
        ms = ms_column(labels, tunings)
        rows = sorted((describe(row, results, config, ms) for row in rows), key=lambda r: labels.index(r["method"]))
        headline = [
            c
            for c in comparisons
            if c["method"] == "M+S" and c["against"] in ("M+N", "M+G", "M+S(evidence)", "M+S(paper)")
        ]
        ex.write(
            experiment="7-DOF Panda reaching with an unknown tool and sparse measurements (paper Fig. 3)",
            tables={
                f"Success rate (within {100 * config.tolerance:.0f} cm in {config.steps} steps), mean [95% CI] over "
                f"{config.seeds} seeds x {config.tasks} arms; the network's held-out RMSE (mean mask) is "
                f"{held_out_rmse:.3f} m; median ms per observation": table(rows, config),
                "M+S paired with M+N, M+G, M+S(evidence) and M+S(paper) over the same arms "
                "(positive: M+S reaches more goals)": verdict_table(headline, cell=("interval",)),
                **task_verdict_table(
                    comparisons,
                    cell=("interval",),
                    over="arms",
                    against=("M+S", "M+G", "M+L", "M+SL"),
                    lower_is_better=False,
                ),
                **{caption: text for t in tunings.values() for caption, text in t.tables().items()},
            },
            rows=rows,
            trials=trial_rows(results, config),
            comparisons=comparisons,
            payload={
                "train_loss": losses,
                **({"task_train_loss": losses_t} if "T" in models else {}),
                "held_out_rmse_m": held_out_rmse,
                "tuning": {name: t.payload() for name, t in tunings.items()},
                "scoreboard": scoreboard_entry(
                    "Panda reaching",
                    rows,
                    comparisons,
                    cell={"interval": HEADLINE_INTERVAL if HEADLINE_INTERVAL in intervals else max(intervals)},
                    metric="success",
                    unit="success rate",
                    lower_is_better=False,
                    ms=ms,
                ),
            },
            plots={
                "panda.png": lambda path: plot(rows, config, path),
                **{f"tuning-{name}.png": t.plot for name, t in tunings.items()},
            },
            files=videos,
        )
    return ex.result


def _evaluate(
    models: dict[str, smcd_rl.AdaptiveModel],
    tunings: dict[str, Tuning],
    config: PandaConfig,
    video_n: int | None,
    device: torch.device,
    progress: bool,
    name: str,
    unit: tuple[str, int],
) -> dict[str, Tensor]:
    """One (method, n)'s reaches over every seed's tasks (a function, so a worker process can run it)."""
    label, n = unit
    per_seed: list[dict[str, Tensor]] = []
    videos: list[dict[str, Tensor]] = []
    for s in tqdm(range(config.seeds), desc=name, unit="seed", disable=not progress):
        tools, goals = sample_tasks(config, s, device)
        kinematics, observe = method_kinematics(label, models, tools, tunings, config, s, device)
        # Measurement noise (if any) from the seed alone: every method and n sees the same draws.
        noise = torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + 104_729 * (s + 1))
        # --video: the first arms (seed 0's, then seed 1's, ...) keep their joint angles at every step.
        record = min(config.video - sum(int(v["q"].shape[0]) for v in videos), config.tasks) if n == video_n else 0
        outcome = reach(kinematics, observe, tools, goals, interval=n, config=config, generator=noise, record=record)
        if record > 0:
            trajectory = outcome.pop("trajectory")
            first_arms = {"tools": tools[:record], "goals": goals[:record], "steps": outcome["steps"][:record]}
            videos.append({"q": trajectory, **{key: value.cpu() for key, value in first_arms.items()}})
        per_seed.append({**outcome, "tools": tools})
    result = {key: torch.stack([r[key].cpu() for r in per_seed]) for key in per_seed[0]}  # [seeds, tasks]
    if videos:
        result |= {f"video_{key}": torch.cat([v[key] for v in videos]) for key in videos[0]}
    return result


def _unit(label: str, n: int) -> tuple[str, int]:
    return label, n


def _video_interval(config: PandaConfig) -> int | None:
    """The interval whose reaches ``--video`` records: the scoreboard's (or the largest), ``None`` without videos."""
    if not config.video:
        return None
    return HEADLINE_INTERVAL if HEADLINE_INTERVAL in config.intervals else max(config.intervals)


def _write_videos(
    results: dict[tuple[str, int], dict[str, Any]], interval: int | None, config: PandaConfig, out: Path
) -> list[str]:
    """``videos/<method>-<k>.gif``: the first ``--video`` arms of each method at ``interval``, until they reach the goal.

    A ring round the end effector marks the steps at which it was measured.
    """
    names = []
    for (label, n), r in results.items():
        if n != interval:
            continue
        for k in range(len(r["video_q"])):
            last = min(int(r["video_steps"][k]), config.steps)  # the first arrival ends the episode
            tool, goal = float(r["video_tools"][k]), r["video_goals"][k].numpy()
            frames = [panda_frame(r["video_q"][k, t].numpy(), tool, goal, measured=t % n == 0) for t in range(last + 1)]
            names.append(video_name(label, k))
            write_gif(frames, out / names[-1], fps=1 / config.dt)
    return names


#: The default run's measured seconds (``smcd-rl panda``: 100 arms x 3 seeds, a 3 x 256 network,
#: 100 particles, one process on one thread of a 2-core Intel Xeon): each training and tuning.
_REFERENCE_SECONDS = {"train": 28.0, "train T": 168.0, "tune M": 45.0, "tune T": 21.0}
#: The same run's milliseconds per method: one control step of every arm (its Jacobians; gradient
#: descent's and the combination's are of every arm's own weights, ten times the others') and one
#: update of every arm, fitted over its five intervals (each stage within 10 %, T+S's within 50 %).
#: Rough forward counts, which they replace, ranked SMCD's updates above gradient descent's, six
#: times cheaper, and the progress line's time left swung between 18 minutes and over an hour.
_REFERENCE_MS = {  # label: (per control step, per update)
    "FK": (3.5, 0.4),
    "M+N": (3.0, 0.5),
    "M+G": (45.0, 310.0),
    "M+S": (4.2, 47.0),
    "M+S(evidence)": (4.2, 49.0),
    "M+S(paper)": (4.1, 98.0),
    "M+C": (64.0, 549.0),
    "M+L": (4.4, 22.0),
    "M+SL": (1.8, 143.0),
    "T+N": (3.5, 0.7),
    "T+G": (42.0, 200.0),
    "T+S": (6.2, 9.7),
    "T+L": (4.2, 21.0),
    "T+SL": (4.6, 93.0),
}


def stage_costs(config: PandaConfig) -> dict[str, float]:
    """Each stage's expected seconds at ``config``, in run order: the default run's, scaled by the settings.

    Training scales as its optimiser steps and forwards
    (:func:`~smcd_rl.experiments.shared.stages.estimate`), a tuning as its filter runs
    (:func:`~smcd_rl.experiments.shared.stages.tuning_cost`), and each (method, n) as its ``seeds x
    steps`` control steps and ``seeds x ceil(steps / n)`` updates, each in proportion to the arms
    and the network's forward cost (and SMCD's updates to the particles).

    Example:
        >>> costs = stage_costs(PandaConfig())
        >>> list(costs)[:4], round(costs["evaluate M+G n=1"]), round(costs["evaluate M+S n=1"])
        (['train', 'train T', 'tune M', 'tune T'], 213, 31)
    """
    default = PandaConfig()

    def flops(c: PandaConfig) -> float:
        return mlp_flops(7, (c.hidden,) * c.depth, 3)

    def training(c: PandaConfig) -> float:
        steps = c.epochs * -(-c.samples // c.batch_size)
        return estimate(steps=steps, forwards=3 * c.epochs * c.samples, flops=flops(c))

    def tuning(c: PandaConfig) -> float:
        return tuning_cost(c, episodes=c.tuning_episodes, steps=c.tuning_steps, flops=flops(c))

    trained = training(config) / training(default)
    costs = {"train": _REFERENCE_SECONDS["train"] * trained}
    if any(m.startswith("T+") for m in config.methods):  # M's training and each tool's posterior every epoch
        costs["train T"] = _REFERENCE_SECONDS["train T"] * trained
    for net in ("M", "T"):
        if tuned_variants(net, config.methods):
            costs[f"tune {net}"] = _REFERENCE_SECONDS[f"tune {net}"] * tuning(config) / tuning(default)
    arms = config.tasks / default.tasks * flops(config) / flops(default)
    for label in method_labels(config):
        step_ms, update_ms = _REFERENCE_MS[label]
        if label.partition("+")[2].startswith("S"):  # SMCD, with or without a readout: a forward per particle
            update_ms *= config.particles / default.particles
        for n in _intervals(label, config):
            steps = config.seeds * config.steps
            updates = config.seeds * -(-config.steps // n)
            costs[f"evaluate {label} n={n}"] = arms * (steps * step_ms + updates * update_ms) / 1000
    return costs


def _adapts(config: PandaConfig) -> bool:
    """Whether a method adapts a network, so that it needs the tuning (every ``M+`` or ``T+`` method but ``M+N``)."""
    return any(m.startswith(("M+", "T+")) and m != "M+N" for m in config.methods)


def _intervals(label: str, config: PandaConfig) -> list[int]:
    # FK with a measurement every step is the reference line of Fig. 3, so it always runs.
    return sorted(set(config.intervals) | ({1} if label == "FK" else set()))


def _held_out_rmse(model: smcd_rl.AdaptiveModel, data: TensorDict) -> float:
    """RMSE (m) of the unadapted network's prediction on fresh samples with random tools."""
    model.reset()
    with torch.no_grad():
        error = model.predict(data["q"]) - data["ee"]
    return float(error.square().sum(-1).mean().sqrt())
