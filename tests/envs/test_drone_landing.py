"""Drone landing: env contract, shared dynamics, simulated operators and their labels, dataset format."""

from __future__ import annotations

import errno
import math
import pickle
import re
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from smcd_rl.envs import register_all
from smcd_rl.envs.drone_landing import (
    DT,
    PLATFORMS,
    START,
    SUCCESS_REWARD,
    TAU,
    DroneLandingEnv,
    drone_transition,
    landing_success,
    platform_index,
    surface_height,
    target_distance,
)
from smcd_rl.envs.drone_operators import (
    SKILLS,
    TASK_SEQUENCE,
    TrajectoryDataset,
    load_dataset,
    save_dataset,
    simulate_operators,
    split_dataset,
)
from smcd_rl.files import FileWriteError

ENV_ID = "smcd_rl/DroneLanding-v0"


@pytest.fixture(scope="module")
def population() -> TrajectoryDataset:
    """The default population: 33 operators x 16 landings (about 0.5 s)."""
    return simulate_operators(seed=0)


def descend_on(env: gymnasium.Env, xy: tuple[float, float], target: int) -> tuple[float, bool, dict]:
    """Fly from above ``xy`` straight down; returns (summed reward, terminated, last info)."""
    env.reset(seed=0, options={"target": target, "position": (*xy, 2.0)})
    total = 0.0
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, -1.0], dtype=np.float32))
        total += float(reward)
        if terminated or truncated:
            return total, terminated, info
    raise AssertionError("the drone never touched down")


# ------------------------------------------------------------------ env contract
def test_check_env_on_registered_id() -> None:
    register_all()
    env = gymnasium.make(ENV_ID)
    with warnings.catch_warnings():
        # The action box is [-2, 2] m/s, like Pendulum's torque box: a documented, deliberate scale.
        warnings.filterwarnings("ignore", message=".*symmetric and normalized space.*")
        check_env(env.unwrapped)


def test_registered_env_truncates_after_300_steps_when_hovering() -> None:
    env = gymnasium.make(ENV_ID)
    env.reset(seed=0)
    for step in range(1, 301):  # noqa: B007 - read after the loop
        _, _, terminated, truncated, _ = env.step(np.zeros(3, dtype=np.float32))
        assert not terminated
        if truncated:
            break
    assert step == 300 and truncated


def test_same_seed_same_rollout_different_seed_differs() -> None:
    actions = np.random.default_rng(0).uniform(-2, 2, size=(30, 3)).astype(np.float32)

    def rollout(seed: int) -> tuple[list[int], np.ndarray]:
        env = gymnasium.make(ENV_ID)
        targets, observations = [], []
        for episode in range(6):
            obs, info = env.reset(seed=seed if episode == 0 else None)
            targets.append(info["target"])
            observations.append(obs)
            for action in actions:
                obs, _, terminated, truncated, _ = env.step(action)
                observations.append(obs)
                if terminated or truncated:
                    break
        return targets, np.stack(observations)

    first, again, other = rollout(3), rollout(3), rollout(4)
    assert first[0] == again[0] and np.array_equal(first[1], again[1])
    assert first[0] != other[0]  # 6 targets from 5 platforms: two seeds agreeing on all has chance 5^-6


def test_pickled_env_continues_identically() -> None:
    env = gymnasium.make(ENV_ID)
    env.reset(seed=1)
    env.step(np.array([1.0, 0.5, -0.2], dtype=np.float32))
    copy = pickle.loads(pickle.dumps(env))
    action = np.array([0.3, -1.0, 0.1], dtype=np.float32)
    assert np.array_equal(env.step(action)[0], copy.step(action)[0])


def test_observation_is_position_velocity_and_distance() -> None:
    env = DroneLandingEnv()
    obs, info = env.reset(seed=0, options={"target": 3})
    assert np.allclose(obs[:3], START) and np.allclose(obs[3:6], 0)
    assert obs[6] == pytest.approx(math.dist(START, PLATFORMS[3][:3]), rel=1e-6)


def test_velocity_follows_the_command_with_a_first_order_lag() -> None:
    """From rest, a constant command u gives v_n = u (1 - exp(-n dt / tau)) exactly."""
    env = DroneLandingEnv()
    env.reset(seed=0, options={"position": (0.0, 0.0, 3.0)})
    for n in range(1, 6):
        obs, *_ = env.step(np.array([1.5, 0.0, 0.0], dtype=np.float32))
        assert obs[3] == pytest.approx(1.5 * (1 - math.exp(-n * DT / TAU)), rel=1e-5)


