"""The config of ``smcd-rl interpret`` (:mod:`smcd_rl.experiments.interpret.run`): its settings, ``--full`` preset and parts.

Example:
    >>> InterpretConfig().parts, FULL["hidden"]
    (('fig9', 'confidence', 'lookahead'), 1024)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from smcd_rl.experiments.shared.adaptation_config import TASK_VARIANTS, VARIANTS, TuningConfig, check_mask_groups
from smcd_rl.experiments.shared.config import setting

__all__ = ["InterpretConfig", "FULL", "PARTS", "METHODS", "DEFAULT_METHODS", "SIMULATED_LABELS"]

#: The parts of the command (``--parts``).
PARTS: tuple[str, ...] = ("fig9", "confidence", "lookahead")
#: Fig. 14's methods: M multi-task / R Reptile training; N none / G gradient descent (tuned) / S SMCD
#: tuned by the look-ahead error / S(evidence) SMCD calibrated by its evidence / S(paper) SMCD at the
#: paper's settings / C the combination of the tuned ones / L the Bayesian last layer / SL SMCD with a
#: Bayesian readout.
METHODS: tuple[str, ...] = (
    *(f"{network}+{variant}" for network in ("M", "R") for variant in VARIANTS),
    # T: the network whose masks were trained to identify the operator (fit(mask_training="task")).
    *(f"T+{variant}" for variant in TASK_VARIANTS),
)
#: What runs by default (R+S(paper) only on request: the R network's comparison is with its tuned methods).
DEFAULT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m != "R+S(paper)")
#: The labels of :func:`~smcd_rl.envs.drone_operators.simulate_operators` (a ``--dataset`` may have others).
SIMULATED_LABELS: tuple[str, ...] = ("skill", "strategy", "phase", "success", "target")


@dataclass
class InterpretConfig(TuningConfig):
    """Settings of ``smcd-rl interpret``; the defaults finish in a few minutes on 2 CPU cores."""

    out: str = setting("runs/interpret", "output directory (results, plots, report, dataset, trained models)")
    parts: tuple[str, ...] = setting(PARTS, "parts to run: fig9, confidence, lookahead", choices=PARTS)
    # --- Fig. 9: two-link masks against link lengths
    fig9_latents: tuple[int, ...] = setting(
        (32, 128, 512), "two-link hidden widths (latent sizes ld), one model each", low=1
    )
    fig9_tasks: int = setting(200, "two-link training arms", low=1)
    fig9_episodes: int = setting(25, "motor-babbling episodes (10 steps) per training arm", low=1)
    fig9_epochs: int = setting(20, "two-link training epochs", low=1)
    fig9_arms: int = setting(200, "held-out arms whose masks are compared", low=2)
    fig9_burn_in: int = setting(20, "motor-babbling steps observed before the masks are read", low=1)
    fig9_particles: int = setting(500, "SMCD particles for the two-link masks", low=1)
    fig9_own_paths: bool = setting(
        False, "each held-out arm babbles along a joint path of its own (default: one shared path)"
    )
    fig9_ks: tuple[int, ...] = setting((1, 2, 5, 10, 20, 50), "k of the top-k link-length accuracy", low=1)
    # --- drone data
    dataset: str = setting(
        "", "a trajectory dataset (.npz, see smcd_rl.envs.drone_operators) instead of the simulated operators"
    )
    operators: int = setting(33, "simulated operators", low=2)
    trajectories_per_operator: int = setting(16, "landings per simulated operator", low=1)
    known_fraction: float = setting(
        0.10, "share of all trajectories held out from training operators", low=0.0, below=1.0
    )
    unknown_fraction: float = setting(0.07, "share of operators held out entirely", low=0.0, below=1.0)
    # --- behaviour-cloning model u = f(x)
    hidden: int = setting(128, "width of each hidden layer", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(0.5, "dropout probability p used in training", above=0.0, below=1.0)
    epochs: int = setting(20, "training epochs (multi-task)", low=1)
    batch_size: int = setting(256, "training batch size (multi-task)", low=1)
    lr: float = setting(1e-3, "Adam learning rate (multi-task)", above=0.0)
    # --- SMCD
    particles: int = setting(300, "SMCD mask particles", low=1)
    flip_prob: float = setting(
        0.002, "SMCD bit-flip probability per step (masks of Figs. 4/9/13; Fig. 14's S(paper))", low=0.0, high=1.0
    )
    noise_scale: float = setting(
        0.7,
        "SMCD likelihood noise, in units of the model's training RMSE per action dim (Figs. 4/13; Fig. 14's S(paper))",
        above=0.0,
    )
    independent_priors: bool = setting(
        False, "draw each mask-comparison filter's prior particles afresh (default: one shared set)"
    )
    chunk: int = setting(64, "trajectories filtered at once (bounds memory: chunk x particles x hidden)", low=1)
    # --- confidence (Fig. 4, Fig. 13)
    labels: tuple[str, ...] = setting(
        ("skill", "strategy", "phase", "success"), "labels to score (per-step or per-trajectory)"
    )
    k: int = setting(5, "nearest stored masks in eq. (9)", low=1)
    steps: tuple[int, ...] = setting(
        (1, 5, 10, 20, 30, 40, 60, 80), "observed steps n at which test masks are scored", low=1
    )
    phase_stride: int = setting(5, "steps between stored masks for per-step labels", low=1)
    # --- look-ahead (Fig. 14)
    methods: tuple[str, ...] = setting(
        DEFAULT_METHODS,
        "look-ahead methods: M (multi-task) or R (Reptile) + N, G (tuned GD), S (SMCD tuned by the look-ahead), "
        "S(evidence) (SMCD calibrated by its evidence), S(paper), C (the combination of the tuned ones), "
        "L (Bayesian last layer) or SL (SMCD with a Bayesian readout); T (masks trained to identify the "
        "operator) + N, G, S, L or SL",
        choices=METHODS,
    )
    burn_in: tuple[float, ...] = setting(
        (0.1, 0.25, 0.5), "burn-in as a fraction of the trajectory", above=0.0, below=1.0
    )
    horizons: tuple[float, ...] = setting(
        (0.1, 0.25, 0.5), "look-ahead horizon as a fraction of the trajectory", above=0.0, below=1.0
    )
    # --- the fair protocol (smcd_rl.experiments.shared.tuning): the grid fields come from TuningConfig
    tuning_episodes: int = setting(
        32,
        "held-out training-distribution flights every method is tuned on (fresh simulated operators, or "
        "flights held out of a --dataset's training split; never test flights)",
        low=2,
    )
    tuning_steps: int = setting(20, "steps of each tuning flight used (flights shorter are not drawn)", low=2)
    # T: every sample through its operator's masks, 16 bits a layer (`smcd-rl task-masks --family
    # drone`'s best on held-out operators, never the test flights).
    task_share: float = setting(
        1.0, "share of T's samples trained through a mask of their operator's posterior", low=0.0, high=1.0
    )
    mask_groups: int = setting(16, "dropout bits per hidden layer of T (0: one per unit)", low=0)
    # The table scores the actions of the next steps after a burn-in: every method is tuned by its
    # look-ahead over a quarter of a tuning flight (the table's middle horizon ratio).
    tuning_horizon: int = setting(
        5, "look-ahead H every method is tuned by (open loop after each step of a tuning flight; 1: one-step)", low=1
    )
    reptile_epochs: int = setting(20, "Reptile epochs (operators as tasks)", low=1)
    reptile_batch_size: int = setting(64, "Reptile inner mini-batch", low=1)
    reptile_lr: float = setting(0.1, "Reptile outer step size", above=0.0)
    reptile_inner_lr: float = setting(0.02, "Reptile inner SGD learning rate (the paper's 0.02)", above=0.0)
    reptile_tasks_per_batch: int = setting(1, "operators per Reptile meta step", low=1)
    full: bool = setting(False, "the paper's scale (B.2, A.5): hidden 1024, 1000 particles, 400/1000 epochs at lr 1e-4")

    NON_EMPTY = (
        "parts",
        "fig9_latents",
        "fig9_ks",
        "labels",
        "steps",
        "methods",
        "burn_in",
        "horizons",
    )  # and TuningConfig's

    def validate(self) -> None:
        """The declared bounds, then the checks across fields and of the dataset file."""
        super().validate()
        check_mask_groups(self, "lookahead" in self.parts and any(m.startswith("T+") for m in self.methods))
        if self.known_fraction + self.unknown_fraction >= 1:
            raise ValueError(
                f"--known-fraction + --unknown-fraction must be below 1, got {self.known_fraction + self.unknown_fraction}"
            )
        if "fig9" in self.parts and max(self.fig9_ks) > self.fig9_arms - 1:
            raise ValueError(f"--fig9-ks must be at most --fig9-arms - 1 = {self.fig9_arms - 1}, got {self.fig9_ks}")
        unknown = sorted(set(self.labels) - set(SIMULATED_LABELS))
        if "confidence" in self.parts and not self.dataset and unknown:
            raise ValueError(
                f"--labels: the simulated operators have no {unknown}; choose from {list(SIMULATED_LABELS)}"
            )
        if "lookahead" in self.parts and self.tuning_horizon >= self.tuning_steps:
            raise ValueError(
                f"--tuning-horizon {self.tuning_horizon} needs tuning flights longer than it; raise --tuning-steps "
                f"(now {self.tuning_steps}) or lower --tuning-horizon"
            )
        if self.dataset and not Path(self.dataset).is_file():
            raise FileNotFoundError(f"--dataset {self.dataset}: no such file")


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "fig9_latents": (64, 256, 1024),
    "fig9_tasks": 1000,
    "fig9_episodes": 150,
    "fig9_epochs": 200,
    "fig9_arms": 1000,
    "fig9_particles": 1000,
    "hidden": 1024,
    "epochs": 400,
    "batch_size": 64,
    "lr": 1e-4,
    "particles": 1000,
    "chunk": 16,
    "reptile_epochs": 1000,
    "threads": 0,
}
