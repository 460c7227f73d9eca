"""Two-link arm look-ahead prediction (paper section 4.1, Fig. 2): ``smcd-rl two-link``.

Reads top to bottom: seed, make data, train the models on the same data (a multi-task dropout
network M, the same architecture trained with Reptile R, a network T whose dropout masks were
trained to identify the arm, and the latent-variable VRNN LV), then
for every method adapt for T burn-in steps on a held-out arm and predict the end effector H steps
ahead with no further observations. Writes ``results.csv`` (the table), ``trials.csv`` (every
trial's RMSE), ``results.json`` (settings, table, training losses, timings, machine) and
``lookahead.png``.
"""

from __future__ import annotations

import copy
import functools
import time
from pathlib import Path
from typing import Any

import torch

import smcd_rl
from smcd_rl.baselines import LatentVariableModel, fit_latent
from smcd_rl.digests import model_digest
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table, ms_cell, save_figure
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stats import cell_statistics, oriented, verdict_table
from smcd_rl.experiments.shared.task_family import task_verdict_table
from smcd_rl.experiments.shared.tuned_methods import method_variant, ms_column, strategy_for, tuned_variants
from smcd_rl.experiments.shared.tuning import TUNED, TuneJob, Tuning, tune_all
from smcd_rl.experiments.shared.two_link_family import (
    babbling_data,
    fit_settings,
    network,
    oracle,
    reptile_model,
    reptile_settings,
    task_fit_settings,
    task_model,
    tuning_episodes,
)
from smcd_rl.experiments.shared.two_link_lookahead import TEST_ARMS_SEED, combined_errors, lookahead_errors, test_arms
from smcd_rl.experiments.two_link.config import DEFAULT_METHODS, FULL, METHODS, TwoLinkConfig
from smcd_rl.experiments.two_link.stages import stage_costs

__all__ = ["TwoLinkConfig", "FULL", "METHODS", "DEFAULT_METHODS", "run", "table"]

#: The adaptive methods, each compared (paired over the same arms) with M+N and with each other
#: (each as the method against those after it: T+S first, so its pairs read T+S minus the other).
ADAPTIVE = (
    "T+S",
    "T+SL",
    *(
        f"{network}+{variant}"
        for network in ("M", "R")
        for variant in ("S", "SL", "L", "S(evidence)", "S(paper)", "G", "C")
    ),
    "T+L",
    "T+G",
    "T+N",
    "R+N",
    "LV+N",
    "O+P",
)

#: The Bayesian last layer and SMCD with a Bayesian readout, each paired with GD and SMCD on its network.
READOUT_PAIRS = (
    ("M+L", "M+G"),
    ("M+L", "M+S"),
    ("M+SL", "M+G"),
    ("M+SL", "M+S"),
    ("M+SL", "M+L"),
    ("T+SL", "T+S"),
    ("T+SL", "T+L"),
    ("T+SL", "M+SL"),
)


