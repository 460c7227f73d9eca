"""Fig. 14 of ``smcd-rl interpret``: predicting a drone operator's next actions after a burn-in.

Per test trajectory of length ``T``, a method adapts on the first ``b = max(1, round(rb T))``
steps, then predicts the operator's actions on the next ``h = max(1, round(rh T))`` steps (clipped
to ``b + h <= T``) from the observed states, with no further adaptation. The score is the RMSE
over the horizon's steps and the 3 action dims, per trajectory; a trajectory with ``b >= T`` is
left out of that burn-in's cells. Methods: M (multi-task) or R (Reptile, operators as tasks:
:func:`smcd_rl.fit_reptile`) with N (none), G (gradient descent, tuned), S (SMCD tuned by one-step
error), S(evidence) (SMCD calibrated by its evidence), S(paper) (SMCD at the paper's settings) or
C (the combination of N, G and S).

The fair protocol (:mod:`smcd_rl.experiments.shared.tuning`): before any test flight is seen, each
trained network's methods are tuned by :func:`smcd_rl.tune` (GD from the grid ``--gd-lr`` x
``--gd-steps`` x ``--gd-window``, SMCD and the combination, all by one-step error) and its SMCD
calibrated by log evidence (``S(evidence)``) on ``--tuning-episodes`` training-distribution flights
that the networks were not fitted on, each cut to its first ``--tuning-steps`` steps
(:func:`tuning_flights`): for the simulated operators, flights of freshly simulated operators (one
flight each, from the same population as the training operators); for a ``--dataset``, flights
held out of the training split (never an operator's last one), which M and R are then not fitted
on. The test flights (known and unknown operators) are never used. S(paper)'s likelihood noise is
``--noise-scale`` times the network's own training RMSE per action dim, its flip probability
``--flip-prob``.

Example:
    >>> from smcd_rl.experiments.interpret.config import InterpretConfig
    >>> flights, fit = tuning_flights(InterpretConfig(tuning_episodes=4), None, None)
    >>> flights.num_trajectories, fit is None, bool((flights.lengths >= 20).all())
    (4, True, True)
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.envs.drone_operators import TrajectoryDataset, simulate_operators
from smcd_rl.experiments.interpret.drone import SETS
from smcd_rl.experiments.interpret.masks import padded
from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.experiments.shared.tuned_methods import method_variant, strategy_for
from smcd_rl.experiments.shared.tuning import Tuning

if TYPE_CHECKING:
    from smcd_rl.experiments.interpret.config import InterpretConfig

__all__ = [
    "TUNING_SEED",
    "tuning_flights",
    "tuning_episodes",
    "reptile_tasks",
    "make_method",
    "method_builder",
    "evaluate_lookahead",
    "cell_scores",
    "table",
    "plot",
]

#: Offset of the tuning flights' seed from ``--seed`` (operators of their own, none of the dataset's).
TUNING_SEED = 7919


def tuning_flights(
    config: InterpretConfig, data: TrajectoryDataset | None, split: dict[str, np.ndarray] | None
) -> tuple[TrajectoryDataset, np.ndarray | None]:
    """The flights every method is tuned on, and the training trajectories the networks are fitted on.

    Simulated operators (no ``--dataset``): one flight, at least ``--tuning-steps`` long, of each of
    ``--tuning-episodes`` freshly simulated operators (seed ``--seed + TUNING_SEED``); the training
    split is fitted whole (``None``). A ``--dataset``: up to ``--tuning-episodes`` training-split
    flights that long, at random, never an operator's last one, held out of the fit; returns the ids
    (into ``data``) of the training trajectories left to fit on.
    """
    steps = config.tuning_steps
    rng = np.random.default_rng(config.seed + TUNING_SEED)
    if not config.dataset:
        fresh = simulate_operators(
            config.tuning_episodes, config.trajectories_per_operator, seed=config.seed + TUNING_SEED
        )
        chosen = []
        for op in range(config.tuning_episodes):
            long_enough = np.flatnonzero((fresh.operator == op) & (fresh.lengths >= steps))
            if long_enough.size:
                chosen.append(int(rng.choice(long_enough)))
        return fresh.select(chosen), None
    assert data is not None and split is not None
    train = split["train"]
    eligible = []
    for op in np.unique(data.operator[train]):
        own = train[data.operator[train] == op]
        eligible += [int(i) for i in own[:-1] if data.lengths[i] >= steps]  # keep each operator's last one
    count = min(config.tuning_episodes, len(eligible))
    held_out = np.sort(rng.choice(np.array(eligible, dtype=np.int64), size=count, replace=False))
    return data.select(held_out), np.setdiff1d(train, held_out)


def tuning_episodes(flights: TrajectoryDataset, config: InterpretConfig, device: torch.device) -> TensorDict:
    """``[E, --tuning-steps]`` states and actions: the first steps of each tuning flight."""
    if flights.num_trajectories < 2 or int(flights.lengths.min()) < config.tuning_steps:
        raise ValueError(
            f"the tuning of every method needs at least 2 training-distribution flights of at least "
            f"--tuning-steps {config.tuning_steps} steps; only {flights.num_trajectories} were found: lower "
            "--tuning-steps or give more training flights"
        )
    return padded(flights, device)[:, : config.tuning_steps]


def reptile_tasks(train: TrajectoryDataset, config: InterpretConfig, device: torch.device) -> TensorDict:
    """``[operators, steps]``: each training operator's steps, subsampled to the smallest operator's count."""
    per_step_operator = train.operator[train.trajectory]
    groups = [np.flatnonzero(per_step_operator == op) for op in np.unique(train.operator)]
    size = min(len(g) for g in groups)
    rng = np.random.default_rng(config.seed)
    index = torch.from_numpy(np.stack([np.sort(rng.choice(g, size=size, replace=False)) for g in groups]))
    return TensorDict(
        {"state": torch.from_numpy(train.state)[index], "action": torch.from_numpy(train.action)[index]},
        list(index.shape),
        device=device,
    )


def make_method(
    name: str,
    bases: dict[str, smcd_rl.AdaptiveModel],
    tunings: dict[str, Tuning],
    config: InterpretConfig,
    device: torch.device,
) -> smcd_rl.AdaptiveModel:
    """Method ``name``: its trained network (``M`` or ``R``) with its strategy (``N``, tuned ``G``, ``S``
    tuned by one-step error, ``S(evidence)``, ``S(paper)`` or ``C``, from that network's
    :class:`~smcd_rl.experiments.shared.tuning.Tuning`)."""
    strategy = strategy_for(name, tunings, seed=config.seed + 41, device=device)
    return bases[method_variant(name)[0]].with_adaptation(strategy)


def method_builder(
    name: str,
    bases: dict[str, smcd_rl.AdaptiveModel],
    tunings: dict[str, Tuning],
    config: InterpretConfig,
    device: torch.device,
) -> Callable[[], smcd_rl.AdaptiveModel]:
    """A builder of method ``name``, called once per test set: each set starts from a freshly seeded filter,
    so neither set's results depend on whether the other ran first."""
    return partial(make_method, name, bases, tunings, config, device)


