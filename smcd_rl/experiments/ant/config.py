"""The config of ``smcd-rl ant`` (:mod:`smcd_rl.experiments.ant.run`): its settings, ``--full`` preset, tasks and cells.

Example:
    >>> AntConfig().task, tuple(TASKS), tuple(PLANNERS), METHOD_LABELS["S"]
    ('l2a', ('l2a', 'ant-v5'), ('cem', 'mppi', 'rs'), 'M+S')
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, ClassVar, TypedDict

from smcd_rl.experiments.shared.adaptation_config import (
    TASK_VARIANTS,
    VARIANTS,
    TuningConfig,
    check_learnt_dynamics,
    check_mask_groups,
)
from smcd_rl.experiments.shared.config import setting

__all__ = [
    "AntConfig",
    "FULL",
    "TASKS",
    "RewardWeights",
    "PLANNERS",
    "METHOD_LABELS",
    "DEFAULT_ADAPTATIONS",
    "PREDICTED",
    "TASK_ADAPTATIONS",
    "CONDITIONS",
    "CELLS",
]


class RewardWeights(TypedDict, total=False):
    """Keyword arguments of :func:`~smcd_rl.envs.crippled_ant.ant_reward` that a task changes."""

    ctrl_cost_weight: float
    healthy_reward: float


#: Per task: CrippledAntEnv arguments, the planners' reward weights, whether episodes end on a fall.
TASKS: dict[str, tuple[dict[str, Any], RewardWeights, bool]] = {
    "l2a": (
        {
            "ctrl_cost_weight": 0.0,
            "contact_cost_weight": 0.0,
            "healthy_reward": 0.05,
            "terminate_when_unhealthy": False,
        },
        {"ctrl_cost_weight": 0.0, "healthy_reward": 0.05},
        False,
    ),
    "ant-v5": ({}, {}, True),
}


#: Planner names and their labels in the table and plot.
PLANNERS: dict[str, str] = {"cem": "CEM", "mppi": "MPPI", "rs": "RS"}
#: Adaptation names (:data:`~smcd_rl.experiments.shared.adaptation_config.VARIANTS`) and their method labels.
METHOD_LABELS: dict[str, str] = {variant: f"M+{variant}" for variant in VARIANTS}
#: Conditions: the Ant the model was trained on, and the Ant with one leg crippled per episode.
CONDITIONS: tuple[str, ...] = ("healthy", "crippled")
#: The adaptations whose prediction error is measured, whichever run the return episodes.
PREDICTED: tuple[str, ...] = VARIANTS
#: The adaptations of the default return episodes: all but S(paper), whose prediction error is still measured.
DEFAULT_ADAPTATIONS: tuple[str, ...] = ("N", "G", "S", "S(evidence)", "C")
#: The adaptations of T, the network whose masks were trained to identify the leg (method ``T+<variant>``).
TASK_ADAPTATIONS: tuple[str, ...] = TASK_VARIANTS
#: Every (planner, adaptation, condition) cell of Fig. 15.
CELLS: tuple[tuple[str, str, str], ...] = tuple(itertools.product(PLANNERS, METHOD_LABELS, CONDITIONS))


@dataclass
class AntConfig(TuningConfig):
    """Settings of ``smcd-rl ant``; the defaults finish in about 25 minutes on 2 CPU cores (stage plan estimate)."""

    out: str = setting("runs/ant", "output directory (results, plot, report, data, trained model)")
    task: str = setting(
        "l2a", "reward and episode end: l2a (Learning to Adapt's, the paper's) or ant-v5", choices=tuple(TASKS)
    )
    data_policy: str = setting(
        "random", "policy that collects the training data: random or sac", choices=("random", "sac")
    )
    sac_steps: int = setting(5000, "training steps of the SAC data policy (--data-policy sac)", low=1)
    transitions: int = setting(100_000, "transitions collected from the healthy Ant (see --validation)", low=3)
    data_episode_steps: int = setting(200, "steps per data-collection episode", low=1)
    hidden: int = setting(200, "width of each hidden layer", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(
        0.1, "dropout probability p (0 < p < 1) used in training (the paper's 0.5 with --full)", above=0.0
    )
    epochs: int = setting(40, "training epochs", low=1)
    batch_size: int = setting(256, "training batch size", low=1)
    lr: float = setting(1e-3, "Adam learning rate", above=0.0)
    validation: float = setting(
        0.1, "fraction (0 < f < 1) of the transitions held out (validation RMSE, SMCD(paper) noise)", above=0.0
    )
    planners: tuple[str, ...] = setting(
        ("cem",), "planners of the return episodes: cem, mppi, rs", choices=tuple(PLANNERS)
    )
    adaptations: tuple[str, ...] = setting(
        DEFAULT_ADAPTATIONS,
        "adaptations of the return episodes: N (none), G (tuned gradient descent), S (SMCD tuned by one-step "
        "error), S(evidence) (SMCD calibrated by its evidence), S(paper) (SMCD at --noise-scale, --flip-prob), "
        "C (the combination of the tuned ones), L (Bayesian last layer), SL (SMCD with a Bayesian readout); the "
        "prediction error always compares all eight",
        choices=tuple(METHOD_LABELS),
    )
    conditions: tuple[str, ...] = setting(CONDITIONS, "conditions to run: healthy, crippled", choices=CONDITIONS)
    crippled_legs: tuple[int, ...] = setting(
        (0, 1, 2, 3), "legs the crippled leg is drawn from per episode", choices=(0, 1, 2, 3)
    )
    task_adaptations: tuple[str, ...] = setting(
        TASK_ADAPTATIONS,
        "adaptations of T (prediction error only): a second network trained on the healthy Ant and on each leg of "
        "--crippled-legs crippled, as many transitions as M's, its masks trained to identify the leg "
        "(fit(mask_training='task'), methods T+S, T+SL...; none: no T)",
        choices=TASK_ADAPTATIONS,
    )
    task_share: float = setting(
        1.0, "share of T's samples trained through a mask of their leg's posterior (the rest random)", low=0.0, high=1.0
    )
    # `smcd-rl task-masks --family ant` (held-out healthy and crippled episodes, never the test episodes):
    # every sample through its condition's masks, 10 bits a layer, predicted best one step ahead.
    mask_groups: int = setting(10, "dropout bits per hidden layer of T, a divisor of --hidden (0: one per unit)", low=0)
    prediction_episodes: int = setting(
        50, "random-action episodes per condition on which the prediction error (primary metric) is paired", low=2
    )
    prediction_steps: int = setting(50, "steps per prediction episode (more than --prediction-horizon)", low=2)
    prediction_horizon: int = setting(10, "open-loop look-ahead H of the H-step prediction error", low=1)
    episodes: int = setting(
        30, "MPC episodes per planner x adaptation x condition cell (return, secondary metric)", low=2
    )
    episode_steps: int = setting(100, "steps per MPC episode (ant-v5: a fall ends it sooner)", low=1)
    horizon: int = setting(10, "planning horizon (steps)", low=1)
    candidates: int = setting(200, "action sequences per planner iteration (RS: times --iterations, once)", low=1)
    elites: int = setting(20, "CEM elites per iteration (at most --candidates)", low=1)
    iterations: int = setting(3, "CEM and MPPI iterations per step", low=1)
    temperature: float = setting(1.0, "MPPI temperature (units of the predicted return)", above=0.0)
    mppi_noise: float = setting(0.5, "MPPI perturbation std (actions lie in [-1, 1])", above=0.0)
    particles: int = setting(100, "SMCD mask particles (every SMCD variant, the combination's too)", low=1)
    flip_prob: float = setting(0.01, "bit-flip probability per step of SMCD at the paper's settings", low=0.0)
    noise_scale: float = setting(
        3.0, "likelihood noise of SMCD at the paper's settings, in units of the held-out RMSE per dimension", above=0.0
    )
    tuning_episodes: int = setting(
        32, "held-out random-action episodes of the healthy Ant (training distribution) SMCD and GD are tuned on", low=2
    )
    tuning_steps: int = setting(25, "steps per tuning episode", low=2)
    full: bool = setting(
        False,
        "the paper's scale: 3 x 1024 model, 10^6 transitions, every planner and adaptation, 110 episodes of 1000 steps",
    )

    #: The planner rolls every candidate through the adapted model at every step: the MMSE mask's
    #: prediction only (the posterior predictive mean would cost a forward pass per particle each).
    SMCD_PREDICTIONS: ClassVar[tuple[str, ...]] = ("mask",)
    NON_EMPTY: ClassVar[tuple[str, ...]] = (
        "planners",
        "adaptations",
        "conditions",
        "crippled_legs",
    )  # and TuningConfig's
    SELECTION = (
        "planners",
        "adaptations",
        "conditions",
        "task_adaptations",
    )  # which cells run: a subset rerun reuses cells

    def validate(self) -> None:
        """The declared bounds, then what they cannot express: upper bounds and bounds across options."""
        super().validate()
        check_learnt_dynamics(self)
        check_mask_groups(self, bool(self.task_adaptations))
        if self.prediction_steps <= self.prediction_horizon:
            raise ValueError(
                f"--prediction-steps ({self.prediction_steps}) must be > --prediction-horizon "
                f"({self.prediction_horizon})"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "transitions": 1_000_000,
    "data_episode_steps": 1000,
    "hidden": 1024,
    "mask_groups": 64,  # a divisor of the 1024 units (10 is the default width's measured choice)
    "depth": 3,
    "dropout": 0.5,
    "epochs": 100,
    "lr": 1e-4,
    "planners": tuple(PLANNERS),
    "adaptations": tuple(METHOD_LABELS),
    "episodes": 110,
    "episode_steps": 1000,
    "horizon": 15,
    "candidates": 500,
    "elites": 50,
    "iterations": 5,
    "particles": 1000,
    "threads": 0,
}
