"""Tests of smcd_rl/CrippledAnt-v0: conformance, determinism, crippling, observation, reward."""

from __future__ import annotations

import doctest
import pickle
import warnings

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.envs.mujoco.ant_v5 import AntEnv
from gymnasium.utils.env_checker import check_env

import smcd_rl.envs.crippled_ant as crippled_ant
from smcd_rl.envs import register_all
from smcd_rl.envs.crippled_ant import (
    LEGS,
    OBS_SLICES,
    TEST_LEG,
    TRAIN_LEGS,
    CrippledAntEnv,
    ant_reward,
    ant_termination,
    leg_indices,
)

ENV_ID = "smcd_rl/CrippledAnt-v0"
# A narrower healthy range than Ant-v5's (0.2, 1.0), so that random actions end several episodes
# within a few hundred steps (seeds below checked to do so).
NARROW_Z = (0.3, 0.9)
MODEL_FIELDS = ("geom_size", "geom_pos", "geom_sameframe", "geom_rgba", "actuator_gear")


@pytest.fixture(scope="module", autouse=True)
def _register() -> None:
    register_all()


def rollout(
    env: CrippledAntEnv, seed: int, n_steps: int, options: dict | None = None
) -> tuple[list[np.ndarray], list[np.ndarray], list[dict], list[bool], list[int]]:
    """Random float64 actions from a seeded generator; resets (unseeded) when an episode ends.

    Returns observations before each step, actions, step infos, terminated flags and the legs of
    all episodes; transition ``t`` is ``(obs[t], actions[t], next_obs[t])``, where ``next_obs[t]``
    is ``obs[t + 1]`` unless the episode ended at ``t``; ``infos[t]["next_obs"]`` holds it (and
    ``infos[t]["reward"]`` the reward).
    """
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed, options=options)
    legs = [info["crippled_leg"]]
    observations, actions, infos, terminated_flags = [], [], [], []
    for _ in range(n_steps):
        action = rng.uniform(-1.0, 1.0, size=8)
        next_obs, reward, terminated, _, info = env.step(action)
        observations.append(obs)
        actions.append(action)
        infos.append({**info, "next_obs": next_obs, "reward": reward})
        terminated_flags.append(terminated)
        obs = next_obs
        if terminated:
            obs, info = env.reset(options=options)
            legs.append(info["crippled_leg"])
    return observations, actions, infos, terminated_flags, legs


def test_check_env() -> None:
    env = gymnasium.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps == 1000
    assert env.observation_space.shape == (41,) and env.observation_space.dtype == np.float64
    with warnings.catch_warnings():
        # Unbounded observations are intended (as in Ant-v5).
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum).*")
        # The render check opens every declared mode, "human" included, which needs a display.
        check_env(env.unwrapped, skip_render_check=True)


def test_same_seed_same_rollout() -> None:
    first, second = (
        rollout(gymnasium.make(ENV_ID, healthy_z_range=NARROW_Z).unwrapped, seed=0, n_steps=300) for _ in range(2)
    )
    np.testing.assert_array_equal(np.stack(first[0]), np.stack(second[0]))
    assert first[3] == second[3] and first[4] == second[4]
    assert len(first[4]) > 2  # several episodes, so several leg draws were compared


def test_leg_table_matches_model_names() -> None:
    model = AntEnv().model
    assert leg_indices(model) == LEGS
    for k, leg in enumerate(LEGS):
        assert (leg.hip_joint, leg.ankle_joint) == (f"hip_{k + 1}", f"ankle_{k + 1}")
        for actuator, joint in zip(leg.actuators, (leg.hip_joint, leg.ankle_joint), strict=True):
            assert model.joint(model.actuator_trnid[actuator, 0]).name == joint
        for geom, joint in zip(leg.geoms, (leg.hip_joint, leg.ankle_joint), strict=True):
            assert model.geom_bodyid[geom] == model.joint(joint).bodyid
    assert [leg.actuators for leg in LEGS] == [(2, 3), (4, 5), (6, 7), (0, 1)]
    assert [leg.geoms for leg in LEGS] == [(3, 4), (6, 7), (9, 10), (12, 13)]
    assert TRAIN_LEGS == (0, 1, 2) and TEST_LEG == 3


@pytest.mark.parametrize("leg", range(4))
def test_crippled_leg_has_no_joint_torque(leg: int) -> None:
    env = CrippledAntEnv()
    env.reset(seed=0, options={"crippled_leg": leg})
    model, data = env.model, env.data
    for _ in range(5):
        env.step(np.full(8, 0.5))
    for k, other in enumerate(LEGS):
        dofs = [model.jnt_dofadr[model.joint(j).id] for j in (other.hip_joint, other.ankle_joint)]
        torques = data.qfrc_actuator[dofs]
        if k == leg:
            np.testing.assert_array_equal(torques, 0.0)
        else:
            np.testing.assert_allclose(torques, 75.0)  # gear 150 * control 0.5


