"""Gymnasium tasks of smcd-rl, registered on ``import smcd_rl``.

Each task lives in its own module with a docstring card; the pure batched torch functions
(kinematics, dynamics, rewards) sit next to the env so planners and the oracle reuse them.

Example:
    >>> import gymnasium, smcd_rl
    >>> env = gymnasium.make("smcd_rl/TwoLinkArm-v0")
    >>> obs, info = env.reset(seed=0)
"""

from __future__ import annotations

import importlib.util

import gymnasium

#: (id, entry point, max_episode_steps) of every task this package provides.
TASKS: tuple[tuple[str, str, int], ...] = (
    ("smcd_rl/TwoLinkArm-v0", "smcd_rl.envs.two_link_arm:TwoLinkArmEnv", 100),
    ("smcd_rl/CrippledAnt-v0", "smcd_rl.envs.crippled_ant:CrippledAntEnv", 1000),
    ("smcd_rl/PandaReach-v0", "smcd_rl.envs.panda_reach:PandaReachEnv", 200),
    ("smcd_rl/TwoLinkTelescoping-v0", "smcd_rl.envs.two_link_telescoping:TwoLinkTelescopingEnv", 100),
    ("smcd_rl/DroneLanding-v0", "smcd_rl.envs.drone_landing:DroneLandingEnv", 300),
)

#: (id, entry point, max_episode_steps) of the task families on gymnasium-robotics, registered only
#: when it is installed (``pip install -e ".[robotics]"``); see :mod:`smcd_rl.integrations.robotics`.
ROBOTICS_TASKS: tuple[tuple[str, str, int], ...] = (
    ("smcd_rl/FetchReachRotated-v0", "smcd_rl.integrations.robotics:FetchReachRotated", 50),
    ("smcd_rl/FetchPushHeavy-v0", "smcd_rl.integrations.robotics:FetchPushHeavy", 50),
    ("smcd_rl/FrankaReachTool-v0", "smcd_rl.integrations.robotics:FrankaReachTool", 200),
)


def register_all() -> None:
    """Register every task id with gymnasium (idempotent); the robotics families only if gymnasium-robotics is installed."""
    # find_spec locates the package without importing it (nor mujoco).
    robotics = ROBOTICS_TASKS if importlib.util.find_spec("gymnasium_robotics") is not None else ()
    for env_id, entry_point, max_steps in (*TASKS, *robotics):
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, max_episode_steps=max_steps)
