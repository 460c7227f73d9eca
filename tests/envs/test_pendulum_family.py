"""Tests of the pendulum family: Pendulum-v1's physics, the per-episode pole, the babbling data."""

from __future__ import annotations

import doctest
import math
import pickle
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from gymnasium.utils.env_checker import check_env

import smcd_rl.envs.pendulum_family as pendulum_family
from smcd_rl.envs import register_all
from smcd_rl.envs.pendulum_family import (
    LENGTH_RANGE,
    MASS_RANGE,
    MAX_SPEED,
    MAX_TORQUE,
    POLE_COLOR,
    PendulumFamilyEnv,
    pendulum_frame,
    pendulum_reward,
    pendulum_step,
    pendulum_transitions,
    sample_pendulum_parameters,
)

ENV_ID = "smcd_rl/PendulumFamily-v0"

# The one warning check_env raises by design: Pendulum-v1's torque box is [-2, 2], not [-1, 1].
EXPECTED_CHECK_ENV_WARNINGS = ("symmetric and normalized space",)


def observe(state: np.ndarray) -> np.ndarray:
    """Pendulum-v1's observation of (th, thdot), in float64."""
    return np.array([np.cos(state[0]), np.sin(state[0]), state[1]])


# ---------------------------------------------------------------------------- the physics
def test_pendulum_step_matches_gymnasiums_pendulum_over_many_states_clipping_included() -> None:
    rng = np.random.default_rng(0)
    n = 400
    th = rng.uniform(-3 * np.pi, 3 * np.pi, n)  # unwrapped angles: pendulum_step only sees cos and sin
    thdot = rng.uniform(-MAX_SPEED, MAX_SPEED, n)
    thdot[:40] = MAX_SPEED * np.sign(thdot[:40])  # at the velocity bound, pushed on by gravity or torque
    u = rng.uniform(-2 * MAX_TORQUE, 2 * MAX_TORQUE, n)  # half of them clip
    mass = rng.uniform(0.3 * MASS_RANGE[0], 1.5 * MASS_RANGE[1], n)
    length = rng.uniform(0.5 * LENGTH_RANGE[0], 1.5 * LENGTH_RANGE[1], n)

    reference = PendulumEnv()
    reference.reset(seed=0)
    expected, expected_obs32, rewards = [], [], []
    for i in range(n):
        reference.state = np.array([th[i], thdot[i]])
        reference.m, reference.l = mass[i], length[i]
        obs32, reward, _, _, _ = reference.step(np.array([u[i]]))
        expected.append(observe(reference.state))
        expected_obs32.append(obs32)
        rewards.append(reward)
    expected = np.stack(expected)

    obs = torch.as_tensor(np.stack([observe(np.array(s)) for s in zip(th, thdot, strict=True)]))
    action = torch.as_tensor(u)[:, None]
    got = pendulum_step(obs, action, torch.as_tensor(mass), torch.as_tensor(length))
    assert got.dtype == torch.float64 and got.shape == (n, 3)
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-12)
    # In float32, as a model sees the env's observations, it agrees to float32 precision.
    got32 = pendulum_step(obs.float(), action.float(), torch.as_tensor(mass).float(), torch.as_tensor(length).float())
    np.testing.assert_allclose(got32.numpy(), np.stack(expected_obs32), rtol=0, atol=2e-5)
    # The cases exercised the clips: torques beyond the box, and velocities pinned at the bound.
    assert (np.abs(u) > MAX_TORQUE).sum() > 100
    assert (np.abs(expected[:, 2]) == MAX_SPEED).sum() > 20 and (np.abs(expected[:, 2]) < MAX_SPEED).sum() > 100
    # And the reward is Pendulum-v1's.
    np.testing.assert_allclose(pendulum_reward(obs, action).numpy(), rewards, rtol=1e-6, atol=1e-6)


def test_pendulum_step_broadcasts_parameters_and_rejects_wrong_shapes() -> None:
    obs = torch.tensor([0.0, 1.0, 0.5]).expand(4, 5, 3)
    action = torch.full((4, 5, 1), 0.7)
    mass = torch.linspace(0.5, 2.0, 4)[:, None]  # one per row, shared along the second axis
    got = pendulum_step(obs, action, mass, 1.2)
    assert got.shape == (4, 5, 3)
    for i in range(4):
        torch.testing.assert_close(got[i], pendulum_step(obs[i], action[i], float(mass[i]), 1.2))
    assert not torch.allclose(got[0], got[-1])  # a heavier pole turns less for the same torque
    with pytest.raises(ValueError, match=r"observation must have shape \[\.\.\., 3\]"):
        pendulum_step(torch.zeros(4, 2), torch.zeros(4, 1), 1.0, 1.0)
    with pytest.raises(ValueError, match=r"action must have shape \[\.\.\., 1\]"):
        pendulum_step(torch.zeros(4, 3), torch.zeros(4), 1.0, 1.0)
    with pytest.raises(ValueError, match="dt must be finite and > 0"):
        pendulum_step(torch.zeros(3), torch.zeros(1), 1.0, 1.0, dt=0.0)