def _burn_in_steps(test: TrajectoryDataset, config: InterpretConfig) -> torch.Tensor:
    """``[len(burn_in), N]`` burn-in steps per ratio and trajectory; a cell scores those with ``b < T``."""
    lengths = torch.from_numpy(test.lengths)
    return torch.stack([(rb * lengths).round().clamp(min=1).long() for rb in config.burn_in])


@torch.no_grad()
def evaluate_lookahead(
    method: smcd_rl.AdaptiveModel,
    test: TrajectoryDataset,
    config: InterpretConfig,
    device: torch.device,
    desc: str,
    progress: bool,
) -> torch.Tensor:
    """Per-trajectory RMSE ``[N, len(burn_in), len(horizons)]`` (NaN where a trajectory is too short)."""
    lengths = torch.from_numpy(test.lengths)
    burn = _burn_in_steps(test, config)  # [R, N]
    horizon = torch.stack([(rh * lengths).round().clamp(min=1).long() for rh in config.horizons])  # [H, N]
    horizon = torch.minimum(horizon.unsqueeze(0), (lengths - burn).unsqueeze(1))  # [R, H, N]: b + h <= T
    result = torch.full((test.num_trajectories, len(config.burn_in), len(config.horizons)), float("nan"))
    sequences = padded(test, device)
    width = int(horizon.max().clamp(min=1))
    # Windows past a trajectory's end read its last step again; the horizon mask drops them.
    ends = torch.arange(sequences.shape[1] + width).clamp(max=sequences.shape[1] - 1)
    order = torch.from_numpy(np.argsort(test.lengths, kind="stable"))
    for begin in tqdm(range(0, len(order), config.chunk), desc=desc, unit="chunk", disable=not progress):
        rows = order[begin : begin + config.chunk]
        part = sequences[rows]
        method.reset(batch_shape=(len(rows),))
        for t in range(int(burn[:, rows].max())):
            method.observe(part[:, t])
            for i in range(len(config.burn_in)):
                due = (burn[i, rows] == t + 1) & (burn[i, rows] < lengths[rows])
                if not bool(due.any()):
                    continue
                window = part[:, ends[t + 1 : t + 1 + width]]
                predicted = method(window.exclude("action"))["action"]
                error = (predicted - window["action"]).square().mean(-1).cpu()  # [B, width]
                for j in range(len(config.horizons)):
                    h = horizon[i, j, rows]
                    inside = torch.arange(width).unsqueeze(0) < h.unsqueeze(1)
                    rmse = ((error * inside).sum(1) / h.clamp(min=1)).sqrt()
                    result[rows[due], i, j] = rmse[due]
    return result


