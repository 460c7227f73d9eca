"""Where each adaptation method wins: ``smcd-rl regimes``.

Reads top to bottom: train the arm network and the pendulum network (each a multi-task dropout
network, as every experiment trains its M) and, on the pendulum's data, a network T whose masks
were trained to identify the pendulum and a Reptile network R; tune every method on held-out episodes of the
training tasks with :func:`smcd_rl.tune` (one criterion, the one-step error; again under a
per-observation budget), then run every method over the same regimes of the same test tasks of
each family (few and many observations, a task switch and back, one corrupted observation,
measurements every n-th step) and compare them paired over the tasks. Writes ``results.csv``,
``trials.csv``, ``comparisons.csv``, ``results.json``, ``regimes.png`` and ``report.md``.
"""

from __future__ import annotations

import functools
from typing import Any

import torch

import smcd_rl
from smcd_rl.digests import model_digest
from smcd_rl.experiments.regimes.config import BUDGETED, FULL, RegimesConfig, regime_names
from smcd_rl.experiments.regimes.families import (
    FAMILIES,
    build_model,
    method_network,
    network_of,
    other_network,
    runs_on,
    split_method,
    split_network,
    training_data,
    tuning_episodes,
)
from smcd_rl.experiments.regimes.protocol import budgeted_label, strategy_of, tune_network
from smcd_rl.experiments.regimes.report import plot, scoreboard_entries, tables
from smcd_rl.experiments.regimes.streams import make_plan, regime_errors
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.stats import cell_statistics
from smcd_rl.experiments.shared.two_link_family import fit_settings

__all__ = ["RegimesConfig", "FULL", "run", "stage_costs"]


