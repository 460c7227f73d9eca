"""Tests of the Panda reaching task: kinematics by hand, Jacobians, the tool, the env contract, PD reaching."""

from __future__ import annotations

import math
import pickle
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from smcd_rl.agents.pd import JacobianPD, batch_jacobian
from smcd_rl.envs import register_all
from smcd_rl.envs.panda_reach import (
    FLANGE_LENGTH,
    JOINT_LOWER,
    JOINT_UPPER,
    READY_POSE,
    PandaReachEnv,
    integrate_panda,
    joint_limits,
    panda_fk,
    panda_kinematics_data,
    sample_goals,
    sample_joint_configurations,
    sample_tool_lengths,
)
from smcd_rl.experiments.shared.runtime import torch_threads

ENV_ID = "smcd_rl/PandaReach-v0"
F64 = torch.float64


def test_fk_at_the_zero_pose_by_hand() -> None:
    # q = 0, links Rx(alpha) Tx(a) Rz(0) Tz(d) from the DH table:
    #   1: Tz(0.333)                       -> p = (0, 0, 0.333), frame = base
    #   2: Rx(-pi/2)                       -> z along +y
    #   3: Rx(+pi/2) Tz(0.316)             -> frame = base again, p = (0, 0, 0.649)
    #   4: Rx(+pi/2) Tx(0.0825)            -> p = (0.0825, 0, 0.649), z along -y
    #   5: Rx(-pi/2) Tx(-0.0825) Tz(0.384) -> frame = base, p = (0, 0, 1.033)
    #   6: Rx(+pi/2)                       -> z along -y
    #   7: Rx(+pi/2) Tx(0.088)             -> total Rx(pi): z along -z, p = (0.088, 0, 1.033)
    #   flange Tz(0.107) along -z           -> (0.088, 0, 0.926); a tool l moves it to 0.926 - l.
    q = torch.zeros(7, dtype=F64)
    torch.testing.assert_close(panda_fk(q), torch.tensor([0.088, 0.0, 0.926], dtype=F64))
    torch.testing.assert_close(panda_fk(q, 0.3), torch.tensor([0.088, 0.0, 0.626], dtype=F64))


def test_fk_at_the_ready_pose_by_hand() -> None:
    # With q1 = q3 = q5 = 0 the arm stays in the x-z plane and joints 2, 4, 6 turn about +y, -y,
    # -y, so the link directions are Ry(q2), Ry(phi) with phi = q2 - q4, Ry(psi) with psi = phi - q6
    # (Ry(t) x = (cos t, 0, -sin t), Ry(t) z = (sin t, 0, cos t)). Ready pose: q2 = -0.3,
    # q4 = -2.2, q6 = 2.0, so phi = 1.9 and psi = -0.1:
    #   p3 = (0, 0, 0.333) + 0.316 (sin q2, 0, cos q2)          = (-0.093384, 0, 0.634886)
    #   p4 = p3 + 0.0825 (cos q2, 0, -sin q2)                    = (-0.014569, 0, 0.659267)
    #   p5 = p4 - 0.0825 (cos phi, 0, -sin phi)
    #           + 0.384 (sin phi, 0, cos phi)                    = ( 0.375481, 0, 0.613193)
    #   p7 = p5 + 0.088 (cos psi, 0, -sin psi)                   = ( 0.463042, 0, 0.621979)
    #   flange = p7 + 0.107 (-sin psi, 0, -cos psi)              = ( 0.473724, 0, 0.515513)
    # (joint 7 turns about the flange axis and moves nothing).
    q = torch.tensor(READY_POSE, dtype=F64)
    torch.testing.assert_close(panda_fk(q), torch.tensor([0.473724, 0.0, 0.515513], dtype=F64), atol=1e-6, rtol=0)


def test_joint_1_turns_the_whole_arm_about_the_base_z_axis() -> None:
    q = sample_joint_configurations(20, generator=torch.Generator().manual_seed(0)).to(F64)
    turned = q.clone()
    turned[:, 0] += 0.7
    c, s = math.cos(0.7), math.sin(0.7)
    rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    torch.testing.assert_close(panda_fk(turned, 0.2), panda_fk(q, 0.2) @ rz.T)


def test_jacobian_matches_central_finite_differences() -> None:
    generator = torch.Generator().manual_seed(1)
    q = sample_joint_configurations(8, generator=generator).to(F64)
    tools = sample_tool_lengths(8, generator=generator).to(F64)
    jacobian = batch_jacobian(lambda angles: panda_fk(angles, tools), q)
    assert jacobian.shape == (8, 3, 7)
    eps = 1e-6
    for j in range(7):
        step = torch.zeros(7, dtype=F64)
        step[j] = eps
        column = (panda_fk(q + step, tools) - panda_fk(q - step, tools)) / (2 * eps)
        torch.testing.assert_close(jacobian[..., j], column, atol=1e-8, rtol=1e-6)


