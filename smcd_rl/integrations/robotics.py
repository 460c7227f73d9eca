"""gymnasium-robotics task families, and a compatibility fix for recent mujoco releases.

Task families (registered on ``import smcd_rl``; making one needs gymnasium-robotics,
``pip install -e ".[robotics]"``, and says so if it is missing), each a
:class:`~smcd_rl.integrations.task_family.TaskFamily`:

| Id | Class | What changes per episode |
|----|-------|--------------------------|
| ``smcd_rl/FetchReachRotated-v0`` | :class:`FetchReachRotated` | rotation about z and gain of the commanded gripper displacement |
| ``smcd_rl/FetchPushHeavy-v0`` | :class:`FetchPushHeavy` | the block's mass and friction |
| ``smcd_rl/FrankaReachTool-v0`` | :class:`FrankaReachTool` | the length of an unknown tool on the Franka Panda (paper section 4.2) |

Their rewards are Python floats, from the family and from the env under it (``env.unwrapped``,
what stable-baselines3's ``check_env`` needs for a goal env): the Fetch envs here are
gymnasium-robotics' with only that changed (it returns ``numpy.float32``).

**The compatibility fix.** Since mujoco 3.12 the enum constants compare equal to numpy integers
only from one side: ``np.int32(3) == mujoco.mjtJoint.mjJNT_HINGE`` is ``True`` but
``mujoco.mjtJoint.mjJNT_HINGE == np.int32(3)`` is ``False``, so membership tests such as
``joint_type in (mjJNT_HINGE, mjJNT_SLIDE)`` fail. gymnasium-robotics 1.4 asserts exactly that in
``gymnasium_robotics.utils.mujoco_utils`` (``get_joint_qpos`` and friends), which makes
``gymnasium.make("FetchReach-v4")`` and the Franka kitchen raise a bare ``AssertionError``.
:func:`fix_mujoco_joint_types` repairs this without touching mujoco itself: it gives
``mujoco_utils`` its own view of the ``mujoco`` module whose ``mjtJoint`` constants are plain
``int`` (which compare equal to numpy integers from both sides); every other attribute is the real
module's. It changes nothing when the comparison works (older mujoco) and is safe to call often.
The Fetch families call it before building their env.

Example:
    >>> from smcd_rl.integrations.robotics import fix_mujoco_joint_types
    >>> fix_mujoco_joint_types()
    >>> import gymnasium, gymnasium_robotics
    >>> gymnasium.register_envs(gymnasium_robotics)
    >>> obs, info = gymnasium.make("FetchReach-v4").reset(seed=0)
    >>> obs["observation"].shape
    (10,)
"""

from __future__ import annotations

import importlib
import math
import os
import tempfile
import types
from typing import Any, Literal

import gymnasium
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from smcd_rl.envs.mujoco_setup import headless_mujoco, missing_extra

try:
    import mujoco
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    # Imported by name: gymnasium-robotics ships no type information.
    _fetch_reach: Any = importlib.import_module("gymnasium_robotics.envs.fetch.reach")
    _fetch_push: Any = importlib.import_module("gymnasium_robotics.envs.fetch.push")
except ModuleNotFoundError as error:
    raise missing_extra(
        error, "robotics", "smcd_rl.integrations.robotics (the Fetch and Franka task families)"
    ) from error

from smcd_rl.integrations.task_family import ActionTransform, Distribution, Fixed, TaskFamily, Uniform

__all__ = [
    "FRANKA_READY_POSE",
    "FetchPushEnv",
    "FetchPushHeavy",
    "FetchReachEnv",
    "FetchReachRotated",
    "FrankaReachEnv",
    "FrankaReachTool",
    "fix_mujoco_joint_types",
    "franka_assets_dir",
    "franka_model_xml",
    "joint_types_broken",
]


def joint_types_broken() -> bool:
    """Whether ``mujoco.mjtJoint`` constants fail to compare equal to numpy integers (mujoco >= 3.12)."""
    hinge = mujoco.mjtJoint.mjJNT_HINGE
    return not bool(hinge == np.int32(int(hinge)))


class _JointTypes(types.SimpleNamespace):
    """``mujoco.mjtJoint`` with its members as plain ``int``."""


