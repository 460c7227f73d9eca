"""TaskFamily on gymnasium's MuJoCo envs: naming, drawing, seeding, restoring, action transforms, errors."""

from __future__ import annotations

import json
import warnings

import gymnasium
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from smcd_rl.integrations.task_family import (
    ActionTransform,
    Choice,
    Fixed,
    LogUniform,
    ModelParameters,
    TaskFamily,
    Uniform,
)


def model_arrays(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Copies of every numpy array of a model, ``opt.gravity`` included."""
    arrays = {"opt.gravity": model.opt.gravity.copy()}
    for name in dir(model):
        if not name.startswith("_"):
            value = getattr(model, name)
            if isinstance(value, np.ndarray):
                arrays[name] = value.copy()
    return arrays


def assert_same_model(model: mujoco.MjModel, expected: dict[str, np.ndarray]) -> None:
    actual = model_arrays(model)
    changed = [name for name in expected if not np.array_equal(actual[name], expected[name], equal_nan=True)]
    assert changed == []


def cheetah_family(**kwargs: object) -> TaskFamily:
    params = {
        "body_mass:torso": Uniform(5.0, 10.0),
        "geom_friction:ffoot": Uniform(0.2, 1.0),
        "geom_size:bshin[0]": Uniform(0.03, 0.09),
        "actuator_gear:bthigh": Choice((60.0, 120.0)),
        "joint_damping:bthigh": LogUniform(1.0, 12.0),
        "gravity": Uniform(-12.0, -8.0),
    }
    return TaskFamily(gymnasium.make("HalfCheetah-v5"), params=params, **kwargs)  # type: ignore[arg-type]


def test_reset_draws_every_parameter_into_the_model_and_info() -> None:
    env = cheetah_family(action=ActionTransform(gain=Uniform(0.5, 1.0), bias=Fixed(0.1)))
    model = env.unwrapped.model
    _, info = env.reset(seed=0)
    task = info["task"]
    assert list(task) == list(env.task_names) == [*env.parameters.names, "action:gain", "action:bias"]
    assert json.loads(json.dumps(task)) == task and all(type(v) is float for v in task.values())
    assert 5.0 <= task["body_mass:torso"] <= 10.0 and task["actuator_gear:bthigh"] in (60.0, 120.0)
    assert task["action:bias"] == 0.1
    torso, ffoot, bshin = model.body("torso").id, model.geom("ffoot").id, model.geom("bshin").id
    assert model.body_mass[torso] == task["body_mass:torso"]
    assert model.geom_friction[ffoot, 0] == task["geom_friction:ffoot"]
    assert model.geom_size[bshin, 0] == task["geom_size:bshin[0]"]
    assert model.actuator_gear[model.actuator("bthigh").id, 0] == task["actuator_gear:bthigh"]
    assert model.dof_damping[model.jnt_dofadr[model.joint("bthigh").id]] == task["joint_damping:bthigh"]
    assert model.opt.gravity[2] == task["gravity"]
    _, _, _, _, step_info = env.step(env.action_space.sample())
    assert step_info["task"] == task == env.task


def test_mass_scales_the_inertia_and_growing_a_geom_grows_its_bounds() -> None:
    env = cheetah_family()
    model = env.unwrapped.model
    torso, bshin = model.body("torso").id, model.geom("bshin").id
    inertia, rbound = model.body_inertia[torso].copy(), model.geom_rbound[bshin]
    mass, radius = model.body_mass[torso], model.geom_size[bshin, 0]
    env.reset(seed=0, options={"task": {"body_mass:torso": 2 * mass, "geom_size:bshin[0]": 3 * radius}})
    np.testing.assert_allclose(model.body_inertia[torso], 2 * inertia)
    assert model.geom_rbound[bshin] == pytest.approx(3 * rbound)  # conservative: the largest ratio


def test_restore_on_reset_and_close_leaves_the_model_bit_identical() -> None:
    env = cheetah_family()
    pristine = model_arrays(env.unwrapped.model)
    env.reset(seed=1)
    env.reset(options={"task": {"geom_size:bshin[0]": 0.2}})  # grows the geom and its bounds
    for _ in range(3):
        env.step(env.action_space.sample())
    env.reset(options={"task": env.parameters.defaults})
    assert_same_model(env.unwrapped.model, pristine)  # nothing of the earlier episodes is left
    env.reset(seed=2)
    env.close()
    assert_same_model(env.unwrapped.model, pristine)


def test_same_seed_same_task_and_rollout() -> None:
    def rollout(seed: int) -> tuple[dict[str, float], np.ndarray]:
        env = cheetah_family()
        obs, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        observations = [obs]
        for _ in range(10):
            observations.append(env.step(env.action_space.sample())[0])
        return info["task"], np.stack(observations)

    first, second, other = rollout(0), rollout(0), rollout(1)
    assert first[0] == second[0] and first[0] != other[0]
    np.testing.assert_array_equal(first[1], second[1])


def test_fixing_some_names_leaves_the_other_draws_unchanged() -> None:
    env = cheetah_family()
    drawn = env.reset(seed=3)[1]["task"]
    fixed = env.reset(seed=3, options={"task": {"gravity": -1.0}})[1]["task"]
    assert fixed == {**drawn, "gravity": -1.0}
    assert env.unwrapped.model.opt.gravity[2] == -1.0


def test_unknown_task_name_raises_and_leaves_the_state_unchanged() -> None:
    env = cheetah_family()
    env.reset(seed=0)
    env.step(env.action_space.sample())
    before, qpos, task = model_arrays(env.unwrapped.model), env.unwrapped.data.qpos.copy(), env.task
    with pytest.raises(ValueError, match=r"unknown task name\(s\) \['mass'\].*body_mass:torso"):
        env.reset(options={"task": {"mass": 3.0}})
    with pytest.raises(ValueError, match="finite"):
        env.reset(options={"task": {"gravity": float("nan")}})
    with pytest.raises(ValueError, match="mapping"):
        env.reset(options={"task": 3.0})
    assert_same_model(env.unwrapped.model, before)
    np.testing.assert_array_equal(env.unwrapped.data.qpos, qpos)
    assert env.task == task


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("body_mass:torsoo", r"no body named 'torsoo'; valid: \[.*'torso'"),
        ("geom_friction:nope", r"no geom named 'nope'; valid: \[.*'ffoot'"),
        ("actuator_gear:nope", r"no actuator named 'nope'; valid: \[.*'bthigh'"),
        ("joint_damping:nope", r"no joint named 'nope'; valid: \[.*'bthigh'"),
        ("body_masses:torso", r"unknown field 'body_masses'; valid: \['body_mass'"),
        ("geom_friction:ffoot[3]", r"component must be in 0..2"),
        ("body_mass:torso[0]", "scalar"),
        ("gravity:torso", "names no element"),
        ("gravity[x]", "integer"),
    ],
)
def test_bad_names_raise_at_construction(name: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        TaskFamily(gymnasium.make("HalfCheetah-v5"), params={name: Uniform(0.0, 1.0)})


def test_bad_arguments_raise() -> None:
    cheetah = gymnasium.make("HalfCheetah-v5")
    with pytest.raises(TypeError, match="sample"):
        TaskFamily(cheetah, params={"gravity": (0.0, 1.0)})  # type: ignore[dict-item]
    with pytest.raises(TypeError, match="MuJoCo env"):
        TaskFamily(gymnasium.make("Pendulum-v1"), params={"gravity": Uniform(0.0, 1.0)})
    with pytest.raises(ValueError, match="exactly three"):
        TaskFamily(cheetah, action=ActionTransform(rotation=Uniform(0.0, 1.0)))  # 6 action entries
    with pytest.raises(ValueError, match="out of range"):
        TaskFamily(cheetah, action=ActionTransform(gain=Uniform(0.0, 1.0), dims=(0, 6)))
    with pytest.raises(ValueError, match="observation wrappers"):
        TaskFamily(gymnasium.wrappers.FlattenObservation(gymnasium.make("HalfCheetah-v5")))
    with pytest.raises(ValueError, match="low <= high"):
        Uniform(1.0, 0.0)
    with pytest.raises(ValueError, match="0 < low"):
        LogUniform(0.0, 1.0)


def test_unnamed_actuators_are_found_by_their_joint_and_free_joints_damp_all_dofs() -> None:
    env = TaskFamily(
        gymnasium.make("Ant-v5"), params={"actuator_gear:hip_1": Fixed(0.0), "joint_damping:root": Fixed(2.0)}
    )
    env.reset(seed=0)
    model = env.unwrapped.model
    assert model.actuator_gear[:, 0].tolist() == [150.0, 150.0, 0.0, *[150.0] * 5]  # hip_1 drives actuator 2
    assert model.dof_damping[:6].tolist() == [2.0] * 6 and model.dof_damping[6] != 2.0


def test_gravity_changes_the_physics() -> None:
    env = TaskFamily(gymnasium.make("Hopper-v5", reset_noise_scale=0.0), params={"gravity": Uniform(-10.0, -9.0)})

    def height_after(gravity: float) -> float:
        env.reset(seed=0, options={"task": {"gravity": gravity}})
        for _ in range(20):
            obs, *_ = env.step(np.zeros(3))
        return float(obs[0])

    assert height_after(0.0) == pytest.approx(1.25, abs=1e-6)  # weightless: stays at its initial height
    assert height_after(-9.81) < 1.21  # falls onto its foot (about 1.203 m)


def test_action_gain_bias_and_clipping_reach_the_env() -> None:
    env = TaskFamily(gymnasium.make("HalfCheetah-v5"), action=ActionTransform(gain=Uniform(0.5, 2.0), bias=Fixed(0.1)))
    env.reset(seed=0, options={"task": {"action:gain": 2.0}})
    action = np.array([0.1, -0.2, 0.3, 0.6, -0.9, 0.0], dtype=np.float32)
    env.step(action)
    expected = np.clip(2.0 * action.astype(np.float64) + 0.1, -1.0, 1.0).astype(np.float32)
    np.testing.assert_array_equal(env.unwrapped.data.ctrl, expected)


def test_rotation_about_an_axis() -> None:
    about_z = ActionTransform(rotation=Uniform(-1.0, 1.0), dims=(0, 1, 2))
    np.testing.assert_allclose(
        about_z.apply(np.array([1.0, 0.0, 0.5, 0.7]), {"action:rotation": 0.3}),
        [np.cos(0.3), np.sin(0.3), 0.5, 0.7],
        atol=1e-15,
    )
    tilted = ActionTransform(rotation=Uniform(-1.0, 1.0), axis=(1.0, 1.0, 0.0), dims=(1, 2, 3))
    vector = np.array([9.0, 0.3, -0.4, 0.8])
    out = tilted.apply(vector, {"action:rotation": 1.1})
    assert out[0] == 9.0 and np.linalg.norm(out[1:]) == pytest.approx(np.linalg.norm(vector[1:]))
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    assert out[1:] @ axis == pytest.approx(vector[1:] @ axis)  # the component along the axis is kept
    np.testing.assert_allclose(tilted.apply(vector, {}), vector)  # no draw: identity


def test_model_parameters_standalone() -> None:
    model = gymnasium.make("Walker2d-v5").unwrapped.model  # type: ignore[attr-defined]
    params = ModelParameters(model, ["geom_pos:foot_geom[2]", "gravity[0]"])
    foot = model.geom("foot_geom").id
    sameframe = int(model.geom_sameframe[foot])
    params.set({"geom_pos:foot_geom[2]": 0.05, "gravity[0]": 1.0})
    assert model.geom_pos[foot, 2] == 0.05 and model.opt.gravity.tolist() == [1.0, 0.0, -9.81]
    assert model.geom_sameframe[foot] == mujoco.mjtSameFrame.mjSAMEFRAME_NONE  # so MuJoCo uses geom_pos
    with pytest.raises(ValueError, match="unknown parameter"):
        params.set({"gravity": 1.0})
    params.restore()
    assert params.values() == params.defaults and int(model.geom_sameframe[foot]) == sameframe


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5"])
def test_check_env_on_gymnasium_mujoco_envs(env_id: str) -> None:
    base = gymnasium.make(env_id)
    torso = "torso"
    env = TaskFamily(
        base, params={f"body_mass:{torso}": Uniform(1.0, 5.0)}, action=ActionTransform(gain=Uniform(0.5, 1.0))
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*(Box observation space|different from the unwrapped).*")
        check_env(env, skip_render_check=True)
    _, info = env.reset(seed=0)
    assert env.unwrapped.model.body(torso).mass[0] == info["task"][f"body_mass:{torso}"]