@pytest.mark.parametrize("leg", range(4))
def test_crippling_changes_only_the_leg_and_is_undone_on_reset(leg: int) -> None:
    fresh = AntEnv().model
    env = CrippledAntEnv()
    env.reset(seed=1, options={"crippled_leg": (leg + 1) % 4})  # another leg first: must be undone
    env.reset(options={"crippled_leg": leg})
    thigh, shin = LEGS[leg].geoms
    expected = {name: getattr(fresh, name).copy() for name in MODEL_FIELDS}
    expected["geom_size"][[thigh, shin], 0:2] /= 2
    expected["geom_pos"][shin] = fresh.geom_pos[thigh]
    expected["geom_sameframe"][shin] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE
    expected["geom_rgba"][[thigh, shin], 0:3] = (1.0, 0.0, 0.0)
    expected["actuator_gear"][list(LEGS[leg].actuators)] = 0.0
    for name in MODEL_FIELDS:
        np.testing.assert_array_equal(getattr(env.model, name), expected[name], err_msg=name)
    assert np.all(env.model.geom_size[[thigh, shin], 0:2] < fresh.geom_size[[thigh, shin], 0:2])

    for _ in range(20):
        env.step(env.action_space.sample())
    _, info = env.reset(options={"crippled_leg": None})
    assert info["crippled_leg"] == -1 and env.crippled_leg is None
    for name in MODEL_FIELDS:
        np.testing.assert_array_equal(getattr(env.model, name), getattr(fresh, name), err_msg=name)


def test_shrunken_shin_still_starts_at_the_knee() -> None:
    # Reading of "move the shin geom to the thigh geom's position": geom_pos is in the parent
    # body's frame and both capsules point the same way, so the half-length shin spans from the
    # knee to the pristine shin's middle.
    env = CrippledAntEnv()
    env.reset(seed=2, options={"crippled_leg": 0})
    model, data = env.model, env.data
    _, shin = LEGS[0].geoms
    axis = data.geom_xmat[shin].reshape(3, 3)[:, 2]
    ends = data.geom_xpos[shin] + np.outer((-1.0, 1.0), model.geom_size[shin, 1] * axis)
    knee = data.xanchor[model.joint(LEGS[0].ankle_joint).id]
    assert np.min(np.linalg.norm(ends - knee, axis=1)) < 1e-12


def test_legs_drawn_only_from_the_given_set() -> None:
    env = CrippledAntEnv(crippled_legs=(TEST_LEG,))
    assert {env.reset(seed=s)[1]["crippled_leg"] for s in range(20)} == {3}

    env = CrippledAntEnv(crippled_legs=TRAIN_LEGS)
    env.reset(seed=0)
    draws = [env.reset()[1]["crippled_leg"] for _ in range(200)]
    # Missing one of three legs in 200 uniform draws has probability < 3 * (2/3) ** 200.
    assert set(draws) == {0, 1, 2}
    assert env.reset(options={"crippled_leg": TEST_LEG})[1]["crippled_leg"] == 3

    for healthy in (None, ()):
        env = CrippledAntEnv(crippled_legs=healthy)
        assert {env.reset(seed=s)[1]["crippled_leg"] for s in range(5)} == {-1}
        assert env.reset(options={"crippled_leg": 2})[1]["crippled_leg"] == 2


def test_initial_state_does_not_depend_on_the_leg() -> None:
    env = CrippledAntEnv()
    healthy, _ = env.reset(seed=4, options={"crippled_leg": None})
    crippled, _ = env.reset(seed=4, options={"crippled_leg": 2})
    drawn, _ = env.reset(seed=4)
    np.testing.assert_array_equal(healthy, crippled)
    np.testing.assert_array_equal(healthy, drawn)


def test_observation_layout() -> None:
    env = CrippledAntEnv()
    obs, _ = env.reset(seed=3)
    data, torso = env.data, env.model.body("torso").id
    for _ in range(10):
        assert obs.shape == (41,) and obs.dtype == np.float64 and obs in env.observation_space
        np.testing.assert_array_equal(obs[OBS_SLICES["qpos"]], data.qpos)
        np.testing.assert_array_equal(obs[OBS_SLICES["qvel"]], data.qvel)
        np.testing.assert_array_equal(obs[OBS_SLICES["torso_xmat"]], data.xmat[torso])
        np.testing.assert_array_equal(obs[OBS_SLICES["torso_subtree_com"]], data.subtree_com[torso])
        # The kinematics belong to the state in qpos (mj_forward after stepping), not a lagged one.
        xmat = np.empty(9)
        mujoco.mju_quat2Mat(xmat, obs[3:7] / np.linalg.norm(obs[3:7]))  # qpos quat is unnormalised
        np.testing.assert_allclose(obs[29:38], xmat, atol=1e-12)
        obs, *_ = env.step(env.action_space.sample())


