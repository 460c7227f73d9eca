"""The config of ``smcd-rl task-masks`` (:mod:`smcd_rl.experiments.task_masks.run`).

Example:
    >>> config = TaskMasksConfig(family="fetch")
    >>> config.shares, config.grid_groups(), FAMILIES[:2]
    ((0.5, 1.0), (8, 16, 32), ('pendulum', 'telescoping'))
    >>> TaskMasksConfig(family="ant").grid_groups()  # divisors of the Ant network's 200 units
    (10, 20, 40)
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from smcd_rl.experiments.shared.config import ExperimentConfig, setting

__all__ = ["TaskMasksConfig", "FAMILIES", "experiment_config"]

#: Family -> the config class (module, name) of the experiment whose T network it trains; two-link's
#: arms are the masks sweep's own (``smcd-rl sweep --study masks``).
EXPERIMENTS = {
    "pendulum": ("smcd_rl.experiments.regimes.config", "RegimesConfig"),
    "telescoping": ("smcd_rl.experiments.telescoping.config", "TelescopingConfig"),
    "fetch": ("smcd_rl.experiments.fetch.config", "FetchConfig"),
    "panda": ("smcd_rl.experiments.panda.config", "PandaConfig"),
    "drone": ("smcd_rl.experiments.interpret.config", "InterpretConfig"),
    "ant": ("smcd_rl.experiments.ant.config", "AntConfig"),
}
#: The mask groups a family's grid tries without ``--groups``: 8, 16, 32, or divisors of a width they do not divide.
DEFAULT_GROUPS = {"ant": (10, 20, 40)}
#: The families ``--family`` takes.
FAMILIES = tuple(EXPERIMENTS)


def experiment_config(family: str, seed: int = 0) -> Any:
    """The default config of the experiment whose T network ``family`` trains (a torch-free import).

    Example:
        >>> config = experiment_config("pendulum")
        >>> type(config).__name__, config.task_share, config.mask_groups
        ('RegimesConfig', 1.0, 16)
    """
    module, name = EXPERIMENTS[family]
    return getattr(importlib.import_module(module), name)(seed=seed)


@dataclass
class TaskMasksConfig(ExperimentConfig):
    """Settings of ``smcd-rl task-masks``: T trained at every (share, groups) of the grid on one family."""

    out: str = setting("runs/task-masks", "output directory (results, plot, report, trained networks)")
    family: str = setting(
        "pendulum",
        "the task family, with its experiment's network, data and criterion: pendulum (regimes), telescoping, "
        "fetch (reach), panda, drone (interpret), ant (healthy and crippled legs)",
        choices=FAMILIES,
    )
    shares: tuple[float, ...] = setting(
        (0.5, 1.0), "shares of samples T trains through a mask of its task's posterior", low=0.0, high=1.0
    )
    groups: tuple[int, ...] = setting(
        (),
        "dropout bits per hidden layer of T, each a divisor of the family's width (default: 8 16 32; the Ant's "
        "200 units: 10 20 40)",
        low=1,
    )

    NON_EMPTY = ("shares",)

    def validate(self) -> None:
        """The declared bounds, then the groups against the family's network width (before any work)."""
        super().validate()
        width = experiment_config(self.family).hidden
        bad = sorted(g for g in self.grid_groups() if width % g)
        if bad:
            raise ValueError(
                f"--groups {bad} do not divide the {self.family} network's width {width}: each group is "
                f"width/groups units, so give divisors of {width}"
            )

    def grid_groups(self) -> tuple[int, ...]:
        """``--groups``, or the family's default grid of mask groups."""
        return self.groups or DEFAULT_GROUPS.get(self.family, (8, 16, 32))

    def points(self) -> list[tuple[float, int]]:
        """Every (share, groups) of the grid, and the experiment's own setting first if the grid lacks it.

        Example:
            >>> TaskMasksConfig(family="pendulum", shares=(0.5,), groups=(8,)).points()
            [(1.0, 16), (0.5, 8)]
        """
        experiment = experiment_config(self.family)
        current = (experiment.task_share, experiment.mask_groups)
        points = [(share, groups) for share in self.shares for groups in self.grid_groups()]
        return points if current in points else [current, *points]
