"""The configs of the adaptation settings every adapting experiment shares (see :mod:`smcd_rl.experiments.shared.adaptations`).

Example:
    >>> AdaptationConfig().particles, TuningConfig().gd_steps, VARIANTS
    (1000, (1, 5), ('N', 'G', 'S', 'S(evidence)', 'S(paper)', 'C', 'L', 'SL'))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from smcd_rl.experiments.shared.config import EvaluationConfig, setting
from smcd_rl.tuning.defaults import FLIP_PROBS, GD_GRID, PREDICTIONS, WEIGHINGS

__all__ = [
    "TuningConfig",
    "AdaptationConfig",
    "VARIANTS",
    "TASK_VARIANTS",
    "LearntDynamicsSettings",
    "check_learnt_dynamics",
    "check_mask_groups",
]

#: The strategies a method name may end in: none, tuned GD, SMCD tuned by one-step error, SMCD
#: calibrated by its evidence, SMCD at the paper's settings, the combination of the tuned ones, the
#: Bayesian last layer, SMCD with a Bayesian readout.
VARIANTS = ("N", "G", "S", "S(evidence)", "S(paper)", "C", "L", "SL")
#: The strategies the network whose masks were trained to identify the task (T) runs: every single
#: tuned strategy (the evidence, the paper's settings and the combination are M's comparisons).
TASK_VARIANTS = ("N", "G", "S", "L", "SL")


@dataclass
class TuningConfig(EvaluationConfig):
    """The settings of the fair protocol (:mod:`smcd_rl.experiments.shared.tuning`), shared by every experiment that adapts.

    Every method is tuned by :func:`smcd_rl.tune` on ``tuning_episodes`` held-out training-task
    episodes: GD from the grid ``gd_lr x gd_steps x gd_window`` (both losses, extended past an
    edge), SMCD over ``calibrate_flips``, and again under ``budget_ms`` per observation. An
    experiment redeclares ``tuning_episodes`` to say what its episodes are. The steps and flip
    probabilities are the library's defaults (:mod:`smcd_rl.tuning.defaults`); the learning rates
    and windows start finer than :data:`~smcd_rl.tuning.defaults.GD_GRID` (4 rates from 0.003,
    windows 5 and 10), the grid every experiment's results were measured with.
    """

    tuning_episodes: int = setting(
        32, "held-out episodes of fresh training-distribution tasks that SMCD and GD are tuned on", low=2
    )
    gd_lr: tuple[float, ...] = setting(
        (0.003, 0.01, 0.03, 0.1), "gradient-descent learning rates tried in tuning (normalised units)", above=0.0
    )
    gd_steps: tuple[int, ...] = setting(GD_GRID["steps"], "gradient steps per observation tried in tuning", low=1)
    gd_window: tuple[int, ...] = setting((5, 10), "recent transitions in the gradient-descent loss tried", low=1)
    calibrate_flips: tuple[float, ...] = setting(
        FLIP_PROBS, "flip probabilities SMCD's calibration tries", low=0.0, high=1.0
    )
    budget_ms: float = setting(10.0, "per-observation budget (ms, one thread) of the budgeted view", above=0.0)

    NON_EMPTY: ClassVar[tuple[str, ...]] = ("gd_lr", "gd_steps", "gd_window", "calibrate_flips")
    #: How the tuned SMCD may predict (``smcd_rl.tune``'s ``predictions``): an experiment whose
    #: controller or planner evaluates the adapted model many times per step keeps the MMSE mask's
    #: prediction, one forward pass where the posterior predictive mean takes one per particle.
    SMCD_PREDICTIONS: ClassVar[tuple[str, ...]] = PREDICTIONS
    #: How the tuned SMCD with a Bayesian readout may weigh its particles (``smcd_rl.tune``'s ``weighings``).
    SL_WEIGHINGS: ClassVar[tuple[str, ...]] = WEIGHINGS


@dataclass
class AdaptationConfig(TuningConfig):
    """The settings of SMCD and of online gradient descent, shared by every experiment that adapts.

    SMCD's ``noise_std`` and ``flip_prob`` are the paper's fixed settings (variant ``S(paper)``); the
    tuned variants' settings come from :class:`TuningConfig`'s fields.
    """

    particles: int = setting(1000, "SMCD mask particles", low=1)
    flip_prob: float = setting(0.01, "bit-flip probability per step of SMCD at the paper's settings", low=0.0, high=1.0)
    noise_std: float = setting(
        0.05, "likelihood noise std of SMCD at the paper's settings (observation units)", above=0.0
    )


class LearntDynamicsSettings(Protocol):
    """The settings of a command that plans with a learnt dynamics model (``ant``, ``fetch``)."""

    dropout: float
    validation: float  # the held-out share of the transitions
    transitions: int
    candidates: int
    elites: int
    flip_prob: float
    calibrate_flips: tuple[float, ...]


def check_learnt_dynamics(config: LearntDynamicsSettings) -> None:
    """What the declared bounds of a learnt-dynamics MPC command cannot express; ValueError naming the option."""
    for name, value in (("dropout", config.dropout), ("validation", config.validation)):
        if value >= 1.0:
            raise ValueError(f"--{name} must be < 1, got {value}")
    if config.elites > config.candidates:
        raise ValueError(f"--elites ({config.elites}) must be <= --candidates ({config.candidates})")
    transitions, validation = config.transitions, config.validation
    if transitions * validation < 1 or transitions * (1 - validation) < 2:
        raise ValueError(f"{transitions} transitions are too few to hold out {validation:.0%}")
    keep = 1.0 - config.dropout  # SMCD's keep_rate transition flips a bit with up to 2 d max(k, 1 - k)
    for name, flips in (("flip-prob", (config.flip_prob,)), ("calibrate-flips", config.calibrate_flips)):
        for flip in flips:
            if flip > 1 / (2 * max(keep, 1 - keep)):
                raise ValueError(
                    f"--{name} {flip} is too large at dropout {config.dropout}: "
                    f"use at most {1 / (2 * max(keep, 1 - keep)):.3g}"
                )


def check_mask_groups(config: Any, runs_task: bool) -> None:
    """Before any work: T's ``--mask-groups`` must split ``--hidden`` evenly where a T method runs.

    Example:
        >>> from types import SimpleNamespace
        >>> check_mask_groups(SimpleNamespace(mask_groups=16, hidden=24), runs_task=False)  # no T: nothing to check
        >>> check_mask_groups(SimpleNamespace(mask_groups=16, hidden=24), runs_task=True)
        Traceback (most recent call last):
        ...
        ValueError: --mask-groups 16 must divide --hidden 24: each of the T network's mask bits switches hidden/mask-groups units; pass a divisor of --hidden, 0 for one bit per unit, or drop the T methods
    """
    if runs_task and config.mask_groups and config.hidden % config.mask_groups:
        raise ValueError(
            f"--mask-groups {config.mask_groups} must divide --hidden {config.hidden}: each of the T network's mask "
            "bits switches hidden/mask-groups units; pass a divisor of --hidden, 0 for one bit per unit, or "
            "drop the T methods"
        )
