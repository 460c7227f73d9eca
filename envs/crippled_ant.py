"""Ant with one crippled leg, as in "Learning to Adapt" (Nagabandi et al. 2019; paper appendix C).

:class:`CrippledAntEnv` is gymnasium's MuJoCo ``Ant-v5`` with the 41-dim observation of Learning
to Adapt and one leg disabled per episode. The planner reward and termination are pure batched
torch functions, :func:`ant_reward` and :func:`ant_termination`, that reproduce the env's own terms
from ``(obs, action, next_obs)``.

Example:
    >>> import torch
    >>> from smcd_rl.envs.crippled_ant import CrippledAntEnv, ant_reward
    >>> env = CrippledAntEnv(crippled_legs=(3,))
    >>> obs, info = env.reset(seed=0)
    >>> obs.shape, info["crippled_leg"]
    ((41,), 3)
    >>> action = env.action_space.sample().astype("float64")
    >>> next_obs, reward, terminated, truncated, info = env.step(action)
    >>> r = ant_reward(torch.from_numpy(obs), torch.from_numpy(action), torch.from_numpy(next_obs))
    >>> bool(abs(r - (reward - info["reward_contact"])) < 1e-9)
    True
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium import utils
from gymnasium.spaces import Box
from numpy.typing import NDArray
from torch import Tensor

from smcd_rl.envs.mujoco_setup import headless_mujoco, missing_extra

try:
    import mujoco
    from gymnasium.envs.mujoco.ant_v5 import AntEnv
except ModuleNotFoundError as error:
    raise missing_extra(error, "mujoco", "smcd_rl/CrippledAnt-v0 (smcd_rl.envs.crippled_ant)") from error

from smcd_rl.integrations.task_family import ModelParameters

__all__ = [
    "LEGS",
    "OBS_DIM",
    "OBS_SLICES",
    "TEST_LEG",
    "TRAIN_LEGS",
    "CrippledAntEnv",
    "Leg",
    "ant_reward",
    "ant_termination",
    "leg_indices",
]

#: Legs crippled during training in Learning to Adapt.
TRAIN_LEGS: tuple[int, ...] = (0, 1, 2)
#: Leg held out for testing in Learning to Adapt.
TEST_LEG: int = 3

#: Where each part of the 41-dim observation sits (see the observation table of the env card).
OBS_SLICES: Mapping[str, slice] = {
    "qpos": slice(0, 15),
    "qvel": slice(15, 29),
    "torso_xmat": slice(29, 38),
    "torso_subtree_com": slice(38, 41),
}
#: Observation size: qpos 15 + qvel 14 + torso rotation matrix 9 + torso subtree centre of mass 3.
OBS_DIM: int = 41

_X, _Z = 0, 2  # torso x and z positions in the observation (qpos[0], qpos[2])
_N_LEGS = 4
_CRIPPLED_RGBA = (1.0, 0.0, 0.0)  # Learning to Adapt paints the crippled leg red
# Ant-v5 arguments that would change the observation this env fixes.
_FIXED_ANT_KWARGS = (
    "exclude_current_positions_from_observation",
    "include_cfrc_ext_in_observation",
)


@dataclass(frozen=True)
class Leg:
    """Model indices of one Ant leg.

    Attributes:
        hip_joint: XML name of the hip joint (torso-thigh hinge), e.g. ``"hip_1"``.
        ankle_joint: XML name of the ankle joint (thigh-shin hinge), e.g. ``"ankle_1"``.
        actuators: Actuator (= action) indices ``(hip, ankle)``.
        geoms: Geom indices ``(thigh, shin)``: the capsule of the hip joint's body and the capsule
            of the ankle joint's body.
    """

    hip_joint: str
    ankle_joint: str
    actuators: tuple[int, int]
    geoms: tuple[int, int]


#: Legs of gymnasium's ``ant.xml`` in Learning to Adapt's numbering (leg ``k`` has joints
#: ``hip_{k+1}``/``ankle_{k+1}``); :func:`leg_indices` derives the same table from model names.
LEGS: tuple[Leg, ...] = (
    Leg("hip_1", "ankle_1", actuators=(2, 3), geoms=(3, 4)),
    Leg("hip_2", "ankle_2", actuators=(4, 5), geoms=(6, 7)),
    Leg("hip_3", "ankle_3", actuators=(6, 7), geoms=(9, 10)),
    Leg("hip_4", "ankle_4", actuators=(0, 1), geoms=(12, 13)),
)


def leg_indices(model: mujoco.MjModel) -> tuple[Leg, ...]:
    """Derive the :class:`Leg` table from a compiled Ant model's names.

    Actuators are found through ``model.actuator_trnid`` (Ant's actuators have no names of their
    own); each geom is the single geom of the body that the hip or ankle joint moves.

    Args:
        model: A compiled Ant model with joints ``hip_1..4`` and ``ankle_1..4``.

    Returns:
        One :class:`Leg` per leg, indexed by Learning to Adapt's leg number ``0..3``.

    Raises:
        ValueError: If a joint is missing, not driven by exactly one joint actuator, or its body
            does not hold exactly one geom.

    Example:
        >>> from gymnasium.envs.mujoco.ant_v5 import AntEnv
        >>> leg_indices(AntEnv().model) == LEGS
        True
    """
    joint_actuators: dict[int, list[int]] = {}
    for a in range(model.nu):
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            joint_actuators.setdefault(int(model.actuator_trnid[a, 0]), []).append(a)

    def actuator_and_geom(joint_name: str) -> tuple[int, int]:
        joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint_name)
        if joint < 0:
            raise ValueError(f"model has no joint named {joint_name!r}")
        actuators = joint_actuators.get(joint, [])
        body = int(model.jnt_bodyid[joint])
        if len(actuators) != 1 or model.body_geomnum[body] != 1:
            raise ValueError(
                f"joint {joint_name!r} has {len(actuators)} actuators and its body "
                f"{model.body_geomnum[body]} geoms; expected one of each"
            )
        return actuators[0], int(model.body_geomadr[body])

    legs = []
    for k in range(_N_LEGS):
        hip, ankle = f"hip_{k + 1}", f"ankle_{k + 1}"
        hip_actuator, thigh = actuator_and_geom(hip)
        ankle_actuator, shin = actuator_and_geom(ankle)
        legs.append(Leg(hip, ankle, actuators=(hip_actuator, ankle_actuator), geoms=(thigh, shin)))
    return tuple(legs)


def ant_termination(next_obs: Tensor, *, healthy_z_range: tuple[float, float] = (0.2, 1.0)) -> Tensor:
    """Whether the Ant is unhealthy, hence the episode terminated, in ``next_obs`` (Ant-v5 rule).

    Unhealthy means the torso height ``next_obs[..., 2]`` lies outside the closed interval
    ``healthy_z_range``, or some entry is not finite. Ant-v5 checks finiteness of qpos and qvel
    only; the other 12 entries are functions of qpos, so on env observations both agree, and on
    model predictions a non-finite entry anywhere ends the rollout.

    Args:
        next_obs: Observations ``[..., 41]`` after the step.
        healthy_z_range: ``(min_z, max_z)`` of a healthy torso; the env's ``healthy_z_range``.

    Returns:
        Bool tensor ``[...]``, ``True`` where the episode terminates.

    Example:
        >>> import torch
        >>> obs = torch.zeros(3, 41, dtype=torch.float64)
        >>> obs[:, 2] = torch.tensor([0.55, 0.1, float("nan")])
        >>> ant_termination(obs)
        tensor([False,  True,  True])
    """
    min_z, max_z = healthy_z_range
    z = next_obs[..., _Z]
    healthy = torch.isfinite(next_obs).all(dim=-1) & (z >= min_z) & (z <= max_z)
    return ~healthy


def ant_reward(
    obs: Tensor,
    action: Tensor,
    next_obs: Tensor,
    *,
    dt: float = 0.05,
    forward_reward_weight: float = 1.0,
    ctrl_cost_weight: float = 0.5,
    healthy_reward: float = 1.0,
    healthy_z_range: tuple[float, float] = (0.2, 1.0),
) -> Tensor:
    """Ant-v5 reward without the contact cost, batched: the planner's objective per step.

    ``forward_reward_weight * (x' - x) / dt + healthy_reward * healthy(next_obs)
    - ctrl_cost_weight * sum(action ** 2)``, with ``x = obs[..., 0]`` the torso x position. This
    equals ``info["reward_forward"] + info["reward_survive"] + info["reward_ctrl"]`` of
    :class:`CrippledAntEnv`, i.e. its reward minus ``info["reward_contact"]``: the contact cost
    needs contact forces, which the observation does not hold (pass ``contact_cost_weight=0`` to
    the env to make the two rewards equal). The control cost is on the commanded action, crippled
    leg included, as in the env.

    Args:
        obs: Observations ``[..., 41]`` before the step.
        action: Commanded actions ``[..., 8]``.
        next_obs: Observations ``[..., 41]`` after the step.
        dt: Seconds per step, the env's ``dt`` (``frame_skip * timestep``, 0.05 by default).
        forward_reward_weight: Weight of the forward velocity, as in Ant-v5.
        ctrl_cost_weight: Weight of the squared action norm, as in Ant-v5.
        healthy_reward: Reward per step while healthy (see :func:`ant_termination`), as in Ant-v5.
        healthy_z_range: Closed torso height interval of a healthy Ant, as in Ant-v5.

    Returns:
        Reward ``[...]`` in the broadcast dtype of the inputs.

    Example:
        >>> import torch
        >>> obs = torch.zeros(2, 41, dtype=torch.float64)
        >>> obs[:, 2] = 0.55
        >>> next_obs = obs.clone()
        >>> next_obs[:, 0] = 0.05
        >>> ant_reward(obs, torch.zeros(2, 8, dtype=torch.float64), next_obs)
        tensor([2., 2.], dtype=torch.float64)
    """
    forward = (next_obs[..., _X] - obs[..., _X]) / dt * forward_reward_weight
    healthy = ~ant_termination(next_obs, healthy_z_range=healthy_z_range)
    ctrl_cost = ctrl_cost_weight * action.square().sum(dim=-1)
    return forward + healthy_reward * healthy.to(forward.dtype) - ctrl_cost


class CrippledAntEnv(AntEnv):
    r"""Ant-v5 with one leg crippled per episode, as in "Learning to Adapt".

    ## Description
    Gymnasium's MuJoCo Ant (``Ant-v5``, ``ant.xml``): a torso with four two-link legs that should
    run in the +x direction. At every reset one leg may be crippled the way Nagabandi et al.
    (2019) did it, for leg ``k`` with thigh geom ``t`` and shin geom ``s`` (see the leg table):

    - its two actuators produce no torque: ``actuator_gear`` of both is set to 0, so the
      commanded action still enters the control cost (zeroing the action instead would also
      zero its cost). ``data.actuator_force`` of these actuators still reports the control
      (force in actuator space, before the gear); the joint torque ``data.qfrc_actuator`` is 0;
    - ``geom_size[t, 0:2]`` and ``geom_size[s, 0:2]`` are halved (capsule radius and half-length);
    - ``geom_pos[s] = geom_pos[t]``. Geom positions are in the parent body's frame and the thigh
      and shin capsules have the same orientation, so the shin's centre moves from the middle of
      the pristine shin to a quarter of its length from the knee: the shrunken shin (half as long)
      still starts at the knee joint and ends where the pristine shin's middle was. MuJoCo 3+
      ignores ``geom_pos`` of a geom whose ``geom_sameframe`` says it sits at its body's inertial
      frame (as the compiler marks every leg geom), so ``geom_sameframe[s]`` is set to
      ``mjSAMEFRAME_NONE``; without it the shin would not move at all (the mujoco-py of Learning
      to Adapt had no such flag). The thigh
      keeps its centre, so the half-length thigh hangs between hip and knee without touching
      either. Only the collision and visual geometry changes: masses and inertias were computed
      from the geoms when the model was compiled and stay as they were. The shrunken geoms lie
      inside the pristine geoms' bounding volumes, which therefore stay valid;
    - the leg's geoms are painted red.

    Legs are numbered as in Learning to Adapt; the x and y columns give the hip's side of the
    torso (+x is forward):

    | Leg | Joints (XML)     | Actions | Geoms (thigh, shin)                       | x | y |
    |-----|------------------|---------|-------------------------------------------|---|---|
    | 0   | hip_1, ankle_1   | 2, 3    | 3, 4 (left_leg_geom, left_ankle_geom)     | + | + |
    | 1   | hip_2, ankle_2   | 4, 5    | 6, 7 (right_leg_geom, right_ankle_geom)   | - | + |
    | 2   | hip_3, ankle_3   | 6, 7    | 9, 10 (back_leg_geom, third_ankle_geom)   | - | - |
    | 3   | hip_4, ankle_4   | 0, 1    | 12, 13 (rightback_leg_geom, fourth_ankle_geom) | + | - |

    Training draws the leg from :data:`TRAIN_LEGS` ``(0, 1, 2)``; :data:`TEST_LEG` ``3`` is held
    out. Each leg's crippling is a set of named model parameters (``actuator_gear:hip_1``,
    ``geom_size:left_leg_geom``, ``geom_pos:left_ankle_geom[2]``, ...) written through
    :class:`~smcd_rl.integrations.task_family.ModelParameters`, the parameter layer of
    :class:`~smcd_rl.integrations.task_family.TaskFamily`. The model arrays are changed in place and
    would persist; the env restores their pristine values (``geom_size``, ``geom_pos``,
    ``geom_sameframe``, ``geom_rgba``, ``actuator_gear``, bit for bit) on every reset before
    crippling again.

    After stepping the physics the env calls ``mj_forward`` (as Learning to Adapt's rllab
    ``forward_dynamics`` did): without it ``data.xpos``, ``xmat`` and ``subtree_com`` belong to an
    intermediate RK4 stage of the last substep, not to the state in ``qpos``. The trajectory is
    unchanged (``qpos``, ``qvel`` match Ant-v5 step for step), but ``info["reward_forward"]``
    is now the torso's x displacement between consecutive observations divided by ``dt``.

    ## Action Space
    ``Box(-1, 1, (8,), float32)``, torques of the eight hinges, as in Ant-v5: actions
    ``0, 1`` = hip_4, ankle_4; ``2, 3`` = hip_1, ankle_1; ``4, 5`` = hip_2, ankle_2;
    ``6, 7`` = hip_3, ankle_3 (gear 150). The crippled leg's two entries have no effect.

    ## Observation Space
    ``Box(-inf, inf, (41,), float64)``, Learning to Adapt's observation; no contact forces, and
    the torso x and y positions are included. Slices are in :data:`OBS_SLICES`.

    | Index  | Observation                                                  | Source                         | Unit   |
    |--------|--------------------------------------------------------------|--------------------------------|--------|
    | 0-2    | torso x, y, z position (world)                               | ``qpos[0:3]`` (root)           | m      |
    | 3-6    | torso orientation quaternion w, x, y, z                      | ``qpos[3:7]`` (root)           | -      |
    | 7-14   | joint angles hip_1, ankle_1, hip_2, ankle_2, hip_3, ankle_3, hip_4, ankle_4 | ``qpos[7:15]`` | rad    |
    | 15-17  | torso linear velocity x, y, z (world frame)                  | ``qvel[0:3]`` (root)           | m/s    |
    | 18-20  | torso angular velocity x, y, z (torso frame)                 | ``qvel[3:6]`` (root)           | rad/s  |
    | 21-28  | joint velocities, same order as 7-14                         | ``qvel[6:14]``                 | rad/s  |
    | 29-37  | torso rotation matrix (torso to world), row-major            | ``data.xmat[torso]``           | -      |
    | 38-40  | centre of mass of the torso's subtree (the whole Ant), world | ``data.subtree_com[torso]``    | m      |

    ## Rewards
    As Ant-v5: ``reward = reward_forward + reward_survive + reward_ctrl + reward_contact``, with
    ``reward_forward = forward_reward_weight * (x' - x) / dt`` (torso x, see the Description),
    ``reward_survive = healthy_reward`` while healthy, else 0,
    ``reward_ctrl = -ctrl_cost_weight * sum(action ** 2)`` on the commanded action, and
    ``reward_contact = -contact_cost_weight * sum(clip(cfrc_ext, contact_force_range) ** 2)``
    (default weight 5e-4). :func:`ant_reward` computes all but the contact cost from
    observations; ``contact_cost_weight=0`` makes it the env's reward exactly.

    ## Starting State
    As Ant-v5: ``qpos = qpos0 + U(-0.1, 0.1)``, ``qvel = N(0, 0.1^2)`` (``reset_noise_scale``),
    torso at height 0.75. The leg is drawn from ``self.np_random`` after the initial state, so a
    seed gives the same initial state whichever leg is crippled.

    ## Episode End
    Terminates when the Ant is unhealthy (:func:`ant_termination`: torso z outside the closed
    ``healthy_z_range``, default ``(0.2, 1.0)``, or a non-finite qpos/qvel), if
    ``terminate_when_unhealthy`` (default). ``gymnasium.make("smcd_rl/CrippledAnt-v0")``
    truncates after 1000 steps.

    ## Arguments
    | Parameter       | Type                     | Default     | Description |
    |-----------------|--------------------------|-------------|-------------|
    | `crippled_legs` | `Sequence[int] \| None`  | `(0, 1, 2)` | Legs the crippled leg is drawn from (uniformly, with ``self.np_random``) at each reset; `None` or empty gives the healthy Ant. |
    | `**kwargs`      |                          |             | Passed to Ant-v5 (`render_mode`, `ctrl_cost_weight`, `contact_cost_weight`, `healthy_z_range`, `reset_noise_scale`, ...), except the two observation flags, which this env fixes. |

    ``reset(options={"crippled_leg": k})`` cripples leg ``k`` in ``0..3`` for that episode,
    whatever ``crippled_legs`` is; ``{"crippled_leg": None}`` gives the healthy Ant. ``info``
    of ``reset`` and ``step`` holds ``"crippled_leg"``: the leg, or -1 when healthy.

    Pickling rebuilds the env from its constructor arguments (Gymnasium's ``EzPickle``, as every
    MuJoCo env does); the simulator state, the current leg and the RNG are not carried over.

    The reward is a Python ``float``. Made with a ``render_mode`` on a machine without a display,
    the env chooses a headless MuJoCo backend (``MUJOCO_GL=egl``, or ``osmesa``) unless
    ``MUJOCO_GL`` is set; see :func:`~smcd_rl.envs.mujoco_setup.headless_mujoco`.

    ## Version History
    * v0: Initial version: Ant-v5, Learning to Adapt's crippling, 41-dim observation, state-
      consistent ``data`` after each step.

    Args:
        crippled_legs: Legs to draw the crippled leg from at each reset; `None` or empty for none.
        **kwargs: Keyword arguments of ``gymnasium.envs.mujoco.ant_v5.AntEnv``.

    Raises:
        ValueError: If ``crippled_legs`` names a leg outside ``0..3``.
        TypeError: If ``exclude_current_positions_from_observation`` or
            ``include_cfrc_ext_in_observation`` is passed.

    Example:
        >>> env = CrippledAntEnv()
        >>> obs, info = env.reset(seed=0, options={"crippled_leg": 1})
        >>> obs.shape, info["crippled_leg"], env.model.actuator_gear[4:6, 0].tolist()
        ((41,), 1, [0.0, 0.0])
        >>> obs, info = env.reset(options={"crippled_leg": None})
        >>> info["crippled_leg"], env.model.actuator_gear[4:6, 0].tolist()
        (-1, [150.0, 150.0])
    """

    def __init__(self, crippled_legs: Sequence[int] | None = TRAIN_LEGS, **kwargs: Any) -> None:
        fixed = [name for name in _FIXED_ANT_KWARGS if name in kwargs]
        if fixed:
            raise TypeError(f"CrippledAntEnv fixes its 41-dim observation; do not pass {fixed}")
        legs = tuple(sorted({_check_leg(leg, "crippled_legs") for leg in crippled_legs or ()}))
        if kwargs.get("render_mode") is not None:
            headless_mujoco()  # before the first frame: gymnasium reads MUJOCO_GL when it makes the renderer
        super().__init__(
            exclude_current_positions_from_observation=False,
            include_cfrc_ext_in_observation=False,
            **kwargs,
        )
        # AntEnv recorded its own arguments; pickling must rebuild this class from ours.
        utils.EzPickle.__init__(self, legs, **kwargs)

        self._crippled_legs = legs
        self._crippled_leg: int | None = None
        self._reset_options: dict[str, Any] = {}
        self.legs = leg_indices(self.model)
        self._torso = self.model.body("torso").id
        # Each leg's crippling is a set of model parameters; ModelParameters restores their defaults.
        self._leg_parameters = [self._crippling(leg) for leg in self.legs]
        self._parameters = ModelParameters(self.model, [name for leg in self._leg_parameters for name in leg])

        self.observation_space = Box(low=-np.inf, high=np.inf, shape=(OBS_DIM,), dtype=np.float64)
        self.observation_structure = {name: s.stop - s.start for name, s in OBS_SLICES.items()}

    @property
    def crippled_legs(self) -> tuple[int, ...]:
        """Legs the crippled leg is drawn from at each reset (empty: always healthy)."""
        return self._crippled_legs

    @property
    def crippled_leg(self) -> int | None:
        """Leg crippled in the current episode, or `None` for the healthy Ant."""
        return self._crippled_leg

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float64], dict[str, Any]]:
        """Reset the state and cripple a leg (see the class card).

        Args:
            seed: Seed of ``self.np_random``.
            options: ``{"crippled_leg": k}`` with ``k`` in ``0..3`` cripples leg ``k`` for this
                episode, ``{"crippled_leg": None}`` gives the healthy Ant; without the key the leg
                is drawn from :attr:`crippled_legs`.

        Returns:
            The 41-dim observation and the info dict (with ``"crippled_leg"``).

        Raises:
            ValueError: On an unknown option or an invalid leg.
        """
        options = dict(options or {})
        unknown = set(options) - {"crippled_leg"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; valid: ['crippled_leg']")
        if "crippled_leg" in options and options["crippled_leg"] is not None:
            _check_leg(options["crippled_leg"], "options['crippled_leg']")
        self._reset_options = options
        return super().reset(seed=seed, options=options)

    def reset_model(self) -> NDArray[np.float64]:
        super().reset_model()  # initial state noise first, so the leg draw does not shift it
        options = self._reset_options
        if "crippled_leg" in options:
            leg = options["crippled_leg"]
            leg = None if leg is None else int(leg)
        elif self._crippled_legs:
            leg = self._crippled_legs[int(self.np_random.integers(len(self._crippled_legs)))]
        else:
            leg = None
        self._cripple(leg)
        mujoco.mj_forward(self.model, self.data)  # contacts of the new geometry
        return self._get_obs()

    def _crippling(self, leg: Leg) -> dict[str, float]:
        """The model parameters (:class:`~smcd_rl.integrations.task_family.ModelParameters` names) of a crippled ``leg``."""
        model = self.model
        thigh, shin = (model.geom(g).name for g in leg.geoms)

        def name(field: str, geom: str, k: int) -> str:  # component 0 is the default: its name has no [0]
            return f"{field}:{geom}" + (f"[{k}]" if k else "")

        values = {f"actuator_gear:{joint}": 0.0 for joint in (leg.hip_joint, leg.ankle_joint)}
        for geom in (thigh, shin):
            values.update({name("geom_size", geom, k): float(model.geom(geom).size[k]) / 2 for k in (0, 1)})
        # Setting geom_pos also clears the shin's geom_sameframe: the compiler marked its frame as its
        # body's inertial frame, and kinematics would then ignore geom_pos.
        values.update({name("geom_pos", shin, k): float(model.geom(thigh).pos[k]) for k in range(3)})
        for geom in (thigh, shin):
            values.update({name("geom_rgba", geom, k): _CRIPPLED_RGBA[k] for k in range(3)})
        return values

    def _cripple(self, leg: int | None) -> None:
        self._parameters.restore()
        self._crippled_leg = leg
        if leg is not None:
            self._parameters.set(self._leg_parameters[leg])

    def do_simulation(self, ctrl: NDArray[np.floating], n_frames: int) -> None:
        super().do_simulation(ctrl, n_frames)
        # Make xpos/xmat/subtree_com (and cfrc_ext) those of the final state; see the card.
        mujoco.mj_forward(self.model, self.data)
        mujoco.mj_rnePostConstraint(self.model, self.data)

    # A Python float reward, as stable-baselines3's checker requires; MujocoEnv's hint says numpy.float64.
    def step(  # type: ignore[override]
        self, action: NDArray[np.floating]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        observation, reward, terminated, truncated, info = super().step(action)
        info["crippled_leg"] = self._leg_info()
        return observation, float(reward), terminated, truncated, info

    def _get_reset_info(self) -> dict[str, Any]:
        return {**super()._get_reset_info(), "crippled_leg": self._leg_info()}

    def _leg_info(self) -> int:
        return -1 if self._crippled_leg is None else self._crippled_leg

    def _get_obs(self) -> NDArray[np.float64]:
        return np.concatenate(
            (
                self.data.qpos,
                self.data.qvel,
                self.data.xmat[self._torso],
                self.data.subtree_com[self._torso],
            )
        )


def _check_leg(leg: Any, what: str) -> int:
    """Return ``leg`` as an int if it names one of the four legs, else raise ValueError."""
    valid = tuple(range(_N_LEGS))
    is_int = isinstance(leg, (int, np.integer)) and not isinstance(leg, (bool, np.bool_))
    if not is_int or leg not in valid:
        raise ValueError(f"{what} must be a leg in {valid} or None (healthy Ant), got {leg!r}")
    return int(leg)
