"""The config of ``smcd-rl regimes`` (:mod:`smcd_rl.experiments.regimes.run`): its settings, ``--full`` preset and methods.

Example:
    >>> config = RegimesConfig()
    >>> config.families, config.burn_in, REGIMES[:2]
    (('two-link', 'telescoping', 'pendulum'), (1, 3, 10, 30), ('T=1', 'T=3'))
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.adaptation_config import VARIANTS
from smcd_rl.experiments.shared.config import setting
from smcd_rl.experiments.shared.two_link_family_config import FAMILY_FULL, TwoLinkFamilyConfig

__all__ = [
    "RegimesConfig",
    "FULL",
    "FAMILIES",
    "SEQUENTIAL",
    "METHODS",
    "OTHER_NETWORK_METHODS",
    "BUDGETED",
    "REGIMES",
    "regime_names",
]

#: The task families: two-link arms (new joint configurations of an arm of unknown link lengths),
#: telescoping arms (the second link changes as the stream goes on) and pendulums of unknown mass
#: and length (``smcd_rl/PendulumFamily-v0``'s dynamics).
FAMILIES = ("two-link", "telescoping", "pendulum")
#: The families whose observations form a trajectory, where measuring only every n-th step is a
#: regime of its own (an arm's observations are independent joint configurations: every n-th of
#: them would be the same as fewer observations).
SEQUENTIAL = ("pendulum",)
#: The methods, each with settings from ``smcd_rl.tune`` on held-out training-task episodes:
#: N none; G gradient descent (squared, Huber or Tukey loss); S SMCD calibrated by one-step error;
#: S(evidence) SMCD calibrated by the filter's evidence; S(paper) SMCD at the paper's noise and
#: flips; C the combination of N and the tuned ones; L the Bayesian last layer (Gaussian or
#: Tukey); SL SMCD with a Bayesian readout.
METHODS = VARIANTS
#: Methods on the families' other networks, trained on the same data: T, whose dropout masks were
#: trained to identify the task (``fit(mask_training="task")``; one for the arm families, one for
#: the pendulum), with no adaptation, gradient descent, SMCD, the Bayesian last layer or SMCD with a
#: Bayesian readout, and
#: R, the pendulum's network trained by Reptile, with gradient descent.
OTHER_NETWORK_METHODS = ("T+N", "T+G", "T+S", "T+L", "T+SL", "R+G")
#: The methods tuned again under ``--budget-ms`` per observation (the budgeted view).
BUDGETED = ("G", "S", "C")
#: The regimes besides ``T=<t>``: a switch to a new task, the switch back, one corrupted
#: observation in the burn-in, and a measurement only every n-th step (:data:`SEQUENTIAL` families).
OTHER_REGIMES = ("switch: new task", "switch: back", "outlier", "every n-th")
#: The regimes at the default ``--burn-in``.
REGIMES = ("T=1", "T=3", "T=10", "T=30", *OTHER_REGIMES)


def regime_names(burn_in: tuple[int, ...], family: str = "pendulum") -> tuple[str, ...]:
    """The regimes' names in table order for these burn-in lengths and this family (default: every regime)."""
    other = OTHER_REGIMES if family in SEQUENTIAL else OTHER_REGIMES[:-1]
    return (*(f"T={t}" for t in burn_in), *other)


@dataclass
class RegimesConfig(TwoLinkFamilyConfig):
    """Settings of ``smcd-rl regimes``; the defaults finish in about 8 minutes on an idle 2-core CPU.

    Example:
        >>> RegimesConfig(families=("pendulum",)).switch_steps
        10
    """

    out: str = setting("runs/regimes", "output directory (results, plots, report, trained models)")
    families: tuple[str, ...] = setting(FAMILIES, "task families to run", choices=FAMILIES)
    methods: tuple[str, ...] = setting(
        (*METHODS, *OTHER_NETWORK_METHODS),
        "methods (see the command's page); T+ ones on each family's task-mask network, R+ ones on the pendulum only",
        choices=(*METHODS, *OTHER_NETWORK_METHODS),
    )
    hidden: int = setting(256, "width of each hidden layer of both networks", low=1)
    trials: int = setting(50, "test tasks per family (every method sees the same ones)", low=2)
    tuning_episodes: int = setting(
        20, "held-out episodes of fresh training-distribution tasks every method is tuned on", low=2
    )
    tuning_steps: int = setting(30, "steps per tuning episode", low=2)
    burn_in: tuple[int, ...] = setting((1, 3, 10, 30), "observations T before the error is scored", low=1)
    eval_points: int = setting(10, "noise-free points of the task each error is scored on", low=1)
    switch_steps: int = setting(
        10, "observations after the switch to a new task (and again after switching back)", low=1
    )
    outlier_scale: float = setting(
        20.0, "the corrupted observation's offset, in multiples of the unadapted model's held-out residual", low=0.0
    )
    outlier_burn_in: int = setting(10, "observations of the outlier regime (the corrupted one is the middle)", low=2)
    every: int = setting(5, "every n-th step measured in the 'every n-th' regime", low=2)
    every_steps: int = setting(30, "steps of the 'every n-th' regime (every n-th of them observed)", low=2)
    # Both T networks train every sample through their task's masks: the masks sweep's choice on
    # held-out two-link arms, and `smcd-rl task-masks --family pendulum`'s on held-out pendulums.
    task_share: float = setting(
        1.0,
        "share of the pendulum T network's samples trained through a mask of their pendulum's posterior",
        low=0.0,
        high=1.0,
    )
    arm_task_share: float = setting(
        1.0, "share of the arm T network's samples trained through a mask of their arm's posterior", low=0.0, high=1.0
    )
    pendulum_tasks: int = setting(200, "training pendulums (mass and length draws)", low=1)
    pendulum_episodes: int = setting(10, "random-torque episodes per training pendulum", low=1)
    pendulum_steps: int = setting(20, "steps per training episode of the pendulum", low=2)
    pendulum_noise: float = setting(0.01, "std of the pendulum's observation noise, data and trials", low=0.0)
    full: bool = setting(False, "a larger scale: 1000 arms x 150 episodes, hidden 1024, 200 test tasks")

    NON_EMPTY = ("families", "methods", "burn_in")
    SELECTION = ("methods",)

    def validate(self) -> None:
        """The declared bounds, then the steps a regime needs."""
        super().validate()
        if self.every > self.every_steps:
            raise ValueError(f"--every {self.every} exceeds --every-steps {self.every_steps}; observe at least twice")


#: What ``--full`` changes (options given explicitly still win).
FULL = {**FAMILY_FULL, "trials": 200, "pendulum_tasks": 1000}
