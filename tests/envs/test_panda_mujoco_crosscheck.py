"""Our modified-DH Panda (``panda_fk``) against the MuJoCo Franka that gymnasium-robotics ships.

The MuJoCo Panda is the arm of FrankaKitchen (``kitchen_franka/franka_assets/chain.xml``, mounted
by ``kitchen_assets/kitchen_env_model.xml``). With the DH angle of joint 6 equal to the MJCF angle
plus pi/2, the base at (0, 0, 1.8) turned 1.57 rad about z, and the ``end_effector`` site 0.210 m
along link 7 (a tool of 0.210 - 0.107 m beyond the DH flange), both chains put the end effector at
the same place to within 0.4 mm: the XML writes pi/2 as 1.57 in the base and in two link frames.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
mujoco = pytest.importorskip("mujoco")

from smcd_rl.envs.panda_reach import FLANGE_LENGTH, JOINT_LOWER, JOINT_UPPER, panda_fk  # noqa: E402

KITCHEN = os.path.join(
    os.path.dirname(gymnasium_robotics.__file__), "envs", "assets", "kitchen_franka", "kitchen_assets"
)
JOINT_6_OFFSET = np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2, 0.0])  # DH angle - MJCF angle
BASE_POSITION = np.array([0.0, 0.0, 1.8])
BASE_YAW = 1.57  # as the XML writes it
SITE_ALONG_LINK_7 = 0.210
# Measured over these 200 poses: 0.23 mm mean, 0.38 mm max.
MEAN_TOLERANCE, MAX_TOLERANCE = 0.3e-3, 0.5e-3


@pytest.fixture(scope="module")
def kitchen() -> tuple[object, object]:
    model = mujoco.MjModel.from_xml_path(os.path.join(KITCHEN, "kitchen_env_model.xml"))
    return model, mujoco.MjData(model)


def arm_qpos(model: object) -> list[int]:
    return [int(model.jnt_qposadr[model.joint(f"robot:panda0_joint{k}").id]) for k in range(1, 8)]


def random_poses(model: object, n: int = 200) -> np.ndarray:
    """MJCF joint angles, uniform within both the MJCF and the DH limits."""
    ranges = np.array([model.jnt_range[model.joint(f"robot:panda0_joint{k}").id] for k in range(1, 8)])
    low = np.maximum(ranges[:, 0], np.array(JOINT_LOWER) - JOINT_6_OFFSET)
    high = np.minimum(ranges[:, 1], np.array(JOINT_UPPER) - JOINT_6_OFFSET)
    return np.random.default_rng(0).uniform(low, high, size=(n, 7))


def mujoco_end_effector(model: object, data: object, poses: np.ndarray) -> np.ndarray:
    site, qpos = model.site("end_effector").id, arm_qpos(model)
    out = []
    for q in poses:
        data.qpos[qpos] = q
        mujoco.mj_kinematics(model, data)
        out.append(data.site_xpos[site].copy())
    return np.array(out)


def dh_end_effector(poses: np.ndarray, joint_6_offset: float = np.pi / 2, yaw: float = BASE_YAW) -> np.ndarray:
    q = torch.from_numpy(poses + np.eye(7)[5] * joint_6_offset)
    base = panda_fk(q, SITE_ALONG_LINK_7 - FLANGE_LENGTH).numpy()
    c, s = np.cos(yaw), np.sin(yaw)
    return base @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + BASE_POSITION


def test_the_kitchen_mounts_the_arm_as_stated(kitchen: tuple[object, object]) -> None:
    model, data = kitchen
    assert arm_qpos(model) == list(range(7))
    mujoco.mj_kinematics(model, data)
    base = model.body("panda0_link0").id
    np.testing.assert_allclose(data.xpos[base], BASE_POSITION, atol=1e-12)
    np.testing.assert_allclose(data.xquat[base], [np.cos(BASE_YAW / 2), 0.0, 0.0, np.sin(BASE_YAW / 2)], atol=1e-12)
    np.testing.assert_allclose(model.site("end_effector").pos, [0.0, 0.0, SITE_ALONG_LINK_7])
    assert model.site_bodyid[model.site("end_effector").id] == model.body("panda0_link7").id


def test_dh_chain_matches_mujoco_at_200_random_poses(kitchen: tuple[object, object]) -> None:
    model, data = kitchen
    poses = random_poses(model)
    error = np.linalg.norm(dh_end_effector(poses) - mujoco_end_effector(model, data, poses), axis=1)
    assert error.mean() < MEAN_TOLERANCE and error.max() < MAX_TOLERANCE, (error.mean(), error.max())


def test_the_joint_6_offset_and_the_base_yaw_are_needed(kitchen: tuple[object, object]) -> None:
    model, data = kitchen
    poses = random_poses(model, 50)
    reference = mujoco_end_effector(model, data, poses)
    no_offset = np.linalg.norm(dh_end_effector(poses, joint_6_offset=0.0) - reference, axis=1)
    no_yaw = np.linalg.norm(dh_end_effector(poses, yaw=0.0) - reference, axis=1)
    assert no_offset.mean() > 0.05 and no_yaw.mean() > 0.05  # centimetres off, not a fraction of a mm


def test_the_reaching_family_mounts_the_same_arm(kitchen: tuple[object, object]) -> None:
    from smcd_rl.integrations.robotics import FrankaReachEnv

    model, data = kitchen
    env = FrankaReachEnv()
    poses = random_poses(model, 20)
    np.testing.assert_allclose(
        mujoco_end_effector(env.model, mujoco.MjData(env.model), poses),
        mujoco_end_effector(model, data, poses),
        atol=1e-12,
    )