def test_healthy_ant_moves_like_ant_v5() -> None:
    ours = CrippledAntEnv(crippled_legs=None)
    ant = AntEnv(include_cfrc_ext_in_observation=False, exclude_current_positions_from_observation=False)
    ours.reset(seed=5)
    ant.reset(seed=5)
    rng = np.random.default_rng(5)
    for _ in range(30):
        action = rng.uniform(-1.0, 1.0, size=8)
        _, _, _, _, info_ours = ours.step(action)
        _, _, _, _, info_ant = ant.step(action)
        np.testing.assert_array_equal(ours.data.qpos, ant.data.qpos)
        np.testing.assert_array_equal(ours.data.qvel, ant.data.qvel)
        assert info_ours["reward_ctrl"] == info_ant["reward_ctrl"]
        assert info_ours["reward_survive"] == info_ant["reward_survive"]


@pytest.mark.parametrize("contact_cost_weight", [5e-4, 0.0])
def test_planner_reward_and_termination_match_the_env(contact_cost_weight: float) -> None:
    env = CrippledAntEnv(contact_cost_weight=contact_cost_weight, healthy_z_range=NARROW_Z)
    observations, actions, infos, terminated, _ = rollout(env, seed=0, n_steps=300)
    assert any(terminated) and not all(terminated)  # both outcomes are compared
    obs = torch.from_numpy(np.stack(observations))
    action = torch.from_numpy(np.stack(actions))
    next_obs = torch.from_numpy(np.stack([info["next_obs"] for info in infos]))

    expected = np.array([info["reward_forward"] + info["reward_survive"] + info["reward_ctrl"] for info in infos])
    reward = ant_reward(obs, action, next_obs, dt=env.dt, healthy_z_range=NARROW_Z)
    assert reward.shape == (300,) and reward.dtype == torch.float64
    np.testing.assert_allclose(reward.numpy(), expected, rtol=0, atol=1e-9)
    contact = np.array([info["reward_contact"] for info in infos])
    if contact_cost_weight == 0.0:
        np.testing.assert_array_equal(contact, 0.0)
    else:
        assert np.all(contact <= 0.0) and np.any(contact < 0.0)  # zero while airborne
    total = np.array([info["reward"] for info in infos])
    np.testing.assert_allclose(total, expected + contact, rtol=0, atol=1e-12)

    done = ant_termination(next_obs, healthy_z_range=NARROW_Z)
    assert done.dtype == torch.bool
    assert done.tolist() == terminated


def test_ant_termination_edges() -> None:
    obs = torch.zeros(5, 41, dtype=torch.float64)
    obs[:, 2] = torch.tensor([0.2, 1.0, 0.55, 0.55, 1.001])
    obs[2, 20] = float("inf")
    obs[3, 40] = float("nan")
    assert ant_termination(obs).tolist() == [False, False, True, True, True]
    assert ant_termination(obs[0], healthy_z_range=(0.3, 1.0)).item() is True


def test_pickle_round_trip() -> None:
    env = CrippledAntEnv(crippled_legs=(1, 3), ctrl_cost_weight=0.25)
    clone = pickle.loads(pickle.dumps(env))
    assert isinstance(clone, CrippledAntEnv) and clone.crippled_legs == (1, 3)
    assert clone._ctrl_cost_weight == 0.25
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        obs_clone, info_clone = clone.reset(seed=seed)
        np.testing.assert_array_equal(obs, obs_clone)
        assert info["crippled_leg"] == info_clone["crippled_leg"]


@pytest.mark.parametrize("leg", [4, -1, 1.0, True, "0"])
def test_invalid_leg_option_raises(leg: object) -> None:
    env = CrippledAntEnv()
    with pytest.raises(ValueError, match=r"\(0, 1, 2, 3\)"):
        env.reset(seed=0, options={"crippled_leg": leg})


def test_invalid_arguments_raise() -> None:
    env = CrippledAntEnv()
    with pytest.raises(ValueError, match="crippled_leg"):
        env.reset(options={"cripled_leg": 1})
    with pytest.raises(ValueError, match=r"\(0, 1, 2, 3\)"):
        CrippledAntEnv(crippled_legs=(0, 5))
    with pytest.raises(TypeError, match="include_cfrc_ext_in_observation"):
        CrippledAntEnv(include_cfrc_ext_in_observation=True)


def test_docstring_examples_run() -> None:
    result = doctest.testmod(crippled_ant, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
