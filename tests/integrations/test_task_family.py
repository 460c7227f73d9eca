"""TaskFamily on gymnasium's MuJoCo envs: naming, drawing, seeding, restoring, action transforms, errors."""

from __future__ import annotations

import copy
import json
import pickle
import warnings
from collections.abc import Callable
from typing import Any

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
        "geom_size:bshin": Uniform(0.03, 0.09),
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
    assert model.geom_size[bshin, 0] == task["geom_size:bshin"]
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
    env.reset(seed=0, options={"task": {"body_mass:torso": 2 * mass, "geom_size:bshin": 3 * radius}})
    np.testing.assert_allclose(model.body_inertia[torso], 2 * inertia)
    assert model.geom_rbound[bshin] == pytest.approx(3 * rbound)  # conservative: the largest ratio


def test_restore_on_reset_and_close_leaves_the_model_bit_identical() -> None:
    env = cheetah_family()
    pristine = model_arrays(env.unwrapped.model)
    env.reset(seed=1)
    env.reset(options={"task": {"geom_size:bshin": 0.2}})  # grows the geom and its bounds
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
    with pytest.raises(ValueError, match="two action entries .* or three .* got 6"):
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


# ---------------------------------------------------------------- copies, names, physical ranges, actions

COPIES: dict[str, Callable[[Any], Any]] = {
    "deepcopy": copy.deepcopy,
    "pickle": lambda env: pickle.loads(pickle.dumps(env)),
}


@pytest.mark.parametrize("how", COPIES)
@pytest.mark.parametrize("env_id", ["Hopper-v5", "HalfCheetah-v5"])
def test_a_copy_simulates_the_task_it_reports_and_leaves_the_original_alone(env_id: str, how: str) -> None:
    # gymnasium's MuJoCo envs rebuild themselves on copy (EzPickle): the copy has a model of its own.
    env = TaskFamily(gymnasium.make(env_id), params={"body_mass:torso": Uniform(1.0, 9.0), "gravity": Fixed(-9.0)})
    env.reset(seed=0, options={"task": {"body_mass:torso": 2.0}})
    original = model_arrays(env.unwrapped.model)
    twin = COPIES[how](env)
    assert twin.unwrapped.model is not env.unwrapped.model
    assert twin.task == env.task and twin.unwrapped.model.body("torso").mass[0] == 2.0  # the task it reports
    _, info = twin.reset(seed=1, options={"task": {"body_mass:torso": 5.5}})
    model = twin.unwrapped.model
    assert info["task"] == {"body_mass:torso": 5.5, "gravity": -9.0} == twin.task
    assert model.body("torso").mass[0] == 5.5 and model.opt.gravity[2] == -9.0
    assert_same_model(env.unwrapped.model, original)  # the original's model is untouched
    twin.close()  # restores the copy's defaults, not the original's
    assert_same_model(env.unwrapped.model, original)
    assert model.body("torso").mass[0] == env.parameters.defaults["body_mass:torso"]


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("gravity[2]", r"write 'gravity'"),
        ("geom_friction:ffoot[0]", r"write 'geom_friction:ffoot'"),
        ("geom_size:bshin[0]", r"write 'geom_size:bshin'"),
        ("actuator_gear:bthigh[0]", r"write 'actuator_gear:bthigh'"),
        ("gravity[00]", r"gravity\[0\]"),
        ("geom_friction:ffoot[01]", r"geom_friction:ffoot\[1\]"),
        ("gravity[\u0662]", "integer"),  # a non-ASCII digit two
        ("gravity:", r"write 'gravity'"),  # an empty element is no second name either
        ("gravity:[1]", r"gravity\[k\]"),
    ],
)
def test_one_name_per_model_element(name: str, canonical: str) -> None:
    cheetah = gymnasium.make("HalfCheetah-v5")
    with pytest.raises(ValueError, match=canonical):
        TaskFamily(cheetah, params={name: Uniform(0.1, 1.0)})
    with pytest.raises(ValueError, match=canonical):
        ModelParameters(cheetah.unwrapped.model, [name])  # type: ignore[attr-defined]


