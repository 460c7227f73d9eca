"""Model-based control of the Fetch task families with online adaptation: ``smcd-rl fetch``.

Reads top to bottom, per family: seed, collect transitions from many draws of the family, fit one
dropout dynamics model of the ``observation`` entry, tune the adaptations by the fair protocol
(:mod:`smcd_rl.experiments.shared.tuning`), then run MPC episodes on held-out test draws for every
planner x adaptation cell, and the same draws under uniform random actions as a reference.
All strategies share the trained network (``model.with_adaptation``).

Families (``--families``; only ``reach`` by default):

* ``reach``: ``smcd_rl/FetchReachRotated-v0``, the commanded gripper displacement rotated about z
  by an angle drawn from ``U(-r, r)`` (``r = --rotation``, 1.5 rad; the family's own default range
  is 0.5 rad, which plain MPC already solves without adaptation) and scaled by a gain from
  ``U(0.5, 1.5)``, per episode. Training data: uniform random actions.
* ``push``: ``smcd_rl/FetchPushHeavy-v0``, the block's mass and friction drawn per episode.
  Training data: a noisy scripted push towards the block (random actions seldom touch it).
  Pushing a block to a goal with MPC on a learnt model is much harder than reaching: at the
  default planner settings no 5-step plan reaches the block, the dense reward (the block's
  distance to the goal) ranks no candidate, and every method ends as random actions do. The
  push family is therefore left out of the default.

The adaptations (``--adaptations``), labelled as in every experiment:

* ``M+N``: no adaptation;
* ``M+G``: online gradient descent tuned on the tuning episodes by the learnt model's 5-step
  rollout error on the logged actions (``--tuning-horizon``, the planning horizon: the proxy of
  success) (:func:`smcd_rl.tune`: the ``--gd-lr x --gd-steps x --gd-window`` grid, squared error or a robust loss);
* ``M+S``: SMCD tuned the same way (:func:`smcd_rl.tune`);
* ``M+S(evidence)``: SMCD calibrated by its evidence (:func:`smcd_rl.calibrate`) on the tuning episodes;
* ``M+S(paper)``: SMCD at fixed settings. The paper has no Fetch task, so the fixed setting is
  this: likelihood noise per observation dimension ``--noise-scale`` (1) times the network's
  held-out one-step RMSE, and ``--flip-prob`` (0.01, the paper's Ant setting);
* ``M+C``: the combination of N and the tuned strategies (:class:`smcd_rl.Combination`), tuned on
  the same episodes. It predicts with every member, inside the planner's rollouts too, so its
  cells cost about as much as its members' together;
* ``M+L``, ``M+SL``: the Bayesian last layer, and SMCD with a Bayesian readout, tuned the same way;
* ``T+S``, ``T+SL`` (``--task-adaptations``): SMCD, and SMCD with a Bayesian readout, on T, a
  second network whose masks were trained to identify the draw
  (:mod:`~smcd_rl.experiments.fetch.task_network`).

**Fair protocol.** The tuning episodes are ``--tuning-episodes`` episodes of ``--tuning-steps``
data-policy actions, each on a fresh draw of the family (the training distribution), from env
seeds of their own (``--seed + 2000003 + k``), neither training data nor any test draw.

**Metric.** ``--episodes`` test draws per family, episode ``k`` from env seed ``--seed + 1000003
+ k`` (its draw and its goal), the same in every cell, one MPC episode of ``--episode-steps``
steps each. Scored by the env's ``is_success`` after the last step (success rate) and by the
final distance (m) of the achieved goal to the goal; the planners rank candidates by the
family's dense reward (``reward_type="dense"``, minus the distance), since the sparse one gives
every candidate the same reward until one already reaches the goal. Per cell the mean with a 95%
bootstrap CI, and paired comparisons over the same draws (and planner seeds) of every adaptive
method against ``M+N`` and each other (:func:`~smcd_rl.experiments.shared.stats.cell_statistics`). The
scoreboard entry is the reach success rate under CEM. Each method's median milliseconds per
observation (one stream, on the family's tuning episodes, measured by the fair protocol) is the
last column of the results table and the ``ms_per_observation`` of its rows and of the entry.

Writes ``results.csv`` (per family, planner, method and metric the mean with its CI),
``trials.csv`` (every episode, with its draw), ``comparisons.csv``, ``results.json`` (with
``training``, ``tuning`` and ``scoreboard``), ``fetch.png`` (success rate and final distance per
cell), ``tuning-<family>.png`` and ``report.md``. The data, training, tuning and finished cells are
reused by a rerun.

Example:
    >>> from smcd_rl.experiments.fetch.config import FetchConfig
    >>> config = FetchConfig()
    >>> config.families, config.planners, config.adaptations, config.task_adaptations
    (('reach',), ('cem', 'mppi'), ('N', 'G', 'S', 'S(evidence)', 'S(paper)', 'C', 'L', 'SL'), ('N', 'G', 'S', 'L', 'SL'))
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import torch

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.experiments.fetch.config import FAMILIES, FULL, METHOD_LABELS, PLANNERS, FetchConfig
from smcd_rl.experiments.fetch.episodes import collect, random_cell, run_cell, tuning_episodes, validation_error
from smcd_rl.experiments.fetch.report import METRICS, plot, rename, table, unrename
from smcd_rl.experiments.fetch.task_network import task_method, task_network
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stats import cell_statistics, verdict_table
from smcd_rl.experiments.shared.task_family import task_mask_settings, task_verdict_table
from smcd_rl.experiments.shared.tuned_methods import ms_column
from smcd_rl.experiments.shared.tuning import tune
from smcd_rl.experiments.shared.video import video_name
from smcd_rl.experiments.shared.workers import computed

__all__ = ["FetchConfig", "FULL", "FAMILIES", "PLANNERS", "METHOD_LABELS", "run", "table"]

#: Offsets of the env seeds from ``--seed``: test draws, tuning draws.
EPISODE_SEED, TUNING_SEED = 1_000_003, 2_000_003
#: Settings that determine the collected transitions (besides the family).
DATA_SETTINGS = ("seed", "rotation", "transitions", "data_episode_steps")
#: The paired comparisons: each adaptive method against M+N and against each other.
ADAPTIVE = ("M+S", "M+S(evidence)", "M+S(paper)", "M+G", "M+C", "M+L", "M+SL", "T+S", "T+SL", "T+L", "T+G", "T+N")
#: The reference row: uniform random actions on the same test draws.
RANDOM = "random actions"
#: Relative stage costs (seconds of the default run on 2 CPU cores, one torch thread). The tuning
#: took 7 s before :func:`smcd_rl.tune`, which runs about twice the filter runs
#: (:func:`~smcd_rl.experiments.shared.stages.tuning_cost` at the defaults: 38 against 19).
COSTS = {"collect": 20.0, "train": 9.0, "tune": 14.0, "evaluate": 15.0, "random": 1.0}


def run(config: FetchConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(_costs(config))
        episode_seeds = [config.seed + EPISODE_SEED + k for k in range(config.episodes)]  # the same in every cell
        episodes: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
        seconds: dict[tuple[str, str, str], float] = {}
        training: dict[str, Any] = {}
        tunings: dict[str, Any] = {}
        ms: dict[str, dict[str, float]] = {}  # family -> method -> median ms per observation
        plots: dict[str, Any] = {}
        tables: dict[str, str] = {}
        videos: list[str] = []  # --video: the GIFs the cells wrote
        for family in config.families:
            # --- data from many draws of the family ------------------------------------------------
            # "layout": the data holds each transition's draw (T's task id); older stored data does not.
            data_key = {"family": family, "layout": "draw ids", **{k: getattr(config, k) for k in DATA_SETTINGS}}
            with ex.stage(f"collect {family}"):
                collected = ex.store.get("data", data_key)
                if collected is None:
                    collected = collect(family, config, progress=progress)
                    ex.store.put("data", data_key, collected)
            data = collected["data"]
            n_val = max(1, int(round(config.validation * data.shape[0])))
            train, val = data[:-n_val].to(ex.device), data[-n_val:].to(ex.device)

            # --- one dropout dynamics model for every strategy ------------------------------------
            obs_dim, action_dim = data["observation"].shape[-1], data["action"].shape[-1]
            torch.manual_seed(config.seed)  # the same initial weights whether the data was collected or loaded
            net = smcd_rl.MaskedMLP(
                obs_dim + action_dim,
                obs_dim,
                hidden=(config.hidden,) * config.depth,
                dropout=config.dropout,
                device=ex.device,
            )
            model = smcd_rl.AdaptiveDynamicsModel(net)
            fit = {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}
            losses = ex.train(family, smcd_rl.fit_dynamics, model, train, **fit)
            model.save(ex.out / f"model-{family}.pt")
            val_rmse = validation_error(model, val)
            paper_noise = (config.noise_scale * val_rmse).clamp_min(1e-4)
            training[family] = {
                "transitions": data.shape[0],
                "held_out": n_val,
                "collect_seconds": collected["seconds"],
                "loss": losses,
                "validation_rmse": val_rmse.tolist(),
                "paper_noise_std": paper_noise.tolist(),
            }

            # --- the fair protocol: tuned on fresh training draws, never the test draws ----------
            tuning_data = tuning_episodes(family, config, seed=config.seed + TUNING_SEED).to(ex.device)
            tuning = tune(
                ex,
                model,
                tuning_data,
                config,
                name=family,
                paper_noise_std=paper_noise.tolist(),
                variants=config.adaptations,
            )
            tunings[family] = tuning
            networks = {"M": tuning}  # the family's model is "M"
            content = {"M": {"model": model_digest(model), "specs": tuning.specs}}
            strategies = {
                variant: functools.partial(tuning.strategy, variant, seed=config.seed + 11, device=ex.device)
                for variant in config.adaptations
            }
            models = dict.fromkeys(config.adaptations, model)

            # --- T: a second network whose masks were trained to identify the draw -----------------
            if config.task_adaptations:
                task = task_network(config, obs_dim, action_dim, ex.device)
                training[family]["task_loss"] = ex.train(
                    f"{family} T", smcd_rl.fit_dynamics, task, train, **fit, **task_mask_settings(config)
                )
                task.save(ex.out / f"task_model-{family}.pt")
                task_tuning = tune(
                    ex,
                    task,
                    tuning_data,
                    config,
                    name=f"{family} T",
                    paper_noise_std=paper_noise.tolist(),
                    variants=config.task_adaptations,
                )
                networks["T"] = task_tuning
                content["T"] = {"model": model_digest(task), "specs": task_tuning.specs}
                for variant in config.task_adaptations:
                    strategies[task_method(variant)] = functools.partial(
                        task_tuning.strategy, variant, seed=config.seed + 11, device=ex.device
                    )
                    models[task_method(variant)] = task
                tables.update(task_tuning.tables())
                plots[f"tuning-{family}-T.png"] = task_tuning.plot
            labels = [*METHOD_LABELS.values(), *(task_method(v) for v in config.task_adaptations)]
            ms[family] = ms_column(labels, networks)

            # --- MPC episodes of every (planner, adaptation) cell on the same test draws ----------
            cells = {
                f"{family}/{planner}/{variant}": functools.partial(
                    run_cell,
                    models[variant],
                    family,
                    planner,
                    config,
                    strategies[variant](),
                    # One planner seed per planner, the same for every adaptation.
                    planner_seed=config.seed + 1000 * (1 + list(PLANNERS).index(planner)),
                    episode_seeds=episode_seeds,
                    device=ex.device,
                    progress=progress,
                    video=min(config.video, config.episodes),
                    video_path=functools.partial(_video_path, ex.out, f"{family}-{planner}-{variant}"),
                )
                for planner in config.planners
                for variant in strategies
            }
            # The videos are written by the cells, so their count keys the cells (only when recorded).
            video = {"video": config.video} if config.video else {}
            keys = {name: {**content[_network(name)], **video} for name in cells}
            done = ex.evaluate(cells, computed, content=keys.__getitem__)
            videos += [v for result in done.values() for v in result.get("videos", []) if Path(v).is_file()]
            reference = ex.evaluate(
                {f"{family}/random": functools.partial(random_cell, family, config, episode_seeds=episode_seeds)},
                computed,
                content={"family": family},
                kind="random",
            )
            for name, result in done.items():
                _, planner, variant = name.split("/")
                label = METHOD_LABELS.get(variant, variant)
                episodes[(family, PLANNERS[planner], label)] = result["episodes"]
                seconds[(family, PLANNERS[planner], label)] = result["seconds"]
            episodes[(family, "-", RANDOM)] = reference[f"{family}/random"]["episodes"]
            seconds[(family, "-", RANDOM)] = reference[f"{family}/random"]["seconds"]
            tables.update(tuning.tables())
            plots[f"tuning-{family}.png"] = tuning.plot

        # --- statistics: paired over the same draws in every cell ----------------------------------
        rows: list[dict[str, Any]] = []
        comparisons: list[dict[str, Any]] = []
        for metric, (_, higher) in METRICS.items():
            scores: dict[tuple[str, ...], dict[str, torch.Tensor]] = {}
            for (family, planner, method), records in episodes.items():
                values = torch.tensor([e[metric] for e in records], dtype=torch.float64)
                scores.setdefault((family, planner), {})[method] = values
            m_rows, m_comparisons = cell_statistics(
                scores,
                cell=("family", "planner"),
                baseline="M+N",
                adaptive=ADAPTIVE,
                metric=metric,
                lower_is_better=not higher,
                seed=config.seed,
            )
            rows += [
                {
                    "metric": metric,
                    **rename(r, metric),
                    "seconds": seconds[(r["family"], r["planner"], r["method"])],
                    "ms_per_observation": ms[r["family"]].get(r["method"]),
                }
                for r in m_rows
            ]
            comparisons += [{"metric": metric, **c} for c in m_comparisons]
        trials = [
            {"family": family, "planner": planner, "method": method, **e}
            for (family, planner, method), records in episodes.items()
            for e in records
        ]

        results_tables = {
            f"Success rate (the env's is_success after the last step) and final distance to the goal, mean [95% CI] "
            f"over {config.episodes} held-out test draws per family, one MPC episode of {config.episode_steps} steps "
            "each (the same draws and planner seeds in every row); median ms per observation on the tuning "
            "episodes": table(rows),
            "M+S paired with every other method over the same draws (success: positive "
            "is better; distance: negative is better)": verdict_table(
                [c for c in comparisons if c["method"] == "M+S"], cell=("metric", "family", "planner")
            ),
            "The other adaptive methods paired with M+N over the same draws": verdict_table(
                [c for c in comparisons if c["method"] != "M+S" and c["against"] == "M+N"],
                cell=("metric", "family", "planner"),
            ),
            **task_verdict_table(
                [c for c in comparisons if c["metric"] == "success"],
                cell=("family", "planner"),
                over="draws",
                against=("M+S", "M+G", "M+L", "M+SL"),
                lower_is_better=False,
            ),
        }
        ex.write(
            experiment="Fetch task families, MPC on a learnt model with online adaptation",
            tables={**results_tables, **tables},
            rows=rows,
            trials=trials,
            comparisons=comparisons,
            payload={
                "training": training,
                "tuning": {family: t.payload() for family, t in tunings.items()},
                "scoreboard": [
                    scoreboard_entry(
                        f"Fetch {family} success ({PLANNERS[config.planners[0]]})",
                        [unrename(r) for r in rows if r["metric"] == "success"],
                        [c for c in comparisons if c["metric"] == "success"],
                        cell={"family": family, "planner": PLANNERS[config.planners[0]]},
                        metric="success",
                        unit="success rate",
                        lower_is_better=False,
                        ms=ms[family],
                    )
                    for family in config.families
                ],
            },
            plots={"fetch.png": lambda path: plot(rows, config, path), **plots},
            files=[str(Path(v).relative_to(ex.out)) for v in videos],
        )
    return ex.result


def _combined(adaptations: tuple[str, ...]) -> int:
    """How many networks' predictions the combination makes per model step: N, G, S and the last layers tuned.

    Example:
        >>> _combined(("N", "G", "S", "C")), _combined(("C", "SL"))
        (3, 5)
    """
    return len({"N", "G", "S"} | ({"L", "SL"} & set(adaptations)) | ({"L"} if "SL" in adaptations else set()))


def _network(cell: str) -> str:
    """The network of a cell ``family/planner/variant``: ``T`` for a ``T+...`` variant, else ``M``."""
    return "T" if cell.rsplit("/", 1)[-1].startswith("T+") else "M"


def _video_path(out: Path, cell: str, k: int) -> Path:
    """``out/videos/<family>-<planner>-<adaptation>-<k>.gif``."""
    return out / video_name(cell, k)


def _costs(config: FetchConfig) -> dict[str, float]:
    """Relative stage costs for the progress line, scaled by the settings from the default run's seconds."""
    defaults = FetchConfig()
    data = COSTS["collect"] * config.transitions / defaults.transitions
    train = COSTS["train"] * config.epochs * config.transitions / (defaults.epochs * defaults.transitions)
    steps = config.episodes * config.episode_steps / (defaults.episodes * defaults.episode_steps)
    plan = float(config.candidates * config.iterations * config.horizon)
    plan /= defaults.candidates * defaults.iterations * defaults.horizon
    costs: dict[str, float] = {}
    for family in config.families:
        costs[f"collect {family}"] = data
        costs[f"train {family}"] = train
        costs[f"tune {family}"] = COSTS["tune"] * config.tuning_episodes / defaults.tuning_episodes
        if config.task_adaptations:  # T's training infers every draw's posterior each epoch
            costs[f"train {family} T"] = 2 * train
            costs[f"tune {family} T"] = costs[f"tune {family}"]
        for planner in config.planners:
            for variant in (*config.adaptations, *(task_method(v) for v in config.task_adaptations)):
                each = float(_combined(config.adaptations)) if variant == "C" else 1.0
                costs[f"evaluate {family}/{planner}/{variant}"] = COSTS["evaluate"] * steps * plan * each
        costs[f"random {family}/random"] = COSTS["random"] * steps
    return costs