class _MujocoView(types.ModuleType):
    """The real ``mujoco`` module, except that ``mjtJoint`` holds plain ``int`` constants."""

    def __init__(self, real: types.ModuleType) -> None:
        super().__init__(real.__name__, real.__doc__)
        self._smcd_real = real
        members = real.mjtJoint.__members__
        self.mjtJoint = _JointTypes(**{name: int(value) for name, value in members.items()})

    def __getattr__(self, name: str) -> Any:
        # Only called for names not set on the view: everything but mjtJoint.
        return getattr(self._smcd_real, name)


def fix_mujoco_joint_types() -> None:
    """Make gymnasium-robotics' joint-type checks work with mujoco >= 3.12 (idempotent).

    Replaces the ``mujoco`` global of ``gymnasium_robotics.utils.mujoco_utils`` by a view whose
    ``mjtJoint`` constants are plain ``int``; all other attributes are the real module's. Does
    nothing when the comparison already works or the fix is already in place.

    Raises:
        ModuleNotFoundError: gymnasium-robotics is not installed (``pip install -e ".[robotics]"``).
    """
    if not joint_types_broken():
        return
    # Imported by name: gymnasium-robotics ships no type information.
    mujoco_utils: Any = importlib.import_module("gymnasium_robotics.utils.mujoco_utils")
    if not isinstance(mujoco_utils.mujoco, _MujocoView):
        mujoco_utils.mujoco = _MujocoView(mujoco_utils.mujoco)


class FetchReachEnv(_fetch_reach.MujocoFetchReachEnv):
    """gymnasium-robotics' ``FetchReach-v4`` env, with a Python float reward (it returns ``numpy.float32``)."""

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, float(reward), terminated, truncated, info


class FetchPushEnv(_fetch_push.MujocoFetchPushEnv):
    """gymnasium-robotics' ``FetchPush-v4`` env, with a Python float reward (it returns ``numpy.float32``)."""

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, float(reward), terminated, truncated, info


def _fetch_env(cls: type[gymnasium.Env[Any, Any]], **kwargs: Any) -> gymnasium.Env[Any, Any]:
    """A Fetch env built from its class (no gymnasium.make wrappers), after the fix."""
    fix_mujoco_joint_types()
    return cls(**kwargs)


def _range(
    family: str, name: str, value: Any, *, unit: str = "", sign: Literal["positive", "non-negative"] | None = None
) -> tuple[float, float]:
    """``value`` as a ``(low, high)`` range of finite numbers, or a ValueError that names the argument."""
    example = f"{name}=(1.0, 2.0)" if sign else f"{name}=(-0.5, 0.5)"
    pair = tuple(value) if isinstance(value, (tuple, list)) else None
    numbers = pair is not None and all(
        isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) for v in pair
    )
    if pair is None or len(pair) != 2 or not numbers:
        fixed = f"; for a fixed value v pass {name}=(v, v)" if isinstance(value, (int, float)) else ""
        raise ValueError(f"{family}: {name} must be a (low, high) range{unit}, e.g. {example}; got {value!r}{fixed}")
    low, high = float(pair[0]), float(pair[1])
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise ValueError(f"{family}: {name} must be a (low, high) range{unit} with low <= high, got {value!r}")
    if (sign == "positive" and not low > 0) or (sign == "non-negative" and not low >= 0):
        raise ValueError(
            f"{family}: {name} must be a range{unit} of {sign} values (MuJoCo simulates others wrongly), "
            f"e.g. {example}; got {value!r}"
        )
    return low, high


class _RegisteredFamily(TaskFamily):
    """A family that builds its own env: its spec is the env's (``gymnasium.make`` rebuilds it from its id)."""

    @property  # Wrapper.spec would add this class as a wrapper around the env it already builds
    def spec(self) -> gymnasium.envs.registration.EnvSpec | None:  # type: ignore[override]
        return self.env.spec


class _FetchFamily(_RegisteredFamily):
    """A Fetch family; a goal env, so it offers Fetch's ``compute_reward`` (for hindsight relabelling)."""

    def compute_reward(self, achieved_goal: Any, desired_goal: Any, info: Any) -> Any:
        """Fetch's reward for ``achieved_goal`` and ``desired_goal`` (batched), as ``env.unwrapped.compute_reward``."""
        base: Any = self.env.unwrapped
        return base.compute_reward(achieved_goal, desired_goal, info)


