"""Mask interpretability and drone look-ahead (paper 4.3, 5, A.5, B.1-B.4): ``smcd-rl interpret``.

Three parts (``--parts``), each resumable, each in a module of its own:

* ``fig9`` (appendix A.5, Fig. 9; :mod:`~smcd_rl.experiments.interpret.links`): for each latent
  size, a two-link model's SMCD masks on held-out arms, and how often the arm nearest in
  link-length space is among the ``k`` nearest in mask space.
* ``confidence`` (Figs. 4 and 13; :mod:`~smcd_rl.experiments.interpret.drone`): eq. (9)
  confidence of drone operators' skill, strategy, phase and success from the ``k`` nearest
  stored masks, known and unknown operators apart.
* ``lookahead`` (Fig. 14; :mod:`~smcd_rl.experiments.interpret.lookahead`): action RMSE of
  M+N, M+G, M+S, M+S(evidence), M+S(paper), M+C and, with Reptile, R+N, R+G, R+S, R+S(evidence),
  R+C (R+S(paper) on request) after a burn-in. The fair protocol
  (:mod:`smcd_rl.experiments.shared.tuning`): per network, :func:`smcd_rl.tune` tunes G, S (SMCD
  tuned by one-step error) and C (the combination of N, G and S) by one-step error, and
  S(evidence) is SMCD calibrated by its evidence, all on ``--tuning-episodes`` training-distribution
  flights the networks were not fitted on (freshly simulated operators, or flights held out of a
  ``--dataset``'s training split), never on the test flights; S(paper) keeps ``--noise-scale`` and
  ``--flip-prob``. Fig. 14's table gives each method's median milliseconds per observation.

Reads top to bottom: for each part, its data, its models (trained or resumed by the harness),
its methods (cached by the models' and the dataset's content), then per-trial scores with 95%
CIs and paired verdicts. Every SMCD run whose masks are compared starts from one shared prior
particle set (unless ``--independent-priors``), so two trajectories' masks differ because their
data selected different particles; the paper does not say how its filters were initialised.

Writes ``fig9.csv``, ``confidence.csv``, ``lookahead.csv`` (each part's table rows),
``results.csv`` (all rows, long format, a ``figure`` column), ``trials.csv`` (every per-trial
score), ``comparisons.csv`` (the paired comparisons), ``results.json``, ``report.md``,
``fig9.png``, ``fig4_skill_strategy.png``, ``fig13_phase_success.png``, ``fig14_lookahead.png``,
``tuning-M.png`` / ``tuning-R.png`` (the tuning's diagnosis), the dataset used (``dataset.npz``) and
the trained models. With the look-ahead part, ``results.json`` holds ``"tuning"`` (chosen settings,
times per observation and the tuning tables, per network) and ``"scoreboard"`` (Fig. 14's headline
cell for ``smcd-rl scoreboard``, with ``ms_per_observation``); ``lookahead.csv``'s rows carry
``ms_per_observation`` where the method was timed.

Example:
    >>> from smcd_rl.experiments.interpret.config import InterpretConfig, METHODS
    >>> InterpretConfig().k, METHODS[:6]
    (5, ('M+N', 'M+G', 'M+S', 'M+S(evidence)', 'M+S(paper)', 'M+C'))
"""

from __future__ import annotations

from functools import partial
from typing import Any

import torch

import smcd_rl
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.envs.drone_operators import save_dataset
from smcd_rl.experiments.interpret import drone, links, lookahead
from smcd_rl.experiments.interpret.config import (
    DEFAULT_METHODS,
    FULL,
    METHODS,
    PARTS,
    SIMULATED_LABELS,
    InterpretConfig,
)
from smcd_rl.experiments.interpret.masks import shared_prior
from smcd_rl.experiments.interpret.multipart import PartsReport
from smcd_rl.experiments.shared.adaptations import StrategySettings
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stages import estimate, mlp_flops, tuning_cost, update_cost
from smcd_rl.experiments.shared.stats import verdict_table
from smcd_rl.experiments.shared.task_family import task_mask_settings
from smcd_rl.experiments.shared.tuned_methods import method_variant, ms_column, tuned_variants
from smcd_rl.experiments.shared.tuning import Tuning, tune

__all__ = ["InterpretConfig", "FULL", "PARTS", "METHODS", "DEFAULT_METHODS", "SIMULATED_LABELS", "run"]

#: The adaptive methods, each compared (paired over the same trajectories) with M+N and with each other
#: (the earlier one of a pair is its ``method``: M+S is compared against every other M method).
ADAPTIVE: tuple[str, ...] = (
    "T+S",  # first: its pairs read T+S minus the other
    "T+SL",
    *(
        f"{network}+{variant}"
        for network in ("M", "R")
        for variant in ("S", "C", "S(evidence)", "S(paper)", "G", "L", "SL")
    ),
    "T+L",
    "T+G",
    "T+N",
    "R+N",
)


