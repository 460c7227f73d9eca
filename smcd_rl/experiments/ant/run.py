"""Model-based control of the crippled-leg Ant (paper appendix C, Fig. 15): ``smcd-rl ant``.

Reads top to bottom: seed, collect transitions from the *healthy* Ant (random actions, or a
small stable-baselines3 SAC policy), fit one dropout dynamics model, tune the adaptations by the
fair protocol (:mod:`smcd_rl.experiments.shared.tuning`), then score every adaptation by the primary
metric, prediction error, and by the secondary one, the return of planner x adaptation episodes,
on the healthy Ant and on the Ant with a crippled leg. All strategies share the trained network
(``model.with_adaptation``). A second network, T, trained on the healthy Ant and on each leg
crippled with masks tied to the leg (:mod:`.task_network`), adds its methods' prediction error
(``--task-adaptations``), paired with M's and with its own T+G and T+N.

The adaptations (``--adaptations``), labelled as in every experiment:

* ``M+N``: no adaptation;
* ``M+G``: online gradient descent tuned by one-step error on the tuning episodes
  (:func:`smcd_rl.tune`: the ``--gd-lr x --gd-steps x --gd-window`` grid, squared error or a robust loss);
* ``M+S``: SMCD tuned by one-step error on the tuning episodes (:func:`smcd_rl.tune`);
* ``M+S(evidence)``: SMCD calibrated by its evidence (:func:`smcd_rl.calibrate`) on the tuning episodes;
* ``M+S(paper)``: SMCD at the paper's settings: likelihood noise per observation dimension
  ``--noise-scale`` (3) times the model's held-out RMSE, and ``--flip-prob``;
* ``M+C``: the combination of N, G and S (:class:`smcd_rl.Combination`), tuned on the same
  episodes. It predicts with every member, inside the planner's rollouts too, so a step of its
  MPC costs about as much as N's, G's and S's together.

**Fair protocol.** The tuning episodes are ``--tuning-episodes`` episodes of ``--tuning-steps``
uniform random actions on the *healthy* Ant (the training distribution: the model never saw a
crippled leg), from env seeds of their own (``--seed + 2000003 + k``), neither the training data
nor any test episode.

**Primary metric: prediction error.** ``--prediction-episodes`` episodes per condition of
``--prediction-steps`` uniform random actions (the default data-collection policy; a fixed
behaviour policy, so every strategy is scored on the same logged states), from env seeds
``--seed + 3000003 + k``. Each strategy filters along each episode
(:mod:`smcd_rl.experiments.ant.prediction`): the *one-step* error predicts step ``t`` from the
steps before it, before observing it; the *H-step* error (``H = --prediction-horizon``) rolls the
adapted model ``H`` steps ahead from the logged state at ``t`` on the logged actions and compares
with the logged states. Both are RMSE in observation units (pooled over the 41 dims), averaged
per episode; strategies are paired over the same episodes (95% bootstrap CIs and paired verdicts
by :func:`~smcd_rl.experiments.shared.stats.cell_statistics`, cells condition x metric). The
scoreboard entries (healthy, crippled) are the one-step error.

**Secondary metric: return.** ``--episodes`` MPC episodes of ``--episode-steps`` steps per
planner x adaptation x condition cell (the episodes are in
:mod:`smcd_rl.experiments.ant.episodes`); episode ``k`` is the same (env seed, start state,
leg) in every cell. By default one planner (CEM) and five adaptations (all but ``S(paper)``), 30
episodes of 100 steps, so that the default finishes in about 25 minutes on 2 CPU cores (the
stage plan's estimate).

**Time.** Each strategy's median milliseconds per observation (one stream, on the tuning
episodes, measured by the fair protocol) is the last column of the prediction table and the
``ms_per_observation`` of its rows in ``results.csv`` and of the scoreboard entries.

Writes ``results.csv`` (``part`` prediction: per condition, metric and strategy the mean error
with its 95% CI; ``part`` return: per planner, adaptation and condition the mean return),
``trials.csv`` (every episode's errors and every return episode), ``comparisons.csv`` (the paired
comparisons of both parts), ``results.json`` (with ``tuning`` and the two ``scoreboard``
entries), ``prediction.png`` (the errors with their CIs), ``ant.png`` (Fig. 15: returns per
planner grouped by adaptation), ``tuning-M.png`` (the strategies on the tuning episodes) and
``report.md``. The collected data, the tuning, the strategies' errors and the finished return
cells (in ``partial/``) and the training (``train-<digest>.ckpt``) are reused by a rerun.

Choices the paper leaves open, made here:

* Crippled condition: each episode cripples a leg drawn uniformly from ``--crippled-legs``
  (default all four: the model never saw any crippled leg, so all are out of distribution).
* The task (``--task l2a``, default) is Learning to Adapt's, which the paper used: reward =
  forward velocity + 0.05 per step, no control or contact cost, and episodes never end early.
  ``--task ant-v5`` uses Ant-v5's reward (forward velocity + 1 while healthy - 0.5 |a|^2 -
  contact cost) and ends an episode when the Ant is unhealthy. The reported reward is the env's;
  the planners optimise :func:`~smcd_rl.envs.crippled_ant.ant_reward` with the same weights (the
  contact term, which needs contact forces, left out) and, for ant-v5,
  :func:`~smcd_rl.envs.crippled_ant.ant_termination`. The prediction and tuning episodes never
  end early (only the dynamics matter there).
* Dropout: ``--full`` uses the paper's p = 0.5 on its 3 x 1024 network. The default network is
  five times narrower and underfits at p = 0.5 (held-out normalised MSE 0.46 on 10^5 random
  transitions, against 0.16 at the default p = 0.1), and planning on it barely moves the Ant.
* Planners get the same budget of model evaluations per step: CEM and MPPI ``iterations x
  candidates``, random shooting that many candidates in one round.

Example:
    >>> from smcd_rl.experiments.ant.config import AntConfig, CELLS
    >>> config = AntConfig()
    >>> len(CELLS), config.planners, config.adaptations, config.conditions
    (48, ('cem',), ('N', 'G', 'S', 'S(evidence)', 'C'), ('healthy', 'crippled'))
"""