class FetchReachRotated(_FetchFamily):
    r"""Fetch reach with an unknown rotation and gain of the commanded displacement.

    ## Description
    gymnasium-robotics' ``FetchReach-v4`` (a mocap-driven Fetch arm moves its gripper to a goal),
    where the gripper displacement that the action commands is rotated about the vertical axis by
    an unknown angle and scaled by an unknown gain, both drawn per episode: the env receives
    ``a'[0:3] = gain * Rz(rotation) @ a[0:3]``, clipped to ``[-1, 1]`` (the gripper entry is
    unchanged). A model of the arm trained on the plain env has to infer the frame and the
    gain from the first steps.

    ## Action Space
    ``Box(-1, 1, (4,), float32)``: commanded gripper displacement x, y, z (times 0.05 m per step,
    before the transform) and the gripper opening (ignored: the gripper is blocked in reach).

    ## Observation Space
    ``Dict``: ``observation`` (10: gripper position, finger state, gripper velocity, finger
    velocity), ``achieved_goal`` (3, gripper position), ``desired_goal`` (3), as FetchReach-v4.

    ## Rewards
    As FetchReach-v4: sparse (``-1`` unless within 5 cm of the goal) by default,
    ``reward_type="dense"`` gives the negative distance.

    ## Episode End
    Never terminates; ``gymnasium.make("smcd_rl/FetchReachRotated-v0")`` truncates after 50 steps.

    ## Task
    ``info["task"]``: ``{"action:rotation": angle (rad), "action:gain": gain}``;
    ``reset(options={"task": {...}})`` fixes them.

    ## Arguments
    | Parameter | Type | Default | Description |
    |---|---|---|---|
    | `rotation` | `tuple[float, float]` | `(-0.5, 0.5)` | range (rad) of the uniform rotation about z |
    | `gain` | `tuple[float, float]` | `(0.5, 1.5)` | range of the uniform gain |

    Each range is a ``(low, high)`` pair with ``low <= high``; ``(v, v)`` fixes the value. A
    single number is refused (with this hint), so that no scalar is silently read as a range.
    | `**kwargs` | | | passed to FetchReach (`reward_type`, `render_mode`, `width`, `height`, ...) |

    ## Version History
    * v0: Initial version, on FetchReach-v4.

    Example:
        >>> env = FetchReachRotated()
        >>> obs, info = env.reset(seed=0, options={"task": {"action:rotation": 0.3}})
        >>> info["task"]["action:rotation"], sorted(info["task"])
        (0.3, ['action:gain', 'action:rotation'])
    """

    def __init__(
        self, *, rotation: tuple[float, float] = (-0.5, 0.5), gain: tuple[float, float] = (0.5, 1.5), **kwargs: Any
    ) -> None:
        rotation = _range("FetchReachRotated", "rotation", rotation, unit=" of angles (rad)")
        gain = _range("FetchReachRotated", "gain", gain)
        env = _fetch_env(FetchReachEnv, **kwargs)
        transform = ActionTransform(rotation=Uniform(*rotation), gain=Uniform(*gain), dims=(0, 1, 2))
        super().__init__(env, action=transform)


