"""gymnasium-robotics: the mujoco joint-type compatibility fix and the registered robotics task families."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; must precede the first mujoco import

import copy
import json
import pickle
import subprocess
import sys
import warnings

import numpy as np
import pytest

pytest.importorskip("gymnasium_robotics")

import gymnasium  # noqa: E402
import mujoco  # noqa: E402

from smcd_rl.integrations import robotics  # noqa: E402
from smcd_rl.integrations.robotics import fix_mujoco_joint_types, joint_types_broken  # noqa: E402

# A fresh interpreter, so that no fix applied earlier in this process hides the bug.
_MAKE_FETCH = """
import gymnasium, gymnasium_robotics
gymnasium.register_envs(gymnasium_robotics)
{fix}
try:
    gymnasium.make("FetchReach-v4").reset(seed=0)
except AssertionError:
    print("AssertionError")
else:
    print("ok")
"""


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_joint_types_broken_matches_the_comparison() -> None:
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    assert joint_types_broken() == (not bool(hinge == np.int32(3)))


@pytest.mark.skipif(not joint_types_broken(), reason="this mujoco compares joint types correctly")
def test_fetch_fails_without_the_fix_and_works_with_it() -> None:
    assert _run(_MAKE_FETCH.format(fix="")) == "AssertionError"
    fix = "from smcd_rl.integrations.robotics import fix_mujoco_joint_types; fix_mujoco_joint_types()"
    assert _run(_MAKE_FETCH.format(fix=fix)) == "ok"


def test_fix_is_idempotent_and_keeps_the_rest_of_mujoco() -> None:
    from gymnasium_robotics.utils import mujoco_utils

    fix_mujoco_joint_types()
    view = mujoco_utils.mujoco
    fix_mujoco_joint_types()
    assert mujoco_utils.mujoco is view
    if joint_types_broken():
        assert isinstance(view, robotics._MujocoView)
    assert view.mj_forward is mujoco.mj_forward
    assert view.mjtObj is mujoco.mjtObj
    for name, member in mujoco.mjtJoint.__members__.items():
        value = getattr(view.mjtJoint, name)
        assert value == int(member) and np.int32(int(member)) in (value,)


def test_fixed_helpers_read_every_joint_type() -> None:
    from gymnasium_robotics.utils import mujoco_utils

    fix_mujoco_joint_types()
    xml = """<mujoco><worldbody>
      <body name="free"><freejoint name="f"/><geom size="0.1"/></body>
      <body name="b" pos="1 0 0"><joint name="ball" type="ball"/><geom size="0.1"/>
        <body name="h"><joint name="hinge" type="hinge"/><geom size="0.1"/>
          <body name="s"><joint name="slide" type="slide"/><geom size="0.1"/></body></body></body>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    sizes = {name: mujoco_utils.get_joint_qpos(model, data, name).shape for name in ("f", "ball", "hinge", "slide")}
    assert sizes == {"f": (7,), "ball": (4,), "hinge": (1,), "slide": (1,)}
    mujoco_utils.set_joint_qpos(model, data, "hinge", 0.25)
    assert mujoco_utils.get_joint_qpos(model, data, "hinge")[0] == 0.25


def test_fix_does_nothing_when_the_comparison_works(monkeypatch: pytest.MonkeyPatch) -> None:
    from gymnasium_robotics.utils import mujoco_utils

    monkeypatch.setattr(robotics, "joint_types_broken", lambda: False)
    monkeypatch.setattr(mujoco_utils, "mujoco", mujoco)
    fix_mujoco_joint_types()
    assert mujoco_utils.mujoco is mujoco


def test_gymnasium_make_fetch_after_the_fix() -> None:
    import gymnasium_robotics

    gymnasium.register_envs(gymnasium_robotics)
    fix_mujoco_joint_types()
    env = gymnasium.make("FetchReach-v4")
    obs, _ = env.reset(seed=0)
    assert obs["observation"].shape == (10,)
    env.close()


# ---------------------------------------------------------------- the registered task families

FAMILIES = ("smcd_rl/FetchReachRotated-v0", "smcd_rl/FetchPushHeavy-v0", "smcd_rl/FrankaReachTool-v0")


@pytest.fixture(scope="module", autouse=True)
def _register() -> None:
    from smcd_rl.envs import register_all

    register_all()


def _quiet_check_env(env: gymnasium.Env) -> None:
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        # Unbounded observations are intended; the families are wrappers by design.
        warnings.filterwarnings("ignore", message=".*(Box observation space|different from the unwrapped).*")
        check_env(env, skip_render_check=True)


