"""Tests of the two-link arm: env contract, shared kinematics, link-length prior, babbling data."""

from __future__ import annotations

import doctest
import math
import pickle
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import smcd_rl.envs.two_link_arm as two_link_arm
from smcd_rl.envs import register_all
from smcd_rl.envs.two_link_arm import (
    DEFAULT_DT,
    TwoLinkArmEnv,
    integrate_joints,
    motor_babbling,
    sample_link_lengths,
    two_link_fk,
    wrap_angle,
)

ENV_ID = "smcd_rl/TwoLinkArm-v0"

# Warnings check_env raises by design: the action box is [-max_speed, max_speed] rad/s (as in
# Pendulum), and the measured end effector is unbounded (Gaussian noise, unbounded link lengths).
EXPECTED_CHECK_ENV_WARNINGS = (
    "symmetric and normalized space",
    "minimum value is -infinity",
    "maximum value is infinity",
)


def rollout(env: gymnasium.Env, actions: np.ndarray) -> np.ndarray:
    return np.stack([env.step(a)[0] for a in actions])


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


def test_registered_env_truncates_after_100_steps_and_never_terminates() -> None:
    register_all()
    env = gymnasium.make(ENV_ID)
    env.reset(seed=0)
    for t in range(100):
        _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert reward == 0.0 and not terminated
        assert truncated == (t == 99)