def test_tool_moves_the_end_effector_along_the_flange_axis_by_exactly_its_length() -> None:
    q = sample_joint_configurations(16, generator=torch.Generator().manual_seed(2)).to(F64)
    flange = panda_fk(q)
    wrist = panda_fk(q, -FLANGE_LENGTH)  # joint 7's frame origin: the flange axis starts here
    axis = (flange - wrist) / FLANGE_LENGTH
    torch.testing.assert_close(axis.norm(dim=-1), torch.ones(16, dtype=F64))
    for tool in (-0.5, -0.2, 0.35):
        moved = panda_fk(q, tool) - flange
        torch.testing.assert_close(moved, tool * axis)
        torch.testing.assert_close(moved.norm(dim=-1), torch.full((16,), abs(tool), dtype=F64))
    spun = q.clone()
    spun[:, 6] += 1.0  # joint 7 spins about the flange axis: the tool tip does not move
    torch.testing.assert_close(panda_fk(spun, 0.4), panda_fk(q, 0.4))


def test_fk_rejects_a_wrong_joint_count() -> None:
    with pytest.raises(ValueError, match=r"\[\.\.\., 7\]"):
        panda_fk(torch.zeros(6))


def test_integrate_respects_acceleration_velocity_and_position_limits() -> None:
    lower, upper = joint_limits(dtype=F64)
    q, q_dot = torch.tensor(READY_POSE, dtype=F64), torch.zeros(7, dtype=F64)
    for _ in range(100):
        q, q_dot = integrate_panda(q, q_dot, torch.full((7,), 1e3, dtype=F64), 0.05)
        assert bool(((q >= lower) & (q <= upper)).all())
        assert bool((q_dot.abs() <= torch.tensor([2.175] * 4 + [2.61] * 3, dtype=F64) + 1e-12).all())
    # Pushed up for 5 s, every joint ends at its upper limit, at rest.
    torch.testing.assert_close(q, upper)
    torch.testing.assert_close(q_dot, torch.zeros(7, dtype=F64))
    # Without limits it is the plain double integrator.
    q, q_dot = integrate_panda(torch.zeros(7), torch.ones(7), torch.full((7,), 100.0), 0.1, limits=False)
    torch.testing.assert_close(q_dot, torch.full((7,), 11.0))
    torch.testing.assert_close(q, torch.full((7,), 1.1))


def test_goals_and_training_data_are_the_chain_at_configurations_within_the_limits() -> None:
    data = panda_kinematics_data(500, generator=torch.Generator().manual_seed(3))
    lower, upper = joint_limits()
    assert bool(((data["q"] >= lower) & (data["q"] <= upper)).all())
    assert float(data["tool_length"].abs().max()) <= 0.5 and float(data["tool_length"].std()) > 0.2
    torch.testing.assert_close(panda_fk(data["q"], data["tool_length"]), data["ee"])
    same = panda_kinematics_data(500, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(same["ee"], data["ee"])
    goals = sample_goals(torch.zeros(100), generator=torch.Generator().manual_seed(4))
    assert goals.shape == (100, 3) and float(goals.norm(dim=-1).max()) < 1.3
    with pytest.raises(ValueError, match="num_samples"):
        panda_kinematics_data(0)
    with pytest.raises(ValueError, match="tool_range"):
        sample_tool_lengths(3, tool_range=-1.0)


def test_pd_with_the_true_kinematics_reaches_nearly_every_goal() -> None:
    """50 random goals with random tools, the true chain (tool known), a measurement every step.

    Not chance: a 5 cm ball is about 1e-4 of the ~1.2 m workspace, and the arm left at rest
    (zero command) reaches none of the goals, checked below. 95% leaves room for goals near
    singularities (the paper's only failure cause for this controller); measured: 50 of 50.
    """
    generator = torch.Generator().manual_seed(5)
    tools = sample_tool_lengths(50, generator=generator).to(F64)
    goals = sample_goals(tools, generator=generator)
    pd = JacobianPD(lambda q: panda_fk(q, tools), k1=20.0, k2=5.0)
    q = torch.tensor(READY_POSE, dtype=F64).expand(50, 7).clone()
    q_dot = torch.zeros_like(q)
    reached = torch.zeros(50, dtype=torch.bool)
    with torch_threads(1):  # tiny [50, 7] ops: extra threads only wait on each other
        for _ in range(199):  # fewer than 200 steps
            q, q_dot = integrate_panda(q, q_dot, pd(q, q_dot, goals), 0.05)
            reached |= (panda_fk(q, tools) - goals).norm(dim=-1) < 0.05
    assert float(reached.float().mean()) >= 0.95
    at_rest = (panda_fk(torch.tensor(READY_POSE, dtype=F64), tools) - goals).norm(dim=-1) < 0.05
    assert not bool(at_rest.any())


# Warning check_env raises by design: the action box is the Panda's acceleration limits, not [-1, 1].
EXPECTED_CHECK_ENV_WARNINGS = ("symmetric and normalized space",)


@pytest.mark.parametrize("kwargs", [{}, {"measurement_interval": 3, "measurement_noise": 0.01}])
def test_check_env_on_registered_id(kwargs: dict) -> None:
    register_all()
    env = gymnasium.make(ENV_ID, **kwargs)
    assert env.spec is not None and env.spec.max_episode_steps == 200
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_CHECK_ENV_WARNINGS)]
    assert unexpected == []