class FetchPushHeavy(_FetchFamily):
    r"""Fetch push with an unknown mass and friction of the block.

    ## Description
    gymnasium-robotics' ``FetchPush-v4`` (the Fetch gripper pushes a 5 cm block on a table to a
    goal), where the block's mass and its sliding friction coefficient are drawn per episode.
    MuJoCo uses the larger of two touching geoms' coefficients, so the table's sliding friction is
    lowered to the bottom of the block's range: the block-table contact then has the block's
    coefficient. The block's inertia scales with its mass (a denser block of the same shape).

    ## Action Space
    ``Box(-1, 1, (4,), float32)``: gripper displacement x, y, z (times 0.05 m per step) and the
    gripper opening (ignored: blocked in push), as FetchPush-v4.

    ## Observation Space
    ``Dict``: ``observation`` (25: gripper position, block position, relative position, finger
    state, block rotation, block velocities, gripper velocity, finger velocity), ``achieved_goal``
    (3, block position), ``desired_goal`` (3), as FetchPush-v4.

    ## Rewards
    As FetchPush-v4: sparse by default (``-1`` unless the block is within 5 cm of the goal),
    ``reward_type="dense"`` gives the negative distance.

    ## Episode End
    Never terminates; ``gymnasium.make("smcd_rl/FetchPushHeavy-v0")`` truncates after 50 steps.

    ## Task
    ``info["task"]``: ``{"body_mass:object0": kg, "geom_friction:object0": block coefficient,
    "geom_friction:table0": table coefficient}`` (the table's geom has no name of its own; it is
    found by its body ``table0``).

    ## Arguments
    | Parameter | Type | Default | Description |
    |---|---|---|---|
    | `mass` | `tuple[float, float]` | `(1.0, 6.0)` | range (kg) of the uniform block mass (FetchPush: 2) |
    | `friction` | `tuple[float, float]` | `(0.1, 1.0)` | range of the uniform block friction (FetchPush: 1); the table gets the lower end |

    Each range is a ``(low, high)`` pair with ``low <= high``; ``(v, v)`` fixes the value. A single
    number is refused (with this hint), and so are a mass <= 0 and a negative friction, which MuJoCo
    would simulate without complaint and wrongly.
    | `**kwargs` | | | passed to FetchPush (`reward_type`, `render_mode`, `width`, `height`, ...) |

    ## Version History
    * v0: Initial version, on FetchPush-v4.

    Example:
        >>> env = FetchPushHeavy()
        >>> obs, info = env.reset(seed=0, options={"task": {"body_mass:object0": 5.0}})
        >>> float(env.unwrapped.model.body("object0").mass[0]), info["task"]["geom_friction:table0"]
        (5.0, 0.1)
    """

    def __init__(
        self, *, mass: tuple[float, float] = (1.0, 6.0), friction: tuple[float, float] = (0.1, 1.0), **kwargs: Any
    ) -> None:
        mass = _range("FetchPushHeavy", "mass", mass, unit=" of masses (kg)", sign="positive")
        friction = _range("FetchPushHeavy", "friction", friction, unit=" of friction coefficients", sign="non-negative")
        env = _fetch_env(FetchPushEnv, **kwargs)
        params: dict[str, Distribution] = {
            "body_mass:object0": Uniform(*mass),
            "geom_friction:object0": Uniform(*friction),
            "geom_friction:table0": Fixed(friction[0]),
        }
        super().__init__(env, params=params)


#: Joint angles (rad, MJCF convention) of the Panda's ready pose: the DH ready pose
#: ``[0, -0.3, 0, -2.2, 0, 2.0, pi/4]`` with joint 6 shifted by ``-pi/2`` (MJCF = DH - pi/2 there).
FRANKA_READY_POSE: tuple[float, ...] = (0.0, -0.3, 0.0, -2.2, 0.0, 2.0 - np.pi / 2, np.pi / 4)
_FRANKA_ARM_JOINTS = tuple(f"robot:panda0_joint{k}" for k in range(1, 8))
_FRANKA_MAX_VELOCITY = 2.0  # rad/s per unit action, as gymnasium-robotics' FrankaRobot
_FRANKA_CAMERA = {"distance": 2.2, "azimuth": 70.0, "elevation": -35.0, "lookat": np.array([0.0, 0.4, 1.6])}


def franka_assets_dir() -> str:
    """Directory of the MuJoCo Franka Panda that gymnasium-robotics ships (``kitchen_franka/franka_assets``)."""
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError('gymnasium-robotics is not installed: pip install -e ".[robotics]"')
    return os.path.join(os.path.dirname(spec.origin), "envs", "assets", "kitchen_franka", "franka_assets")


def franka_model_xml() -> str:
    """MJCF of the Franka Panda alone, as the kitchen mounts it: base at (0, 0, 1.8) rotated 1.57 rad about z.

    Includes gymnasium-robotics' ``chain.xml``, ``assets.xml`` and ``actuator.xml`` (position servos
    with the real gains and force limits) by absolute path, on a floor, with a ``goal`` site.
    """
    assets = franka_assets_dir()
    return f"""<mujoco model="franka_reach">
  <include file="{assets}/basic_scene.xml"/>
  <include file="{assets}/assets.xml"/>
  <include file="{assets}/actuator.xml"/>
  <compiler inertiafromgeom="auto" inertiagrouprange="3 5" angle="radian" meshdir="{assets}/meshes"/>
  <worldbody>
    <body name="panda0_base" pos="0 0 1.8" euler="0 0 1.57">
      <geom type="cylinder" size=".120 .90" pos="-.04 0 -0.90"/>
      <include file="{assets}/chain.xml"/>
    </body>
    <site name="goal" pos="0 0.5 2.0" size="0.03" rgba="0 0.8 0 0.6"/>
  </worldbody>
</mujoco>
"""