def test_same_seed_same_observations_different_seed_differs() -> None:
    actions = np.random.default_rng(0).uniform(-3, 3, size=(20, 2)).astype(np.float32)
    runs = []
    for seed in (7, 7, 8):
        env = TwoLinkArmEnv(measurement_noise=0.05)  # noise makes every step use the rng
        obs0, info = env.reset(seed=seed)
        runs.append((obs0, info["link_lengths"], rollout(env, actions)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    np.testing.assert_array_equal(runs[0][2], runs[1][2])
    assert not np.array_equal(runs[0][1], runs[2][1])
    assert not np.array_equal(runs[0][2], runs[2][2])


def test_pickled_env_continues_identically() -> None:
    env = TwoLinkArmEnv(measurement_noise=0.05)
    env.reset(seed=3)
    actions = np.random.default_rng(1).uniform(-3, 3, size=(10, 2)).astype(np.float32)
    rollout(env, actions[:5])
    copy = pickle.loads(pickle.dumps(env))
    np.testing.assert_array_equal(rollout(env, actions[5:]), rollout(copy, actions[5:]))
    # The rng state travelled too: the next random reset is the same.
    obs_a, info_a = env.reset()
    obs_b, info_b = copy.reset()
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(info_a["link_lengths"], info_b["link_lengths"])


def test_env_observation_is_wrapped_q_and_fk_of_q() -> None:
    env = TwoLinkArmEnv(dt=0.5)
    obs, info = env.reset(seed=0, options={"link_lengths": (1.0, 0.5), "q": (3.0, 0.0)})
    obs, _, _, _, info = env.step(np.array([1.0, 100.0], dtype=np.float32))  # 100 clips to 3
    q_expected = integrate_joints(torch.tensor([3.0, 0.0]), torch.tensor([1.0, 3.0]), 0.5)
    np.testing.assert_allclose(obs[:2], q_expected.numpy(), atol=1e-6)
    assert -math.pi <= obs[0] < 0  # 3.5 rad wrapped to 3.5 - 2 pi
    ee = two_link_fk(torch.tensor(obs[:2], dtype=torch.float64), torch.tensor([1.0, 0.5]))
    np.testing.assert_allclose(obs[2:], ee.numpy(), atol=1e-6)
    np.testing.assert_array_equal(obs[2:], info["ee_true"])  # no noise by default


def test_env_measurement_noise_has_the_requested_std() -> None:
    env = TwoLinkArmEnv(measurement_noise=0.1)
    env.reset(seed=0)
    errors = []
    for _ in range(500):
        obs, _, _, _, info = env.step(env.action_space.sample())
        errors.append(obs[2:] - info["ee_true"])
    # 1000 draws: the sample std is 0.1 +- ~2 % (1 sigma), so +-15 % cannot fail by chance.
    assert np.std(errors) == pytest.approx(0.1, rel=0.15)


def test_env_link_lengths_follow_truncated_prior() -> None:
    env = TwoLinkArmEnv(link_length_std=3.0, min_link_length=0.2)
    lengths = np.stack([env.reset(seed=s)[1]["link_lengths"] for s in range(200)])
    assert lengths.dtype == np.float32
    assert (lengths >= 0.2).all()
    assert len(np.unique(lengths)) == lengths.size  # redrawn each reset, not clamped


def test_reset_options_are_honoured() -> None:
    env = TwoLinkArmEnv()
    obs, info = env.reset(seed=0, options={"link_lengths": (2.0, 1.0), "q": (math.pi / 2, 0.0)})
    np.testing.assert_array_equal(info["link_lengths"], np.array([2.0, 1.0], dtype=np.float32))
    np.testing.assert_allclose(obs, [math.pi / 2, 0.0, 0.0, 3.0], atol=1e-6)
    # Only q fixed: lengths still random; only lengths fixed: q still random.
    obs_a, info_a = env.reset(seed=1, options={"q": (0.0, 0.0)})
    obs_b, _ = env.reset(seed=2, options={"link_lengths": (2.0, 1.0)})
    np.testing.assert_array_equal(obs_a[:2], [0.0, 0.0])
    assert not np.array_equal(info_a["link_lengths"], [1.0, 1.0])
    assert not np.array_equal(obs_b[:2], [math.pi / 2, 0.0])


@pytest.mark.parametrize(
    "options",
    [
        {"link_lengths": (1.0, 0.0)},
        {"link_lengths": (-1.0, 1.0)},
        {"link_lengths": (1.0, 1.0, 1.0)},
        {"link_lengths": (1.0, float("nan"))},
        {"link_lengths": "long"},
        {"q": (0.0,)},
        {"q": (0.0, float("inf"))},
        {"goal": (1.0, 1.0)},
    ],
)
def test_invalid_reset_options_raise(options: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        TwoLinkArmEnv().reset(seed=0, options=options)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"dt": 0.0},
        {"max_speed": -1.0},
        {"measurement_noise": -0.1},
        {"link_length_std": -0.3},
        {"link_length_mean": -5.0},  # truncated normal would (almost) never accept a draw
        {"render_mode": "human"},
    ],
)
def test_invalid_env_arguments_raise(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        TwoLinkArmEnv(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("q", "lengths", "expected"),
    [
        ((0.0, 0.0), (1.0, 1.0), (2.0, 0.0)),
        ((math.pi / 2, 0.0), (1.0, 1.0), (0.0, 2.0)),
        ((0.0, math.pi / 2), (1.0, 0.5), (1.0, 0.5)),
        ((math.pi / 2, -math.pi / 2), (2.0, 1.0), (1.0, 2.0)),
        ((math.pi, 0.0), (1.0, 1.0), (-2.0, 0.0)),
    ],
)
def test_fk_matches_eq8_at_hand_computed_points(
    q: tuple[float, float], lengths: tuple[float, float], expected: tuple[float, float]
) -> None:
    f64 = torch.float64
    ee = two_link_fk(torch.tensor(q, dtype=f64), torch.tensor(lengths, dtype=f64))
    torch.testing.assert_close(ee, torch.tensor(expected, dtype=torch.float64), atol=1e-12, rtol=0)


def test_fk_broadcasts_and_is_differentiable() -> None:
    q = torch.rand(5, 7, 2, dtype=torch.float64, requires_grad=True)
    lengths = torch.tensor([[[1.0, 0.5]]], dtype=torch.float64, requires_grad=True)  # [1, 1, 2]
    ee = two_link_fk(q, lengths)
    assert ee.shape == (5, 7, 2)
    torch.testing.assert_close(ee[3, 4], two_link_fk(q[3, 4], lengths[0, 0]))
    assert torch.autograd.gradcheck(two_link_fk, (q[:2, :2].detach().requires_grad_(), lengths))


def test_integrate_joints_wraps_to_half_open_interval() -> None:
    q = torch.tensor([[3.0, -3.0], [0.0, 0.0]])
    u = torch.tensor([[1.0, -1.0], [1.0, 2.0]])
    torch.testing.assert_close(
        integrate_joints(q, u, 0.5),
        torch.tensor([[3.5 - 2 * math.pi, -3.5 + 2 * math.pi], [0.5, 1.0]]),
    )
    angles = torch.linspace(-20, 20, 10_001, dtype=torch.float64)
    # Just below -pi, remainder() rounds up to 2 pi; the result must still be < pi.
    below = torch.nextafter(torch.tensor(-math.pi, dtype=torch.float64), torch.tensor(-4.0))
    edges = torch.tensor([math.pi, -math.pi, -1e-300, below.item()], dtype=torch.float64)
    wrapped = wrap_angle(torch.cat([angles, edges]))
    assert bool((wrapped >= -math.pi).all()) and bool((wrapped < math.pi).all())
    torch.testing.assert_close(torch.sin(wrapped[:-4]), torch.sin(angles))


def test_sample_link_lengths_respects_min_length_without_clamping() -> None:
    g = torch.Generator().manual_seed(0)
    x = sample_link_lengths((20_000,), std=5.0, min_length=0.1, generator=g)
    assert x.shape == (20_000, 2)
    assert bool((x >= 0.1).all())
    # Clamping would put ~42 % of the draws exactly at 0.1; rejection puts none there.
    assert int((x == 0.1).sum()) == 0


def test_sample_link_lengths_mean_matches_prior() -> None:
    x = sample_link_lengths((50_000,), generator=torch.Generator().manual_seed(0))
    # Truncating N(1, 0.3) at 0.1 (3 sigma) shifts the mean by 0.3 * phi(3) / Phi(3) ~ 0.0013;
    # the standard error over 1e5 draws is 0.3 / sqrt(1e5) ~ 0.001, so a 0.01 tolerance is
    # > 8 standard errors beyond the shift, and a wrong mean (e.g. 0.9 or 1.1) cannot pass.
    assert float(x.mean()) == pytest.approx(1.0, abs=0.01)
    assert float(x.std()) == pytest.approx(0.3, abs=0.01)
    torch.testing.assert_close(x, sample_link_lengths((50_000,), generator=torch.Generator().manual_seed(0)))


def test_sample_link_lengths_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="std"):
        sample_link_lengths((3,), std=-1.0)
    with pytest.raises(ValueError, match="min_length"):
        sample_link_lengths((3,), mean=-3.0, std=0.3)
    assert bool((sample_link_lengths(4, std=0.0) == 1.0).all())