def run(config: TwoLinkConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        # --- seed, data, models -----------------------------------------------------------------
        data = babbling_data(config, ex)
        model = smcd_rl.AdaptiveModel(network(config, ex.device), in_keys=["q"], out_key="ee")
        reptile, task, latent = _baselines(config, ex.device)
        trainings: dict[str, Any] = {"train": (smcd_rl.fit, model, data, fit_settings(config))}
        if reptile is not None:
            trainings["reptile"] = (smcd_rl.fit_reptile, reptile, data, reptile_settings(config))
        if task is not None:
            trainings["task"] = (smcd_rl.fit, task, data, task_fit_settings(config))
        if latent is not None:
            trainings["latent"] = (fit_latent, latent, data, _latent_settings(config))
        trained = ex.train_all(trainings)  # independent: side by side with --workers
        losses = {f"{'' if name == 'train' else name + '_'}train_loss": value for name, value in trained.items()}
        model.save(ex.out / "model.pt")
        if reptile is not None:
            reptile.save(ex.out / "reptile_model.pt")
        if task is not None:
            task.save(ex.out / "task_model.pt")

        # --- the fair protocol: SMCD and GD tuned on held-out babbling of fresh training arms -------
        # Long enough for the look-ahead they are tuned by after every burn-in (calibration needs 2 steps).
        episodes = tuning_episodes(config, ex.device, steps=max(config.burn_in) + config.tuning_horizon)
        networks = {"M": model, "R": reptile, "T": task}
        jobs = {
            name: TuneJob(trained, episodes, options=config.tuning_options, variants=variants)
            for name, trained in networks.items()
            if trained is not None and (variants := tuned_variants(name, config.methods))
        }
        tunings = tune_all(ex, jobs, config)  # independent: side by side with --workers

        # --- every method on the same held-out arms -------------------------------------------------
        q, ee, ee_true, lengths = test_arms(config, ex.device, count=config.trials, seed=config.seed + TEST_ARMS_SEED)
        combined = _combined(config.methods, tunings)  # each combination from its members' runs, not run again
        recorded = frozenset(member for members in combined.values() for member in members)
        methods = {
            name: functools.partial(_method, name, networks, latent, tunings, config)
            for name in config.methods
            if name not in combined
        }
        content = {name: model_digest(m) for name, m in {**networks, "LV": latent}.items() if m is not None}
        done = ex.evaluate(
            methods, functools.partial(_errors, q, ee, ee_true, config, progress, recorded), content=content
        )
        for name, members in combined.items():
            with ex.stage(f"evaluate {name}"):
                started = time.perf_counter()
                adapted = networks[method_variant(name)[0]]
                assert adapted is not None
                spec = tunings[method_variant(name)[0]].specs["C"]["settings"]
                errors = combined_errors(
                    [done[m] for m in members],
                    ee,
                    ee_true,
                    copy.deepcopy(adapted.output_norm).cpu(),
                    config,
                    eta=spec["eta"],
                    share=spec["share"],
                )
                done[name] = {"sq_errors": errors, "seconds": time.perf_counter() - started}
                ex.timings[f"evaluate {name}"] = done[name]["seconds"]
        done = {name: done[name] for name in config.methods}

        # --- results: per-arm RMSE per (T, H), CIs, paired verdicts ---------------------------------
        scores = {
            (t, h): {name: r["sq_errors"][:, i, :h].mean(-1).sqrt() for name, r in done.items()}
            for i, t in enumerate(config.burn_in)
            for h in config.horizons
        }
        rows, comparisons = cell_statistics(
            scores, cell=("burn_in", "horizon"), baseline="M+N", adaptive=ADAPTIVE, metric="rmse", seed=config.seed
        )
        trial_rows = [
            {"method": name, "burn_in": t, "horizon": h, "trial": k, "rmse": float(v)}
            for (t, h), by_method in scores.items()
            for name, values in by_method.items()
            for k, v in enumerate(values)
        ]
        headline = [
            c
            for c in comparisons
            if c["method"] == "M+S" and c["against"] in ("M+N", "M+G", "M+S(evidence)", "M+S(paper)")
        ]
        # One burn-in (the scoreboard's) keeps the table to a page: the means table has the others.
        burn_in = 10 if 10 in config.burn_in else max(config.burn_in)
        readouts = [c for c in oriented(comparisons, READOUT_PAIRS) if c["burn_in"] == burn_in]
        ms = ms_column(config.methods, tunings)
        rows = [{**r, "ms_per_observation": ms.get(r["method"])} for r in rows]
        ex.write(
            experiment="two-link look-ahead prediction (paper Fig. 2)",
            tables={
                "End-effector RMSE (m), mean [95% CI] over held-out arms; median ms per observation": (
                    table(rows, config, ms)
                ),
                "M+S paired with M+N, M+G, M+S(evidence) and M+S(paper) over the same arms "
                "(negative: M+S's error is lower)": verdict_table(headline, cell=("burn_in", "horizon")),
                **(
                    {
                        f"The Bayesian last layer (L) and SMCD with a Bayesian readout (SL) paired with GD and SMCD "
                        f"over the same arms after T = {burn_in} (negative: the first method's error is lower)": (
                            verdict_table(readouts, cell=("burn_in", "horizon"))
                        )
                    }
                    if readouts
                    else {}
                ),
                **task_verdict_table(comparisons, cell=("burn_in", "horizon"), over="arms"),
                **{caption: text for t in tunings.values() for caption, text in t.tables().items()},
            },
            rows=rows,
            trials=trial_rows,
            comparisons=comparisons,
            payload={
                **losses,
                "test_link_lengths": lengths.tolist(),
                "tuning": {name: t.payload() for name, t in tunings.items()},
                "scoreboard": scoreboard_entry(
                    "two-link look-ahead",
                    rows,
                    comparisons,
                    cell={"burn_in": 10, "horizon": 1},
                    metric="rmse",
                    unit="m",
                    ms=ms,
                ),
            },
            plots={
                "lookahead.png": lambda path: _plot(rows, config, path),
                **{f"tuning-{name}.png": t.plot for name, t in tunings.items()},
            },
        )
    return ex.result


def table(rows: list[dict[str, Any]], config: TwoLinkConfig, ms: dict[str, float] | None = None) -> str:
    """RMSE (mean [95% CI] over arms) with burn-in T down and horizon H across, one block per method.

    The last column is the method's median milliseconds per observation on the tuning episodes
    (``ms``; "-" for a method without one).
    """
    ms = ms or {}
    header = ["method", "T", *[f"H={h}" for h in config.horizons], "ms / observation"]
    lookup = {
        (r["method"], r["burn_in"], r["horizon"]): f"{r['rmse_mean']:.3f} [{r['rmse_low']:.3f}, {r['rmse_high']:.3f}]"
        for r in rows
    }
    methods = list(dict.fromkeys(r["method"] for r in rows))
    body = [
        [m, t, *[lookup[(m, t, h)] for h in config.horizons], ms_cell(ms.get(m))]
        for m in methods
        for t in config.burn_in
    ]
    return format_table(body, header)


def _baselines(
    config: TwoLinkConfig, device: torch.device
) -> tuple[smcd_rl.AdaptiveModel | None, smcd_rl.AdaptiveModel | None, LatentVariableModel | None]:
    """The untrained Reptile and task-mask networks and VRNN that the chosen methods need (``None`` where none does).

    Their initial weights come from seeds of their own, and the global RNG is left as it was,
    so adding or dropping these methods changes nothing for the others.
    """
    reptile = task = latent = None
    if any(name.startswith("R+") for name in config.methods):
        reptile = reptile_model(config, device, init_seed=config.seed + 17)
    if any(name.startswith("T+") for name in config.methods):
        task = task_model(config, device, init_seed=config.seed + 29)
    if "LV+N" in config.methods:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed + 19)
            latent = LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=config.lv_width, device=device)
    return reptile, task, latent