def test_both_names_of_one_element_cannot_be_reported_at_once() -> None:
    with pytest.raises(ValueError, match="write 'gravity'"):
        TaskFamily(gymnasium.make("HalfCheetah-v5"), params={"gravity": Fixed(-9.0), "gravity[2]": Fixed(-5.0)})


@pytest.mark.parametrize(
    ("name", "dist", "bound"),
    [
        ("body_mass:torso", Uniform(-3.0, -1.0), "> 0"),
        ("body_mass:torso", Fixed(0.0), "> 0"),
        ("geom_friction:ffoot", Uniform(-0.5, 1.0), ">= 0"),
        ("joint_damping:bthigh", Choice((-1.0, 2.0)), ">= 0"),
        ("geom_size:bshin", Uniform(0.0, 0.1), "> 0"),
        ("actuator_gear:bthigh", Fixed(-120.0), ">= 0"),
        ("geom_rgba:bshin[1]", Uniform(0.5, 1.5), r"in \[0, 1\]"),
    ],
)
def test_a_distribution_outside_the_physical_range_is_refused_at_construction(name: str, dist: Any, bound: str) -> None:
    with pytest.raises(ValueError, match=rf"{name.replace('[', '.').replace(']', '.')}.*must be {bound}"):
        TaskFamily(gymnasium.make("HalfCheetah-v5"), params={name: dist})


def test_physically_invalid_task_values_are_refused_and_leave_the_state_unchanged() -> None:
    env = cheetah_family()
    env.reset(seed=0)
    env.step(env.action_space.sample())
    before, qpos, task = model_arrays(env.unwrapped.model), env.unwrapped.data.qpos.copy(), env.task
    for name, value in [
        ("body_mass:torso", -1.0),
        ("geom_friction:ffoot", -0.1),
        ("joint_damping:bthigh", -2.0),
        ("geom_size:bshin", 0.0),
        ("actuator_gear:bthigh", -60.0),
    ]:
        with pytest.raises(ValueError, match=rf"options\['task'\] of '{name}' is .*must be >=? 0"):
            env.reset(options={"task": {name: value}})
    with pytest.raises(ValueError, match="must be a number"):
        env.reset(options={"task": {"body_mass:torso": "5.5"}})
    assert_same_model(env.unwrapped.model, before)
    np.testing.assert_array_equal(env.unwrapped.data.qpos, qpos)
    assert env.task == task
    with pytest.raises(ValueError, match="body_mass must be > 0"):
        env.parameters.set({"body_mass:torso": -1.0})
    assert_same_model(env.unwrapped.model, before)


class Normal:
    """A distribution of one's own, without ``support()``: its draws are checked one by one."""

    def sample(self, rng: np.random.Generator) -> float:
        return float(rng.normal(0.0, 1.0))


def test_a_draw_outside_the_range_from_a_distribution_without_support_is_refused() -> None:
    env = TaskFamily(gymnasium.make("HalfCheetah-v5"), params={"body_mass:torso": Normal()})
    with pytest.raises(ValueError, match="the draw of 'body_mass:torso' is .* must be > 0"):
        for seed in range(20):  # about half the draws are negative
            env.reset(seed=seed)
    assert env.task == {}  # no task is applied: the model has its defaults
    assert env.unwrapped.model.body("torso").mass[0] == env.parameters.defaults["body_mass:torso"]


def test_a_draw_that_is_not_finite_is_refused_and_no_action_transform_receives_it() -> None:
    class NotANumber:
        def sample(self, rng: np.random.Generator) -> float:
            return float("nan")

    env = TaskFamily(gymnasium.make("HalfCheetah-v5"), action=ActionTransform(gain=NotANumber()))
    with pytest.raises(ValueError, match="the draw of 'action:gain' must be finite"):
        env.reset(seed=0)
    assert env.task == {}