def test_motor_babbling_shapes_and_consistency() -> None:
    data = motor_babbling(6, 5, steps=10, dt=0.3, generator=torch.Generator().manual_seed(0))
    assert data.batch_size == (6, 5, 10)
    for key in ["q", "action", "ee", ("next", "q"), ("next", "ee"), "link_lengths"]:
        assert data[key].shape == (6, 5, 10, 2), key
    assert data["task"].dtype == torch.int64
    torch.testing.assert_close(data["task"][:, 0, 0], torch.arange(6))
    assert bool((data["task"] == data["task"][:, :1, :1]).all())
    torch.testing.assert_close(data["next", "q"], integrate_joints(data["q"], data["action"], 0.3))
    torch.testing.assert_close(data["next", "ee"], two_link_fk(data["next", "q"], data["link_lengths"]))
    torch.testing.assert_close(data["ee"], two_link_fk(data["q"], data["link_lengths"]))
    # Episodes chain: the next state of step t is the state of step t + 1.
    torch.testing.assert_close(data["next", "q"][..., :-1, :], data["q"][..., 1:, :])
    # Link lengths constant within a task, different across tasks.
    lengths = data["link_lengths"]
    assert bool((lengths == lengths[:, :1, :1, :]).all())
    assert len(torch.unique(lengths[:, 0, 0, 0])) == 6
    # Start angles cover U(-pi, pi) and stay wrapped.
    assert bool((data["q"].abs() <= math.pi).all())


def test_motor_babbling_action_std() -> None:
    for action_std in (0.5, 2.0):
        data = motor_babbling(10, 20, action_std=action_std, generator=torch.Generator().manual_seed(1))
        # 4000 N(0, s^2) draws: the sample std is s +- ~1.1 % (1 sigma); +-10 % is ~9 sigma.
        assert float(data["action"].std()) == pytest.approx(action_std, rel=0.1)
        assert float(data["action"].mean()) == pytest.approx(0.0, abs=0.1 * action_std)


def test_motor_babbling_measurement_noise_and_given_lengths() -> None:
    lengths = torch.tensor([[1.0, 1.0], [2.0, 0.5]])
    g = torch.Generator().manual_seed(2)
    data = motor_babbling(2, 100, link_lengths=lengths, measurement_noise=0.05, generator=g)
    torch.testing.assert_close(data["link_lengths"][:, 0, 0], lengths)
    error = data["ee"] - two_link_fk(data["q"], data["link_lengths"])
    # 4000 draws: sample std 0.05 +- ~1.1 %; +-10 % cannot fail by chance.
    assert float(error.std()) == pytest.approx(0.05, rel=0.1)
    # One measurement per visited state: next ee of step t is ee of step t + 1.
    torch.testing.assert_close(data["next", "ee"][..., :-1, :], data["ee"][..., 1:, :])


def test_motor_babbling_is_repeatable() -> None:
    a = motor_babbling(3, 4, measurement_noise=0.1, generator=torch.Generator().manual_seed(5))
    b = motor_babbling(3, 4, measurement_noise=0.1, generator=torch.Generator().manual_seed(5))
    c = motor_babbling(3, 4, measurement_noise=0.1, generator=torch.Generator().manual_seed(6))
    assert bool((a == b).all())
    assert not torch.equal(a["q"], c["q"])


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_tasks": 0}, "num_tasks"),
        ({"episodes_per_task": -1}, "episodes_per_task"),
        ({"steps": 0}, "steps"),
        ({"dt": 0.0}, "dt"),
        ({"action_std": -1.0}, "action_std"),
        ({"measurement_noise": -0.1}, "measurement_noise"),
        ({"link_lengths": torch.ones(3, 2)}, "link_lengths"),
        ({"link_lengths": torch.ones(2, 3)}, "link_lengths"),
        ({"link_lengths": torch.tensor([[1.0, 0.0], [1.0, 1.0]])}, "link_lengths"),
    ],
)
def test_motor_babbling_rejects_bad_arguments(kwargs: dict[str, object], name: str) -> None:
    args: dict[str, object] = {"num_tasks": 2, "episodes_per_task": 2, **kwargs}
    with pytest.raises(ValueError, match=name):
        motor_babbling(**args)  # type: ignore[arg-type]


def test_default_dt_is_documented_step() -> None:
    assert DEFAULT_DT == 0.2
    assert TwoLinkArmEnv().dt == DEFAULT_DT


def test_docstring_examples_run() -> None:
    result = doctest.testmod(two_link_arm, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