@pytest.mark.parametrize("env_id", FAMILIES)
def test_gymnasium_check_env(env_id: str) -> None:
    env = gymnasium.make(env_id)
    assert env.spec is not None and env.spec.id == env_id
    _quiet_check_env(env)  # the family, as users get it
    _quiet_check_env(env.unwrapped)  # and the env under it


@pytest.mark.parametrize("env_id", FAMILIES)
def test_torchrl_check_env_specs(env_id: str) -> None:
    pytest.importorskip("torchrl")
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv(env_id)
    check_env_specs(env, seed=0)
    assert "observation" in env.observation_spec.keys()


@pytest.mark.parametrize("family", ["FetchReachRotated", "FetchPushHeavy", "FrankaReachTool"])
def test_stable_baselines3_check_env(family: str) -> None:
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no complaint at all
        check_env(getattr(robotics, family)(), skip_render_check=True)


_RENDER = """
import json, gymnasium, numpy as np, smcd_rl
frames = {}
for env_id in %r:
    env = gymnasium.make(env_id, render_mode="rgb_array", width=64, height=48)
    env.reset(seed=0)
    frame = env.render()
    frames[env_id] = [list(frame.shape), str(frame.dtype), float(frame.std())]
    env.close()
print(json.dumps(frames))
"""


@pytest.mark.slow
def test_every_family_renders_an_rgb_frame_headless() -> None:
    # A fresh interpreter: MuJoCo picks its GL backend on import, which an earlier test may have done.
    env = {**os.environ, "MUJOCO_GL": "egl"}
    code = _RENDER % (FAMILIES,)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, check=True
    )
    frames = json.loads(done.stdout.strip().splitlines()[-1])
    assert list(frames) == list(FAMILIES)
    for shape, dtype, std in frames.values():
        assert shape == [48, 64, 3] and dtype == "uint8"
        assert std > 1.0  # a scene, not a blank image


def test_same_seed_same_task_and_observations() -> None:
    for env_id in FAMILIES:
        first, second = (gymnasium.make(env_id) for _ in range(2))
        (obs_a, info_a), (obs_b, info_b) = first.reset(seed=7), second.reset(seed=7)
        assert info_a["task"] == info_b["task"]
        assert info_a["task"] != first.reset(seed=8)[1]["task"]
        flat = gymnasium.spaces.utils.flatten
        np.testing.assert_array_equal(flat(first.observation_space, obs_a), flat(second.observation_space, obs_b))


def test_rotated_reach_moves_the_gripper_target_by_the_rotated_command() -> None:
    from gymnasium_robotics.utils import mujoco_utils

    env = robotics.FetchReachRotated()
    angle, gain = 0.4, 0.8
    _, info = env.reset(seed=1, options={"task": {"action:rotation": angle, "action:gain": gain}})
    assert info["task"] == {"action:rotation": angle, "action:gain": gain}
    base = env.unwrapped
    command = np.array([0.5, 0.2, -0.1, 1.0], dtype=np.float32)
    c, s = np.cos(angle), np.sin(angle)
    rotated = gain * np.array([c * 0.5 - s * 0.2, s * 0.5 + c * 0.2, -0.1])
    for _ in range(3):
        mujoco_utils.reset_mocap2body_xpos(base.model, base.data)  # Fetch's own first move in a step
        target = base.data.mocap_pos[0].copy()
        env.step(command)
        np.testing.assert_allclose(base.data.mocap_pos[0] - target, 0.05 * rotated, atol=1e-6)  # 5 cm per unit
    # The gripper follows: over ten more steps it travels along the rotated direction.
    start = env.step(command)[0]["observation"][:3]
    for _ in range(10):
        obs = env.step(command)[0]
    moved = obs["observation"][:3] - start
    cosine = moved @ rotated / (np.linalg.norm(moved) * np.linalg.norm(rotated))
    assert cosine > 0.99


def _push(env: gymnasium.Env, mass: float, friction: float) -> float:
    """Put the gripper behind the block, shove it along +x for 3 steps, let it slide: the block's x travel."""
    obs, _ = env.reset(seed=0, options={"task": {"body_mass:object0": mass, "geom_friction:object0": friction}})
    block = obs["observation"][3:6].copy()
    for t in range(29):
        gripper = obs["observation"][:3]
        if t < 10:
            move = np.clip((block + [-0.08, 0.0, 0.08] - gripper) * 20, -1, 1)  # above the back of the block
        elif t < 18:
            move = np.clip((block + [-0.08, 0.0, 0.0] - gripper) * 20, -1, 1)  # down to the table
        else:
            move = np.array([1.0, 0.0, 0.0]) if t < 21 else np.zeros(3)
        obs, *_ = env.step(np.r_[move, 0.0].astype(np.float32))
    travel = obs["observation"][3:6] - block
    assert abs(travel[2]) < 0.01  # still on the table
    return float(travel[0])


