"""The config of ``smcd-rl panda`` (:mod:`smcd_rl.experiments.panda.run`): its settings, ``--full`` preset and methods.

Example:
    >>> config = PandaConfig()
    >>> config.tasks * config.seeds, config.intervals, FULL["seeds"]
    (300, (1, 2, 5, 10, 20), 5)
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.adaptation_config import TASK_VARIANTS, VARIANTS, AdaptationConfig, check_mask_groups
from smcd_rl.experiments.shared.config import setting

__all__ = [
    "PandaConfig",
    "FULL",
    "METHODS",
    "DEFAULT_METHODS",
    "DEFAULT_INTERVALS",
    "DEFAULT_DT",
    "GOAL_TOLERANCE",
    "MAX_EPISODE_STEPS",
    "TOOL_RANGE",
]

# The defaults of --dt, --tolerance, --steps and --tool-range: those of smcd_rl.envs.panda_reach
# (which imports torch), repeated here so that --help does not; tests/test_cli.py checks that they agree.
#: The tool extends the end effector by ``l ~ U(-TOOL_RANGE, TOOL_RANGE)`` m along the flange axis.
TOOL_RANGE: float = 0.5
#: Control period (s): ``q_dot += dt * u; q += dt * q_dot``.
DEFAULT_DT: float = 0.05
#: A goal is reached within this distance (m) ...
GOAL_TOLERANCE: float = 0.05
#: ... in at most this many control steps.
MAX_EPISODE_STEPS: int = 200

#: The measurement intervals n run by default.
DEFAULT_INTERVALS = (1, 2, 5, 10, 20)

#: Methods that this command runs: Fig. 3's N none, G tuned GD, S SMCD tuned by one-step error,
#: S(evidence) SMCD calibrated by its evidence, S(paper) SMCD at the paper's settings, C the
#: combination of N and the tuned ones; L the Bayesian last layer and SL SMCD with a Bayesian
#: readout.
METHODS = ("FK", *(f"M+{variant}" for variant in VARIANTS), *(f"T+{variant}" for variant in TASK_VARIANTS))
#: What runs by default: every method.
DEFAULT_METHODS = METHODS

# Power (the default trial count). The methods run on the same arms, so a verdict such as M+S
# against M+G is a paired comparison of binary outcomes: only the discordant arms (one method
# reaches, the other does not) carry information, and the SE of the success-rate difference d over
# n arms is about sqrt((discordant share - d^2) / n). Detecting d = 0.1 at the 5 % level with 80 %
# power needs (1.96 + 0.84) SE <= 0.1, i.e. SE <= 0.036, so n >= (discordant share - 0.01) / 0.036^2:
# 110 arms at 15 % discordant (M+S vs M+G at n = 20 in a 100-arm run), 180 at 23 % (M+S vs M+N),
# 230 at 30 %, 300 at 40 %. 3 seeds x 100 tasks = 300 arms covers up to 40 % discordant (power 0.9
# at 30 %); the old 3 x 50 = 150 arms gave SE 0.044 at 30 % (power 0.6).
# Time (1 thread, 2 shared cores), measured on 1 seed x 100 arms at n = 1 and 20 with 100
# particles: M+S 8 s and M+S(paper) 16 s at n = 1 (SMCD's cost is its observations, ~1/n of that at
# n > 1), M+G 35 s at n = 1 and 13 s at n = 20 (its per-arm weights cost at every control step),
# FK and M+N under 1 s. Over n in {1, 2, 5, 10, 20} that is ~150 s per seed, so those five methods
# take ~8-9 min with training (20 s) and tuning (25 s, before smcd_rl.tune). Estimated, not measured:
# M+S(evidence) costs about what M+S does (~15 s per seed) and M+C about M+G and M+S together (it
# runs both; ~115 s per seed), so the seven default methods take ~280 s per seed, ~15 min in all.
# 300 particles would triple SMCD's share, so the default is 100 (the paper's smaller count; --full
# uses 1000).


@dataclass
class PandaConfig(AdaptationConfig):
    """Settings of ``smcd-rl panda``; the defaults finish in about 15 minutes on 2 CPU cores (estimated).

    SMCD and gradient descent follow the fair protocol (:mod:`smcd_rl.experiments.shared.tuning`): on
    ``--tuning-episodes`` held-out episodes of fresh training-distribution tools, ``M+S`` is SMCD
    tuned by one-step error, ``M+G`` gradient descent tuned by it too (``--gd-lr x --gd-steps x
    --gd-window``, extended past an edge) and ``M+C`` the combination of N, G and S; ``M+S(evidence)``
    is SMCD calibrated by its evidence and ``M+S(paper)`` SMCD at ``--noise-std`` and ``--flip-prob``.
    """

    out: str = setting("runs/panda", "output directory (results, plot, report, trained model)")
    samples: int = setting(50_000, "training samples (joint angles, end effector) with random tools", low=1)
    hidden: int = setting(256, "width of each hidden layer", low=1)
    depth: int = setting(3, "number of hidden layers", low=1)
    dropout: float = setting(0.5, "dropout probability p used in training", above=0.0, below=1.0)
    epochs: int = setting(30, "training epochs", low=1)
    batch_size: int = setting(256, "training batch size", low=1)
    lr: float = setting(1e-3, "Adam learning rate", above=0.0)
    tasks: int = setting(100, "test reaching tasks per seed (all run at once as one batch)", low=1)
    seeds: int = setting(3, "seeds (each draws its own test tasks and filter noise)", low=1)
    intervals: tuple[int, ...] = setting(
        DEFAULT_INTERVALS, "measurement intervals n: a measurement every n-th step (1: every step)", low=1
    )
    steps: int = setting(MAX_EPISODE_STEPS, "control steps per task: success is reaching the goal within them", low=1)
    methods: tuple[str, ...] = setting(
        DEFAULT_METHODS,
        "methods to run: FK (chain without the tool); M (the network) + N (none), G (GD, tuned), S (SMCD tuned "
        "by one-step error), S(evidence) (SMCD calibrated by its evidence), S(paper) (SMCD at --noise-std and "
        "--flip-prob), C (the combination of N and the tuned ones), L (Bayesian last layer) or SL (SMCD with a "
        "Bayesian readout); T (masks trained to identify the tool) + S or SL",
        choices=METHODS,
    )
    task_tools: int = setting(
        500, "tools of T's training data, --samples / --task-tools samples each (T's masks learn to identify it)", low=1
    )
    # Every sample through its tool's masks, 16 bits a layer: `smcd-rl task-masks --family panda`
    # found none significantly better on held-out tools (8 groups: within its interval).
    task_share: float = setting(
        1.0, "share of T's samples trained through a mask of their tool's posterior", low=0.0, high=1.0
    )
    mask_groups: int = setting(16, "dropout bits per hidden layer of T (0: one per unit)", low=0)
    particles: int = setting(100, "SMCD mask particles (every SMCD method, M+C's too, and the tuning)", low=1)
    flip_prob: float = setting(
        0.05, "bit-flip probability per step of M+S(paper), SMCD at the paper's settings", low=0.0, high=1.0
    )
    noise_std: float = setting(0.02, "likelihood noise std (m) of M+S(paper), SMCD at the paper's settings", above=0.0)
    tuning_steps: int = setting(
        20, "measurements per tuning episode (evenly spaced along a reach of a fresh tool and goal)", low=2
    )
    gd_max_steps: int = setting(
        10,
        "most gradient steps per observation tuning may extend GD's grid to: 40 took 177 ms per observation on "
        "one thread, over three control periods; every method must fit the step it adapts in",
        low=1,
    )
    k1: float = setting(20.0, "PD gain on the end-effector error", low=0.0)
    k2: float = setting(5.0, "PD gain on the joint velocity", low=0.0)
    dt: float = setting(DEFAULT_DT, "control period (s)", above=0.0)
    tolerance: float = setting(GOAL_TOLERANCE, "success distance (m)", above=0.0)
    tool_range: float = setting(TOOL_RANGE, "tools are drawn from U(-tool_range, tool_range) (m)", low=0.0)
    measurement_noise: float = setting(
        0.0, "std of the end-effector measurement noise (m), test and tuning episodes", low=0.0
    )
    full: bool = setting(False, "the paper's scale: 3 x 1024 network, 100000 samples, 100 tasks x 5 seeds")

    NON_EMPTY = ("intervals", "methods")
    #: The controller differentiates the adapted kinematics at every control step, not only at
    #: measurements: the MMSE mask's prediction only (the posterior predictive mean would cost a
    #: forward and backward pass per particle each).
    SMCD_PREDICTIONS = ("mask",)
    # Which (method, n) runs there are; a run's name says its method and n.
    SELECTION = ("methods", "intervals")

    def validate(self) -> None:
        """The declared bounds, then those across options: the GD grid within its step limit, T's mask groups."""
        super().validate()
        check_mask_groups(self, any(m.startswith("T+") for m in self.methods))
        if max(self.gd_steps) > self.gd_max_steps:
            raise ValueError(
                f"--gd-steps {max(self.gd_steps)} is above --gd-max-steps {self.gd_max_steps}; lower it or raise "
                "--gd-max-steps"
            )


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "samples": 100_000,
    "hidden": 1024,
    "epochs": 100,
    "batch_size": 64,
    "lr": 1e-4,
    "tasks": 100,
    "seeds": 5,
    "particles": 1000,
    "threads": 0,
}