def test_env_is_pendulum_v1_with_the_drawn_pole() -> None:
    """Same seed: the same start state as Pendulum-v1, and the same rollout with m and l set."""
    actions = np.random.default_rng(1).uniform(-3, 3, size=(30, 1)).astype(np.float32)
    env, reference = PendulumFamilyEnv(), PendulumEnv()
    obs, info = env.reset(seed=5)
    ref_obs, _ = reference.reset(seed=5)
    np.testing.assert_array_equal(obs, ref_obs)
    assert env.unwrapped.m == info["mass"] and env.unwrapped.l == info["length"]
    reference.m, reference.l = info["mass"], info["length"]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        ref_obs, ref_reward, _, _, _ = reference.step(a)
        np.testing.assert_array_equal(obs, ref_obs)
        assert reward == ref_reward and type(reward) is float
        assert not terminated and not truncated
        assert info == {"mass": reference.m, "length": reference.l}


# ---------------------------------------------------------------------------- reset and its options
def test_reset_draws_the_pole_within_the_prior_and_repeats_with_the_seed() -> None:
    env = PendulumFamilyEnv()
    drawn = np.array([[info["mass"], info["length"]] for info in (env.reset(seed=s)[1] for s in range(200))])
    assert (drawn[:, 0] >= MASS_RANGE[0]).all() and (drawn[:, 0] <= MASS_RANGE[1]).all()
    assert (drawn[:, 1] >= LENGTH_RANGE[0]).all() and (drawn[:, 1] <= LENGTH_RANGE[1]).all()
    # 200 uniform draws spread over their range (each quarter holds ~50; < 20 has odds ~1e-7).
    for column, (low, high) in enumerate((MASS_RANGE, LENGTH_RANGE)):
        quarters = np.histogram(drawn[:, column], bins=4, range=(low, high))[0]
        assert quarters.min() > 20
    again = [env.reset(seed=s)[1] for s in (3, 3, 4)]
    assert again[0] == again[1] and again[0] != again[2]
    unseeded = [env.reset()[1]["mass"] for _ in range(3)]  # each reset draws a new pole
    assert len(set(unseeded)) == 3


def test_reset_options_fix_the_pole_and_leave_the_other_draw_alone() -> None:
    env = PendulumFamilyEnv()
    obs, free = env.reset(seed=9)
    obs_mass, info = env.reset(seed=9, options={"mass": 3.0})
    assert info == {"mass": 3.0, "length": free["length"]} and env.unwrapped.m == 3.0
    np.testing.assert_array_equal(obs_mass, obs)  # the start state does not depend on the pole
    _, info = env.reset(seed=9, options={"length": np.float32(0.25)})
    assert info == {"mass": free["mass"], "length": 0.25} and env.unwrapped.l == 0.25
    _, info = env.reset(options={"mass": 1, "length": 2})
    assert info == {"mass": 1.0, "length": 2.0}
    _, info = env.step(np.array([0.0], dtype=np.float32))[3:]
    assert info == {"mass": 1.0, "length": 2.0}
    # Pendulum-v1's own options pass through: a zero range starts upright at rest.
    obs, _ = env.reset(options={"x_init": 0.0, "y_init": 0.0})
    np.testing.assert_array_equal(obs, [1.0, 0.0, 0.0])


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"mass": 0.0}, r"options\['mass'\] must be a finite number > 0, got 0.0"),
        ({"mass": -1.0}, r"options\['mass'\] must be a finite number > 0"),
        ({"length": math.nan}, r"options\['length'\] must be a finite number > 0"),
        ({"length": math.inf}, r"options\['length'\] must be a finite number > 0"),
        ({"length": "long"}, r"options\['length'\] must be a finite number > 0, got 'long'"),
        ({"mass": (1.0, 2.0)}, r"options\['mass'\] must be a finite number > 0"),
        ({"mass": True}, r"options\['mass'\] must be a finite number > 0"),
        ({"masses": 1.0}, r"unknown reset options \['masses'\]; use 'mass', 'length'"),
    ],
)
def test_reset_rejects_bad_options_with_a_message_and_changes_nothing(options: dict, match: str) -> None:
    env = PendulumFamilyEnv()
    obs, info = env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.reset(seed=1, options=options)
    assert (env.unwrapped.m, env.unwrapped.l) == (info["mass"], info["length"])
    np.testing.assert_array_equal(env.unwrapped._get_obs(), obs)