@pytest.mark.parametrize(
    "make",
    [
        lambda: Uniform("1", "2"),
        lambda: Uniform(True, 2.0),
        lambda: LogUniform("0.5", 2.0),
        lambda: Fixed("1"),
        lambda: Choice(("a", "b")),
        lambda: Choice(1.0),
    ],
)
def test_distributions_refuse_non_numbers_at_construction(make: Callable[[], Any]) -> None:
    with pytest.raises(ValueError, match="number"):
        make()


def test_distribution_fields_are_floats_and_report_their_support() -> None:
    assert Uniform(1, 2) == Uniform(1.0, 2.0) and type(Uniform(1, 2).low) is float
    assert Uniform(1, 2).support() == (1.0, 2.0) and LogUniform(0.5, 2).support() == (0.5, 2.0)
    assert Choice((3, -1, 2)).support() == (-1.0, 3.0) and Fixed(4).support() == (4.0, 4.0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"gain": Fixed(1.0), "dims": (1.5,)}, "non-negative ints"),
        ({"gain": Fixed(1.0), "dims": (True,)}, "non-negative ints"),
        ({"gain": Fixed(1.0), "dims": (-1,)}, "non-negative ints"),
        ({"gain": Fixed(1.0), "dims": (0, 0)}, "each action entry once"),
        ({"rotation": Fixed(1.0), "dims": {1, 0}}, "non-negative ints"),  # a set has no order
        ({"rotation": Fixed(1.0), "dims": (0, 0, 1)}, "each action entry once"),
        ({"rotation": Fixed(1.0), "dims": (0,)}, "two action entries .* or three"),
        ({"rotation": Fixed(1.0), "dims": (0, 1), "axis": (0.0, 0.0, 1.0)}, "planar rotation .* takes no axis"),
        ({"rotation": Fixed(1.0), "dims": (0, 1, 2), "axis": (0.0, 0.0)}, "3-vector"),
    ],
)
def test_action_transform_refuses_bad_dims_and_axes(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ActionTransform(**kwargs)


@pytest.mark.parametrize("action", [None, ActionTransform(gain=Fixed(2.0))])
def test_a_wrong_action_shape_names_the_expected_shape(action: ActionTransform | None) -> None:
    env = TaskFamily(gymnasium.make("HalfCheetah-v5"), params={"body_mass:torso": Uniform(5.0, 9.0)}, action=action)
    env.reset(seed=0)
    qpos = env.unwrapped.data.qpos.copy()
    for wrong in (np.zeros(5), np.zeros((2, 6)), 0.5):
        with pytest.raises(ValueError, match=r"shape \(6,\)"):
            env.step(wrong)
    np.testing.assert_array_equal(env.unwrapped.data.qpos, qpos)


def test_planar_rotation_turns_a_2d_command() -> None:
    # Reacher's action is the torque of its two joints: a 2-D command.
    env = TaskFamily(gymnasium.make("Reacher-v5"), action=ActionTransform(rotation=Uniform(-np.pi, np.pi)))
    _, info = env.reset(seed=0, options={"task": {"action:rotation": np.pi / 2}})
    assert info["task"] == {"action:rotation": np.pi / 2}
    env.step(np.array([0.5, 0.0], dtype=np.float32))
    np.testing.assert_allclose(env.unwrapped.data.ctrl, [0.0, 0.5], atol=1e-7)  # turned counter-clockwise
    env.reset(options={"task": {"action:rotation": 0.3}})
    command = np.array([0.2, -0.4])
    turned = env.transform_action(command.astype(np.float32))
    c, s = np.cos(0.3), np.sin(0.3)
    np.testing.assert_allclose(turned, [c * 0.2 + s * 0.4, s * 0.2 - c * 0.4], atol=1e-7)
    assert np.linalg.norm(turned) == pytest.approx(np.linalg.norm(command), abs=1e-7)  # a rotation keeps the length
    with pytest.raises(ValueError, match="two action entries .* or three .* got 6"):
        TaskFamily(gymnasium.make("HalfCheetah-v5"), action=ActionTransform(rotation=Fixed(0.1)))