def _latent_settings(config: TwoLinkConfig) -> dict[str, Any]:
    return {"epochs": config.lv_epochs, "batch_size": config.lv_batch_size, "lr": config.lv_lr, "seed": config.seed}


def _method(
    name: str,
    networks: dict[str, smcd_rl.AdaptiveModel | None],
    latent: LatentVariableModel | None,
    tunings: dict[str, Tuning],
    config: TwoLinkConfig,
) -> Any:
    if name == "LV+N":
        return latent
    if name == "O+P":
        return oracle(config, "cpu")
    # M, R and T differ only in how the network was trained; they adapt with identical strategies.
    trained = networks[method_variant(name)[0]]
    assert trained is not None
    return trained.with_adaptation(strategy_for(name, tunings, seed=config.seed + 11, device=config.device))


def _errors(
    q: torch.Tensor,
    ee: torch.Tensor,
    ee_true: torch.Tensor,
    config: TwoLinkConfig,
    progress: bool,
    recorded: frozenset[str],
    name: str,
    method: Any,
) -> dict[str, torch.Tensor]:
    """One method's squared look-ahead errors on the test arms (a function, so a worker process can run it),
    and for a member of a combination (``recorded``) its predictions (:func:`lookahead_errors`)."""
    record: dict[str, torch.Tensor] | None = {} if name in recorded else None
    errors = lookahead_errors(method, q, ee, ee_true, config, desc=name, progress=progress, record=record)
    return {"sq_errors": errors, **(record or {})}


def _combined(methods: tuple[str, ...], tunings: dict[str, Tuning]) -> dict[str, list[str]]:
    """Each combination method (``M+C``...) whose members run as methods of their own, with their names.

    The combination's members are its network's tuned none, GD, SMCD (and last layer and SMCD
    with a Bayesian readout where they are tuned), the strategies of ``M+N``, ``M+G``, ``M+S``
    (``M+L``, ``M+SL``) with the same seed: their runs are the members' runs, so the
    combination's errors follow from their recorded predictions. A combination whose members do
    not all run (``--methods M+C`` alone) is run as it is.
    """
    found = {}
    for name in methods:
        network, variant = method_variant(name)
        if variant != "C" or network not in tunings:
            continue
        specs = tunings[network].specs
        members = specs["C"]["settings"]["members"]
        names = {kind: variant for variant, kind in TUNED.items()}
        labels = [f"{network}+{names[m['name']]}" for m in members]
        if all(
            label in methods and (m["name"] == "none" or specs[names[m["name"]]]["settings"] == m["settings"])
            for label, m in zip(labels, members, strict=True)
        ):
            found[name] = labels
    return found


def _plot(rows: list[dict[str, Any]], config: TwoLinkConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(config.burn_in), figsize=(3.2 * len(config.burn_in) + 1.0, 3.2), sharey=True)
    axes = [axes] if len(config.burn_in) == 1 else list(axes)
    for ax, t in zip(axes, config.burn_in, strict=True):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["method"] == method and r["burn_in"] == t]
            ax.errorbar(
                [r["horizon"] for r in sel],
                [r["rmse_mean"] for r in sel],
                yerr=[[r["rmse_mean"] - r["rmse_low"] for r in sel], [r["rmse_high"] - r["rmse_mean"] for r in sel]],
                marker="o",
                capsize=2,
                label=method,
            )
        ax.set_title(f"burn-in T = {t}")
        ax.set_xlabel("look-ahead H (steps)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("end-effector RMSE (m)")
    axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside: eight methods would hide lines
    fig.suptitle(f"Two-link look-ahead prediction ({config.trials} held-out arms)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