def test_constructor_and_step_check_their_inputs() -> None:
    with pytest.raises(ValueError, match="render_mode"):
        PendulumFamilyEnv(render_mode="human")  # a pygame window: not offered
    with pytest.raises(ValueError, match="g must be finite"):
        PendulumFamilyEnv(g=math.nan)
    env = PendulumFamilyEnv(g=9.81)
    assert env.g == 9.81
    with pytest.raises(RuntimeError, match=r"reset\(\) before step"):
        env.step(np.zeros(1, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(1,\)"):
        env.step(np.zeros(2, dtype=np.float32))


def test_pickled_env_continues_identically() -> None:
    env = PendulumFamilyEnv()
    env.reset(seed=3)
    actions = np.random.default_rng(1).uniform(-2, 2, size=(10, 1)).astype(np.float32)
    for a in actions[:5]:
        env.step(a)
    copy = pickle.loads(pickle.dumps(env))
    for a in actions[5:]:
        np.testing.assert_array_equal(env.step(a)[0], copy.step(a)[0])
    assert env.reset()[1] == copy.reset()[1]  # the rng travelled too


# ---------------------------------------------------------------------------- registration, rendering
def test_registered_id_passes_check_env_and_truncates_after_200_steps() -> None:
    register_all()
    env = gymnasium.make(ENV_ID, render_mode="rgb_array")
    assert env.spec is not None and env.spec.max_episode_steps == 200
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # its render checks included
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_CHECK_ENV_WARNINGS)]
    assert unexpected == []
    env.reset(seed=0)
    env.action_space.seed(0)
    for t in range(200):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        assert not terminated and truncated == (t == 199)


