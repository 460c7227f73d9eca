"""7-DOF Franka Panda reaching with an unknown tool extension (paper section 4.2, Fig. 3).

The forward kinematics (the modified-DH chain of the Panda plus a tool of unknown length along
the flange axis), the joint integrator, the samplers of tools, joint configurations and goals, and
the training-data generator are pure batched torch functions; :class:`PandaReachEnv` calls the
same functions, so the env, the controllers of ``smcd-rl panda`` and the benchmark share one
implementation.

Example:
    >>> import torch
    >>> from smcd_rl.envs.panda_reach import panda_fk
    >>> panda_fk(torch.zeros(7)).round(decimals=3)  # all joints at zero: the flange above the base
    tensor([0.0880, 0.0000, 0.9260])
    >>> panda_fk(torch.zeros(7), tool_length=0.1).round(decimals=3)  # the flange points down
    tensor([0.0880, 0.0000, 0.8260])
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import ArrayLike
from tensordict import TensorDict
from torch import Tensor

from smcd_rl.envs.rendering import FRAME_SIZE, RENDER_MODES, Canvas, check_render_mode, render_state

__all__ = [
    "ACCELERATION_LIMITS",
    "DEFAULT_DT",
    "DH_TABLE",
    "FLANGE_LENGTH",
    "GOAL_TOLERANCE",
    "JOINT_LOWER",
    "JOINT_UPPER",
    "MAX_EPISODE_STEPS",
    "READY_POSE",
    "TOOL_RANGE",
    "VELOCITY_LIMITS",
    "PandaReachEnv",
    "integrate_panda",
    "joint_limits",
    "panda_fk",
    "panda_frame",
    "panda_kinematics_data",
    "panda_points",
    "sample_goals",
    "sample_joint_configurations",
    "sample_tool_lengths",
]

#: Modified DH (Craig) parameters ``(a, d, alpha)`` of joints 1..7; each link is
#: ``Rx(alpha) Tx(a) Rz(q) Tz(d)``, with no joint offsets.
DH_TABLE: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
)
#: Distance (m) of the flange from joint 7's frame along its z axis.
FLANGE_LENGTH: float = 0.107
#: Joint position limits (rad).
JOINT_LOWER: tuple[float, ...] = (-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973)
JOINT_UPPER: tuple[float, ...] = (2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973)
#: Franka's joint velocity (rad/s) and acceleration (rad/s^2) limits, enforced by the env.
VELOCITY_LIMITS: tuple[float, ...] = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
ACCELERATION_LIMITS: tuple[float, ...] = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)
#: The fixed reference pose every episode starts from.
READY_POSE: tuple[float, ...] = (0.0, -0.3, 0.0, -2.2, 0.0, 2.0, math.pi / 4)
#: The tool extends the end effector by ``l ~ U(-TOOL_RANGE, TOOL_RANGE)`` m along the flange axis.
TOOL_RANGE: float = 0.5
#: Control period (s): ``q_dot += dt * u; q += dt * q_dot``.
DEFAULT_DT: float = 0.05
#: A goal is reached within this distance (m) ...
GOAL_TOLERANCE: float = 0.05
#: ... in at most this many control steps.
MAX_EPISODE_STEPS: int = 200

_N_JOINTS = 7


def joint_limits(
    *, device: torch.device | str | None = None, dtype: torch.dtype | None = None
) -> tuple[Tensor, Tensor]:
    """The joint position limits ``(lower, upper)``, each ``[7]``.

    Example:
        >>> lower, upper = joint_limits()
        >>> bool((lower < upper).all())
        True
    """
    lower = torch.tensor(JOINT_LOWER, device=device, dtype=dtype)
    return lower, torch.tensor(JOINT_UPPER, device=device, dtype=dtype)


def panda_fk(q: Tensor, tool_length: float | Tensor = 0.0) -> Tensor:
    """End-effector position of the Panda with a tool ``tool_length`` m beyond the flange.

    The chain is :data:`DH_TABLE` (each link ``Rx(alpha) Tx(a) Rz(q) Tz(d)``) followed by
    ``Tz(FLANGE_LENGTH + tool_length)``: the tool moves the end effector along the flange's z
    axis, and a negative length moves it back towards the wrist.

    Args:
        q: joint angles ``[..., 7]`` (rad).
        tool_length: tool extension (m), a float or a tensor broadcastable against ``q[..., 0]``
            (e.g. one length per row of a batch).

    Returns:
        ``[..., 3]`` base-frame position (m); differentiable in ``q`` and ``tool_length``, and
        every batch row depends only on its own angles (so :func:`smcd_rl.agents.pd.batch_jacobian`
        applies).

    Raises:
        ValueError: if the last dimension of ``q`` is not 7.

    Example:
        >>> import torch
        >>> q = torch.tensor([[0.0] * 7, [math.pi / 2] + [0.0] * 6])
        >>> panda_fk(q, torch.tensor([0.0, 0.2])).round(decimals=3) + 0.0  # joint 1 turns the arm about z
        tensor([[0.0880, 0.0000, 0.9260],
                [0.0000, 0.0880, 0.7260]])
    """
    if q.shape[-1:] != (_N_JOINTS,):
        raise ValueError(f"q must have shape [..., 7] (the Panda's joint angles), got {list(q.shape)}")
    batch = q.shape[:-1]
    rotation = torch.eye(3, dtype=q.dtype, device=q.device).expand(*batch, 3, 3)
    position = torch.zeros(*batch, 3, dtype=q.dtype, device=q.device)
    zero, one = torch.zeros_like(q[..., 0]), torch.ones_like(q[..., 0])
    for i, (a, d, alpha) in enumerate(DH_TABLE):
        if a != 0.0:  # Tx(a) along the previous frame's x axis (Rx leaves x unchanged)
            position = position + a * rotation[..., :, 0]
        if alpha != 0.0:
            rotation = rotation @ _rot_x(alpha, q)
        c, s = torch.cos(q[..., i]), torch.sin(q[..., i])
        rot_z = torch.stack(
            (torch.stack((c, -s, zero), -1), torch.stack((s, c, zero), -1), torch.stack((zero, zero, one), -1)), -2
        )
        rotation = rotation @ rot_z
        if d != 0.0:
            position = position + d * rotation[..., :, 2]
    reach = FLANGE_LENGTH + torch.as_tensor(tool_length, dtype=q.dtype, device=q.device)
    return position + reach.unsqueeze(-1) * rotation[..., :, 2]


def panda_points(q: Tensor, tool_length: float | Tensor = 0.0) -> Tensor:
    """The points of the Panda's stick figure: base, the chain's offsets, flange and tool tip, ``[..., 9, 3]``.

    The chain of :func:`panda_fk`, keeping the position after each of its translations (joint 1's
    ``d``, joint 3's ``d``, joint 4's ``a``, joint 5's ``a`` and ``d``, joint 7's ``a``), then the
    flange and the tool tip; the last point is :func:`panda_fk`'s end effector.

    Example:
        >>> import torch
        >>> q = torch.tensor(READY_POSE)
        >>> points = panda_points(q, 0.2)
        >>> points.shape, bool(torch.allclose(points[-1], panda_fk(q, 0.2)))
        (torch.Size([9, 3]), True)
    """
    if q.shape[-1:] != (_N_JOINTS,):
        raise ValueError(f"q must have shape [..., 7] (the Panda's joint angles), got {list(q.shape)}")
    batch = q.shape[:-1]
    rotation = torch.eye(3, dtype=q.dtype, device=q.device).expand(*batch, 3, 3)
    position = torch.zeros(*batch, 3, dtype=q.dtype, device=q.device)
    points = [position]
    zero, one = torch.zeros_like(q[..., 0]), torch.ones_like(q[..., 0])
    for i, (a, d, alpha) in enumerate(DH_TABLE):
        if a != 0.0:
            position = position + a * rotation[..., :, 0]
            points.append(position)
        if alpha != 0.0:
            rotation = rotation @ _rot_x(alpha, q)
        c, s = torch.cos(q[..., i]), torch.sin(q[..., i])
        rot_z = torch.stack(
            (torch.stack((c, -s, zero), -1), torch.stack((s, c, zero), -1), torch.stack((zero, zero, one), -1)), -2
        )
        rotation = rotation @ rot_z
        if d != 0.0:
            position = position + d * rotation[..., :, 2]
            points.append(position)
    points.append(position + FLANGE_LENGTH * rotation[..., :, 2])
    reach = FLANGE_LENGTH + torch.as_tensor(tool_length, dtype=q.dtype, device=q.device)
    points.append(position + reach.unsqueeze(-1) * rotation[..., :, 2])
    return torch.stack(points, dim=-2)


#: The camera of :func:`panda_frame`: azimuth and elevation (rad) of an orthographic view.
_VIEW_AZIMUTH, _VIEW_ELEVATION = math.radians(35.0), math.radians(20.0)
_ARM_COLOR, _JOINT_COLOR, _TOOL_COLOR = (40, 70, 120), (20, 20, 20), (210, 50, 40)
_GOAL_COLOR, _FLOOR_COLOR, _SHADOW_COLOR = (30, 150, 60), (215, 215, 208), (185, 185, 178)


def _project(points: np.ndarray) -> np.ndarray:
    """World points ``[..., 3]`` to the view plane ``[..., 2]`` (orthographic, z up on screen)."""
    ca, sa = math.cos(_VIEW_AZIMUTH), math.sin(_VIEW_AZIMUTH)
    ce, se = math.cos(_VIEW_ELEVATION), math.sin(_VIEW_ELEVATION)
    right = np.array([-sa, ca, 0.0])
    up = np.array([-ca * se, -sa * se, ce])
    return np.stack((points @ right, points @ up), axis=-1)


_FLOOR_HALF = 0.7  # m: the floor grid spans [-0.7, 0.7]^2
_VIEW_CENTER, _VIEW_EXTENT = (0.0, 0.4), 1.0  # view-plane centre and half span (m)


@functools.lru_cache(maxsize=4)
def _floor(height: int, width: int) -> np.ndarray:
    """The static part of every Panda frame, the floor grid, drawn once per frame size."""
    canvas = Canvas(center=_VIEW_CENTER, extent=_VIEW_EXTENT, height=height, width=width)
    for v in np.linspace(-_FLOOR_HALF, _FLOOR_HALF, 9):
        for start, end in (
            ((v, -_FLOOR_HALF, 0.0), (v, _FLOOR_HALF, 0.0)),
            ((-_FLOOR_HALF, v, 0.0), (_FLOOR_HALF, v, 0.0)),
        ):
            canvas.line(_project(np.array(start)), _project(np.array(end)), color=_FLOOR_COLOR)
    canvas.image.flags.writeable = False  # shared by every frame of this size
    return canvas.image


def panda_frame(
    q: ArrayLike,
    tool_length: float,
    goal: ArrayLike | None = None,
    *,
    measured: bool = False,
    height: int = FRAME_SIZE[0],
    width: int = FRAME_SIZE[1],
) -> np.ndarray:
    """An RGB frame of the Panda as a stick figure in an oblique orthographic view: a pure function of the state.

    The arm (blue, joints black) stands on a floor grid of 1.4 x 1.4 m; the tool from the flange to
    the end effector is red, the goal a green ring, and the goal's and the end effector's
    shadows on the floor (grey) show their heights. ``measured`` draws a ring round the end
    effector: the steps at which the true position was measured.

    Args:
        q: joint angles ``[7]`` (rad).
        tool_length: the tool's extension beyond the flange (m).
        goal: an optional goal ``(x, y, z)``.
        measured: mark the end effector as measured at this step.
        height: frame height in pixels.
        width: frame width in pixels.

    Returns:
        ``uint8 [height, width, 3]``.

    Example:
        >>> frame = panda_frame(READY_POSE, 0.1, goal=(0.5, 0.2, 0.4))
        >>> frame.shape, frame.dtype
        ((480, 480, 3), dtype('uint8'))
    """
    joints = torch.as_tensor(np.asarray(q, dtype=np.float64))
    points = panda_points(joints, float(tool_length)).numpy()
    canvas = Canvas(
        center=_VIEW_CENTER, extent=_VIEW_EXTENT, height=height, width=width, background=_floor(height, width)
    )
    unit = 0.01
    tip = points[-1]
    shadows = [tip] if goal is None else [tip, np.asarray(goal, dtype=np.float64)]
    for point in shadows:
        floor = point * np.array([1.0, 1.0, 0.0])
        canvas.line(_project(floor), _project(point), color=_SHADOW_COLOR, width=0.4 * unit)
        canvas.disc(_project(floor), 1.2 * unit, color=_SHADOW_COLOR)
    screen = _project(points)
    canvas.box(screen[0] - 4 * unit, screen[0] + 4 * unit, color=_JOINT_COLOR)  # the base
    canvas.polyline(screen[:-1], color=_ARM_COLOR, width=2.2 * unit)
    for point in screen[1:-1]:
        canvas.disc(point, 1.4 * unit, color=_JOINT_COLOR)
    canvas.line(screen[-2], screen[-1], color=_TOOL_COLOR, width=1.4 * unit)
    if goal is not None:
        centre = _project(np.asarray(goal, dtype=np.float64))
        canvas.ring(centre, GOAL_TOLERANCE, color=_GOAL_COLOR, width=0.8 * unit)
        canvas.disc(centre, 0.8 * unit, color=_GOAL_COLOR)
    canvas.disc(screen[-1], 1.6 * unit, color=_TOOL_COLOR)
    if measured:
        canvas.ring(screen[-1], 3.2 * unit, color=_TOOL_COLOR, width=0.6 * unit)
    return canvas.image


def _rot_x(alpha: float, like: Tensor) -> Tensor:
    c, s = round(math.cos(alpha), 12), round(math.sin(alpha), 12)  # exact 0 and +-1 for +-pi/2
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=like.dtype, device=like.device)


def integrate_panda(
    q: Tensor, q_dot: Tensor, acceleration: Tensor, dt: float = DEFAULT_DT, *, limits: bool = True
) -> tuple[Tensor, Tensor]:
    """One semi-implicit Euler step of the double integrator ``q_ddot = u``.

    ``q_dot += dt * u; q += dt * q_dot``. With ``limits`` (the env's default), the command is first
    clipped to :data:`ACCELERATION_LIMITS`, the velocity to :data:`VELOCITY_LIMITS`, and a joint that
    would pass its position limit stops there (its velocity becomes zero).

    Args:
        q: joint angles ``[..., 7]`` (rad).
        q_dot: joint velocities ``[..., 7]`` (rad/s).
        acceleration: commanded joint accelerations ``[..., 7]`` (rad/s^2).
        dt: step (s).
        limits: enforce the Panda's acceleration, velocity and position limits.

    Returns:
        ``(q, q_dot)`` after the step.

    Example:
        >>> import torch
        >>> start = torch.tensor([0.0, 0.0, 0.0, -0.08, 0.0, 1.0, 0.0])  # joint 4 just below its limit
        >>> q, q_dot = integrate_panda(start, torch.zeros(7), torch.full((7,), 100.0), 0.1)
        >>> q_dot  # 100 rad/s^2 is clipped to each joint's acceleration limit; joint 4 hit its limit
        tensor([1.5000, 0.7500, 1.0000, 0.0000, 1.5000, 2.0000, 2.0000])
        >>> round(float(q[3]), 4)  # stopped at the limit instead of moving 0.125 rad
        -0.0698
    """
    if not (q.shape == q_dot.shape == acceleration.shape) or q.shape[-1:] != (_N_JOINTS,):
        raise ValueError(
            f"q, q_dot and acceleration must all be [..., 7], got {list(q.shape)}, {list(q_dot.shape)}, "
            f"{list(acceleration.shape)}"
        )
    if not limits:
        q_dot = q_dot + dt * acceleration
        return q + dt * q_dot, q_dot
    dtype, device = q.dtype, q.device
    max_acc = torch.tensor(ACCELERATION_LIMITS, dtype=dtype, device=device)
    max_vel = torch.tensor(VELOCITY_LIMITS, dtype=dtype, device=device)
    lower, upper = joint_limits(dtype=dtype, device=device)
    q_dot = (q_dot + dt * torch.clamp(acceleration, -max_acc, max_acc)).clamp(-max_vel, max_vel)
    q = q + dt * q_dot
    stopped = (q <= lower) | (q >= upper)
    return q.clamp(lower, upper), torch.where(stopped, torch.zeros_like(q_dot), q_dot)


def sample_tool_lengths(
    shape: int | Sequence[int],
    *,
    tool_range: float = TOOL_RANGE,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Tool extensions ``l ~ U(-tool_range, tool_range)`` (m), of shape ``shape``.

    Example:
        >>> import torch
        >>> lengths = sample_tool_lengths(1000, generator=torch.Generator().manual_seed(0))
        >>> bool(lengths.abs().max() <= 0.5), bool(lengths.min() < -0.4 and lengths.max() > 0.4)
        (True, True)
    """
    if not (math.isfinite(tool_range) and tool_range >= 0):
        raise ValueError(f"tool_range must be finite and >= 0, got {tool_range!r}; the paper uses 0.5")
    size = (shape,) if isinstance(shape, int) else tuple(shape)
    return (2 * torch.rand(size, generator=generator, device=device) - 1) * tool_range


def sample_joint_configurations(
    shape: int | Sequence[int],
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Joint angles drawn uniformly within the joint limits, ``[*shape, 7]``.

    Example:
        >>> import torch
        >>> q = sample_joint_configurations((4,), generator=torch.Generator().manual_seed(0))
        >>> lower, upper = joint_limits()
        >>> q.shape, bool(((q >= lower) & (q <= upper)).all())
        (torch.Size([4, 7]), True)
    """
    size = (shape,) if isinstance(shape, int) else tuple(shape)
    lower, upper = joint_limits(device=device)
    return lower + (upper - lower) * torch.rand(*size, _N_JOINTS, generator=generator, device=device)


def sample_goals(tool_length: Tensor, *, generator: torch.Generator | None = None) -> Tensor:
    """Kinematically feasible goals: the end effector at random joint angles within the limits.

    Args:
        tool_length: the tool of each task, any shape ``S``; the goals are ``[*S, 3]``, on its device.
        generator: random source (on ``tool_length``'s device).

    Example:
        >>> import torch
        >>> goals = sample_goals(torch.zeros(5), generator=torch.Generator().manual_seed(0))
        >>> goals.shape, bool(goals.norm(dim=-1).max() < 1.3)  # the arm reaches about 1.2 m
        (torch.Size([5, 3]), True)
    """
    q = sample_joint_configurations(tuple(tool_length.shape), generator=generator, device=tool_length.device)
    return panda_fk(q.to(tool_length.dtype), tool_length)


def panda_kinematics_data(
    num_samples: int,
    *,
    tool_range: float = TOOL_RANGE,
    measurement_noise: float = 0.0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> TensorDict:
    """Training data for a forward-kinematics model: random joint angles, each with its own random tool.

    The paper trains on 100000 such samples ("with an arbitrary tool offset"). The tool is not an
    input: a model learns the kinematics averaged over tools, and adaptation must find the tool.

    Args:
        num_samples: number of (joint angles, end effector) pairs.
        tool_range: tools are drawn from ``U(-tool_range, tool_range)`` m.
        measurement_noise: std (m) of Gaussian noise on the end-effector positions.
        generator: random source (on ``device``); the same seed gives the same data.
        device: where the data lives.

    Returns:
        TensorDict ``[num_samples]`` with ``"q"`` ``[., 7]``, ``"ee"`` ``[., 3]`` and
        ``"tool_length"`` ``[.]``.

    Example:
        >>> import torch
        >>> data = panda_kinematics_data(100, generator=torch.Generator().manual_seed(0))
        >>> data["q"].shape, data["ee"].shape
        (torch.Size([100, 7]), torch.Size([100, 3]))
        >>> bool(torch.allclose(panda_fk(data["q"], data["tool_length"]), data["ee"]))
        True
    """
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 1:
        raise ValueError(f"num_samples must be a positive int, got {num_samples!r}; the paper uses 100000")
    if not (math.isfinite(measurement_noise) and measurement_noise >= 0):
        raise ValueError(f"measurement_noise must be finite and >= 0, got {measurement_noise!r}")
    q = sample_joint_configurations(num_samples, generator=generator, device=device)
    tool = sample_tool_lengths(num_samples, tool_range=tool_range, generator=generator, device=device)
    ee = panda_fk(q, tool)
    if measurement_noise > 0:
        ee = ee + measurement_noise * torch.randn(ee.shape, generator=generator, device=ee.device)
    return TensorDict({"q": q, "ee": ee, "tool_length": tool}, batch_size=[num_samples], device=device)


class PandaReachEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """Reach a goal with a 7-DOF Franka Panda that holds a tool of unknown length.

    ## Description

    The Panda (modified-DH kinematics, see `panda_fk`) holds a tool that extends its end effector
    by an unknown `l ~ U(-0.5, 0.5)` m along the flange axis, redrawn every episode (paper
    section 4.2). From the fixed ready pose `qr = [0, -0.3, 0, -2.2, 0, 2.0, pi/4]` the arm must
    bring the end effector within 5 cm of a goal. The true end-effector position is measured only
    every `measurement_interval`-th step, so a controller must rely on its own model in between
    (model-reference control).

    The joints are acceleration controlled: `q_dot += dt u; q += dt q_dot` with `dt = 0.05` s,
    so the PD law of the paper, `u = -K1 J^+ (x - x_g) - K2 q_dot`, has a real joint velocity to
    damp. Accelerations, velocities and joint positions are limited to the Panda's specification
    (`ACCELERATION_LIMITS`, `VELOCITY_LIMITS`, `JOINT_LOWER`/`JOINT_UPPER`); a joint that reaches
    a position limit stops there.

    ## Action Space

    `Box(-ACCELERATION_LIMITS, ACCELERATION_LIMITS, (7,), float32)`: joint accelerations in
    rad/s^2 (15, 7.5, 10, 12.5, 15, 20, 20), clipped to the box.

    ## Observation Space

    `Box((21,), float32)`:

    | Num   | Observation                                                          | Min   | Max   |
    |-------|----------------------------------------------------------------------|-------|-------|
    | 0-6   | joint angles q1..q7 (rad)                                            | limit | limit |
    | 7-13  | joint velocities (rad/s)                                             | -vmax | vmax  |
    | 14-16 | goal position x, y, z (m)                                            | -2    | 2     |
    | 17-19 | the last measured end-effector position x, y, z (m)                  | -2    | 2     |
    | 20    | 1.0 if that measurement was taken at this step, 0.0 if it is older  | 0     | 1     |

    A measurement is taken at reset (step 0) and after every `measurement_interval`-th step
    (steps `n, 2n, ...`); in between, entries 17-19 repeat the last one and entry 20 is 0. The
    measured position is the true one plus `N(0, measurement_noise^2)` noise. The true position
    is in `info["ee_true"]` (for scoring only).

    ## Rewards

    `-distance` (m) between the true end effector and the goal.

    ## Starting State

    The ready pose at rest. The tool `l ~ U(-0.5, 0.5)` and the goal, the end effector with that
    tool at joint angles drawn uniformly within the limits (always reachable). `options` may fix
    `"tool_length"` (float), `"goal"` (3 floats) or `"q"` (7 floats, the start pose);
    `info["tool_length"]` reports the tool.

    ## Episode End

    Terminates when the true end effector is within `goal_tolerance` (5 cm) of the goal
    (`info["is_success"]` is then True); `gymnasium.make("smcd_rl/PandaReach-v0")` truncates after
    200 steps.

    ## Arguments

    - `measurement_interval`: a measurement every n-th step (default 1: every step).
    - `measurement_noise`: std (m) of the measurement noise (default 0).
    - `dt`: control period in seconds (default 0.05).
    - `tool_range`: tools are drawn from `U(-tool_range, tool_range)` (default 0.5 m).
    - `goal_tolerance`: success distance in m (default 0.05).
    - `render_mode`: `None` or `"rgb_array"` (a 480 x 480 stick figure of the arm with its tool and
      the goal, `panda_frame`; a ring marks a measured step).

    ```python
    >>> import gymnasium, numpy as np, smcd_rl
    >>> env = gymnasium.make("smcd_rl/PandaReach-v0", measurement_interval=5)
    >>> obs, info = env.reset(seed=0, options={"tool_length": 0.0})
    >>> obs[:7].round(2), bool(obs[20])  # the ready pose, measured at reset
    (array([ 0.  , -0.3 ,  0.  , -2.2 ,  0.  ,  2.  ,  0.79], dtype=float32), True)
    >>> [bool(env.step(np.zeros(7, np.float32))[0][20]) for _ in range(5)]
    [False, False, False, False, True]

    ```

    ## Version History

    * v0: Initial version (paper section 4.2).
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / DEFAULT_DT)}
    # Narrowed from gymnasium.Env's Space: __init__ always sets Boxes, and _observation clips to their bounds.
    action_space: spaces.Box
    observation_space: spaces.Box

    def __init__(
        self,
        measurement_interval: int = 1,
        measurement_noise: float = 0.0,
        dt: float = DEFAULT_DT,
        tool_range: float = TOOL_RANGE,
        goal_tolerance: float = GOAL_TOLERANCE,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode)
        if (
            isinstance(measurement_interval, bool)
            or not isinstance(measurement_interval, int)
            or measurement_interval < 1
        ):
            raise ValueError(
                f"measurement_interval must be an int >= 1, got {measurement_interval!r}; 1 measures every step"
            )
        for name, value in (("dt", dt), ("goal_tolerance", goal_tolerance)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}")
        for name, value in (("measurement_noise", measurement_noise), ("tool_range", tool_range)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        self.measurement_interval = measurement_interval
        self.measurement_noise = float(measurement_noise)
        self.dt = float(dt)
        self.tool_range = float(tool_range)
        self.goal_tolerance = float(goal_tolerance)
        self.render_mode = render_mode

        max_acc = np.array(ACCELERATION_LIMITS, dtype=np.float32)
        self.action_space = spaces.Box(-max_acc, max_acc, dtype=np.float32)
        max_vel = np.array(VELOCITY_LIMITS, dtype=np.float32)
        # The arm reaches about 1.2 m; goals and measurements (with any tool and noise) stay well inside 2 m.
        low = np.concatenate([JOINT_LOWER, -max_vel, [-2.0] * 6, [0.0]]).astype(np.float32)
        high = np.concatenate([JOINT_UPPER, max_vel, [2.0] * 6, [1.0]]).astype(np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)

        self._q: Tensor | None = None  # float64 state, set by reset()
        self._q_dot = torch.zeros(_N_JOINTS, dtype=torch.float64)
        self._tool = 0.0
        self._goal = np.zeros(3)
        self._measured = np.zeros(3)
        self._fresh = False  # whether the last step measured (for render)
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start at the ready pose (or ``options["q"]``) with a new tool and goal (or the given ones).

        Raises:
            ValueError: on unknown option keys or values of the wrong size, non-finite, or joint
                angles outside the limits.

        Example:
            >>> env = PandaReachEnv()
            >>> obs, info = env.reset(seed=0, options={"tool_length": 0.25})
            >>> info["tool_length"], info["is_success"]
            (0.25, False)
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"tool_length", "goal", "q"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; use 'tool_length', 'goal', 'q'")
        # One torch generator per episode, seeded from self.np_random, so gymnasium's seed decides
        # every draw while the env shares the batched torch samplers with the experiments.
        generator = torch.Generator().manual_seed(int(self.np_random.integers(2**63 - 1)))
        if "tool_length" in options:
            tool = float(_vector("tool_length", options["tool_length"], ())[()])
        else:
            tool = float(sample_tool_lengths((), tool_range=self.tool_range, generator=generator))
        if "q" in options:
            q = torch.from_numpy(_vector("q", options["q"], (_N_JOINTS,)))
            lower, upper = joint_limits(dtype=torch.float64)
            if not bool(((q >= lower) & (q <= upper)).all()):
                raise ValueError(f"options['q'] must lie within the joint limits {JOINT_LOWER} .. {JOINT_UPPER}")
        else:
            q = torch.tensor(READY_POSE, dtype=torch.float64)
        if "goal" in options:
            goal = _vector("goal", options["goal"], (3,))
        else:
            goal = sample_goals(torch.tensor(tool, dtype=torch.float64), generator=generator).numpy()
        self._tool, self._goal, self._q = tool, goal, q
        self._q_dot = torch.zeros(_N_JOINTS, dtype=torch.float64)
        self._steps = 0
        ee = self._ee_true()
        self._measure(ee)
        self._fresh = True
        return self._observation(fresh=True), self._info(ee, fresh=True)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply joint accelerations for ``dt`` seconds.

        Returns:
            ``(observation, -distance, reached, False, info)``; ``info`` has ``"ee_true"``,
            ``"distance"``, ``"is_success"``, ``"measured"`` and ``"tool_length"``.

        Example:
            >>> import numpy as np
            >>> env = PandaReachEnv(measurement_interval=2)
            >>> _ = env.reset(seed=0)
            >>> obs, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
            >>> info["measured"], bool(np.allclose(obs[:7], env.reset(seed=0)[0][:7]))  # at rest
            (False, True)
        """
        if self._q is None:
            raise RuntimeError("call reset() before step()")
        u = np.asarray(action, dtype=np.float64)
        if u.shape != (_N_JOINTS,):
            raise ValueError(f"action must have shape (7,) (joint accelerations), got {u.shape}")
        self._q, self._q_dot = integrate_panda(self._q, self._q_dot, torch.from_numpy(u), self.dt)
        self._steps += 1
        fresh = self._steps % self.measurement_interval == 0
        ee = self._ee_true()
        if fresh:
            self._measure(ee)
        self._fresh = fresh
        info = self._info(ee, fresh=fresh)
        return self._observation(fresh=fresh), -info["distance"], info["is_success"], False, info

    def render(self) -> np.ndarray | None:
        """The arm, its tool and the goal as ``uint8 [480, 480, 3]`` (``render_mode="rgb_array"``), else None.

        Example:
            >>> env = PandaReachEnv(render_mode="rgb_array")
            >>> _ = env.reset(seed=0)
            >>> env.render().shape
            (480, 480, 3)
        """
        return render_state(
            self.render_mode, self._q, lambda q: panda_frame(q.numpy(), self._tool, self._goal, measured=self._fresh)
        )

    def _ee_true(self) -> np.ndarray:
        assert self._q is not None
        return panda_fk(self._q, self._tool).numpy()

    def _measure(self, ee: np.ndarray) -> None:
        noise = self.measurement_noise * self.np_random.standard_normal(3) if self.measurement_noise > 0 else 0.0
        self._measured = ee + noise

    def _observation(self, *, fresh: bool) -> np.ndarray:
        assert self._q is not None
        parts: list[ArrayLike] = [self._q.numpy(), self._q_dot.numpy(), self._goal, self._measured, [float(fresh)]]
        return np.clip(np.concatenate(parts), self.observation_space.low, self.observation_space.high).astype(
            np.float32
        )

    def _info(self, ee: np.ndarray, *, fresh: bool) -> dict[str, Any]:
        distance = float(np.linalg.norm(ee - self._goal))
        return {
            "ee_true": ee.astype(np.float32),
            "distance": distance,
            "is_success": distance < self.goal_tolerance,
            "measured": fresh,
            "tool_length": self._tool,
        }


def _vector(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"options[{name!r}] must be numbers of shape {shape}, got {value!r}") from err
    if arr.shape != shape or not np.isfinite(arr).all():
        raise ValueError(f"options[{name!r}] must be finite numbers of shape {shape}, got {value!r}")
    return arr