def test_commands_are_clipped_to_max_speed() -> None:
    p, v = torch.zeros(3) + torch.tensor([0.0, 0.0, 3.0]), torch.zeros(3)
    _, fast, _ = drone_transition(p, v, torch.tensor([50.0, 0.0, 0.0]))
    _, capped, _ = drone_transition(p, v, torch.tensor([2.0, 0.0, 0.0]))
    assert torch.equal(fast, capped)


def test_landing_on_the_target_succeeds_and_beside_it_fails() -> None:
    env = DroneLandingEnv()
    x, y, top, _ = PLATFORMS[1]
    reward, terminated, info = descend_on(env, (x + 0.3, y - 0.3), target=1)
    assert terminated and info["success"] and info["landed_on"] == 1
    # Progress from 2 m above to the top, 0.3 m off centre horizontally, plus the bonus.
    progress = math.hypot(0.3, 0.3, 2.0 - top) - math.hypot(0.3, 0.3)
    assert reward == pytest.approx(progress + SUCCESS_REWARD, rel=1e-5)
    _, terminated, info = descend_on(env, (x + 0.8, y), target=1)  # beside the 1 m face
    assert terminated and not info["success"] and info["landed_on"] == -1
    _, _, info = descend_on(env, PLATFORMS[0][:2], target=1)  # on the wrong platform
    assert info["landed_on"] == 0 and not info["success"]


def test_a_platform_side_is_a_wall() -> None:
    x, y, top, half = PLATFORMS[2]
    position = torch.tensor([x - half - 0.05, y, top - 0.3])  # beside the platform, below its top
    velocity = torch.tensor([1.0, 0.0, 0.0])
    moved, velocity, down = drone_transition(position, velocity, torch.tensor([2.0, 0.0, 0.0]))
    assert not down and moved[0] == position[0] and velocity[0] == 0
    # Above the top the same move enters the footprint.
    above = torch.tensor([x - half - 0.05, y, top + 0.5])
    moved, _, _ = drone_transition(above, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([2.0, 0.0, 0.0]))
    assert int(platform_index(moved[:2])) == 2


def test_geometry_functions_agree_with_the_platform_table() -> None:
    centres = torch.tensor([p[:2] for p in PLATFORMS])
    assert platform_index(centres).tolist() == list(range(len(PLATFORMS)))
    assert surface_height(centres).tolist() == pytest.approx([p[2] for p in PLATFORMS])
    assert int(platform_index(torch.tensor([0.0, 0.0]))) == -1
    tops = torch.tensor([p[:3] for p in PLATFORMS])
    assert torch.allclose(target_distance(tops, torch.arange(5)), torch.zeros(5))
    assert landing_success(tops, torch.arange(5)).all()
    assert not landing_success(tops + torch.tensor([0.0, 0.0, 0.5]), torch.arange(5)).any()  # hovering


@pytest.mark.parametrize(
    "options",
    [
        {"target": 5},
        {"target": -1},
        {"target": 1.5},
        {"position": (0.0, 0.0)},
        {"position": (0.0, 0.0, 9.0)},
        {"position": (3.0, -1.5, 0.3)},
        {"wind": 1},
    ],
)
def test_invalid_reset_options_raise(options: dict) -> None:
    with pytest.raises(ValueError):
        DroneLandingEnv().reset(seed=0, options=options)


def test_invalid_arguments_and_actions_raise() -> None:
    with pytest.raises(ValueError, match="dt"):
        DroneLandingEnv(dt=0.0)
    env = DroneLandingEnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(3))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(2))


# ------------------------------------------------------------------ simulated operators
def test_population_shape_proportions_and_task_sequence(population: TrajectoryDataset) -> None:
    assert population.num_trajectories == 33 * 16
    skill = population.trajectory_labels["skill"].reshape(33, 16)
    assert (skill == skill[:, :1]).all()  # one skill per operator
    assert np.bincount(skill[:, 0], minlength=3).tolist() == [3, 27, 3]  # B.1: 10% novices, 10% experts
    targets = population.trajectory_labels["target"].reshape(33, 16)
    assert (targets == np.array(TASK_SEQUENCE)).all()
    assert np.array_equal(population.operator, np.repeat(np.arange(33), 16))


def test_simulation_is_repeatable_from_its_seed(population: TrajectoryDataset) -> None:
    again, other = simulate_operators(seed=0), simulate_operators(seed=1)
    assert np.array_equal(again.state, population.state) and np.array_equal(again.action, population.action)
    assert not np.array_equal(other.trajectory_labels["strategy"], population.trajectory_labels["strategy"])