def test_rgb_array_frames_without_a_display_follow_the_pole() -> None:
    env = PendulumFamilyEnv(render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    env.reset(seed=0, options={"x_init": 0.0, "y_init": 0.0, "length": 1.0})  # upright
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    # Upright: the pole runs from the pivot (the centre) up to the top; the extent is 1.2 * 1.5 m.
    row_of_tip = int(240 - 0.9 * 240 / 1.8)
    assert frame[row_of_tip, 240].tolist() == list(POLE_COLOR)
    assert frame[480 - row_of_tip, 240].tolist() != list(POLE_COLOR)
    np.testing.assert_array_equal(pendulum_frame(0.0, 1.0, env.unwrapped.m), frame)  # a function of the state
    env.step(np.array([2.0], dtype=np.float32))
    assert (env.render() != frame).any()
    assert (pendulum_frame(0.0, 0.6) != pendulum_frame(0.0, 1.4)).any()  # the length shows
    assert (pendulum_frame(0.0, 1.0, 0.5) != pendulum_frame(0.0, 1.0, 2.0)).any()  # and the mass
    with pytest.warns(UserWarning, match="render_mode"):
        assert PendulumFamilyEnv().render() is None


# ---------------------------------------------------------------------------- the prior and the data
def test_sample_pendulum_parameters_follows_the_prior_and_the_seed() -> None:
    parameters = sample_pendulum_parameters((50, 4), generator=torch.Generator().manual_seed(0))
    assert parameters.shape == (50, 4, 2) and parameters.dtype == torch.get_default_dtype()
    mass, length = parameters[..., 0], parameters[..., 1]
    assert MASS_RANGE[0] <= float(mass.min()) and float(mass.max()) <= MASS_RANGE[1]
    assert LENGTH_RANGE[0] <= float(length.min()) and float(length.max()) <= LENGTH_RANGE[1]
    assert float(mass.mean()) == pytest.approx(1.25, abs=0.1) and float(length.mean()) == pytest.approx(1.0, abs=0.1)
    again = sample_pendulum_parameters((50, 4), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(parameters, again, rtol=0, atol=0)
    assert sample_pendulum_parameters(3).shape == (3, 2) and sample_pendulum_parameters(()).shape == (2,)
    with pytest.raises(ValueError, match="shape must be"):
        sample_pendulum_parameters((2, -1))


def test_pendulum_transitions_shapes_and_babbling() -> None:
    data = pendulum_transitions(5, 4, 12, generator=torch.Generator().manual_seed(0))
    assert data.batch_size == (5, 4, 12)
    assert data["observation"].shape == data["next", "observation"].shape == (5, 4, 12, 3)
    assert data["action"].shape == (5, 4, 12, 1)
    assert data["mass"].shape == data["length"].shape == data["task"].shape == (5, 4, 12)
    assert data["task"].dtype == torch.int64
    torch.testing.assert_close(data["task"], torch.arange(5)[:, None, None].expand(5, 4, 12))
    # One pole per task, from the prior.
    for key, (low, high) in (("mass", MASS_RANGE), ("length", LENGTH_RANGE)):
        per_task = data[key][:, 0, 0]
        assert (data[key] == per_task[:, None, None]).all() and len(set(per_task.tolist())) == 5
        assert low <= float(per_task.min()) and float(per_task.max()) <= high
    # Starts as Pendulum-v1 resets, then torques in the box.
    start = data["observation"][:, :, 0]
    torch.testing.assert_close(start[..., 0] ** 2 + start[..., 1] ** 2, torch.ones(5, 4))
    assert float(start[..., 2].abs().max()) <= 1.0
    assert float(data["action"].abs().max()) <= MAX_TORQUE and float(data["action"].std()) > 0.5
    # Without noise, each next observation is pendulum_step of observation and action.
    step = pendulum_step(data["observation"], data["action"], data["mass"], data["length"])
    torch.testing.assert_close(data["next", "observation"], step, rtol=0, atol=1e-6)


def test_pendulum_transitions_chain_one_measurement_per_state_and_repeat_with_the_seed() -> None:
    def make(seed: int, noise: float = 0.1):
        return pendulum_transitions(3, 2, 8, measurement_noise=noise, generator=torch.Generator().manual_seed(seed))

    data = make(0)
    # The observation after a step is the same measurement as the step's next observation.
    torch.testing.assert_close(
        data["observation"][..., 1:, :], data["next", "observation"][..., :-1, :], rtol=0, atol=0
    )
    assert (make(0) == data).all() and not (make(1)["observation"] == data["observation"]).all()
    # The noise is on top of the noise-free data of the same draws (parameters, starts, torques first).
    clean = make(0, noise=0.0)
    torch.testing.assert_close(clean["action"], data["action"], rtol=0, atol=0)
    errors = (data["next", "observation"] - clean["next", "observation"]).flatten()
    assert float(errors.std()) == pytest.approx(0.1, rel=0.2)  # 144 draws: +-6 % at 1 sigma


def test_pendulum_transitions_use_given_parameters() -> None:
    parameters = torch.tensor([[0.5, 0.5], [2.0, 1.5]], dtype=torch.float64)
    data = pendulum_transitions(2, 3, 4, parameters=parameters, generator=torch.Generator().manual_seed(0))
    assert data["observation"].dtype == torch.float64
    torch.testing.assert_close(data["mass"][:, 0, 0], parameters[:, 0])
    torch.testing.assert_close(data["length"][:, 0, 0], parameters[:, 1])
    step = pendulum_step(data["observation"], data["action"], data["mass"], data["length"])
    torch.testing.assert_close(data["next", "observation"], step, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_tasks": 0}, "num_tasks must be a positive int, got 0"),
        ({"episodes_per_task": 2.0}, "episodes_per_task must be a positive int"),
        ({"steps": True}, "steps must be a positive int"),
        ({"measurement_noise": -0.1}, "measurement_noise must be finite and >= 0"),
        ({"dt": -0.05}, "dt must be finite and > 0"),
        ({"parameters": torch.ones(3, 2)}, r"parameters must have shape \(num_tasks, 2\) = \(2, 2\), got \(3, 2\)"),
        ({"parameters": torch.tensor([[1.0, 1.0], [1.0, 0.0]])}, "parameters must all be finite and > 0"),
        ({"parameters": torch.tensor([[1.0, 1.0], [math.nan, 1.0]])}, "parameters must all be finite and > 0"),
    ],
)
def test_pendulum_transitions_rejects_bad_arguments(kwargs: dict, match: str) -> None:
    arguments = {"num_tasks": 2, "episodes_per_task": 2, "steps": 3, **kwargs}
    with pytest.raises(ValueError, match=match):
        pendulum_transitions(**arguments)


def test_docstring_examples_run() -> None:
    result = doctest.testmod(pendulum_family, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