class FrankaReachEnv(MujocoEnv):
    r"""The MuJoCo Franka Panda reaching for a goal, its end effector measured every ``measure_every`` steps.

    ## Description
    gymnasium-robotics' MuJoCo Panda (``kitchen_franka/franka_assets``, the arm of FrankaKitchen,
    with its position-servo actuators, joint damping and armature) alone on a floor. Each episode
    starts at the ready pose :data:`FRANKA_READY_POSE` at rest, with a goal drawn uniformly from a
    0.4 m cube centred 0.1 m in front of the ready pose's end effector. The fingers are held closed.
    The end-effector position (site ``end_effector``, 0.21 m along link 7) is measured at reset and
    then every ``measure_every`` steps; in between the observation repeats the last measurement
    (the setting of the paper's section 4.2, where a model must stand in for the missing measurements).

    ## Action Space
    ``Box(-1, 1, (7,), float32)``: joint velocities, times 2 rad/s, integrated over ``dt`` into
    position targets of the servos from the current joint angles (as FrankaKitchen does).

    ## Observation Space
    ``Box(-inf, inf, (20,), float64)``: joint angles (7, rad, MJCF convention), joint velocities
    (7, rad/s), last measured end-effector position (3, world, m), goal (3, world, m).

    ## Rewards
    ``-|ee - goal|``, the true end effector's distance (m) to the goal after the step.
    ``info["distance"]`` holds it, ``info["is_success"]`` whether it is below 5 cm,
    ``info["measured"]`` whether this step's observation holds a new measurement.

    ## Episode End
    Never terminates; ``gymnasium.make("smcd_rl/FrankaReachTool-v0")`` truncates after 200 steps.
    ``dt`` = 0.08 s (40 substeps of 2 ms).

    ## Arguments
    | Parameter | Type | Default | Description |
    |---|---|---|---|
    | `measure_every` | `int` | `1` | steps between end-effector measurements |
    | `**kwargs` | | | passed to ``MujocoEnv`` (`render_mode`, `width`, `height`, `camera_name`, ...) |

    ## Version History
    * v0: Initial version.

    Example:
        >>> env = FrankaReachEnv(measure_every=5)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, bool(info["measured"])
        ((20,), True)
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> bool(info["measured"]), bool(reward == -info["distance"])
        (False, True)
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"], "render_fps": 12}

    def __init__(self, measure_every: int = 1, **kwargs: Any) -> None:
        if isinstance(measure_every, bool) or not isinstance(measure_every, (int, np.integer)) or measure_every < 1:
            raise ValueError(f"measure_every must be a positive int, got {measure_every!r}")
        if kwargs.get("render_mode") is not None:
            headless_mujoco()  # before the first frame
        self.measure_every = int(measure_every)
        observation_space = spaces.Box(-np.inf, np.inf, shape=(20,), dtype=np.float64)
        kwargs.setdefault("default_camera_config", _FRANKA_CAMERA)
        with tempfile.TemporaryDirectory() as folder:
            path = os.path.join(folder, "franka_reach.xml")
            with open(path, "w") as file:
                file.write(franka_model_xml())
            super().__init__(path, frame_skip=40, observation_space=observation_space, **kwargs)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32)
        model = self.model
        self._qpos_ids = [int(model.jnt_qposadr[model.joint(j).id]) for j in _FRANKA_ARM_JOINTS]
        self._dof_ids = [int(model.jnt_dofadr[model.joint(j).id]) for j in _FRANKA_ARM_JOINTS]
        self._ee = model.site("end_effector").id
        self._goal_site = model.site("goal").id
        self.init_qpos = np.zeros(model.nq)
        self.init_qpos[self._qpos_ids] = FRANKA_READY_POSE
        self.init_qvel = np.zeros(model.nv)
        self._ready_ee = self._end_effector_at(self.init_qpos)
        self.goal = self._ready_ee.copy()
        self._steps = 0
        self._measured = self._ready_ee.copy()

    def _end_effector_at(self, qpos: NDArray[np.float64]) -> NDArray[np.float64]:
        data = mujoco.MjData(self.model)
        data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, data)
        return data.site_xpos[self._ee].copy()

    @property
    def end_effector(self) -> NDArray[np.float64]:
        """True end-effector position (world, m) of the current state."""
        return self.data.site_xpos[self._ee].copy()

    def reset_model(self) -> NDArray[np.float64]:
        self.set_state(self.init_qpos, self.init_qvel)
        self.data.ctrl[:] = self.init_qpos[: self.model.nu]  # servos hold the ready pose
        offset = self.np_random.uniform(-0.2, 0.2, size=3) + np.array([0.0, 0.1, 0.0])
        self.goal = self._ready_ee + offset
        self.model.site_pos[self._goal_site] = self.goal
        self._steps = 0
        return self._get_obs()

    # A Python float reward, as stable-baselines3's checker requires; MujocoEnv's hint says numpy.float64.
    def step(self, action: NDArray[Any]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        if np.shape(action) != self.action_space.shape:
            raise ValueError(f"the action has shape {np.shape(action)}; this env takes actions of shape (7,)")
        velocity = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0) * _FRANKA_MAX_VELOCITY
        ctrl = self.data.qpos[: self.model.nu].copy()  # fingers: hold where they are
        ctrl[: len(velocity)] = self.data.qpos[self._qpos_ids] + velocity * self.dt
        low, high = self.model.actuator_ctrlrange.T
        self.do_simulation(np.clip(ctrl, low, high), self.frame_skip)
        self._steps += 1
        obs = self._get_obs()
        distance = float(np.linalg.norm(self.end_effector - self.goal))
        if self.render_mode == "human":
            self.render()
        info = {"distance": distance, "is_success": distance < 0.05, "measured": self._steps % self.measure_every == 0}
        return obs, -distance, False, False, info

    def _get_reset_info(self) -> dict[str, Any]:
        distance = float(np.linalg.norm(self.end_effector - self.goal))
        return {"distance": distance, "is_success": distance < 0.05, "measured": True}

    def _get_obs(self) -> NDArray[np.float64]:
        if self._steps % self.measure_every == 0:  # idempotent between steps, so it may be called again
            self._measured = self.end_effector
        qpos, qvel = self.data.qpos[self._qpos_ids], self.data.qvel[self._dof_ids]
        return np.concatenate((qpos, qvel, self._measured, self.goal))


class FrankaReachTool(_RegisteredFamily):
    r"""The paper's Panda reaching (section 4.2) on the MuJoCo Franka: an unknown tool length per episode.

    ## Description
    :class:`FrankaReachEnv` with a tool of unknown length ``l ~ U(-0.5, 0.5)`` m that moves the
    end effector along link 7: the ``end_effector`` site sits ``0.21 + l`` m along link 7 (0.21 m
    is the Franka hand's tip). Observation, action, reward and episode length are those of
    :class:`FrankaReachEnv`; the goal is drawn before the tool, from a box around the default tool's
    ready pose, so it does not reveal the tool.

    ## Task
    ``info["task"]``: ``{"site_pos:end_effector[2]": 0.21 + l}``; ``reset(options={"task":
    {"site_pos:end_effector[2]": 0.5}})`` fixes it.

    ## Arguments
    | Parameter | Type | Default | Description |
    |---|---|---|---|
    | `tool` | `tuple[float, float]` | `(-0.5, 0.5)` | range (m) of the uniform tool length ``l``, ``low <= high``; ``(l, l)`` fixes it |
    | `measure_every` | `int` | `1` | steps between end-effector measurements |
    | `**kwargs` | | | passed to :class:`FrankaReachEnv` (`render_mode`, ...) |

    ## Version History
    * v0: Initial version.

    Example:
        >>> env = FrankaReachTool()
        >>> obs, info = env.reset(seed=0)
        >>> -0.29 <= info["task"]["site_pos:end_effector[2]"] <= 0.71
        True
    """

    def __init__(self, *, tool: tuple[float, float] = (-0.5, 0.5), measure_every: int = 1, **kwargs: Any) -> None:
        tool = _range("FrankaReachTool", "tool", tool, unit=" of tool lengths (m)")
        env = FrankaReachEnv(measure_every=measure_every, **kwargs)
        tip = float(env.model.site("end_effector").pos[2])
        super().__init__(env, params={"site_pos:end_effector[2]": Uniform(tip + tool[0], tip + tool[1])})
