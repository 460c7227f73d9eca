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

Reads top to bottom: resolve the grid, list the grid points (one trial configuration each), run
what the result cache does not hold yet as Ray tasks (a local Ray by default, ``--address`` for an
existing cluster), gather them with ``ray.wait`` as they finish, then write ``results.csv`` (every
grid point), ``summary.csv`` (per parameter value: mean, std and min over the other parameters),
``results.json`` and ``sweep.png`` (one panel per parameter), and print the summary table.

On a cluster every node needs ``smcd-rl`` installed (and, with Ray's token authentication, the
cluster's token, e.g. in ``RAY_AUTH_TOKEN``); a ``--dataset`` path must exist on every node.

A trial is a pure function of its configuration (:func:`trial`, which seeds itself), so a grid
point computed on Ray equals the same call in-process. Work is shared without changing any result:
grid points that differ only in ``epochs`` are one training run (:func:`smcd_rl.fit` is
deterministic per (seed, epoch) with no schedule, so a shorter run's losses are a prefix of a longer
run's), and the smcd study trains each model once and evaluates its filter settings as separate
Ray tasks on it. Every grid point uses the same seed: same data, same initial weights, same
held-out arms, so differences come from the hyper-parameters alone.

Example:
    >>> points = trial_configs(SweepConfig(study="smcd", grid=("particles=10,20",)))
    >>> len(points), sorted({point["particles"] for point in points})
    (162, [10, 20])
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import itertools
import json
import logging
import math
import os
import statistics
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    seed_everything,
    torch_threads,
    write_csv,
    write_json,
)

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

STUDIES = ("training", "smcd", "drone")

#: The parameters each study sweeps (config fields; the names ``--grid`` takes).
PARAMETERS: dict[str, tuple[str, ...]] = {
    "training": ("hidden", "dropout", "lr", "batch_size", "epochs"),
    "smcd": ("hidden", "dropout", "flip_prob", "noise_std", "particles"),
    "drone": ("hidden", "dropout", "lr", "batch_size", "epochs"),
}

#: Default grids: factorial and small enough for minutes on 2 CPU cores (36, 162 and 36 grid points).
GRIDS: dict[str, dict[str, tuple[Any, ...]]] = {
    "training": {
        "hidden": (64, 256, 512),
        "dropout": (0.25, 0.5, 0.75),
        "lr": (1e-3, 1e-4),
        "batch_size": (64, 256),
        "epochs": (5, 10, 20),
    },
    "smcd": {
        "hidden": (64, 256, 512),
        "dropout": (0.25, 0.5, 0.75),
        "flip_prob": (0.001, 0.01, 0.05),
        "noise_std": (0.02, 0.05, 0.1),
        "particles": (100, 500),
    },
    "drone": {
        "hidden": (64, 256, 512),
        "dropout": (0.25, 0.5, 0.75),
        "lr": (1e-3, 1e-4),
        "batch_size": (64, 256),
        "epochs": (10, 25, 50),
    },
}

#: ``--full`` grids. The paper names the parameters but not their values (they are only in the
#: figures' axes); these span its stated optima (latent 512/1024, p = 0.5, lr 1e-4, batch 64,
#: about 100 epochs) on both sides. Meant for a cluster (``--address``): thousands of trials.
FULL_GRIDS: dict[str, dict[str, tuple[Any, ...]]] = {
    "training": {
        "hidden": (64, 128, 256, 512, 1024),
        "dropout": (0.1, 0.25, 0.5, 0.75),
        "lr": (1e-2, 1e-3, 1e-4),
        "batch_size": (32, 64, 128, 256),
        "epochs": (25, 50, 100, 150, 200),
    },
    "smcd": {
        "hidden": (64, 128, 256, 512, 1024),
        "dropout": (0.1, 0.25, 0.5, 0.75),
        "flip_prob": (0.001, 0.005, 0.01, 0.05),
        "noise_std": (0.01, 0.02, 0.05, 0.1),
        "particles": (100, 500, 1000, 5000),
    },
    "drone": {
        "hidden": (64, 128, 256, 512, 1024),
        "dropout": (0.1, 0.25, 0.5, 0.75),
        "lr": (1e-2, 1e-3, 1e-4),
        "batch_size": (32, 64, 128, 256),
        "epochs": (25, 50, 75, 100),
    },
}

LABELS = {
    "hidden": "latent dimension",
    "dropout": "dropout p",
    "lr": "learning rate",
    "batch_size": "batch size",
    "epochs": "epochs",
    "flip_prob": "bit-flip probability",
    "noise_std": "likelihood noise (m)",
    "particles": "particles N",
}

#: Settings besides the swept parameters that a study's results depend on.
_SETTINGS: dict[str, tuple[str, ...]] = {
    "training": ("seed", "depth", "tasks", "episodes", "steps", "measurement_noise", *PARAMETERS["training"]),
    "smcd": (
        "seed", "depth", "tasks", "episodes", "steps", "measurement_noise", "lr", "batch_size", "epochs",
        "arms", "chunk", "burn_in", "horizons", *PARAMETERS["smcd"],
    ),
    "drone": (
        "seed", "depth", "dataset", "operators", "trajectories_per_operator", "subset", *PARAMETERS["drone"],
    ),
}  # fmt: skip

#: Settings read off a trained model rather than changing it: not part of the training run's key.
_EVALUATION_KEYS: dict[str, tuple[str, ...]] = {
    "training": ("epochs",),
    "smcd": ("flip_prob", "noise_std", "particles", "arms", "chunk", "burn_in", "horizons"),
    "drone": ("epochs",),
}

_DESIGNS = ("factorial", "one-at-a-time")


@dataclass
class SweepConfig:
    """Settings of ``smcd-rl sweep``; each study's default grid finishes in minutes on 2 CPU cores."""

    out: str = option("runs/sweep", "output directory (results, summary, plot, trained models of the smcd study)")
    study: str = option("training", "training (Fig. 5), smcd (Fig. 6) or drone (Fig. 12)")
    grid: tuple[str, ...] = option(
        (),
        "replace a parameter's values, NAME=V1,V2,... (e.g. hidden=64,256 dropout=0.5); the others keep the study's "
        "grid. Names: training and drone: hidden dropout lr batch_size epochs; smcd: hidden dropout flip_prob "
        "noise_std particles",
    )
    design: str = option("factorial", "factorial (every combination, as the paper's figures) or one-at-a-time")
    seed: int = option(0, "seed of data, initial weights, training masks, held-out arms and filters (all trials)")
    # Base values: a parameter's value when it is not swept, and the centre of --design one-at-a-time.
    hidden: int = option(256, "latent dimension (width of each hidden layer)")
    depth: int = option(2, "number of hidden layers")
    dropout: float = option(0.5, "dropout probability p in training")
    lr: float = option(1e-3, "Adam learning rate")
    batch_size: int = option(256, "training batch size")
    epochs: int = option(20, "training epochs")
    flip_prob: float = option(0.01, "SMCD bit-flip probability per step")
    noise_std: float = option(0.05, "SMCD likelihood noise std (m)")
    particles: int = option(500, "SMCD mask particles")
    # Two-link data and held-out arms (training and smcd studies).
    tasks: int = option(100, "two-link training arms (link-length draws)")
    episodes: int = option(30, "motor-babbling episodes per training arm")
    steps: int = option(10, "steps per motor-babbling episode")
    measurement_noise: float = option(0.01, "std of the end-effector measurement noise (m), data and held-out arms")
    arms: int = option(100, "held-out arms each SMCD setting is evaluated on (smcd study)")
    chunk: int = option(100, "held-out arms filtered at once (bounds memory: chunk x particles x latent)")
    burn_in: tuple[int, ...] = option((1, 10), "burn-in (adaptation) steps T (smcd study)")
    horizons: tuple[int, ...] = option((10,), "look-ahead horizons H (smcd study); one MSE per (T, H) pair")
    # Drone data (drone study).
    dataset: str = option(
        "", "drone study: a trajectory dataset (.npz, smcd_rl.envs.drone_operators format); empty: simulate"
    )
    operators: int = option(33, "drone study: simulated operators (the paper had 33)")
    trajectories_per_operator: int = option(16, "drone study: landings per simulated operator (the paper had 16)")
    subset: int = option(192, "drone study: training trajectories used, drawn at random (the paper used 192; 0: all)")
    # Ray.
    address: str = option(
        "", "address of an existing Ray cluster (e.g. auto or ray://host:10001); empty: start a local Ray"
    )
    cpus: int = option(0, "CPUs of the local Ray (0: all of this machine's); ignored with --address")
    cpus_per_trial: int = option(1, "CPUs reserved per Ray task, and its torch threads")
    gpus_per_trial: float = option(0.0, "GPUs reserved per Ray task (needs --device cuda)")
    device: str = option("cpu", "torch device of each trial (cuda needs --gpus-per-trial > 0)")
    full: bool = option(
        False, "the paper's scale: the full factorial grids, 1000 arms x 150 episodes, 1000 held-out arms"
    )


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


# ---------------------------------------------------------------------------------- grid
def resolve_grid(config: SweepConfig) -> dict[str, tuple[Any, ...]]:
    """The study's grid (``FULL_GRIDS`` with ``--full``) with ``--grid`` overrides applied and checked.

    Example:
        >>> resolve_grid(SweepConfig(study="smcd", grid=("particles=10,20",)))["particles"]
        (10, 20)
    """
    if config.study not in STUDIES:
        raise ValueError(f"unknown study {config.study!r}; choose from {', '.join(STUDIES)}")
    if config.design not in _DESIGNS:
        raise ValueError(f"unknown design {config.design!r}; choose from {', '.join(_DESIGNS)}")
    names = PARAMETERS[config.study]
    grid = dict((FULL_GRIDS if config.full else GRIDS)[config.study])
    seen: set[str] = set()
    for entry in config.grid:
        name, sep, values = entry.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not values.strip():
            raise ValueError(f"grid entry {entry!r} must read NAME=V1,V2,... (e.g. hidden=64,256)")
        if name not in names:
            raise ValueError(
                f"unknown parameter {name!r} for study {config.study!r}; its parameters: {', '.join(names)}"
            )
        if name in seen:
            raise ValueError(
                f"parameter {name!r} is given twice in --grid; list all its values in one NAME=V1,V2 entry"
            )
        seen.add(name)
        kind = type(getattr(config, name))
        try:
            grid[name] = tuple(dict.fromkeys(_parse(kind, v.strip()) for v in values.split(",")))
        except ValueError as err:
            raise ValueError(f"grid entry {entry!r}: values of {name} must be {kind.__name__}s ({err})") from err
    for name, values in grid.items():
        for value in values:
            _check_value(name, value)
    return grid


def _parse(kind: type, text: str) -> Any:
    if kind is int:
        value = float(text)
        if value != int(value):
            raise ValueError(f"{text!r} is not a whole number")
        return int(value)
    return kind(text)


#: Allowed values of each parameter: (check, what the error message asks for).
_RANGES = {
    "hidden": (lambda v: v >= 1, "an int >= 1"),
    "batch_size": (lambda v: v >= 1, "an int >= 1"),
    "epochs": (lambda v: v >= 1, "an int >= 1"),
    "particles": (lambda v: v >= 1, "an int >= 1"),
    "dropout": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "flip_prob": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "lr": (lambda v: 0 < v < math.inf, "positive and finite"),
    "noise_std": (lambda v: 0 < v < math.inf, "positive and finite"),
}


def _check_value(name: str, value: Any) -> None:
    ok, wanted = _RANGES[name]
    if not ok(value):
        raise ValueError(f"{name} = {value} is out of range: it must be {wanted}")


def trial_configs(config: SweepConfig, grid: Mapping[str, Sequence[Any]] | None = None) -> list[dict[str, Any]]:
    """One trial configuration per grid point: the study's settings with the point's values.

    Each is all :func:`trial` needs (a plain dict, JSON-ready), ``threads`` and ``device`` included.

    Example:
        >>> config = SweepConfig(grid=("hidden=8", "dropout=0.5", "lr=0.1,0.01", "batch_size=64", "epochs=1"))
        >>> [(p["hidden"], p["lr"], p["study"]) for p in trial_configs(config)]
        [(8, 0.1, 'training'), (8, 0.01, 'training')]
    """
    grid = resolve_grid(config) if grid is None else grid
    settings = config_dict(config)
    base = {"study": config.study, **{k: settings[k] for k in _SETTINGS[config.study]}}
    base |= {"threads": config.cpus_per_trial, "device": config.device}
    names = list(grid)
    if config.design == "factorial":
        combos = [dict(zip(names, values, strict=True)) for values in itertools.product(*(grid[n] for n in names))]
    else:
        combos = [{}] + [{name: value} for name in names for value in grid[name]]
    points: list[dict[str, Any]] = []
    for combo in combos:
        point = base | combo
        if point not in points:  # one-at-a-time repeats the base point once per parameter
            points.append(point)
    return points


# ---------------------------------------------------------------------------------- trial
def trial(config: Mapping[str, Any]) -> dict[str, float]:
    """Metrics of one grid point, from its configuration alone (it seeds itself).

    Training and drone studies: ``train_loss``, the mean training loss (MSE in normalised units,
    dropout on, as the paper plots) of the last epoch. smcd study: ``mse_T{t}_H{h}``, the mean
    squared end-effector error (m^2) over held-out arms and the first ``h`` look-ahead steps after
    ``t`` burn-in steps.

    Example:
        >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=1"), tasks=4, episodes=2))[0]
        >>> list(trial(point))
        ['train_loss']
    """
    return evaluate(config, train(config))


def train(config: Mapping[str, Any]) -> dict[str, Any]:
    """Train the grid point's model: ``{"losses", "seconds", "checkpoint"}`` (a checkpoint only for smcd).

    Example:
        >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=2"), tasks=4, episodes=2))[0]
        >>> len(train(point)["losses"])
        2
    """
    with torch_threads(int(config["threads"])):
        generator = seed_everything(int(config["seed"]))
        data = _data(config, generator)
        model = _model(config, data)
        started = time.perf_counter()
        losses = smcd_rl.fit(
            model,
            data.to(config["device"]),
            epochs=int(config["epochs"]),
            batch_size=int(config["batch_size"]),
            lr=float(config["lr"]),
            seed=int(config["seed"]),
            progress=False,
        )
        seconds = time.perf_counter() - started
    checkpoint = model.checkpoint() if config["study"] == "smcd" else None
    return {"losses": losses, "seconds": seconds, "checkpoint": checkpoint}


def evaluate(config: Mapping[str, Any], trained: Mapping[str, Any]) -> dict[str, float]:
    """The grid point's metrics from a model trained by :func:`train` (with at least its epochs).

    Example:
        >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=1"), tasks=4, episodes=2))[0]
        >>> evaluate(point, {"losses": [0.5, 0.25]})
        {'train_loss': 0.5}
    """
    if config["study"] != "smcd":
        epochs = int(config["epochs"])
        if len(trained["losses"]) < epochs:
            raise ValueError(f"the trained model ran {len(trained['losses'])} epochs; this grid point needs {epochs}")
        return {"train_loss": float(trained["losses"][epochs - 1])}
    from smcd_rl.experiments.two_link import TwoLinkConfig, _evaluate, _trials

    device = torch.device(config["device"])
    with torch_threads(int(config["threads"])):
        model = _model(config, None)
        model.load_checkpoint(trained["checkpoint"])
        # The held-out arms and their evaluation are two-link's own, so the numbers are comparable to Fig. 2's.
        lookahead = TwoLinkConfig(
            seed=int(config["seed"]),
            trials=int(config["arms"]),
            chunk=int(config["chunk"]),
            burn_in=tuple(config["burn_in"]),
            horizons=tuple(config["horizons"]),
            measurement_noise=float(config["measurement_noise"]),
            device=str(device),
        )
        q, ee, ee_true, _ = _trials(lookahead, device)
        method = model.with_adaptation(
            smcd_rl.SMCD(
                num_particles=int(config["particles"]),
                flip_prob=float(config["flip_prob"]),
                noise_std=float(config["noise_std"]),
                generator=torch.Generator(device=device).manual_seed(int(config["seed"]) + 11),
            )
        )
        errors = _evaluate(method, q, ee, ee_true, lookahead, desc="smcd", progress=False)
    return {
        f"mse_T{t}_H{h}": float(errors[:, i, :h].mean())
        for i, t in enumerate(lookahead.burn_in)
        for h in lookahead.horizons
    }


def _data(config: Mapping[str, Any], generator: torch.Generator) -> TensorDict:
    if config["study"] == "drone":
        state, action = _drone_data(
            str(config["dataset"]),
            int(config["operators"]),
            int(config["trajectories_per_operator"]),
            int(config["subset"]),
            int(config["seed"]),
        )
        return TensorDict({"state": state, "action": action}, [state.shape[0]])
    from smcd_rl.envs.two_link_arm import motor_babbling

    return motor_babbling(
        int(config["tasks"]),
        int(config["episodes"]),
        int(config["steps"]),
        measurement_noise=float(config["measurement_noise"]),
        generator=generator,
    )


@functools.lru_cache(maxsize=2)  # a Ray worker runs many trials on the same data; simulating takes seconds
def _drone_data(dataset: str, operators: int, per_operator: int, subset: int, seed: int) -> tuple[torch.Tensor, ...]:
    """States and actions of the training trajectories used: the paper's split, then ``subset`` at random."""
    import numpy as np

    from smcd_rl.envs import drone_operators

    if dataset:
        data = drone_operators.load_dataset(dataset)
    else:
        data = drone_operators.simulate_operators(operators, per_operator, seed=seed)
    train_ids = drone_operators.split_dataset(data, seed=seed)["train"]
    if subset > len(train_ids):
        raise ValueError(
            f"subset = {subset} but the dataset has only {len(train_ids)} training trajectories; lower --subset"
        )
    if subset:
        train_ids = np.sort(np.random.default_rng(seed).choice(train_ids, size=subset, replace=False))
    chosen = data.select(train_ids)
    return torch.from_numpy(chosen.state), torch.from_numpy(chosen.action)


def _model(config: Mapping[str, Any], data: TensorDict | None) -> smcd_rl.AdaptiveModel:
    hidden = (int(config["hidden"]),) * int(config["depth"])
    device = config["device"]
    if config["study"] == "drone":
        assert data is not None
        net = smcd_rl.MaskedMLP(
            data["state"].shape[-1],
            data["action"].shape[-1],
            hidden=hidden,
            dropout=float(config["dropout"]),
            device=device,
        )
        return smcd_rl.AdaptiveModel(net, in_keys=["state"], out_key="action")
    net = smcd_rl.MaskedMLP(2, 2, hidden=hidden, dropout=float(config["dropout"]), device=device)
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")


# ---------------------------------------------------------------------------------- run
def run(config: SweepConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the sweep (on Ray, skipping grid points already in the result cache) and write its files."""
    grid = resolve_grid(config)
    _check_config(config)
    points = trial_configs(config, grid)
    parameters = list(grid)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    # --- what is left to do, then do it on Ray -----------------------------------------------
    work = _Work(config, points, out)
    reused = work.reused
    if work.todo and config.study == "drone":  # a bad --dataset or --subset fails here, not in every Ray task
        _data(points[0], seed_everything(config.seed))
    if work.todo:
        with _ray_session(config) as ray:
            work.run(ray, progress=progress)

    # --- results --------------------------------------------------------------------------
    rows = [{**{name: point[name] for name in parameters}, **work.metrics[i]} for i, point in enumerate(points)]
    metric_names = list(work.metrics[0])
    # A parameter with one value is a fixed setting here: it has no panel (unless nothing varies).
    varied = [name for name in parameters if len(grid[name]) > 1 or config.design == "one-at-a-time"] or parameters
    summary = summarise(rows, varied, metric_names)
    write_csv(out / "results.csv", rows)
    write_csv(out / "summary.csv", summary)
    payload = {
        "experiment": f"hyper-parameter sweep, study {config.study} (paper Fig. {_FIGURE[config.study]})",
        "config": config_dict(config),
        "machine": machine_info(),
        "design": config.design,
        "grid": {name: list(values) for name, values in grid.items()},
        "metrics": metric_names,
        "grid_points": len(points),
        "computed": len(points) - reused,
        "reused": reused,
        "wall_seconds": time.perf_counter() - started,
        "train_seconds": work.train_seconds,
        "evaluate_seconds": work.evaluate_seconds,
        "results": rows,
        "summary": summary,
    }
    write_json(out / "results.json", payload)
    _plot(rows, summary, varied, metric_names, config, out / "sweep.png")
    print(table(summary))
    print(f"\n{len(points)} grid points ({len(points) - reused} computed, {reused} from the cache)")
    print(f"wrote {out}/results.csv, summary.csv, results.json, sweep.png")
    return payload


_FIGURE = {"training": 5, "smcd": 6, "drone": 12}


def _check_config(config: SweepConfig) -> None:
    if config.cpus_per_trial < 1 or config.cpus < 0 or config.gpus_per_trial < 0:
        raise ValueError("need --cpus-per-trial >= 1, --cpus >= 0 and --gpus-per-trial >= 0")
    if not config.address and config.cpus_per_trial > (config.cpus or os.cpu_count() or 1):
        raise ValueError(
            f"--cpus-per-trial {config.cpus_per_trial} exceeds the local Ray's {config.cpus or os.cpu_count()} CPUs; "
            "no trial could ever be scheduled"
        )
    if torch.device(config.device).type != "cpu" and config.gpus_per_trial <= 0:
        raise ValueError(
            f"--device {config.device} needs --gpus-per-trial > 0: Ray hides GPUs from tasks that reserve none"
        )
    for name in ("depth", "tasks", "episodes", "steps", "arms", "chunk"):
        if getattr(config, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(config, name)}")
    if config.study == "smcd" and (
        not config.burn_in or not config.horizons or min(config.burn_in + config.horizons) < 1
    ):
        raise ValueError("--burn-in and --horizons need at least one value each, all >= 1")
    if config.study == "drone" and config.subset < 0:
        raise ValueError(f"--subset must be >= 0 (0: all training trajectories), got {config.subset}")


@contextlib.contextmanager
def _ray_session(config: SweepConfig) -> Iterator[Any]:
    """Ray, started locally (or connected to ``--address``) for the block; shut down after if we started it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError(
            'smcd-rl sweep runs its trials on Ray, which is not installed; install it with: pip install "smcd-rl[ray]"'
        ) from err
    started = not ray.is_initialized()
    if started:
        if config.address:
            ray.init(address=config.address, logging_level=logging.WARNING)
        else:
            # "local": always a fresh instance, never a cluster that `ray start` once left behind.
            ray.init(
                address="local", num_cpus=config.cpus or None, include_dashboard=False, logging_level=logging.WARNING
            )
    try:
        available = ray.cluster_resources().get("CPU", 0)
        if config.cpus_per_trial > available:
            raise ValueError(
                f"--cpus-per-trial {config.cpus_per_trial} exceeds the Ray cluster's {available:g} CPUs; "
                "no trial could ever be scheduled"
            )
        yield ray
    finally:
        if started:
            ray.shutdown()


class _Work:
    """The sweep's bookkeeping: grid points grouped by training run, and what the cache already holds.

    Cache entries are keyed by each trial's full configuration (``point/{json}``, ``train/{json}``),
    so a changed setting never reuses a stale result, and growing a grid reuses every finished point.
    """

    def __init__(self, config: SweepConfig, points: list[dict[str, Any]], out: Path) -> None:
        self.config, self.points, self.out = config, points, out
        self.smcd = config.study == "smcd"
        self.cache = ResultCache(out / "partial.pt", {"experiment": "smcd-rl sweep", "format": 1})
        self.point_keys = [_key("point", p) for p in points]
        self.groups: dict[str, list[int]] = {}  # training-run key -> its grid points
        self.model_configs: dict[str, dict[str, Any]] = {}
        for index, point in enumerate(points):
            model_config = {k: v for k, v in point.items() if k not in _EVALUATION_KEYS[config.study]}
            key = _key("train", model_config)
            self.groups.setdefault(key, []).append(index)
            self.model_configs[key] = model_config
        self.metrics: dict[int, dict[str, float]] = {}
        for index, key in enumerate(self.point_keys):
            if (done := self.cache.get(key)) is not None:
                self.metrics[index] = done["metrics"]
        self.reused = len(self.metrics)  # grid points finished before this run
        if not self.smcd:  # new epoch counts of a cached training run are read off its losses, no Ray needed
            for key in self.groups:
                done = self.cache.get(key)
                if done is not None and len(done["losses"]) >= self._epochs(key):
                    self._read_losses(key, done)
        self.todo = [i for i in range(len(points)) if i not in self.metrics]
        self.train_seconds: list[float] = []
        self.evaluate_seconds: list[float] = []

    def run(self, ray: Any, *, progress: bool) -> None:
        """Submit the missing training runs and evaluations at once; store each result as it finishes."""
        resources = {"num_cpus": self.config.cpus_per_trial, "num_gpus": self.config.gpus_per_trial}
        remote_train = ray.remote(train).options(**resources)
        remote_evaluate = ray.remote(_timed_evaluate).options(**resources)
        pending: dict[Any, tuple[str, Any]] = {}  # object ref -> ("train", run key) | ("evaluate", point index)
        for key, indices in self.groups.items():
            missing = [i for i in indices if i not in self.metrics]
            if not missing:
                continue
            epochs = self._epochs(key)
            done = self.cache.get(key)
            saved = done is not None and done["model"] is not None and (self.out / done["model"]).is_file()
            if self.smcd and saved and len(done["losses"]) >= epochs:  # evaluate on the saved model
                checkpoint = torch.load(self.out / done["model"], map_location="cpu", weights_only=False)
                source = ray.put({**done, "checkpoint": checkpoint})
            else:
                source = remote_train.remote({**self.model_configs[key], "epochs": epochs})
                pending[source] = ("train", key)
            if self.smcd:  # each filter setting is its own task on the (possibly still training) model
                for index in missing:
                    pending[remote_evaluate.remote(self.points[index], source)] = ("evaluate", index)

        with tqdm(total=len(pending), desc=f"sweep {self.config.study}", unit="task", disable=not progress) as bar:
            bar.set_postfix(cached=self.reused)
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    kind, what = pending.pop(ref)
                    if kind == "train":
                        self._store_run(what, ray.get(ref))
                    else:
                        self.metrics[what], seconds = ray.get(ref)
                        self.evaluate_seconds.append(seconds)
                        self.cache.put(self.point_keys[what], {"metrics": self.metrics[what]})
                    bar.update()

    def _epochs(self, key: str) -> int:
        """Epochs of a training run: the most any of its grid points needs."""
        return max(int(self.points[i]["epochs"]) for i in self.groups[key])

    def _store_run(self, key: str, result: dict[str, Any]) -> None:
        self.train_seconds.append(result["seconds"])
        record = {"losses": result["losses"], "seconds": result["seconds"], "model": None}
        if result["checkpoint"] is not None:  # saved beside the cache, so a resumed run can evaluate on it
            record["model"] = f"models/{hashlib.sha256(key.encode()).hexdigest()[:16]}.pt"
            (self.out / "models").mkdir(exist_ok=True)
            torch.save(result["checkpoint"], self.out / record["model"])
        self.cache.put(key, record)
        if not self.smcd:
            self._read_losses(key, result)

    def _read_losses(self, key: str, run: Mapping[str, Any]) -> None:
        for index in self.groups[key]:
            if index not in self.metrics:
                self.metrics[index] = evaluate(self.points[index], run)
                self.cache.put(self.point_keys[index], {"metrics": self.metrics[index]})


def _key(kind: str, config: Mapping[str, Any]) -> str:
    return kind + "/" + json.dumps(config, sort_keys=True)


def _timed_evaluate(config: Mapping[str, Any], trained: Mapping[str, Any]) -> tuple[dict[str, float], float]:
    started = time.perf_counter()
    return evaluate(config, trained), time.perf_counter() - started


# ---------------------------------------------------------------------------------- results
def summarise(
    rows: Sequence[Mapping[str, Any]], parameters: Sequence[str], metrics: Sequence[str]
) -> list[dict[str, Any]]:
    """Per metric, parameter and value: trials, mean, std (population) and min over the other parameters.

    Example:
        >>> rows = [{"lr": 0.1, "hidden": 8, "loss": 1.0}, {"lr": 0.1, "hidden": 16, "loss": 3.0}]
        >>> summarise(rows, ["lr"], ["loss"])
        [{'metric': 'loss', 'parameter': 'lr', 'value': 0.1, 'trials': 2, 'mean': 2.0, 'std': 1.0, 'min': 1.0}]
    """
    summary = []
    for metric in metrics:
        for name in parameters:
            for value in dict.fromkeys(row[name] for row in rows):
                values = [float(row[metric]) for row in rows if row[name] == value]
                summary.append(
                    {
                        "metric": metric,
                        "parameter": name,
                        "value": value,
                        "trials": len(values),
                        "mean": statistics.fmean(values),
                        "std": statistics.pstdev(values),
                        "min": min(values),
                    }
                )
    return summary


def table(summary: Sequence[Mapping[str, Any]]) -> str:
    """The summary as a Markdown table (4 significant digits: losses and learning rates span decades).

    Example:
        >>> print(table([{"metric": "loss", "parameter": "lr", "value": 0.0001, "trials": 2, "mean": 2.0, "std": 1.0, "min": 1.0}]))
        | metric | parameter | value  | trials | mean | std | min |
        |--------|-----------|--------|--------|------|-----|-----|
        | loss   | lr        | 0.0001 | 2      | 2    | 1   | 1   |
    """
    header = ["metric", "parameter", "value", "trials", "mean", "std", "min"]
    body = [
        [row["metric"], row["parameter"], _number(row["value"]), row["trials"]] + [_number(row[k]) for k in header[4:]]
        for row in summary
    ]
    return format_table(body, header)


def _number(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _plot(
    rows: Sequence[Mapping[str, Any]],
    summary: Sequence[Mapping[str, Any]],
    parameters: Sequence[str],
    metrics: Sequence[str],
    config: SweepConfig,
    path: Path,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(parameters), figsize=(3.0 * len(parameters), 3.4), sharey=True, squeeze=False)
    for ax, name in zip(axes[0], parameters, strict=True):
        values = list(dict.fromkeys(row[name] for row in rows))
        positions = range(len(values))
        if len(metrics) == 1:  # every trial as a dot: the spread the paper's panels show
            for x, value in zip(positions, values, strict=True):
                ys = [row[metrics[0]] for row in rows if row[name] == value]
                jitter = [x + 0.25 * ((k + 0.5) / len(ys) - 0.5) for k in range(len(ys))]
                ax.scatter(jitter, ys, s=8, color="0.6", zorder=1)
        for metric in metrics:
            sel = {row["value"]: row for row in summary if row["metric"] == metric and row["parameter"] == name}
            line = ax.errorbar(
                positions,
                [sel[v]["mean"] for v in values],
                yerr=[sel[v]["std"] for v in values],
                marker="o",
                capsize=3,
                label=f"{_metric_label(metric)} mean",
                zorder=3,
            )
            ax.plot(positions, [sel[v]["min"] for v in values], ls=":", marker="v", color=line[0].get_color(), zorder=3)
        ax.set_xticks(list(positions), [_number(v) for v in values])
        ax.set_xlabel(LABELS[name])
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("training loss (normalised MSE)" if config.study != "smcd" else "look-ahead MSE (m$^2$)")
    axes[0][-1].legend(fontsize=7, title="dotted: min", title_fontsize=7)
    fig.suptitle(
        f"Sweep, study {config.study} (cf. paper Fig. {_FIGURE[config.study]}): mean ± std and min over the other parameters"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _metric_label(metric: str) -> str:
    if metric.startswith("mse_T"):
        t, h = metric[len("mse_T") :].split("_H")
        return f"T={t}, H={h}"
    return metric.replace("_", " ")
