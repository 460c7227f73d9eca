"""The grids of ``smcd-rl sweep``: each study's parameters and values, ``--grid`` overrides, grid points.

A grid point is a plain dict, everything :func:`~smcd_rl.experiments.sweep_trials.trial` needs
(the study's settings with the point's values, threads and device included), so it travels to a
Ray worker as is and doubles as the key its result is stored under.

Example:
    >>> from smcd_rl.experiments.sweep import SweepConfig
    >>> grid = resolve_grid(SweepConfig(study="smcd", grid=("particles=10,20",)))
    >>> grid["particles"], len(trial_configs(SweepConfig(study="smcd"), grid))
    ((10, 20), 162)
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from smcd_rl.digests import file_digest
from smcd_rl.experiments.common import config_dict, resolve_device
from smcd_rl.experiments.configs import ExperimentConfig
from smcd_rl.experiments.configs.sweep import DESIGNS, STUDIES

if TYPE_CHECKING:
    from smcd_rl.experiments.configs.sweep import SweepConfig

__all__ = [
    "STUDIES",
    "DESIGNS",
    "PARAMETERS",
    "GRIDS",
    "FULL_GRIDS",
    "EVALUATION_KEYS",
    "resolve_grid",
    "trial_configs",
]

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
EVALUATION_KEYS: dict[str, tuple[str, ...]] = {
    "training": ("epochs",),
    "smcd": ("flip_prob", "noise_std", "particles", "arms", "chunk", "burn_in", "horizons"),
    "drone": ("epochs",),
}


def resolve_grid(config: SweepConfig) -> dict[str, tuple[Any, ...]]:
    """The study's grid (``FULL_GRIDS`` with ``--full``) with ``--grid`` overrides applied and checked.

    Every value must pass the bounds of the option of the same name (``dropout=1.5`` is refused
    as ``--dropout 1.5`` would be).
    """
    names = PARAMETERS[config.study]
    grid = dict((FULL_GRIDS if config.full else GRIDS)[config.study])
    seen: set[str] = set()
    for entry in config.grid:
        name, sep, text = entry.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not text.strip():
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
            grid[name] = tuple(dict.fromkeys(_parse(kind, v.strip()) for v in text.split(",")))
        except ValueError as err:
            raise ValueError(f"grid entry {entry!r}: values of {name} must be {kind.__name__}s ({err})") from err
    for name, values in grid.items():
        for value in values:
            try:  # the option's own checks; not the sweep's validate(), which resolves this grid
                candidate = dataclasses.replace(config, grid=(), **{name: value})
                ExperimentConfig.validate(candidate)
            except ValueError as err:
                raise ValueError(f"--grid {name}={value}: {err}") from err
    return grid


def _parse(kind: type, text: str) -> Any:
    if kind is int:
        value = float(text)
        if value != int(value):
            raise ValueError(f"{text!r} is not a whole number")
        return int(value)
    return kind(text)


def trial_configs(config: SweepConfig, grid: Mapping[str, Sequence[Any]] | None = None) -> list[dict[str, Any]]:
    """One trial configuration per grid point: the study's settings with the point's values.

    Each is all :func:`~smcd_rl.experiments.sweep_trials.trial` needs (a plain dict, JSON-ready),
    ``threads`` and ``device`` included; with ``--dataset``, also the file's digest, so that a
    result is tied to the data it came from, not to the file's name.

    Example:
        >>> from smcd_rl.experiments.sweep import SweepConfig
        >>> config = SweepConfig(grid=("hidden=8", "dropout=0.5", "lr=0.1,0.01", "batch_size=64", "epochs=1"))
        >>> [(p["hidden"], p["lr"], p["study"]) for p in trial_configs(config)]
        [(8, 0.1, 'training'), (8, 0.01, 'training')]
    """
    grid = resolve_grid(config) if grid is None else grid
    settings = config_dict(config)
    base = {"study": config.study, **{k: settings[k] for k in _SETTINGS[config.study]}}
    base |= {"threads": config.cpus_per_trial, "device": resolve_device(config.device)}
    if config.study == "drone" and config.dataset:
        base["dataset_digest"] = file_digest(config.dataset)
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