def cell_scores(
    errors: dict[str, dict[str, Any]], tests: dict[str, TrajectoryDataset], config: InterpretConfig
) -> dict[tuple[str, float, float], dict[str, torch.Tensor]]:
    """(set, burn-in ratio, horizon ratio) -> method -> RMSE of the trajectories long enough for that burn-in.

    Which trajectories a cell holds depends on their lengths only, so every method is scored on
    the same ones, in the same order: the comparisons are paired.
    """
    scores: dict[tuple[str, float, float], dict[str, torch.Tensor]] = {}
    for set_name, test in tests.items():
        valid = _burn_in_steps(test, config) < torch.from_numpy(test.lengths)  # [R, N]
        for i, rb in enumerate(config.burn_in):
            if not bool(valid[i].any()):
                continue
            for j, rh in enumerate(config.horizons):
                scores[set_name, rb, rh] = {name: done[set_name][valid[i], i, j] for name, done in errors.items()}
    return scores


def table(rows: list[dict[str, Any]], config: InterpretConfig, ms: Mapping[str, float] | None = None) -> str:
    """Action RMSE, mean [95% CI] over test trajectories: rows set, method, burn-in ratio; columns horizon ratio.

    The last column is the method's median milliseconds per observation on the tuning flights
    (``ms``, by :func:`~smcd_rl.experiments.shared.tuned_methods.ms_column`; "-" for a method without one).
    """
    ms = ms or {}
    lookup = {
        (r["set"], r["method"], r["burn_in"], r["horizon"]): f"{r['rmse_mean']:.3f} [{r['rmse_low']:.3f}, "
        f"{r['rmse_high']:.3f}]"
        for r in rows
    }
    body = [
        [
            set_name,
            method,
            rb,
            *[lookup.get((set_name, method, rb, rh), "-") for rh in config.horizons],
            f"{ms[method]:.3g}" if method in ms else "-",
        ]
        for set_name in SETS
        for method in config.methods
        for rb in config.burn_in
    ]
    header = ["operators", "method", "burn-in", *[f"h={rh}" for rh in config.horizons], "ms / observation"]
    return format_table(body, header)


def plot(rows: list[dict[str, Any]], config: InterpretConfig, path: Path) -> None:
    """``fig14_lookahead.png``: RMSE against horizon, one panel per test set and burn-in, 95% CIs as error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(SETS), len(config.burn_in), figsize=(3.4 * len(config.burn_in), 6), sharey=True, squeeze=False
    )
    for r_i, set_name in enumerate(SETS):
        for c_i, rb in enumerate(config.burn_in):
            ax = axes[r_i][c_i]
            for method in config.methods:
                sel = [r for r in rows if r["set"] == set_name and r["method"] == method and r["burn_in"] == rb]
                ax.errorbar(
                    [r["horizon"] for r in sel],
                    [r["rmse_mean"] for r in sel],
                    yerr=[
                        [r["rmse_mean"] - r["rmse_low"] for r in sel],
                        [r["rmse_high"] - r["rmse_mean"] for r in sel],
                    ],
                    marker="o",
                    capsize=2,
                    label=method,
                    ls="-" if method.startswith("M") else "--",
                )
            ax.set_title(f"{set_name} operators, burn-in {rb:g} T", fontsize=9)
            ax.grid(alpha=0.3)
            if r_i == len(SETS) - 1:
                ax.set_xlabel("horizon (fraction of T)")
        axes[r_i][0].set_ylabel("action RMSE (m/s)")
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def evaluate_sets(
    tests: Mapping[str, Any], config: InterpretConfig, device: Any, progress: bool, name: str, build: Any
) -> dict[str, Any]:
    """One method's look-ahead errors on every test set (a function, so a worker process can run it)."""
    return {s: evaluate_lookahead(build(), test, config, device, f"{name} {s}", progress) for s, test in tests.items()}
