"""The config of ``smcd-rl sweep`` (:mod:`smcd_rl.experiments.sweep.run`): its settings, ``--full`` preset, studies and designs.

Example:
    >>> SweepConfig().study, STUDIES, FULL["arms"]
    ('training', ('training', 'smcd', 'drone', 'masks'), 1000)
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from smcd_rl.experiments.shared.config import ExperimentConfig, setting

__all__ = [
    "SweepConfig",
    "FULL",
    "STUDIES",
    "FILTER_STUDIES",
    "DESIGNS",
    "PARAMETERS",
    "GRIDS",
    "FULL_GRIDS",
    "resolve_grid",
]

#: The studies (``--study``): Figs. 5, 6 and 12 of the paper, and the networks trained for mask adaptation.
STUDIES = ("training", "smcd", "drone", "masks")
#: The studies that filter held-out two-link arms with each trained network (the others report its training loss).
FILTER_STUDIES = ("smcd", "masks")
#: How the grid is laid out (``--design``): every combination, or one parameter at a time.
DESIGNS = ("factorial", "one-at-a-time")


@dataclass
class SweepConfig(ExperimentConfig):
    """Settings of ``smcd-rl sweep``; each study's default grid finishes in minutes on 2 CPU cores."""

    out: str = setting("runs/sweep", "output directory (results, summary, plot, report, stored trials)")
    threads: int = setting(
        1, "torch CPU threads of this process (the statistics); each trial runs --cpus-per-trial", low=0
    )
    device: str = setting(
        "cpu", "torch device of each trial: cpu, cuda, cuda:1 or auto (cuda needs --gpus-per-trial > 0)"
    )
    study: str = setting(
        "training",
        "training (Fig. 5), smcd (Fig. 6), drone (Fig. 12) or masks (networks trained for mask adaptation)",
        choices=STUDIES,
    )
    grid: tuple[str, ...] = setting(
        (),
        "replace a parameter's values, NAME=V1,V2,... (e.g. hidden=64,256 dropout=0.5); the others keep the study's "
        "grid. Names: training and drone: hidden dropout lr batch_size epochs; smcd: hidden dropout flip_prob "
        "noise_std particles; masks: task_share mask_groups tasks particles",
    )
    design: str = setting(
        "factorial", "factorial (every combination, as the paper's figures) or one-at-a-time", choices=DESIGNS
    )
    # Base values: a parameter's value when it is not swept, and the centre of --design one-at-a-time.
    hidden: int = setting(256, "latent dimension (width of each hidden layer)", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(0.5, "dropout probability p in training", low=0.0, below=1.0)
    lr: float = setting(1e-3, "Adam learning rate", above=0.0, below=math.inf)
    batch_size: int = setting(256, "training batch size", low=1)
    epochs: int = setting(20, "training epochs", low=1)
    flip_prob: float = setting(0.01, "SMCD bit-flip probability per step", low=0.0, high=1.0)
    noise_std: float = setting(0.05, "SMCD likelihood noise std (m)", above=0.0, below=math.inf)
    particles: int = setting(500, "SMCD mask particles", low=1)
    # The masks study's networks: smcd_rl.fit(mask_training="task") (the concepts page "Mask training").
    task_share: float = setting(
        0.5,
        "masks study: share of samples trained through a mask of their arm's posterior (0: random dropout)",
        low=0.0,
        high=1.0,
    )
    mask_groups: int = setting(
        16, "masks study: dropout bits per hidden layer, each for hidden/mask_groups units (0: one per unit)", low=0
    )
    # The smcd study's reference M+G on each trained network (not swept).
    gd_lr: float = setting(
        0.01, "smcd study: M+G's online gradient-descent learning rate (normalised units)", above=0.0
    )
    gd_steps: int = setting(5, "smcd study: M+G's gradient steps per observation", low=1)
    gd_window: int = setting(10, "smcd study: recent transitions in M+G's loss", low=1)
    # Two-link data and held-out arms (training and smcd studies).
    tasks: int = setting(100, "two-link training arms (link-length draws)", low=1)
    episodes: int = setting(30, "motor-babbling episodes per training arm", low=1)
    steps: int = setting(10, "steps per motor-babbling episode", low=1)
    measurement_noise: float = setting(
        0.01, "std of the end-effector measurement noise (m), data and held-out arms", low=0.0
    )
    arms: int = setting(100, "held-out arms each SMCD setting is evaluated on (smcd study)", low=2)
    chunk: int = setting(100, "held-out arms filtered at once (bounds memory: chunk x particles x latent)", low=1)
    burn_in: tuple[int, ...] = setting((1, 10), "burn-in (adaptation) steps T (smcd study)", low=1)
    horizons: tuple[int, ...] = setting((10,), "look-ahead horizons H (smcd study); one MSE per (T, H) pair", low=1)
    # Drone data (drone study).
    dataset: str = setting(
        "", "drone study: a trajectory dataset (.npz, smcd_rl.envs.drone_operators format); empty: simulate"
    )
    operators: int = setting(33, "drone study: simulated operators (the paper had 33)", low=1)
    trajectories_per_operator: int = setting(
        16, "drone study: landings per simulated operator (the paper had 16)", low=1
    )
    subset: int = setting(
        192, "drone study: training trajectories used, drawn at random (the paper used 192; 0: all)", low=0
    )
    # Ray.
    address: str = setting(
        "", "address of an existing Ray cluster (e.g. auto or ray://host:10001); empty: start a local Ray"
    )
    cpus: int = setting(0, "CPUs of the local Ray (0: all of this machine's); ignored with --address", low=0)
    cpus_per_trial: int = setting(1, "CPUs reserved per Ray task, and its torch threads", low=1)
    gpus_per_trial: float = setting(0.0, "GPUs reserved per Ray task (needs --device cuda)", low=0.0)
    full: bool = setting(
        False, "the paper's scale: the full factorial grids, 1000 arms x 150 episodes, 1000 held-out arms"
    )

    NON_EMPTY = ("burn_in", "horizons")

    def validate(self) -> None:
        """The declared bounds, then the grid and the checks that involve several options."""
        import torch  # only once a run is about to start: --help must not import it

        from smcd_rl.experiments.shared.runtime import resolve_device

        super().validate()
        self._check_bases_used(resolve_grid(self))
        local_cpus = self.cpus or os.cpu_count() or 1
        if not self.address and self.cpus_per_trial > local_cpus:
            raise ValueError(
                f"--cpus-per-trial {self.cpus_per_trial} exceeds the local Ray's {local_cpus} CPUs; "
                "no trial could ever be scheduled"
            )
        if torch.device(resolve_device(self.device)).type != "cpu" and self.gpus_per_trial <= 0:
            raise ValueError(
                f"--device {self.device} needs --gpus-per-trial > 0: Ray hides GPUs from tasks that reserve none"
            )
        gpus = torch.cuda.device_count()
        if not self.address and self.gpus_per_trial > gpus:
            raise ValueError(
                f"--gpus-per-trial {self.gpus_per_trial:g} exceeds the local Ray's {gpus} GPUs; no trial could ever "
                "be scheduled (use --gpus-per-trial 0 on a machine without a GPU)"
            )
        if self.study == "masks":
            self._check_masks(resolve_grid(self))
        if self.study == "drone" and self.dataset and not Path(self.dataset).is_file():
            raise FileNotFoundError(f"--dataset {self.dataset}: no such file; give a .npz dataset or leave it empty")

    def _check_bases_used(self, grid: dict[str, tuple[Any, ...]]) -> None:
        """A factorial grid sweeps its parameters over the grid's values, so their options (the base values
        of one-at-a-time designs) are unused there: one set to another value than its default, or than
        ``--full``'s, is refused rather than silently ignored."""
        if self.design != "factorial":
            return
        presets = {field.name: [field.default] for field in dataclasses.fields(self)}
        for name, value in FULL.items() if self.full else ():
            presets[name].append(value)
        for name, values in grid.items():
            value = getattr(self, name)
            if value not in presets[name] and value not in values:
                option = "--" + name.replace("_", "-")
                raise ValueError(
                    f"{option} {value} is not used: the {self.study} study's factorial grid sweeps {name} over "
                    f"{', '.join(map(str, values))}; pass --grid {name}={value} to sweep it, or --design "
                    f"one-at-a-time to centre the sweep on it"
                )

    def _check_masks(self, grid: dict[str, tuple[Any, ...]]) -> None:
        """The masks study's networks can be trained and report posteriors: groups divide the layers, two
        arms or more, dropout on, two epochs or more. One-at-a-time also runs the options' own values."""
        base = self.design == "one-at-a-time"
        groups = (*grid["mask_groups"], *([self.mask_groups] if base else []))
        tasks = (*grid["tasks"], *([self.tasks] if base else []))
        if uneven := [g for g in groups if g and self.hidden % g]:
            raise ValueError(
                f"mask_groups {uneven[0]} does not divide --hidden {self.hidden}: each mask bit switches "
                "hidden/mask_groups units; use divisors of --hidden, or 0 for one bit per unit"
            )
        if single := [t for t in tasks if t < 2]:
            raise ValueError(
                f"tasks {single[0]}: the masks study ties masks to training arms and needs at least 2 of them"
            )
        if self.dropout == 0:
            raise ValueError(
                "--dropout 0 leaves a single mask to train and filter; the masks study needs --dropout > 0"
            )
        if self.epochs < 2:
            raise ValueError(
                "--epochs 1: task masks are inferred from the second epoch on, so the masks study needs --epochs 2 "
                "or more"
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


#: The parameters each study sweeps (config fields; the names ``--grid`` takes).
PARAMETERS: dict[str, tuple[str, ...]] = {
    "training": ("hidden", "dropout", "lr", "batch_size", "epochs"),
    "smcd": ("hidden", "dropout", "flip_prob", "noise_std", "particles"),
    "drone": ("hidden", "dropout", "lr", "batch_size", "epochs"),
    "masks": ("task_share", "mask_groups", "tasks", "particles"),
}

#: Default grids: factorial and small enough for minutes on 2 CPU cores (36, 162 and 36 grid points);
#: the masks study trains 24 networks factorially, 7 with ``--design one-at-a-time``.
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
    "masks": {
        "task_share": (0.0, 0.25, 0.5, 1.0),
        "mask_groups": (0, 16, 64),
        "tasks": (25, 100),
        "particles": (100, 500),
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
    "masks": {
        "task_share": (0.0, 0.1, 0.25, 0.5, 0.75, 1.0),
        "mask_groups": (0, 8, 16, 64, 256),
        "tasks": (25, 100, 300, 1000),
        "particles": (100, 500, 1000, 5000),
    },
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