def test_heavier_block_moves_less_and_slippery_block_further_under_the_same_push() -> None:
    env = robotics.FetchPushHeavy()
    model = env.unwrapped.model
    _, info = env.reset(seed=0)
    table = model.body_geomadr[model.body("table0").id]
    assert model.geom_friction[table, 0] == info["task"]["geom_friction:table0"] == 0.1
    light, heavy = _push(env, 1.0, 1.0), _push(env, 6.0, 1.0)
    slippery = _push(env, 1.0, 0.1)
    # Measured: 0.19 m, 0.06 m and 0.37 m.
    assert 0.05 < heavy < 0.5 * light and slippery > 1.5 * light
    assert model.body("object0").mass[0] == 1.0 and model.body("object0").inertia[0] == pytest.approx(
        0.000833 / 2, rel=1e-3
    )


def test_tool_length_moves_the_end_effector_along_link_7_and_the_first_observation_sees_it() -> None:
    env = robotics.FrankaReachTool()
    base = env.unwrapped
    positions = {}
    for tip in (0.21, 0.61):
        obs, info = env.reset(seed=0, options={"task": {"site_pos:end_effector[2]": tip}})
        np.testing.assert_array_equal(obs[14:17], base.end_effector)  # measured with this episode's tool
        assert info["distance"] == pytest.approx(np.linalg.norm(base.end_effector - base.goal))
        positions[tip] = base.end_effector
    link7 = base.data.xmat[base.model.body("panda0_link7").id].reshape(3, 3)
    np.testing.assert_allclose(positions[0.61] - positions[0.21], 0.4 * link7[:, 2], atol=1e-12)
    np.testing.assert_array_equal(obs[:7], robotics.FRANKA_READY_POSE)


def test_end_effector_is_measured_every_n_steps() -> None:
    env = robotics.FrankaReachTool(measure_every=3)
    obs, info = env.reset(seed=0)
    assert info["measured"]
    measured, measured_flags = [obs[14:17]], []
    for _ in range(7):
        obs, _, _, _, info = env.step(np.full(7, 0.5, dtype=np.float32))
        measured.append(obs[14:17])
        measured_flags.append(info["measured"])
        if info["measured"]:
            np.testing.assert_array_equal(obs[14:17], env.unwrapped.end_effector)
    assert measured_flags == [False, False, True, False, False, True, False]
    np.testing.assert_array_equal(measured[0], measured[2])  # held between measurements
    assert not np.array_equal(measured[2], measured[3])  # the arm moved


def test_bad_family_arguments_raise() -> None:
    with pytest.raises(ValueError, match="measure_every"):
        robotics.FrankaReachEnv(measure_every=0)
    with pytest.raises(ValueError, match="low <= high"):
        robotics.FetchPushHeavy(mass=(3.0, 1.0))
    with pytest.raises(ValueError, match="unknown task name"):
        robotics.FetchPushHeavy().reset(options={"task": {"body_mass:object": 1.0}})