def run(config: RegimesConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        ex.plan(stage_costs(config))
        # --- one network per kind of task, trained on many tasks ------------------------------------
        networks = sorted({network_of(f) for f in config.families})
        models = {net: build_model(net, config, ex.device) for net in networks}
        data = {net: training_data(net, config, ex.generator) for net in networks}
        jobs = {net: (smcd_rl.fit, models[net], data[net], fit_settings(config)) for net in networks}
        other = _other_variants(config)
        for net in other:  # T and R train on their base network's data
            models[net], fit, net_data, net_settings = other_network(
                net, config, data[split_network(net)[0]], ex.device
            )
            jobs[net] = (fit, models[net], net_data, net_settings)
        losses = ex.train_all(jobs)
        for net, model in models.items():
            model.save(ex.out / f"model-{net}.pt")

        # --- the fair protocol: every method tuned on held-out training-task episodes --------------
        # Alone in the main process, so that the measured time per observation is a quiet one.
        tunings = {
            net: tune_network(
                ex,
                model,
                tuning_episodes(split_network(net)[0], config),
                config,
                name=net,
                methods=other.get(net, config.methods),
                **({"variants": other[net], "budgeted": ()} if net in other else {}),
            )
            for net, model in models.items()
        }

        # --- every method over the same regimes of the same test tasks ----------------------------
        plans = {
            family: make_plan(family, config, residual=torch.tensor(tunings[network_of(family)]["residual"]))
            for family in config.families
        }
        labels = _labels(config)
        runs = {
            f"{family} {method}": method_network(family, method)
            for family in config.families
            for method in labels
            if runs_on(family, method)
        }
        runs = {name: (net, variant) for name, (net, variant) in runs.items() if variant in tunings[net]["specs"]}
        methods = {
            name: functools.partial(
                _built, models[net], tunings[net]["specs"][variant], plans[name.split(" ")[0]], _target(name)
            )
            for name, (net, variant) in runs.items()
        }
        done = ex.evaluate(
            methods,
            _evaluate,
            content=lambda name: {
                "model": model_digest(models[runs[name][0]]),
                "spec": tunings[runs[name][0]]["specs"][runs[name][1]],
            },
        )

        # --- results: per-task RMSE per (family, regime), CIs, paired verdicts ---------------------
        scores = {
            (family, regime): {
                method: done[f"{family} {method}"]["errors"][regime]
                for method in labels
                if f"{family} {method}" in done
            }
            for family in config.families
            for regime in regime_names(config.burn_in, family)
        }
        rows, comparisons = cell_statistics(
            scores,
            cell=("family", "regime"),
            baseline="N" if "N" in labels else None,
            # T+S first: its pairs read T+S minus the other
            adaptive=sorted((m for m in labels if m != "N"), key=lambda m: m != "T+S"),
            metric="rmse",
            seed=config.seed,
        )
        ms = {net: t["ms"] for net, t in tunings.items()}
        for row in rows:
            net, variant = method_network(row["family"], row["method"])
            row["ms_per_observation"] = ms[net].get(variant)
        refused = {name: r["refused"] for name, r in done.items() if r["refused"]}
        trial_rows = [
            {"family": family, "regime": regime, "method": method, "task": k, "rmse": float(v)}
            for (family, regime), by_method in scores.items()
            for method, values in by_method.items()
            for k, v in enumerate(values)
        ]
        ex.write(
            experiment="adaptation regimes: every method tuned by one criterion",
            tables={
                **tables(rows, comparisons, config, ms, refused),
                **{caption: text for t in tunings.values() for caption, text in t["tables"].items()},
            },
            rows=rows,
            trials=trial_rows,
            comparisons=comparisons,
            payload={
                "train_loss": losses,
                "tuning": {net: {k: v for k, v in t.items() if k != "tables"} for net, t in tunings.items()},
                "refused_observations": refused,
                "scoreboard": scoreboard_entries(rows, comparisons, config),
            },
            plots={"regimes.png": lambda path: plot(rows, config, path)},
        )
    return ex.result


def _labels(config: RegimesConfig) -> list[str]:
    """The methods in table order: each tuned one, then the budgeted ones."""
    return [*config.methods, *(budgeted_label(m, config) for m in BUDGETED if m in config.methods)]


def _other_variants(config: RegimesConfig) -> dict[str, list[str]]:
    """The other networks the families' methods use -> the variants they run (``"T+S"``: ``"S"``).

    Example:
        >>> _other_variants(RegimesConfig(methods=("G", "T+N", "T+S", "R+G")))
        {'arm-task': ['N', 'S'], 'pendulum-task': ['N', 'S'], 'pendulum-reptile': ['G']}
    """
    found: dict[str, list[str]] = {}
    for family in config.families:
        for method in config.methods:
            if split_method(method)[0] and runs_on(family, method):
                net, variant = method_network(family, method)
                if variant not in found.setdefault(net, []):
                    found[net].append(variant)
    return found


def _target(name: str) -> object:
    return FAMILIES[name.split(" ")[0]].target


def _built(model: smcd_rl.AdaptiveModel, spec: dict[str, Any], plan: Any, target: Any) -> tuple[Any, ...]:
    return model.with_adaptation(strategy_of(spec)), plan, target


def _evaluate(name: str, built: tuple[Any, ...]) -> dict[str, Any]:
    model, plan, target = built
    return regime_errors(model, plan, target)


#: Seconds of each training at the defaults on a 2-core AMD EPYC (one thread): the overall
#: progress line scales the plan by this run's measured speed to say how long is left.
_TRAIN_SECONDS = {
    "train arm": 60.0,
    "train pendulum": 30.0,
    "train pendulum-task": 60.0,  # the pendulum network's training and each pendulum's mask posterior
    "train pendulum-reptile": 30.0,
    "train arm-task": 70.0,  # the arm network's training and each arm's mask posterior
}
#: Seconds of each network's tuning and of each method's evaluation at the defaults (50 tasks,
#: 1000 particles), measured on a 2-core Intel Xeon with one thread. With ``--workers`` the
#: workers take the costliest first, so these rank the stages as they run: a costly one planned
#: cheap starts last and runs alone.
_TUNE_SECONDS = {"arm": 82.0, "pendulum": 98.0, "arm-task": 86.0, "pendulum-task": 73.0, "pendulum-reptile": 11.0}
#: Method kind -> (seconds on a family of the arm network, on the pendulum). A budgeted method
#: (``G@10ms``) is its kind with ``@``; the tuned settings set the cost, not the kind alone.
_EVALUATE_SECONDS = {
    "N": (0.05, 0.05),
    "G": (4.7, 13.8),
    "G@": (4.6, 12.9),
    "S": (11.4, 16.1),
    "S@": (11.4, 15.6),
    "S(evidence)": (10.9, 11.9),
    "S(paper)": (5.9, 11.1),
    "L": (0.5, 0.5),
    "SL": (22.0, 31.0),
    "C": (43.0, 82.0),  # its members run again
    "C@": (13.0, 25.0),
    "T+G": (31.0, 20.0),  # gradients through the arm posteriors of the task-mask network
    "T+S": (7.2, 8.9),  # grouped masks
    "T+SL": (18.0, 25.0),
    "R+G": (10.0, 10.0),
}


def stage_costs(config: RegimesConfig) -> dict[str, float]:
    """Each stage's expected relative cost at ``config``, in the order the stages run.

    Example:
        >>> costs = stage_costs(RegimesConfig())
        >>> costs["evaluate pendulum S"] > costs["evaluate pendulum N"], "evaluate two-link T+S" in costs
        (True, True)
        >>> [stage for stage in costs if stage.startswith("train")]
        ['train arm', 'train pendulum', 'train arm-task', 'train pendulum-task', 'train pendulum-reptile']
    """
    scale = config.trials / 50 * config.particles / 1000
    other = _other_variants(config)
    networks = [*sorted({network_of(f) for f in config.families}), *other]
    epochs = {"pendulum-reptile": config.reptile_epochs}  # the others train config.epochs
    costs = {f"train {net}": _TRAIN_SECONDS[f"train {net}"] * epochs.get(net, config.epochs) / 20 for net in networks}
    tuning = config.tuning_episodes / 20 * config.tuning_steps / 30
    # The other networks tune only the kinds of their methods: their share of the defaults' kinds.
    default = _other_variants(RegimesConfig())
    share = {
        net: len({v for v in variants if v != "N"}) / max(1, len({v for v in default.get(net, ()) if v != "N"}))
        for net, variants in other.items()
    }
    costs.update({f"tune {net}": _TUNE_SECONDS[net] * tuning * share.get(net, 1.0) for net in networks})
    for family in config.families:
        for method in _labels(config):
            if runs_on(family, method):
                costs[f"evaluate {family} {method}"] = _evaluate_seconds(family, method) * scale
    return costs


def _evaluate_seconds(family: str, method: str) -> float:
    """``method``'s evaluation seconds on ``family`` at the defaults: its own kind's, else its variant's.

    Example:
        >>> _evaluate_seconds("pendulum", "G@10ms"), _evaluate_seconds("two-link", "T+N")
        (12.9, 0.05)
    """
    prefix, variant = split_method(method)
    kind = variant.split("@")[0] + "@" if "@" in variant else variant
    for key in (f"{prefix}+{kind}" if prefix else kind, kind, kind[0]):
        if key in _EVALUATE_SECONDS:
            return _EVALUATE_SECONDS[key][family == "pendulum"]
    return _EVALUATE_SECONDS["S"][family == "pendulum"]
