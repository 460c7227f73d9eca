"""Tests of the telescoping two-link tracking task: shared pure functions, env contract, PD tracking."""

from __future__ import annotations

import math
import pickle
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from smcd_rl.agents.pd import JacobianPD
from smcd_rl.envs import register_all
from smcd_rl.envs.two_link_arm import two_link_fk
from smcd_rl.envs.two_link_telescoping import (
    RADIUS_RANGE,
    TwoLinkTelescopingEnv,
    circle_target,
    integrate_acceleration,
    sample_initial_state,
    telescoping_length,
    telescoping_link_lengths,
    tracking_reward,
)

ENV_ID = "smcd_rl/TwoLinkTelescoping-v0"

# check_env warns by design: the acceleration box is not [-1, 1], and velocities, the measured end
# effector and the target are unbounded in the observation space.
EXPECTED_CHECK_ENV_WARNINGS = (
    "symmetric and normalized space",
    "minimum value is -infinity",
    "maximum value is infinity",
)


def test_telescoping_length_follows_the_papers_formula() -> None:
    k = torch.tensor([0, 10, 20, 30, 40, 7])
    expected = torch.tensor([1.0, 1.25, 1.0, 0.75, 1.0, 1 + 0.25 * math.sin(math.pi * 7 / 20)])
    assert torch.allclose(telescoping_length(k), expected, atol=1e-6)
    lengths = telescoping_link_lengths(torch.arange(3).unsqueeze(-1), torch.tensor([0.5, 2.0]))
    assert lengths.shape == (3, 2, 2)
    assert torch.equal(lengths[..., 0], torch.tensor([0.5, 2.0]).expand(3, 2))
    assert torch.allclose(lengths[2, :, 1], telescoping_length(2).expand(2))


def test_env_second_link_telescopes_step_by_step() -> None:
    env = TwoLinkTelescopingEnv()
    _, info = env.reset(seed=3, options={"l1": 0.9})
    seen = [info["link_lengths"]]
    for _ in range(25):
        seen.append(env.step(np.zeros(2, dtype=np.float32))[4]["link_lengths"])
    seen = np.stack(seen)
    np.testing.assert_allclose(seen[:, 0], 0.9, rtol=1e-6)
    np.testing.assert_allclose(seen[:, 1], telescoping_length(torch.arange(26)).numpy(), rtol=1e-6)


def test_target_moves_on_the_circle_of_radius_r() -> None:
    radius, start = torch.tensor([0.4, 1.3]), torch.tensor([-2.0, 1.0])
    k = torch.arange(101).unsqueeze(-1)
    path = circle_target(k, radius, start, step_angle=0.03)
    assert path.shape == (101, 2, 2)
    assert torch.allclose(path.norm(dim=-1), radius.expand(101, 2), atol=1e-6)
    angle = torch.atan2(path[..., 1], path[..., 0])
    assert torch.allclose(
        torch.remainder(angle - start - 0.03 * k + math.pi, 2 * math.pi) - math.pi, torch.zeros(101, 2), atol=1e-5
    )

    env = TwoLinkTelescopingEnv()
    obs, info = env.reset(seed=0)
    r = info["radius"]
    assert RADIUS_RANGE[0] <= r <= RADIUS_RANGE[1]
    targets = [obs[6:]]
    for _ in range(100):
        targets.append(env.step(env.action_space.sample())[0][6:])
    targets = np.stack(targets)
    np.testing.assert_allclose(np.linalg.norm(targets, axis=1), r, rtol=1e-5)
    # Half a revolution over the episode by default: the last target is opposite the first.
    np.testing.assert_allclose(targets[-1], -targets[0], atol=1e-5)


def test_reward_is_minus_the_true_distance_to_the_target() -> None:
    env = TwoLinkTelescopingEnv(measurement_noise=0.1)
    env.reset(seed=1)
    obs, reward, *_, info = env.step(np.array([3.0, -2.0], dtype=np.float32))
    assert reward == pytest.approx(-np.linalg.norm(info["ee_true"] - obs[6:]), abs=1e-5)
    assert reward == pytest.approx(
        float(tracking_reward(torch.as_tensor(info["ee_true"]), torch.as_tensor(obs[6:]))), abs=1e-5
    )


