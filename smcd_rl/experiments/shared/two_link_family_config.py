"""The config of the two-link experiments' shared settings (see :mod:`smcd_rl.experiments.shared.two_link_family`).

Example:
    >>> TwoLinkFamilyConfig().hidden, TwoLinkFamilyConfig().oracle_particles
    (512, 1000)
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.adaptation_config import AdaptationConfig, check_mask_groups
from smcd_rl.experiments.shared.config import setting

__all__ = ["TwoLinkFamilyConfig", "FAMILY_FULL"]

#: The paper's scale of the shared data and training, which every two-link command's ``--full``
#: starts from (1000 arms x 150 episodes, hidden 1024, 200 epochs; Reptile trained 1000 epochs
#: against the M model's 200, as the paper remarks), with all CPU threads.
FAMILY_FULL = {
    "tasks": 1000,
    "episodes": 150,
    "hidden": 1024,
    "epochs": 200,
    "batch_size": 64,
    "lr": 1e-4,
    "reptile_epochs": 1000,
    "threads": 0,
}


@dataclass
class TwoLinkFamilyConfig(AdaptationConfig):
    """Settings of the two-link experiments: training arms, the M, R and T networks, the oracle, the strategies."""

    tasks: int = setting(200, "training arms (link-length draws)", low=1)
    episodes: int = setting(50, "motor-babbling episodes per training arm", low=1)
    steps: int = setting(10, "steps per motor-babbling episode", low=2)
    measurement_noise: float = setting(0.01, "std of the end-effector measurement noise (m), data and trials", low=0.0)
    hidden: int = setting(512, "width of each hidden layer (the paper's latent dimension)", low=1)
    depth: int = setting(2, "number of hidden layers", low=1)
    dropout: float = setting(0.5, "dropout probability p used in training", above=0.0, below=1.0)
    epochs: int = setting(20, "training epochs of the multi-task (M) network", low=1)
    batch_size: int = setting(256, "training batch size of the M network", low=1)
    lr: float = setting(1e-3, "Adam learning rate of the M network", above=0.0)
    reptile_epochs: int = setting(20, "Reptile (R) epochs (passes over all tasks)", low=1)
    reptile_batch_size: int = setting(64, "samples per inner SGD step of Reptile", low=1)
    reptile_lr: float = setting(0.1, "Reptile outer (meta) step size", above=0.0)
    reptile_inner_lr: float = setting(0.02, "Reptile inner SGD learning rate (the paper's 0.02)", above=0.0)
    reptile_inner_epochs: int = setting(1, "Reptile inner epochs per task (the paper's 1)", low=1)
    reptile_tasks_per_batch: int = setting(1, "tasks per Reptile meta step", low=1)
    # Every sample through its arm's masks: the masks sweep's choice on held-out two-link arms (0.0051 m2
    # after 10 observations against 0.029 m2 at 0.5), and task-masks' on the telescoping family's.
    task_share: float = setting(
        1.0,
        "share of samples the T network trains through a mask of its task's posterior (the rest random)",
        low=0.0,
        high=1.0,
    )
    mask_groups: int = setting(
        16, "dropout bits per hidden layer of the T network, each for hidden/mask_groups units (0: one per unit)", low=0
    )
    noise_std: float = setting(0.05, "likelihood noise std (m) of SMCD and the oracle", above=0.0)
    oracle_particles: int = setting(1000, "oracle particle count over link lengths", low=1)
    oracle_jitter: float = setting(0.005, "oracle random-walk std of link lengths per step", low=0.0)

    def validate(self) -> None:
        """The declared bounds, then that the T network's mask groups split its layers evenly, if a T method runs."""
        super().validate()
        check_mask_groups(self, any(m.startswith("T+") for m in getattr(self, "methods", ())))
