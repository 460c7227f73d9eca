"""The grid points of ``smcd-rl sweep``: one trial configuration per point of the study's grid.

The grids themselves (each study's parameters and values, ``--grid`` overrides) are settings,
in :mod:`smcd_rl.experiments.sweep.config`.

A grid point is a plain dict, everything :func:`~smcd_rl.experiments.sweep.trials.trial` needs
(the study's settings with the point's values, threads and device included), so it travels to a
Ray worker as is and doubles as the key its result is stored under.

Example:
    >>> from smcd_rl.experiments.sweep.config import SweepConfig, resolve_grid
    >>> grid = resolve_grid(SweepConfig(study="smcd", grid=("particles=10,20",)))
    >>> grid["particles"], len(trial_configs(SweepConfig(study="smcd"), grid))
    ((10, 20), 162)
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

from smcd_rl.digests import file_digest
from smcd_rl.experiments.shared.config import config_dict
from smcd_rl.experiments.shared.runtime import resolve_device
from smcd_rl.experiments.sweep.config import PARAMETERS, SweepConfig, resolve_grid

__all__ = ["EVALUATION_KEYS", "trial_configs"]

_FILTERING = (
    "seed", "depth", "tasks", "episodes", "steps", "measurement_noise", "lr", "batch_size", "epochs",
    "arms", "chunk", "burn_in", "horizons", "hidden", "dropout", "flip_prob", "noise_std", "particles",
)  # fmt: skip

#: Settings besides the swept parameters that a study's results depend on.
_SETTINGS: dict[str, tuple[str, ...]] = {
    "training": ("seed", "depth", "tasks", "episodes", "steps", "measurement_noise", *PARAMETERS["training"]),
    "smcd": _FILTERING,
    "masks": (*_FILTERING, "task_share", "mask_groups"),
    "drone": (
        "seed", "depth", "dataset", "operators", "trajectories_per_operator", "subset", *PARAMETERS["drone"],
    ),
}  # fmt: skip

#: Settings read off a trained model rather than changing it: not part of the training run's key.
EVALUATION_KEYS: dict[str, tuple[str, ...]] = {
    "training": ("epochs",),
    "smcd": ("flip_prob", "noise_std", "particles", "arms", "chunk", "burn_in", "horizons"),
    "drone": ("epochs",),
    "masks": ("flip_prob", "noise_std", "particles", "arms", "chunk", "burn_in", "horizons"),
}


def trial_configs(config: SweepConfig, grid: Mapping[str, Sequence[Any]] | None = None) -> list[dict[str, Any]]:
    """One trial configuration per grid point: the study's settings with the point's values.

    Each is all :func:`~smcd_rl.experiments.sweep.trials.trial` needs (a plain dict, JSON-ready),
    ``threads`` and ``device`` included; with ``--dataset``, also the file's digest, so that a
    result is tied to the data it came from, not to the file's name.

    Example:
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