def test_recorded_actions_replayed_in_the_env_give_the_recorded_states_and_success(
    population: TrajectoryDataset,
) -> None:
    """The dataset is the env's dynamics: replaying a trajectory's commands reproduces it and its label."""
    env = DroneLandingEnv()
    offsets = population.offsets
    for i in range(0, population.num_trajectories, 37):
        states = population.state[offsets[i] : offsets[i + 1]]
        actions = population.action[offsets[i] : offsets[i + 1]]
        obs, _ = env.reset(options={"target": int(population.trajectory_labels["target"][i])})
        info: dict = {}
        for t, action in enumerate(actions):
            np.testing.assert_allclose(obs, states[t], atol=1e-4)
            obs, _, terminated, _, info = env.step(action)
            assert terminated == (t == len(actions) - 1) or len(actions) == 300
        assert info.get("success", False) == bool(population.trajectory_labels["success"][i])


def test_phase_is_approach_then_descent(population: TrajectoryDataset) -> None:
    phase, offsets = population.step_labels["phase"], population.offsets
    for i in range(population.num_trajectories):
        steps = phase[offsets[i] : offsets[i + 1]]
        assert steps[0] == 0 and np.all(np.diff(steps) >= 0)
    assert 0.2 < phase.mean() < 0.6  # both phases are well represented


def test_skill_is_recoverable_from_command_roughness_and_final_distance(population: TrajectoryDataset) -> None:
    """Skill labels come from the landing record (B.1); the flying itself must show them too.

    Per operator: roughness = RMS change of the command between steps (noise, delayed over-correction)
    and the mean distance to the target at the last recorded step. Every expert beats every novice
    on both, and the group means are ordered novice > intermediate > expert.
    """
    offsets, ops = population.offsets, population.operator
    roughness = np.array(
        [
            np.sqrt(np.mean(np.diff(population.action[offsets[i] : offsets[i + 1]], axis=0) ** 2))
            for i in range(population.num_trajectories)
        ]
    )
    final_distance = population.state[offsets[1:] - 1, 6]
    skill = population.trajectory_labels["skill"]
    for statistic in (roughness, final_distance):
        per_operator = np.array([statistic[ops == o].mean() for o in range(33)])
        label = np.array([skill[ops == o][0] for o in range(33)])
        novice, middle, expert = (per_operator[label == SKILLS.index(s)] for s in SKILLS)
        assert expert.max() < novice.min()
        assert novice.mean() > middle.mean() > expert.mean()


def test_strategy_is_recoverable_from_altitude_lost_while_approaching(population: TrajectoryDataset) -> None:
    """Diagonal landings lose height during the approach, orthogonal ones at the end: a threshold separates all 528."""
    offsets, phase = population.offsets, population.step_labels["phase"]
    share = np.empty(population.num_trajectories)
    for i in range(population.num_trajectories):
        z = population.state[offsets[i] : offsets[i + 1], 2]
        approach = z[phase[offsets[i] : offsets[i + 1]] == 0]
        share[i] = (z[0] - approach.mean()) / max(z[0] - z[-1], 1e-6)  # mean height lost while approaching
    strategy = population.trajectory_labels["strategy"]
    assert share[strategy == 0].max() < share[strategy == 1].min()


def test_success_is_common_enough_to_matter_and_grows_with_skill(population: TrajectoryDataset) -> None:
    success, skill = population.trajectory_labels["success"], population.trajectory_labels["skill"]
    assert 0.3 < success.mean() < 0.8
    rates = [success[skill == s].mean() for s in range(3)]
    assert rates[0] < rates[1] < rates[2]


def test_simulate_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="num_operators"):
        simulate_operators(num_operators=0)
    with pytest.raises(ValueError, match="max_steps"):
        simulate_operators(max_steps=1.5)  # type: ignore[arg-type]


# ------------------------------------------------------------------ split and dataset format
def test_split_matches_the_paper(population: TrajectoryDataset) -> None:
    split = split_dataset(population, seed=0)
    sizes = {k: len(v) for k, v in split.items()}
    assert sizes == {"train": 443, "known": 53, "unknown": 32}  # 83.9 / 10.0 / 6.1 %
    everything = np.concatenate(list(split.values()))
    assert np.array_equal(np.sort(everything), np.arange(528))
    train_ops = set(population.operator[split["train"]])
    assert set(population.operator[split["known"]]) <= train_ops
    assert not set(population.operator[split["unknown"]]) & train_ops
    assert split_dataset(population, seed=0)["known"].tolist() == split["known"].tolist()