#: Mean steps of a simulated landing (62 in the tiny test run's dataset), and the drone model's sizes.
LANDING_STEPS = 60
DRONE_STATE, DRONE_ACTION = 7, 3


def stage_costs(config: InterpretConfig) -> dict[str, float]:
    """Each stage's rough seconds at ``config`` (see :func:`~smcd_rl.experiments.shared.stages.estimate`), in run order.

    Training counts its optimiser steps and a forward and backward (3 forwards) per sample and
    epoch (Fig. 9's babbling, 10 steps an episode; the drone's training landings, ``LANDING_STEPS``
    each, also for Reptile); Fig. 9's masks ``fig9_burn_in`` steps of ``fig9_particles`` forwards
    per held-out arm; the confidence masks (SMCD) and each look-ahead method one update
    (:func:`~smcd_rl.experiments.shared.stages.update_cost`) and a forward per landing step, in chunks of
    ``chunk`` landings; the tuning its filter runs
    (:func:`~smcd_rl.experiments.shared.stages.tuning_cost`). A ``--dataset`` of another size scales every
    drone stage alike, so the estimate of the time left is still right once a drone stage is timed.

    Example:
        >>> costs = stage_costs(InterpretConfig())
        >>> list(costs)[:2], costs["lookahead M+S"] > costs["lookahead M+N"]
        (['train fig9_ld32', 'train fig9_ld128'], True)
    """
    costs: dict[str, float] = {}
    if "fig9" in config.parts:
        samples = config.fig9_tasks * config.fig9_episodes * 10
        for latent in config.fig9_latents:
            flops = mlp_flops(2, (latent, latent), 2)
            steps = config.fig9_epochs * -(-samples // config.batch_size)
            costs[f"train fig9_ld{latent}"] = estimate(
                steps=steps, forwards=3 * config.fig9_epochs * samples, flops=flops
            )
        for latent in config.fig9_latents:
            forwards = config.fig9_arms * config.fig9_burn_in * config.fig9_particles
            flops = mlp_flops(2, (latent, latent), 2)
            costs[f"fig9 ld={latent}"] = estimate(steps=config.fig9_burn_in, forwards=forwards, flops=flops)
    if "confidence" not in config.parts and "lookahead" not in config.parts:
        return costs
    flops = mlp_flops(DRONE_STATE, (config.hidden,) * config.depth, DRONE_ACTION)
    landings = config.operators * config.trajectories_per_operator
    shares = {"known": config.known_fraction, "unknown": config.unknown_fraction}
    shares["stored"] = max(0.0, 1.0 - shares["known"] - shares["unknown"])

    def filtering(share: float, variant: str) -> float:  # over the landings of one share of the data
        overhead, update = update_cost(variant, config)
        chunks = -(-max(1, round(share * landings)) // config.chunk)
        forwards = share * landings * LANDING_STEPS * (1 + update)
        return estimate(steps=chunks * LANDING_STEPS * (1 + overhead), forwards=forwards, flops=flops)

    train = shares["stored"] * landings * LANDING_STEPS
    steps = config.epochs * -(-round(train) // config.batch_size)
    costs["train bc"] = estimate(steps=steps, forwards=3 * config.epochs * train, flops=flops)
    if "confidence" in config.parts:
        for s in ("stored", *drone.SETS):
            costs[f"confidence {s}"] = filtering(shares[s], "S")
    if "lookahead" in config.parts:
        if any(name.startswith("R+") for name in config.methods):
            steps = config.reptile_epochs * -(-round(train) // config.reptile_batch_size)
            costs["train reptile"] = estimate(steps=steps, forwards=3 * config.reptile_epochs * train, flops=flops)
        if any(name.startswith("T+") for name in config.methods):  # bc's, and each epoch's posteriors
            costs["train task"] = 2 * costs["train bc"]
        for family in sorted(
            {method_variant(m)[0] for m in config.methods if method_variant(m)[1] != "N"}, key="MRT".index
        ):
            costs[f"tune {family}"] = tuning_cost(
                config, episodes=config.tuning_episodes, steps=config.tuning_steps, flops=flops
            )
        for name in config.methods:
            costs[f"lookahead {name}"] = sum(filtering(shares[s], method_variant(name)[1]) for s in drone.SETS)
    return costs


def run(config: InterpretConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the selected parts and write their files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        report = PartsReport()

        # --- Fig. 9: two-link masks against link lengths ---------------------------------------------
        if "fig9" in config.parts:
            arms, babbling = links.held_out_arms(config, ex.device), links.babbling(config).to(ex.device)
            two_link, losses = {}, {}
            fit = {"epochs": config.fig9_epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}
            for latent in config.fig9_latents:
                model = links.make_model(latent, config, ex.device)
                losses[latent] = ex.train(f"fig9_ld{latent}", smcd_rl.fit, model, babbling, **fit)
                two_link[f"ld={latent}"] = model
            hits = ex.evaluate(
                {name: partial(links.smcd_model, m, config, ex.device) for name, m in two_link.items()},
                partial(links.evaluate_hits, arms, config, progress),
                content={name: model_digest(m) for name, m in two_link.items()},
                kind="fig9",
            )
            accuracy = {
                (k,): {
                    "chance": torch.full((config.fig9_arms,), k / (config.fig9_arms - 1), dtype=torch.float64),
                    **{name: done["hits"][:, i] for name, done in hits.items()},
                }
                for i, k in enumerate(config.fig9_ks)
            }
            fig9 = report.add(
                "fig9",
                accuracy,
                cell=("k",),
                baseline="chance",
                adaptive=list(two_link),
                metric="accuracy",
                lower_is_better=False,
                seed=config.seed,
            )
            report.tables[FIG9] = links.table(fig9, config)
            report.plots["fig9.png"] = lambda path: links.plot(fig9, config, path)
            report.payload["fig9_train_loss"] = losses

        # --- the drone data and the behaviour-cloning model M ----------------------------------------
        if "confidence" in config.parts or "lookahead" in config.parts:
            data, split = drone.load(config)
            drone.check(config, data, split)
            save_dataset(data, ex.out / "dataset.npz")
            dataset = content_digest(drone.dataset_content(data))  # a --dataset's content, not its path
            train, tests = data.select(split["train"]), {s: data.select(split[s]) for s in drone.SETS}
            report.payload["dataset"] = drone.summary(data, split)
            # The look-ahead's tuning flights, which the networks are not fitted on (none of a simulated
            # run's training flights: those are freshly simulated operators).
            flights, fit_ids = lookahead.tuning_flights(config, data, split)
            fitted = train if fit_ids is None else data.select(fit_ids)
            adapting = sorted(
                {method_variant(m)[0] for m in config.methods if method_variant(m)[1] != "N"}, key="MRT".index
            )
            tuning_episodes = None
            if "lookahead" in config.parts and adapting:  # too few tuning flights: refused before training
                tuning_episodes = lookahead.tuning_episodes(flights, config, ex.device)
            model = drone.make_model(config, fitted, ex.device)
            fit = {"epochs": config.epochs, "batch_size": config.batch_size, "lr": config.lr, "seed": config.seed}
            report.payload["train_loss"] = ex.train("bc", smcd_rl.fit, model, drone.steps(fitted, ex.device), **fit)
            model.save(ex.out / "bc_model.pt")

        # --- Figs. 4 and 13: eq. (9) confidence from the k nearest stored masks ----------------------
        if "confidence" in config.parts:
            sets = {"stored": train, **tests}
            seeds = {"stored": config.seed + 31, "known": config.seed + 37, "unknown": config.seed + 37}
            noise = drone.noise_std(model, fitted, config, ex.device)
            prior = None if config.independent_priors else shared_prior(model.net, config.particles, config.seed + 29)
            smcd = StrategySettings(
                particles=config.particles,
                noise_std=tuple(noise),
                flip_prob=config.flip_prob,
                gd_lr=config.gd_lr[0],
                gd_steps=config.gd_steps[0],
                gd_window=config.gd_window[0],
            )
            masks = ex.evaluate(
                {s: partial(smcd.strategy, "S", seed=seeds[s], device=ex.device) for s in sets},
                partial(drone.evaluate_masks, model, sets, prior, config, ex.device, progress),
                content={"M": model_digest(model), "dataset": dataset},
                kind="confidence",
            )
            confidence_scores = {
                (s, label, cls, n): by_method
                for label in config.labels
                for s in drone.SETS
                for (n, cls), by_method in drone.confidence_scores(
                    label, train, tests[s], masks["stored"], masks[s], config
                ).items()
            }
            confidence = report.add(
                "confidence",
                confidence_scores,
                cell=("set", "label", "class", "steps"),
                baseline="chance",
                adaptive=["masks"],
                metric="confidence",
                trials_where=lambda where: where["class"] == "all",  # a class's trials are among those of "all"
                lower_is_better=False,
                seed=config.seed,
            )
            report.tables[CONFIDENCE.format(k=config.k)] = drone.table(confidence, config)
            for name, group in (("fig4_skill_strategy.png", SKILL), ("fig13_phase_success.png", PHASE)):
                if set(group) & set(config.labels):
                    report.plots[name] = partial(drone.plot, confidence, group, config)

        # --- Fig. 14: look-ahead of the operators' actions --------------------------------------------
        if "lookahead" in config.parts:
            bases = {"M": model}
            if any(name.startswith("R+") for name in config.methods):
                reptile = drone.make_model(config, fitted, ex.device)  # from the same initial weights as M
                report.payload["reptile_train_loss"] = ex.train(
                    "reptile",
                    smcd_rl.fit_reptile,
                    reptile,
                    lookahead.reptile_tasks(fitted, config, ex.device),
                    epochs=config.reptile_epochs,
                    batch_size=config.reptile_batch_size,
                    lr=config.reptile_lr,
                    inner_lr=config.reptile_inner_lr,
                    inner_epochs=1,
                    tasks_per_batch=config.reptile_tasks_per_batch,
                    seed=config.seed,
                )
                reptile.save(ex.out / "reptile_model.pt")
                bases["R"] = reptile
            if any(name.startswith("T+") for name in config.methods):
                task = drone.make_model(config, fitted, ex.device, mask_groups=config.mask_groups or None)
                report.payload["task_train_loss"] = ex.train(
                    "task",
                    smcd_rl.fit,
                    task,
                    drone.steps(fitted, ex.device),
                    **fit,
                    **task_mask_settings(config),
                )
                task.save(ex.out / "task_model.pt")
                bases["T"] = task
            # The fair protocol: each network's methods tuned on the tuning flights.
            tunings: dict[str, Tuning] = {}
            if tuning_episodes is not None:
                for key in adapting:
                    paper_noise = drone.noise_std(bases[key], fitted, config, ex.device)
                    tunings[key] = tune(
                        ex,
                        bases[key],
                        tuning_episodes,
                        config,
                        name=key,
                        paper_noise_std=paper_noise,
                        variants=tuned_variants(key, config.methods),
                    )
                    report.tables.update(tunings[key].tables())
                    report.plots[f"tuning-{key}.png"] = tunings[key].plot
                report.payload["tuning"] = {key: t.payload() for key, t in tunings.items()}
            errors = ex.evaluate(
                {
                    name: partial(lookahead.method_builder, name, bases, tunings, config, ex.device)
                    for name in config.methods
                },
                partial(lookahead.evaluate_sets, tests, config, ex.device, progress),
                content={
                    **{key: model_digest(m) for key, m in bases.items()},
                    "dataset": dataset,
                    "tuning": {key: t.specs for key, t in tunings.items()},
                },
                kind="lookahead",
            )
            cell = ("set", "burn_in", "horizon")
            rmse = report.add(
                "lookahead",
                lookahead.cell_scores(errors, tests, config),
                cell=cell,
                baseline="M+N",
                adaptive=ADAPTIVE,
                metric="rmse",
                seed=config.seed,
            )
            ms = ms_column(config.methods, tunings)
            for row in rmse:  # the rows of lookahead.csv and results.csv, timed where the method was
                if row["method"] in ms:
                    row["ms_per_observation"] = ms[row["method"]]
            report.tables[LOOKAHEAD] = lookahead.table(rmse, config, ms)
            comparisons = report.comparisons["lookahead"]
            headline = [c for c in comparisons if c["method"] == "M+S" and c["against"] in HEADLINE_AGAINST]
            if headline:
                report.tables[HEADLINE] = verdict_table(headline, cell=cell)
            report.plots["fig14_lookahead.png"] = lambda path: lookahead.plot(rmse, config, path)
            report.payload["scoreboard"] = scoreboard_entry(
                "drone look-ahead",
                rmse,
                comparisons,
                cell={"set": "unknown", "burn_in": max(config.burn_in), "horizon": min(config.horizons)},
                metric="rmse",
                unit="m/s",
                ms=ms,
            )

        # --- results: each part's CSV, every part in results.csv / trials.csv / comparisons.csv ------
        report.write(ex, experiment="mask interpretability (paper Figs. 4, 9, 13) and drone look-ahead (Fig. 14)")
    return ex.result


# Table captions and the label groups of the two confidence figures.
FIG9 = "Fig. 9: top-k link-length accuracy of two-link masks, mean [95% CI] over held-out arms"
CONFIDENCE = "Figs. 4 / 13: eq. (9) confidence of the true label, k = {k}, mean [95% CI] over test trajectories"
LOOKAHEAD = (
    "Fig. 14: look-ahead action RMSE (m/s), mean [95% CI] over test trajectories; columns: horizon ratio, "
    "then the median ms per observation"
)
#: The methods M+S is paired with in the headline table.
HEADLINE_AGAINST = ("M+N", "M+G", "M+S(evidence)", "M+S(paper)", "M+C")
HEADLINE = (
    "M+S paired with M+N, M+G, M+S(evidence), M+S(paper) and M+C over the same trajectories "
    "(negative: M+S's error is lower)"
)
SKILL, PHASE = ("skill", "strategy"), ("phase", "success")