from __future__ import annotations

import functools
from typing import Any

import torch

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.experiments.ant.config import CELLS, CONDITIONS, FULL, METHOD_LABELS, PLANNERS, PREDICTED, TASKS, AntConfig
from smcd_rl.experiments.ant.episodes import ACTION_DIM, OBS_DIM, collect, run_cell, validation_error
from smcd_rl.experiments.ant.plan import stage_costs
from smcd_rl.experiments.ant.prediction import evaluate_predictions, random_episodes
from smcd_rl.experiments.ant.report import (
    plot_prediction,
    plot_returns,
    prediction_table,
    return_rows,
    table,
    write_videos,
)
from smcd_rl.experiments.ant.task_network import task_data, task_network, task_tuning_episodes
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stats import cell_statistics, verdict_table
from smcd_rl.experiments.shared.task_family import task_mask_settings, task_verdict_table
from smcd_rl.experiments.shared.tuned_methods import ms_column
from smcd_rl.experiments.shared.tuning import Tuning, tune
from smcd_rl.experiments.shared.workers import computed

__all__ = [
    "AntConfig",
    "FULL",
    "PLANNERS",
    "METHOD_LABELS",
    "CONDITIONS",
    "CELLS",
    "TASKS",
    "run",
    "table",
    "prediction_table",
]

#: Settings that determine the collected transitions.
DATA_SETTINGS = ("seed", "task", "data_policy", "sac_steps", "transitions", "data_episode_steps")
#: Offsets of the env seeds from ``--seed``: MPC episodes, tuning episodes, prediction episodes.
EPISODE_SEED, TUNING_SEED = 1_000_003, 2_000_003
#: The scoreboard's note on the Ant rows: T+S's network trained on what M's never saw.
TASK_NOTE = "T+S's network T trained on the crippled legs as well (the leg as its task); M's on the healthy Ant only"
#: The paired comparisons: each adaptive method against M+N and against each other.
ADAPTIVE = ("M+S", "M+S(evidence)", "M+S(paper)", "M+G", "M+C", "M+L", "M+SL")