def test_double_integrator_and_action_clipping() -> None:
    q, q_dot = integrate_acceleration(torch.tensor([3.1, 0.0]), torch.tensor([1.0, 0.0]), torch.tensor([0.0, 2.0]), 0.1)
    assert torch.allclose(q_dot, torch.tensor([1.0, 0.2]))
    assert torch.allclose(q, torch.tensor([3.2 - 2 * math.pi, 0.02]))  # wrapped to [-pi, pi)
    env = TwoLinkTelescopingEnv(max_acceleration=5.0)
    env.reset(seed=0, options={"q": (0.0, 0.0)})
    obs = env.step(np.array([50.0, -50.0]))[0]
    np.testing.assert_allclose(obs[2:4], [0.5, -0.5], rtol=1e-6)  # dt * clipped acceleration


@pytest.mark.parametrize("measurement_noise", [0.0, 0.05])
def test_check_env_on_registered_id(measurement_noise: float) -> None:
    register_all()
    env = gymnasium.make(ENV_ID, measurement_noise=measurement_noise)
    assert env.spec is not None and env.spec.max_episode_steps == 100
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_CHECK_ENV_WARNINGS)]
    assert unexpected == []


def test_registered_env_truncates_after_100_steps() -> None:
    register_all()
    env = gymnasium.make(ENV_ID)
    env.reset(seed=0)
    for t in range(100):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        assert not terminated and truncated == (t == 99)


def test_same_seed_same_rollout_different_seed_differs() -> None:
    actions = np.random.default_rng(0).uniform(-20, 20, size=(30, 2)).astype(np.float32)
    runs = []
    for seed in (5, 5, 6):
        env = TwoLinkTelescopingEnv(measurement_noise=0.05)  # noise makes every step use the rng
        obs0, _ = env.reset(seed=seed)
        runs.append(np.stack([obs0] + [env.step(a)[0] for a in actions]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_env_pickles_mid_episode() -> None:
    env = TwoLinkTelescopingEnv()
    env.reset(seed=2)
    env.step(np.ones(2, dtype=np.float32))
    clone = pickle.loads(pickle.dumps(env))
    action = np.array([1.0, -4.0], dtype=np.float32)
    np.testing.assert_array_equal(env.step(action)[0], clone.step(action)[0])


def test_reset_options_and_bad_input_are_named() -> None:
    env = TwoLinkTelescopingEnv()
    obs, info = env.reset(seed=0, options={"l1": 1.0, "q": (0.0, 0.0), "radius": 0.7, "start_angle": math.pi / 2})
    np.testing.assert_allclose(obs[4:], [2.0, 0.0, 0.0, 0.7], atol=1e-6)
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"l2": 1.0})
    with pytest.raises(ValueError, match="radius"):
        env.reset(options={"radius": -1.0})
    with pytest.raises(ValueError, match="'q'"):
        env.reset(options={"q": (1.0, 2.0, 3.0)})
    with pytest.raises(ValueError, match="radius_range"):
        sample_initial_state((2,), radius_range=(1.5, 0.3))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    with pytest.raises(RuntimeError, match="reset"):
        TwoLinkTelescopingEnv().step(np.zeros(2))


def test_pd_with_the_true_telescoping_kinematics_tracks_the_target() -> None:
    """The paper's PD law (K1 = 20, K2 = 5) through the env, with the true Jacobian at each step.

    Arms start at random angles, 0.6 to 2.4 m from their targets; left alone (u = 0) they stay
    0.9 to 2.4 m away on average over steps 30-60, so no episode can pass by chance. With the
    true kinematics the error left after convergence is the PD law's lag behind the moving target
    and the telescoping link (it has no feed-forward): measured 0.06-0.12 m. l1 = 1 gives a
    workspace (0.25 to 2 m from the base) that holds every target circle.
    """
    env = TwoLinkTelescopingEnv()
    start, tracking = [], []
    for seed in range(10):
        obs, _ = env.reset(seed=seed, options={"l1": 1.0})
        start.append(np.linalg.norm(obs[4:6] - obs[6:]))
        errors = []
        for k in range(60):
            lengths = telescoping_link_lengths(k, torch.tensor(1.0, dtype=torch.float64))
            pd = JacobianPD(lambda q, lengths=lengths: two_link_fk(q, lengths), k1=20.0, k2=5.0)
            q, q_dot, ee, target = (torch.as_tensor(obs[i : i + 2], dtype=torch.float64) for i in (0, 2, 4, 6))
            obs, reward, *_ = env.step(pd(q, q_dot, target, position=ee).numpy().astype(np.float32))
            errors.append(-reward)
        tracking.append(np.mean(errors[30:]))
    assert np.mean(start) > 1.0
    assert np.mean(tracking) < 0.12 and np.max(tracking) < 0.25
