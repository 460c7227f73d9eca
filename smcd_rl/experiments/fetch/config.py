"""The config of ``smcd-rl fetch`` (:mod:`smcd_rl.experiments.fetch.run`): its settings, ``--full`` preset and families.

Example:
    >>> FetchConfig().families, tuple(FAMILIES), tuple(PLANNERS), METHOD_LABELS["S(paper)"]
    (('reach',), ('reach', 'push'), ('cem', 'mppi'), 'M+S(paper)')
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from smcd_rl.experiments.shared.adaptation_config import (
    TASK_VARIANTS,
    VARIANTS,
    TuningConfig,
    check_learnt_dynamics,
    check_mask_groups,
)
from smcd_rl.experiments.shared.config import setting

__all__ = ["FetchConfig", "FULL", "FAMILIES", "PLANNERS", "METHOD_LABELS", "TASK_ADAPTATIONS"]

#: Family name -> its registered gymnasium id.
FAMILIES: dict[str, str] = {
    "reach": "smcd_rl/FetchReachRotated-v0",
    "push": "smcd_rl/FetchPushHeavy-v0",
}
#: Planner names and their labels in the tables and plot.
PLANNERS: dict[str, str] = {"cem": "CEM", "mppi": "MPPI"}
#: Adaptation names (:data:`~smcd_rl.experiments.shared.adaptation_config.VARIANTS`) and their method labels.
METHOD_LABELS: dict[str, str] = {variant: f"M+{variant}" for variant in VARIANTS}
#: The adaptations of the default run: every one.
DEFAULT_ADAPTATIONS: tuple[str, ...] = VARIANTS
#: The adaptations of the network whose masks were trained to identify the draw (method ``T+<variant>``).
TASK_ADAPTATIONS: tuple[str, ...] = TASK_VARIANTS


@dataclass
class FetchConfig(TuningConfig):
    """Settings of ``smcd-rl fetch``; the defaults (FetchReachRotated only) finish in about 4 minutes on 2 CPU cores."""

    out: str = setting("runs/fetch", "output directory (results, plot, report, data, trained models)")
    families: tuple[str, ...] = setting(
        ("reach",),
        "task families: reach (FetchReachRotated: unknown action rotation and gain), "
        "push (FetchPushHeavy: unknown block mass and friction; much harder for MPC, not in the default)",
        choices=tuple(FAMILIES),
    )
    rotation: float = setting(
        1.5, "largest |rotation| (rad) about z of the reach draws (the family's default range is 0.5)", above=0.0
    )
    transitions: int = setting(
        20_000, "training transitions per family, from draws of the family (see --validation)", low=3
    )
    data_episode_steps: int = setting(50, "steps per data-collection episode (one draw each)", low=1)
    hidden: int = setting(128, "width of each hidden layer", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(0.1, "dropout probability p (0 < p < 1) used in training", above=0.0)
    epochs: int = setting(20, "training epochs", low=1)
    batch_size: int = setting(128, "training batch size", low=1)
    lr: float = setting(2e-3, "Adam learning rate", above=0.0)
    task_adaptations: tuple[str, ...] = setting(
        TASK_ADAPTATIONS,
        "adaptations of T, a second network whose masks were trained to identify the draw "
        "(fit(mask_training='task'), methods T+S, T+SL...)",
        choices=TASK_ADAPTATIONS,
    )
    # Every sample through its draw's masks, 16 bits a layer: `smcd-rl task-masks --family fetch`'s
    # best on held-out draws (never the test draws).
    task_share: float = setting(
        1.0,
        "share of T's samples trained through a mask of their draw's posterior (the rest random)",
        low=0.0,
        high=1.0,
    )
    mask_groups: int = setting(16, "dropout bits per hidden layer of T (0: one per unit)", low=0)
    validation: float = setting(
        0.1, "fraction (0 < f < 1) of the transitions held out (one-step RMSE: S(paper)'s noise)", above=0.0
    )
    planners: tuple[str, ...] = setting(("cem", "mppi"), "planners: cem, mppi", choices=tuple(PLANNERS))
    adaptations: tuple[str, ...] = setting(
        DEFAULT_ADAPTATIONS,
        "adaptations: N (none), G (tuned gradient descent), S (SMCD tuned like it), S(evidence) (SMCD "
        "calibrated by its evidence), S(paper) (SMCD at fixed settings: noise --noise-scale x held-out RMSE, "
        "--flip-prob), C (the combination of N and the tuned ones: it predicts with all of them, so its cells "
        "cost about theirs together), L (Bayesian last layer), SL (SMCD with a Bayesian readout)",
        choices=tuple(METHOD_LABELS),
    )
    episodes: int = setting(100, "held-out test draws per family (one MPC episode each, the same in every cell)", low=2)
    episode_steps: int = setting(15, "steps per MPC episode", low=1)
    horizon: int = setting(5, "planning horizon (steps)", low=1)
    candidates: int = setting(100, "action sequences per planner iteration", low=1)
    elites: int = setting(10, "CEM elites per iteration (at most --candidates)", low=1)
    iterations: int = setting(3, "CEM and MPPI iterations per step", low=1)
    temperature: float = setting(
        0.01, "MPPI temperature (units of the predicted return: metres of summed distance)", above=0.0
    )
    mppi_noise: float = setting(0.5, "MPPI perturbation std (actions lie in [-1, 1])", above=0.0)
    particles: int = setting(100, "SMCD mask particles (every SMCD variant, the combination's too)", low=1)
    flip_prob: float = setting(0.01, "bit-flip probability per step of SMCD at fixed settings (S(paper))", low=0.0)
    noise_scale: float = setting(
        1.0, "likelihood noise of S(paper), in units of the network's held-out one-step RMSE per dimension", above=0.0
    )
    tuning_episodes: int = setting(
        16,
        "held-out random-action episodes of fresh training draws (never the test draws) SMCD and GD are tuned on",
        low=2,
    )
    tuning_steps: int = setting(20, "steps per tuning episode", low=2)
    # Success is a control outcome: its proxy is the learnt model's rollout over the planner's horizon.
    tuning_horizon: int = setting(
        5,
        "look-ahead H every method is tuned by: the model rolled out open loop on the logged actions (the "
        "planning horizon; 1: one-step)",
        low=1,
    )
    gd_lr: tuple[float, ...] = setting(
        (0.001, 0.003, 0.01, 0.03),
        "gradient-descent learning rates tried in tuning (normalised units)",
        above=0.0,
    )
    gd_max_lr: float = setting(
        0.03,
        "largest learning rate tuning may extend GD's grid to (0.1 makes MPC's rollouts overflow here)",
        above=0.0,
    )
    full: bool = setting(
        False, "larger: both families, 50k transitions, 3 x 256 network, 100 test draws of 25 steps, more candidates"
    )

    #: The planner rolls every candidate through the adapted model at every step: the MMSE mask's
    #: prediction only (the posterior predictive mean would cost a forward pass per particle each).
    SMCD_PREDICTIONS: ClassVar[tuple[str, ...]] = ("mask",)
    NON_EMPTY: ClassVar[tuple[str, ...]] = ("families", "planners", "adaptations")  # and TuningConfig's
    SELECTION = (
        "families",
        "planners",
        "adaptations",
        "task_adaptations",
    )  # which cells run: a subset rerun reuses cells

    def validate(self) -> None:
        """The declared bounds, then what they cannot express: upper bounds and bounds across options."""
        super().validate()
        check_learnt_dynamics(self)
        if max(self.gd_lr) > self.gd_max_lr:
            raise ValueError(
                f"--gd-lr {max(self.gd_lr)} is above --gd-max-lr {self.gd_max_lr}; lower it or raise --gd-max-lr"
            )
        check_mask_groups(self, bool(self.task_adaptations))
        if self.tuning_horizon >= self.tuning_steps:
            raise ValueError(
                f"--tuning-horizon {self.tuning_horizon} needs tuning episodes longer than it; raise --tuning-steps "
                f"(now {self.tuning_steps}) or lower --tuning-horizon"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "families": tuple(FAMILIES),
    "transitions": 50_000,
    "hidden": 256,
    "depth": 3,
    "epochs": 40,
    "episodes": 100,
    "episode_steps": 25,
    "horizon": 8,
    "candidates": 300,
    "elites": 30,
    "iterations": 4,
    "particles": 300,
    "tuning_episodes": 32,
    "threads": 0,
}