def run(config: AntConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        # --- seed, data from the healthy Ant ----------------------------------------------------
        data_key = {k: getattr(config, k) for k in DATA_SETTINGS}
        with ex.stage("collect"):
            collected = ex.store.get("data", data_key)
            if collected is None:
                collected = collect(config, progress=progress)
                ex.store.put("data", data_key, collected)
        n_val = max(1, int(round(config.validation * config.transitions)))
        train, val = collected["data"][:-n_val].to(ex.device), collected["data"][-n_val:].to(ex.device)

        # --- one dropout dynamics model for every strategy ----------------------------------------
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
        paper_noise = (config.noise_scale * val_rmse).clamp_min(1e-4)

        # --- the fair protocol: every strategy tuned on held-out healthy episodes -----------------
        task_env = TASKS[config.task][0]
        tuning_episodes, _ = random_episodes(
            task_env,
            None,
            count=config.tuning_episodes,
            steps=config.tuning_steps,
            seed=config.seed + TUNING_SEED,
        )
        tuning = tune(
            ex,
            model,
            tuning_episodes.to(ex.device),
            config,
            name="M",
            paper_noise_std=paper_noise.tolist(),
            variants=tuple(dict.fromkeys((*PREDICTED, *config.adaptations))),
        )
        strategy = functools.partial(_strategy, tuning, config, ex.device)
        content = {"model": model_digest(model), "specs": tuning.specs}

        # --- T: a second network whose masks were trained to identify the leg (prediction only) ----
        networks = {"M": (model, strategy, content, PREDICTED)}
        tunings = {"M": tuning}
        if config.task_adaptations:
            task = task_network(config, ex.device)
            task_key = {**data_key, "network": "T", "legs": config.crippled_legs}
            with ex.stage("collect T"):
                data_t = ex.store.get("data", task_key)
                if data_t is None:
                    data_t = {"data": task_data(config)}
                    ex.store.put("data", task_key, data_t)
            task_fit = {**fit, **task_mask_settings(config)}
            task_losses = ex.train("T", smcd_rl.fit_dynamics, task, data_t["data"].to(ex.device), **task_fit)
            task.save(ex.out / "task_model.pt")
            tunings["T"] = tune(
                ex,
                task,
                task_tuning_episodes(tuning_episodes, config).to(ex.device),
                config,
                name="T",
                paper_noise_std=paper_noise.tolist(),
                variants=config.task_adaptations,
            )
            task_strategy = functools.partial(_strategy, tunings["T"], config, ex.device)
            task_content = {"model": model_digest(task), "specs": tunings["T"].specs}
            networks["T"] = (task, task_strategy, task_content, config.task_adaptations)
        task_methods = [f"T+{v}" for v in config.task_adaptations]
        ms = ms_column([*METHOD_LABELS.values(), *task_methods], tunings)

        # --- primary: every strategy's prediction error on the same logged episodes ----------------
        prediction, legs = evaluate_predictions(ex, config, networks)
        scores = {
            (condition, name): {method: r[metric] for method, r in by_method.items()}
            for condition, by_method in prediction.items()
            for name, metric in _metrics(config)
        }
        p_rows, p_comparisons = cell_statistics(
            scores,
            cell=("condition", "prediction"),
            baseline="M+N",
            adaptive=[*ADAPTIVE, *task_methods],
            metric="rmse",
            seed=config.seed,
        )
        p_trials = [
            {
                "part": "prediction",
                "condition": condition,
                "method": method,
                "episode": k,
                "leg": legs[condition][k],
            }
            | {name: float(r[metric][k]) for name, metric in _metrics(config)}
            for condition, by_method in prediction.items()
            for method, r in by_method.items()
            for k in range(config.prediction_episodes)
        ]

        # --- secondary: returns of every (planner, adaptation, condition) cell on the same episodes -
        cells = [
            c for c in CELLS if c[0] in config.planners and c[1] in config.adaptations and c[2] in config.conditions
        ]
        episode_seeds = [config.seed + EPISODE_SEED + k for k in range(config.episodes)]  # the same in every cell
        cell_runs = {
            "/".join(cell): functools.partial(
                run_cell,
                model,
                cell,
                config,
                strategy(cell[1]),
                # One planner seed per planner, the same in every adaptation and condition.
                planner_seed=config.seed + 1000 * (1 + list(PLANNERS).index(cell[0])),
                episode_seeds=episode_seeds,
                device=ex.device,
                progress=progress,
                record=min(config.video, config.episodes),  # --video: the first episodes keep their states
            )
            for cell in cells
        }
        # Recorded videos are part of a cell's results, so their count keys them (only when recorded).
        cell_content = {**content, **({"video": config.video} if config.video else {})}
        done = ex.evaluate(cell_runs, computed, content=cell_content)
        videos = write_videos({cell: done["/".join(cell)] for cell in cells}, config, ex.out)
        episodes = {cell: done["/".join(cell)]["episodes"] for cell in cells}
        returns: dict[tuple[str, str], dict[str, torch.Tensor]] = {}
        for (planner, adaptation, condition), records in episodes.items():
            values = torch.tensor([e["return"] for e in records], dtype=torch.float64)
            returns.setdefault((PLANNERS[planner], condition), {})[METHOD_LABELS[adaptation]] = values
        stats, r_comparisons = cell_statistics(
            returns,
            cell=("planner", "condition"),
            baseline="M+N",
            adaptive=ADAPTIVE,
            metric="return",
            lower_is_better=False,
            seed=config.seed,
        )
        r_rows = return_rows(stats, episodes, {cell: done["/".join(cell)]["seconds"] for cell in cells})
        r_trials = [
            {"part": "return", "planner": PLANNERS[p], "method": METHOD_LABELS[a], "condition": c, **e}
            for (p, a, c), records in episodes.items()
            for e in records
        ]

        # --- report: primary table and verdicts first, then returns, then the tuning --------------
        one_step = "one-step"
        headline = [c for c in p_comparisons if c["method"] == "M+S" and c["against"].startswith("M+")]
        tables = {
            f"Prediction error (RMSE, observation units), mean [95% CI] over {config.prediction_episodes} random-action "
            f"episodes of {config.prediction_steps} steps per condition (one-step: step t from the steps before it; "
            f"{config.prediction_horizon}-step: open loop on the logged actions); median ms per observation on the "
            "tuning episodes": prediction_table(p_rows, ms),
            "M+S paired with M+N, M+S(evidence), M+S(paper), M+G and M+C over the same episodes "
            "(negative: M+S's error is lower)": verdict_table(headline, cell=("condition", "prediction")),
            # T saw the crippled legs in training, M did not: T+S's own network is its fair reference.
            **task_verdict_table(p_comparisons, cell=("condition", "prediction"), over="episodes"),
        }
        if r_rows:
            tables[
                f"Episode return (task {config.task}), mean [95% CI] over {config.episodes} MPC episodes of up to "
                f"{config.episode_steps} steps"
            ] = table(r_rows)
            r_headline = [c for c in r_comparisons if c["method"] == "M+S"]
            tables[
                "M+S paired with the other adaptations over the same MPC episodes (positive: M+S's return is higher)"
            ] = verdict_table(r_headline, cell=("planner", "condition"))
        for network in tunings.values():
            tables.update(network.tables())
        results = [("prediction", r) for r in p_rows] + [("return", r) for r in r_rows]
        plots = {"prediction.png": lambda path: plot_prediction(p_rows, config, path)}
        if r_rows:
            plots["ant.png"] = lambda path: plot_returns(r_rows, config, path)
        plots.update({f"tuning-{name}.png": network.plot for name, network in tunings.items()})
        ex.write(
            experiment="crippled-leg Ant, model-based control with adaptation (paper appendix C, Fig. 15)",
            tables=tables,
            rows=[{"part": part, **r, "ms_per_observation": ms.get(r["method"])} for part, r in results],
            trials=p_trials + r_trials,
            comparisons=[{"part": "prediction", **c} for c in p_comparisons]
            + [{"part": "return", **c} for c in r_comparisons],
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
                    **({"task_loss": task_losses} if config.task_adaptations else {}),
                    "validation_nmse": val_nmse,
                    "validation_rmse": val_rmse.tolist(),
                    "paper_noise_std": paper_noise.tolist(),
                },
                "tuning": {name: network.payload() for name, network in tunings.items()},
                "prediction": {
                    "episodes": config.prediction_episodes,
                    "steps": config.prediction_steps,
                    "horizon": config.prediction_horizon,
                    "legs": legs,
                    "refused": {
                        c: {method: r["refused"] for method, r in by_method.items()}
                        for c, by_method in prediction.items()
                    },
                },
                "scoreboard": [
                    scoreboard_entry(
                        f"Ant one-step prediction ({condition})",
                        p_rows,
                        p_comparisons,
                        cell={"condition": condition, "prediction": one_step},
                        metric="rmse",
                        unit="observation units",
                        ms=ms,
                        note=TASK_NOTE if config.task_adaptations else None,
                    )
                    for condition in config.conditions
                ],
            },
            plots=plots,
            files=videos,
        )
    return ex.result


def _strategy(tuning: Tuning, config: AntConfig, device: torch.device, variant: str) -> smcd_rl.Adaptation:
    """A fresh strategy of ``variant`` with its settings from the fair protocol; every SMCD's generator seeded alike."""
    return tuning.strategy(variant, seed=config.seed + 11, device=device)


def _metrics(config: AntConfig) -> list[tuple[str, str]]:
    """(name in the tables, key of :func:`~smcd_rl.experiments.ant.prediction.prediction_errors`)."""
    return [("one-step", "one_step"), (f"{config.prediction_horizon}-step", "open_loop")]