def test_dataset_round_trips_through_npz(tmp_path, population: TrajectoryDataset) -> None:
    path = tmp_path / "drone.npz"
    save_dataset(population, path)
    loaded = load_dataset(path)
    assert np.array_equal(loaded.state, population.state) and np.array_equal(loaded.trajectory, population.trajectory)
    assert loaded.label_names == population.label_names
    assert all(np.array_equal(loaded.labels[k], v) for k, v in population.labels.items())


def test_a_save_that_fails_midway_keeps_the_old_file_and_leaves_no_partial_one(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    small = simulate_operators(num_operators=2, trajectories_per_operator=2)
    path = tmp_path / "drone.npz"
    save_dataset(small, path)
    before = path.read_bytes()

    def full_disk(handle, **arrays) -> None:
        handle.write(b"PK\x03\x04 half an archive")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", full_disk)
    with pytest.raises(
        FileWriteError, match=re.escape(f"cannot write dataset {path}: no space left on the disk of {tmp_path}")
    ):
        save_dataset(small, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["drone.npz"]  # no temporary file left behind


def test_saving_onto_a_directory_or_under_a_file_names_the_path_and_leaves_nothing(tmp_path) -> None:
    small = simulate_operators(num_operators=2, trajectories_per_operator=2)
    (tmp_path / "taken.npz").mkdir()
    with pytest.raises(FileWriteError, match=re.escape(f"{tmp_path / 'taken.npz'} is a directory")):
        save_dataset(small, tmp_path / "taken.npz")
    (tmp_path / "file").write_text("")
    with pytest.raises(FileWriteError, match=re.escape(f"{tmp_path / 'file'} (or a folder above it) is a file")):
        save_dataset(small, tmp_path / "file" / "drone.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "taken.npz"]
    assert not any((tmp_path / "taken.npz").iterdir())


def test_select_keeps_trajectories_and_labels(population: TrajectoryDataset) -> None:
    part = population.select([5, 2])
    offsets = population.offsets
    assert np.array_equal(
        part.state,
        np.concatenate([population.state[offsets[5] : offsets[6]], population.state[offsets[2] : offsets[3]]]),
    )
    assert part.trajectory_labels["strategy"].tolist() == population.trajectory_labels["strategy"][[5, 2]].tolist()


def _arrays(**changes: object) -> dict:
    arrays = {
        "state": np.zeros((5, 7)),
        "action": np.zeros((5, 3)),
        "trajectory": np.array([0, 0, 0, 1, 1]),
        "operator": np.array([0, 1]),
        "traj/skill": np.array([0, 2]),
        "step/phase": np.array([0, 0, 1, 0, 1]),
    }
    arrays.update(changes)
    return {k: v for k, v in arrays.items() if v is not None}


@pytest.mark.parametrize(
    ("changes", "error", "match"),
    [
        ({"operator": None}, KeyError, "operator"),
        ({"state": None}, KeyError, "state"),
        ({"action": np.zeros((4, 3))}, ValueError, "steps"),
        ({"trajectory": np.array([0, 0, 1, 0, 1])}, ValueError, "non-decreasing"),
        ({"trajectory": np.array([0, 0, 0, 2, 2])}, ValueError, "0..N-1"),
        ({"operator": np.array([0, 1, 2])}, ValueError, "0..N-1"),
        ({"traj/skill": np.array([0, 2, 1])}, ValueError, "skill"),
        ({"step/phase": np.array([0, 1])}, ValueError, "phase"),
        ({"traj/skill": np.array([0, -1])}, ValueError, ">= 0"),
        ({"state": np.full((5, 7), np.nan)}, ValueError, "finite"),
        ({"extra": np.zeros(3)}, KeyError, "unknown key"),
    ],
)
def test_bad_dataset_files_raise_naming_the_problem(tmp_path, changes: dict, error: type, match: str) -> None:
    path = tmp_path / "bad.npz"
    np.savez(path, **_arrays(**changes))
    with pytest.raises(error, match=match):
        load_dataset(path)


def test_missing_and_unreadable_dataset_files_raise(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        load_dataset(tmp_path / "none.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(ValueError, match="npz"):
        load_dataset(tmp_path / "text.npz")


def test_a_flipped_bit_in_a_dataset_names_the_file_and_the_fix(tmp_path) -> None:
    path = tmp_path / "flights.npz"
    state = np.arange(35.0).reshape(5, 7) + 0.5
    np.savez(path, **_arrays(state=state))  # stored uncompressed: the array's bytes sit in the file as written
    raw = bytearray(path.read_bytes())
    at = bytes(raw).index(state.tobytes()) + 8
    raw[at] ^= 0x01  # a bit flip inside the state array: the zip's CRC-32 no longer matches
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"flights\.npz is corrupt .*save_dataset"):
        load_dataset(path)
