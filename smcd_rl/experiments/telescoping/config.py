"""The config of ``smcd-rl telescoping`` (:mod:`smcd_rl.experiments.telescoping.run`): its settings, ``--full`` preset and methods.

Example:
    >>> TelescopingConfig().dt, FULL["trials"], METHODS[0]
    (0.1, 1000, 'true')
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from smcd_rl.experiments.shared.adaptation_config import TASK_VARIANTS, VARIANTS
from smcd_rl.experiments.shared.config import setting
from smcd_rl.experiments.shared.two_link_family_config import FAMILY_FULL, TwoLinkFamilyConfig

__all__ = ["TelescopingConfig", "FULL", "METHODS", "DEFAULT_METHODS", "TELESCOPING_DT", "TARGET_ANGULAR_SPEED"]

# The defaults of --dt and --angular-speed: those of smcd_rl.envs.two_link_telescoping (which imports
# torch), repeated here so that --help does not; tests/test_cli.py checks that they agree.
#: Step size in seconds of the joint double integrator (100 steps = 10 s).
TELESCOPING_DT: float = 0.1
#: Target speed around the circle in rad/s: half a revolution in a 100-step episode at ``TELESCOPING_DT``.
TARGET_ANGULAR_SPEED: float = math.pi / (100 * TELESCOPING_DT)

#: Fig. 8's methods, plus "true": the PD law with the true telescoping kinematics (the floor
#: that the controller's lag behind the moving target and link sets for every method). On each
#: network: N none, G tuned GD, S SMCD tuned by one-step error, S(evidence) SMCD calibrated by its
#: evidence, S(paper) SMCD at the paper's settings, C the combination of N and the tuned ones, L
#: the Bayesian last layer, SL SMCD with a Bayesian readout. T is the network whose masks were
#: trained to identify the arm (``fit(mask_training="task")``).
METHODS = (
    "true",
    "O+P",
    *(f"{network}+{variant}" for network in ("M", "R") for variant in VARIANTS),
    *(f"T+{variant}" for variant in TASK_VARIANTS),
)
#: What runs by default: Fig. 8's methods, T's, and the last layers on every network (R+S(paper)
#: only on request: the R network's comparison is R+S against R+G).
DEFAULT_METHODS = tuple(m for m in METHODS if m != "R+S(paper)")


@dataclass
class TelescopingConfig(TwoLinkFamilyConfig):
    """Settings of ``smcd-rl telescoping``; the defaults finish in minutes on 2 CPU cores.

    Example:
        >>> config = TelescopingConfig(trials=10, feedback="measured")
        >>> config.horizon, config.k1, config.k2, config.methods[:2]
        (100, 20.0, 5.0, ('true', 'O+P'))
    """

    out: str = setting("runs/telescoping", "output directory (results, plot, report, trained models)")
    model: str = setting(
        "",
        "use this trained M model (e.g. runs/two-link/model.pt) instead of training one; --hidden etc. then shape R only",
    )
    hidden: int = setting(
        256, "width of each hidden layer (the paper's latent dimension; 256 keeps the default run short)", low=1
    )
    reptile_tasks_per_batch: int = setting(5, "tasks per Reptile meta step", low=1)
    # `smcd-rl task-masks --family telescoping` (held-out training arms, never the test episodes): 32
    # bits a layer, with every sample through its arm's masks, predicted best one step ahead.
    mask_groups: int = setting(
        32, "dropout bits per hidden layer of the T network, each for hidden/mask_groups units (0: one per unit)", low=0
    )
    trials: int = setting(100, "tracking episodes per method (all run as one batch)", low=2)
    horizon: int = setting(100, "steps per tracking episode (the paper's 100)", low=1)
    dt: float = setting(TELESCOPING_DT, "step (s) of the joint double integrator", above=0.0)
    angular_speed: float = setting(TARGET_ANGULAR_SPEED, "target speed around its circle (rad/s)")
    k1: float = setting(20.0, "PD gain on the end-effector error (paper: 20)", low=0.0)
    k2: float = setting(5.0, "PD gain on the joint velocity (paper: 5)", low=0.0)
    damping: float = setting(0.0, "damped least-squares lambda of J^+ (0: the paper's Moore-Penrose inverse)", low=0.0)
    max_acceleration: float = setting(100.0, "joint acceleration bound (rad/s^2), as in the env", above=0.0)
    feedback: str = setting(
        "predicted",
        "x in the PD law: 'measured' end effector or the method's 'predicted' one",
        choices=("predicted", "measured"),
    )
    report_steps: tuple[int, ...] = setting((10, 25, 50, 100), "steps k whose mean error the table shows", low=0)
    methods: tuple[str, ...] = setting(
        DEFAULT_METHODS,
        "methods: true, O+P (oracle PF); M or R + N, G (tuned GD), S (SMCD tuned by one-step error), S(evidence) "
        "(SMCD calibrated by its evidence), S(paper), C (the combination of N and the tuned ones), L (Bayesian "
        "last layer) or SL (SMCD with a Bayesian readout); T (masks trained to identify the arm) + N, G, S, L "
        "or SL",
        choices=METHODS,
    )
    full: bool = setting(False, "the paper's scale: 1000 tasks x 150 episodes, hidden 1024, 1000 trials")

    NON_EMPTY = ("report_steps", "methods")
    #: The controller differentiates the adapted kinematics at every control step, not only at
    #: measurements: the MMSE mask's prediction only (the posterior predictive mean would cost a
    #: forward and backward pass per particle each).
    SMCD_PREDICTIONS = ("mask",)
    # Which methods run, which steps the table shows, and the path of --model (the loaded model's
    # digest keys the M methods instead).
    SELECTION = ("methods", "report_steps", "model")

    def validate(self) -> None:
        """The declared bounds, then what they cannot say: report steps within the episode, an existing --model."""
        super().validate()
        beyond = [k for k in self.report_steps if k > self.horizon]
        if beyond:
            raise ValueError(
                f"--report-steps {beyond} lie beyond --horizon {self.horizon}; pass steps within 0..{self.horizon}"
            )
        if self.model and not Path(self.model).is_file():
            raise FileNotFoundError(
                f"--model {self.model}: no such file; train one with `smcd-rl two-link` or drop --model"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {**FAMILY_FULL, "trials": 1000}
