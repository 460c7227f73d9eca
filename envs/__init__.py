"""Gymnasium tasks of smcd-rl, registered on ``import smcd_rl``.

Each task lives in its own module with a docstring card; the pure batched torch functions
(kinematics, dynamics, rewards) sit next to the env so planners and the oracle reuse them.

Example:
    >>> import gymnasium, smcd_rl
    >>> env = gymnasium.make("smcd_rl/TwoLinkArm-v0")
    >>> obs, info = env.reset(seed=0)
"""

from __future__ import annotations

import gymnasium

#: (id, entry point, max_episode_steps) of every task this package provides.
TASKS: tuple[tuple[str, str, int], ...] = (
    ("smcd_rl/TwoLinkArm-v0", "smcd_rl.envs.two_link_arm:TwoLinkArmEnv", 100),
    ("smcd_rl/CrippledAnt-v0", "smcd_rl.envs.crippled_ant:CrippledAntEnv", 1000),
    ("smcd_rl/PandaReach-v0", "smcd_rl.envs.panda_reach:PandaReachEnv", 200),
    ("smcd_rl/TwoLinkTelescoping-v0", "smcd_rl.envs.two_link_telescoping:TwoLinkTelescopingEnv", 100),
    ("smcd_rl/DroneLanding-v0", "smcd_rl.envs.drone_landing:DroneLandingEnv", 300),
    ("smcd_rl/PendulumFamily-v0", "smcd_rl.envs.pendulum_family:PendulumFamilyEnv", 200),
)

#: (id, entry point, max_episode_steps) of the task families on gymnasium-robotics; see
#: :mod:`smcd_rl.integrations.robotics`. Registered always: without gymnasium-robotics, making one
#: raises a ModuleNotFoundError that names the extra (``pip install -e ".[robotics]"``).
ROBOTICS_TASKS: tuple[tuple[str, str, int], ...] = (
    ("smcd_rl/FetchReachRotated-v0", "smcd_rl.integrations.robotics:FetchReachRotated", 50),
    ("smcd_rl/FetchPushHeavy-v0", "smcd_rl.integrations.robotics:FetchPushHeavy", 50),
    ("smcd_rl/FrankaReachTool-v0", "smcd_rl.integrations.robotics:FrankaReachTool", 200),
)


def register_all() -> None:
    """Register every task id with gymnasium (idempotent), importing none of the tasks' modules.

    A task whose extra is not installed (``[mujoco]`` for CrippledAnt, ``[robotics]`` for the
    Fetch and Franka families) is registered too; ``gymnasium.make`` of it raises a
    ``ModuleNotFoundError`` that names the extra and the command that installs it.
    """
    for env_id, entry_point, max_steps in (*TASKS, *ROBOTICS_TASKS):
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, max_episode_steps=max_steps)