def rollout(env: gymnasium.Env, actions: np.ndarray) -> np.ndarray:
    return np.stack([env.step(a)[0] for a in actions])


def test_same_seed_same_rollout_different_seed_differs() -> None:
    actions = np.random.default_rng(0).uniform(-3, 3, size=(15, 7)).astype(np.float32)
    runs = []
    for seed in (7, 7, 8):
        env = PandaReachEnv(measurement_interval=2, measurement_noise=0.01)  # noise draws from the rng
        obs0, info = env.reset(seed=seed)
        runs.append((obs0, info["tool_length"], rollout(env, actions)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    np.testing.assert_array_equal(runs[0][2], runs[1][2])
    assert runs[0][1] != runs[2][1]
    assert not np.array_equal(runs[0][2], runs[2][2])


def test_the_end_effector_is_measured_only_every_nth_step() -> None:
    env = PandaReachEnv(measurement_interval=4)
    obs, info = env.reset(seed=0)
    assert obs[20] == 1.0 and info["measured"]
    np.testing.assert_allclose(obs[17:20], info["ee_true"], atol=1e-6)
    last = obs[17:20].copy()
    action = np.full(7, 1.0, np.float32)  # keeps the arm moving, so a new measurement differs
    for step in range(1, 13):
        obs, _, _, _, info = env.step(action)
        fresh = step % 4 == 0
        assert obs[20] == float(fresh) and info["measured"] == fresh
        if fresh:
            np.testing.assert_allclose(obs[17:20], info["ee_true"], atol=1e-6)
            assert not np.allclose(obs[17:20], last)
            last = obs[17:20].copy()
        else:  # the last measurement is held while the arm moves on
            np.testing.assert_array_equal(obs[17:20], last)
            assert not np.allclose(obs[17:20], info["ee_true"], atol=1e-3)


def test_reaching_the_goal_terminates_with_success_and_the_reward_is_minus_the_distance() -> None:
    env = PandaReachEnv()
    start = panda_fk(torch.tensor(READY_POSE, dtype=F64), 0.1).numpy()
    env.reset(seed=0, options={"tool_length": 0.1, "goal": start + np.array([0.0, 0.0, 0.2])})
    _, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert not terminated and not truncated and not info["is_success"]
    assert reward == pytest.approx(-0.2, abs=1e-9)
    env.reset(seed=0, options={"tool_length": 0.1, "goal": start + np.array([0.0, 0.03, 0.0])})
    _, reward, terminated, _, info = env.step(np.zeros(7, np.float32))
    assert terminated and info["is_success"] and reward == pytest.approx(-0.03, abs=1e-9)


def test_reset_options_and_arguments_are_checked() -> None:
    env = PandaReachEnv()
    obs, info = env.reset(seed=1, options={"q": [0.0] * 3 + [-1.0] + [0.0] * 3, "tool_length": -0.2})
    np.testing.assert_allclose(obs[:7], [0.0] * 3 + [-1.0] + [0.0] * 3)
    assert info["tool_length"] == -0.2
    for options, match in [
        ({"tol": 0.1}, "unknown reset options"),
        ({"goal": [0.0, 1.0]}, "goal"),
        ({"q": [0.0] * 7}, "joint limits"),  # joint 4's upper limit is -0.0698
        ({"tool_length": float("nan")}, "tool_length"),
    ]:
        with pytest.raises(ValueError, match=match):
            env.reset(options=options)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(6, np.float32))
    for kwargs, match in [
        ({"measurement_interval": 0}, "measurement_interval"),
        ({"dt": 0.0}, "dt"),
        ({"measurement_noise": -1.0}, "measurement_noise"),
    ]:
        with pytest.raises(ValueError, match=match):
            PandaReachEnv(**kwargs)
    with pytest.raises(RuntimeError, match="reset"):
        PandaReachEnv().step(np.zeros(7, np.float32))


def test_env_pickles_mid_episode() -> None:
    env = PandaReachEnv(measurement_interval=3)
    env.reset(seed=3)
    env.step(np.ones(7, np.float32))
    clone = pickle.loads(pickle.dumps(env))
    action = np.full(7, -0.5, np.float32)
    np.testing.assert_array_equal(env.step(action)[0], clone.step(action)[0])


def test_limits_constants_agree_with_the_ready_pose() -> None:
    assert all(lo < q < hi for lo, q, hi in zip(JOINT_LOWER, READY_POSE, JOINT_UPPER, strict=True))