@pytest.mark.parametrize(
    ("family", "kwargs", "message"),
    [
        ("FetchPushHeavy", {"mass": 3}, r"mass must be a \(low, high\) range .* pass mass=\(v, v\)"),
        ("FetchPushHeavy", {"mass": (-3, -1)}, "mass must be a range of masses .* positive"),
        ("FetchPushHeavy", {"mass": (0.0, 1.0)}, "mass must be a range of masses .* positive"),
        ("FetchPushHeavy", {"friction": (-0.5, 1.0)}, "friction must be a range .* non-negative"),
        ("FetchPushHeavy", {"mass": ("1", "2")}, r"mass must be a \(low, high\) range"),
        ("FetchPushHeavy", {"mass": (1.0, 2.0, 3.0)}, r"mass must be a \(low, high\) range"),
        ("FetchReachRotated", {"gain": 1.0}, r"gain must be a \(low, high\) range"),
        ("FetchReachRotated", {"rotation": (0.5, -0.5)}, "rotation must be .* low <= high"),
        ("FrankaReachTool", {"tool": (1, -1)}, "FrankaReachTool: tool must be .* low <= high"),
        ("FrankaReachTool", {"tool": (0.0, float("nan"))}, "tool must be"),
    ],
)
def test_family_arguments_are_checked_by_name(family: str, kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        getattr(robotics, family)(**kwargs)
    env_id = f"smcd_rl/{family}-v0"
    with pytest.raises(ValueError, match=message):
        gymnasium.make(env_id, **kwargs)


def test_fixed_ranges_and_physically_invalid_task_values() -> None:
    env = robotics.FetchPushHeavy(mass=(3.0, 3.0))
    assert env.reset(seed=0)[1]["task"]["body_mass:object0"] == 3.0
    model = env.unwrapped.model
    before = model.body_mass.copy(), model.geom_friction.copy()
    for name, value in [("body_mass:object0", -2.0), ("geom_friction:object0", -0.1)]:
        with pytest.raises(ValueError, match=f"options\\['task'\\] of '{name}' is .* must be"):
            env.reset(options={"task": {name: value}})
    np.testing.assert_array_equal(model.body_mass, before[0])
    np.testing.assert_array_equal(model.geom_friction, before[1])


_COPIES = {"deepcopy": copy.deepcopy, "pickle": lambda env: pickle.loads(pickle.dumps(env))}
_TASKS = {  # a value for each family's model parameter (FetchReachRotated has only an action transform)
    "smcd_rl/FetchReachRotated-v0": ({"action:rotation": 0.25}, None),
    "smcd_rl/FetchPushHeavy-v0": ({"body_mass:object0": 5.5}, lambda m: m.body("object0").mass[0]),
    "smcd_rl/FrankaReachTool-v0": ({"site_pos:end_effector[2]": 0.5}, lambda m: m.site("end_effector").pos[2]),
}


@pytest.mark.parametrize("how", _COPIES)
@pytest.mark.parametrize("env_id", FAMILIES)
def test_copies_of_every_family_simulate_the_task_they_report(env_id: str, how: str) -> None:
    env = gymnasium.make(env_id)
    env.reset(seed=0)
    task, read = _TASKS[env_id]
    before = None if read is None else float(read(env.unwrapped.model))
    twin = _COPIES[how](env)
    _, info = twin.reset(seed=1, options={"task": task})
    assert {name: info["task"][name] for name in task} == task
    if read is not None:  # the copy simulates what it reports, and the original is unchanged
        assert float(read(twin.unwrapped.model)) == next(iter(task.values()))
        assert float(read(env.unwrapped.model)) == before
    twin.step(twin.action_space.sample())


def test_franka_reaching_is_feasible_with_the_true_tool() -> None:
    """A damped least-squares Jacobian controller that knows the tool reaches most goals in time (6 of 8 here)."""
    env = gymnasium.make("smcd_rl/FrankaReachTool-v0")
    base = env.unwrapped
    jac = np.zeros((3, base.model.nv))
    successes = 0
    for seed in range(8):
        env.reset(seed=seed)
        for _ in range(200):
            mujoco.mj_jacSite(base.model, base.data, jac, None, base.model.site("end_effector").id)
            j = jac[:, :7]
            velocity = j.T @ np.linalg.solve(j @ j.T + 1e-2 * np.eye(3), 8.0 * (base.goal - base.end_effector))
            _, _, _, truncated, info = env.step(np.clip(velocity / 2.0, -1, 1).astype(np.float32))
            if info["is_success"] or truncated:
                break
        successes += info["is_success"]
    assert successes >= 5


def test_import_smcd_rl_registers_the_families_without_importing_mujoco() -> None:
    code = """
import json, sys
import gymnasium, smcd_rl
loaded = sorted({m.split(".")[0] for m in sys.modules} & {"mujoco", "gymnasium_robotics"})
print(json.dumps({"loaded": loaded, "ids": sorted(i for i in gymnasium.registry if i.startswith("smcd_rl/F"))}))
"""
    assert json.loads(_run(code)) == {"loaded": [], "ids": sorted(FAMILIES)}


def test_the_spec_rebuilds_the_family_and_vector_envs_work() -> None:
    for env_id in FAMILIES:
        env = gymnasium.make(env_id)
        assert env.spec is not None and env.spec.additional_wrappers == ()
        again = gymnasium.make(env.spec)
        assert type(again.unwrapped) is type(env.unwrapped)
        assert again.reset(seed=0)[1]["task"] == env.reset(seed=0)[1]["task"]
    vector = gymnasium.make_vec("smcd_rl/FetchPushHeavy-v0", num_envs=2)
    _, infos = vector.reset(seed=0)
    masses = infos["task"]["body_mass:object0"]
    assert masses.shape == (2,) and masses[0] != masses[1]  # each sub-env draws its own task
