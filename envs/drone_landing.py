"""Drone landing with linear-velocity commands (paper section 4.3), simulated.

The paper's drone data came from human operators flying a simulated drone onto one of five
platforms; neither the simulator nor the data was released. This module is a small stand-in with
the paper's state and action: the drone follows its velocity command with a first-order lag, and
an episode ends when it touches down on a platform or the ground. The dynamics, the platform
geometry, the observation, the reward and the success test of appendix B.1 are pure batched torch
functions; :class:`DroneLandingEnv` and the simulated operators of
:mod:`smcd_rl.envs.drone_operators` call the same functions.

Example:
    >>> import torch
    >>> from smcd_rl.envs.drone_landing import START, drone_transition
    >>> p, v = torch.tensor(START), torch.zeros(3)
    >>> p, v, down = drone_transition(p, v, torch.tensor([1.0, 0.0, 0.0]))
    >>> bool(v[0] > 0), bool(down)
    (True, False)
"""

from __future__ import annotations

import math
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import ArrayLike
from torch import Tensor

from smcd_rl.envs.rendering import FRAME_SIZE, RENDER_MODES, Canvas, check_render_mode, render_state

__all__ = [
    "DT",
    "TAU",
    "MAX_SPEED",
    "START",
    "PLATFORMS",
    "NUM_PLATFORMS",
    "ARENA_LOW",
    "ARENA_HIGH",
    "STATE_DIM",
    "ACTION_DIM",
    "SUCCESS_REWARD",
    "DroneLandingEnv",
    "drone_frame",
    "drone_observation",
    "drone_reward",
    "drone_transition",
    "landing_success",
    "platform_index",
    "platform_tensor",
    "surface_height",
    "target_distance",
]

#: Control period in seconds (5 Hz, a keyboard operator's pace).
DT: float = 0.2
#: Time constant of the first-order velocity response, in seconds.
TAU: float = 0.4
#: Largest velocity command per axis, m/s.
MAX_SPEED: float = 2.0
#: Where every episode starts, hovering (x forward from the operator's viewpoint, y left, z up).
START: tuple[float, float, float] = (0.0, 0.0, 3.0)
#: The five platforms, one row each: centre x, centre y, top height, half side of the square top (m).
#: They lie at increasing depth from the start, where the paper's fixed viewpoint made them harder.
PLATFORMS: tuple[tuple[float, float, float, float], ...] = (
    (3.0, -1.5, 0.6, 0.5),
    (5.0, 1.5, 1.0, 0.5),
    (7.0, -0.5, 0.8, 0.5),
    (9.0, 2.0, 1.2, 0.5),
    (11.0, -2.0, 0.5, 0.5),
)
NUM_PLATFORMS: int = len(PLATFORMS)
#: The flight volume: positions are held inside this box (walls stop the drone on that axis).
ARENA_LOW: tuple[float, float, float] = (-2.0, -6.0, 0.0)
ARENA_HIGH: tuple[float, float, float] = (14.0, 6.0, 6.0)
#: Sizes of the paper's state ``x = (position 3, velocity 3, distance to target 1)`` and action.
STATE_DIM: int = 7
ACTION_DIM: int = 3
#: Reward at touchdown: ``+SUCCESS_REWARD`` for a landing that meets :func:`landing_success`,
#: ``-SUCCESS_REWARD`` for any other touchdown.
SUCCESS_REWARD: float = 10.0


def platform_tensor(*, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Tensor:
    """:data:`PLATFORMS` as a ``[5, 4]`` tensor (x, y, top height, half side).

    Example:
        >>> platform_tensor().shape
        torch.Size([5, 4])
    """
    return torch.tensor(PLATFORMS, dtype=dtype or torch.get_default_dtype(), device=device)


def platform_index(xy: Tensor) -> Tensor:
    """Index of the platform whose top face lies under each point, ``-1`` over the ground.

    Args:
        xy: horizontal positions ``[..., 2]``; a point on a face's edge counts as on it.

    Returns:
        ``int64 [...]``.

    Example:
        >>> import torch
        >>> platform_index(torch.tensor([[3.0, -1.5], [0.0, 0.0]]))
        tensor([ 0, -1])
    """
    table = platform_tensor(dtype=xy.dtype, device=xy.device)
    inside = ((xy.unsqueeze(-2) - table[:, :2]).abs() <= table[:, 3:4]).all(-1)  # [..., 5]
    # Platforms do not overlap, so at most one is True; argmax picks it.
    return torch.where(
        inside.any(-1), inside.to(torch.int8).argmax(-1), torch.full_like(inside[..., 0], -1, dtype=torch.long)
    )


def surface_height(xy: Tensor) -> Tensor:
    """Height of whatever is under each point: a platform's top, else the ground (0).

    Example:
        >>> import torch
        >>> surface_height(torch.tensor([[5.0, 1.5], [5.0, 3.0]]))
        tensor([1., 0.])
    """
    table = platform_tensor(dtype=xy.dtype, device=xy.device)
    index = platform_index(xy)
    return torch.where(index >= 0, table[index.clamp(min=0), 2], torch.zeros_like(xy[..., 0]))


def _target_point(target: Tensor | int, like: Tensor) -> Tensor:
    """Centre of the target platforms' top faces, ``[..., 3]``."""
    table = platform_tensor(dtype=like.dtype, device=like.device)
    index = torch.as_tensor(target, device=like.device)
    if index.dtype.is_floating_point or bool(((index < 0) | (index >= NUM_PLATFORMS)).any()):
        raise ValueError(f"target must be integer platform indices in 0..{NUM_PLATFORMS - 1}, got {target}")
    return table[index][..., :3]


def target_distance(position: Tensor, target: Tensor | int) -> Tensor:
    """Euclidean distance ``d = |g - p|`` from the drone to the centre of the target's top face.

    Args:
        position: ``[..., 3]``.
        target: platform indices, broadcastable against ``position[..., 0]``.

    Example:
        >>> import torch
        >>> target_distance(torch.tensor([3.0, -1.5, 1.6]), 0)
        tensor(1.)
    """
    return (position - _target_point(target, position)).norm(dim=-1)


def drone_observation(position: Tensor, velocity: Tensor, target: Tensor | int) -> Tensor:
    """The paper's state ``x = (p, v, d)``, ``[..., 7]``.

    Example:
        >>> import torch
        >>> drone_observation(torch.tensor([3.0, -1.5, 1.6]), torch.zeros(3), 0)
        tensor([ 3.0000, -1.5000,  1.6000,  0.0000,  0.0000,  0.0000,  1.0000])
    """
    return torch.cat([position, velocity, target_distance(position, target).unsqueeze(-1)], dim=-1)


def drone_transition(
    position: Tensor,
    velocity: Tensor,
    command: Tensor,
    *,
    dt: float = DT,
    tau: float = TAU,
    max_speed: float = MAX_SPEED,
) -> tuple[Tensor, Tensor, Tensor]:
    """One step of the drone: first-order velocity response, then motion, walls and touchdown.

    The command is clipped to ``[-max_speed, max_speed]`` per axis; the velocity moves towards it
    with the exact discretisation of ``tau * dv/dt = u - v``, and the position moves with the new
    velocity. A wall of the arena stops the drone on that axis (the velocity there becomes 0); a
    platform's side stops its horizontal motion (flying into a platform below its top).
    Touchdown happens when the drone reaches the surface below it (a platform's top or the
    ground): it is then set on the surface, at rest.

    Args:
        position: ``[..., 3]``, broadcastable against the others.
        velocity: ``[..., 3]``.
        command: ``[..., 3]``, the velocity command.
        dt: step in seconds.
        tau: velocity time constant in seconds.
        max_speed: command bound per axis, m/s.

    Returns:
        ``(position, velocity, touched_down)``; ``touched_down`` is bool ``[...]``.

    Example:
        >>> import torch
        >>> p, v, down = drone_transition(torch.tensor([0.0, 0.0, 0.1]), torch.zeros(3), torch.tensor([0.0, 0.0, -2.0]))
        >>> p, bool(down)
        (tensor([0., 0., 0.]), True)
    """
    alpha = 1.0 - math.exp(-dt / tau)
    command = command.clamp(-max_speed, max_speed)
    velocity = velocity + alpha * (command - velocity)
    moved = position + dt * velocity
    low = torch.tensor(ARENA_LOW, dtype=moved.dtype, device=moved.device)
    high = torch.tensor(ARENA_HIGH, dtype=moved.dtype, device=moved.device)
    clamped = torch.minimum(torch.maximum(moved, low), high)
    velocity = torch.where(clamped != moved, torch.zeros_like(velocity), velocity)
    # A platform's side is a wall too: moving into its footprint below its top keeps the old XY.
    surface = surface_height(clamped[..., :2])
    position, clamped = torch.broadcast_tensors(position, clamped)
    side = (clamped[..., 2] < surface) & (surface_height(position[..., :2]) < surface)
    clamped = torch.cat([torch.where(side.unsqueeze(-1), position[..., :2], clamped[..., :2]), clamped[..., 2:]], -1)
    velocity = torch.cat([torch.where(side.unsqueeze(-1), 0.0, velocity[..., :2]), velocity[..., 2:]], -1)
    surface = surface_height(clamped[..., :2])
    touched_down = clamped[..., 2] <= surface
    landed = torch.cat([clamped[..., :2], surface.unsqueeze(-1)], dim=-1)
    position = torch.where(touched_down.unsqueeze(-1), landed, clamped)
    velocity = torch.where(touched_down.unsqueeze(-1), torch.zeros_like(velocity), velocity)
    return position, velocity, touched_down


def landing_success(position: Tensor, target: Tensor | int, *, tolerance: float = 1e-6) -> Tensor:
    """Appendix B.1's success test of a trajectory's final position.

    Success if and only if the drone's final height is not above the target platform's top
    (it has landed, not hovering) and its final XY position lies within the top face.

    Example:
        >>> import torch
        >>> landing_success(torch.tensor([[3.2, -1.3, 0.6], [3.2, -1.3, 1.5], [4.0, -1.5, 0.0]]), 0)
        tensor([ True, False, False])
    """
    table = platform_tensor(dtype=position.dtype, device=position.device)
    row = table[torch.as_tensor(target, device=position.device)]
    low_enough = position[..., 2] <= row[..., 2] + tolerance
    within = ((position[..., :2] - row[..., :2]).abs() <= row[..., 3:4] + tolerance).all(-1)
    return low_enough & within


def drone_reward(position: Tensor, next_position: Tensor, target: Tensor | int, touched_down: Tensor) -> Tensor:
    """Progress towards the target's top centre, plus +-:data:`SUCCESS_REWARD` at touchdown.

    ``r = d(p) - d(p')``; at touchdown add ``SUCCESS_REWARD`` if :func:`landing_success` holds,
    else subtract it.

    Example:
        >>> import torch
        >>> p = torch.tensor([3.0, -1.5, 1.0])
        >>> drone_reward(p, torch.tensor([3.0, -1.5, 0.6]), 0, torch.tensor(True))
        tensor(10.4000)
    """
    progress = target_distance(position, target) - target_distance(next_position, target)
    bonus = torch.where(landing_success(next_position, target), SUCCESS_REWARD, -SUCCESS_REWARD)
    return progress + torch.where(touched_down, bonus, torch.zeros_like(bonus))


_PLATFORM_COLOR, _TARGET_COLOR, _ARENA_COLOR = (170, 170, 165), (235, 150, 40), (120, 120, 115)
_DRONE_COLOR, _ROTOR_COLOR, _TRAIL_COLOR = (40, 70, 120), (210, 50, 40), (150, 170, 205)
# The frame shows the top view (x right, y up) above the side view (x right, z up): a top-view
# point (x, y) is drawn at (x, y + _TOP_OFFSET) in one world plane with the side view's (x, z).
_TOP_OFFSET = ARENA_HIGH[2] - ARENA_LOW[1] + 0.8
_VIEW_HIGH = _TOP_OFFSET + ARENA_HIGH[1]


def drone_frame(
    position: ArrayLike,
    target: int | None = None,
    *,
    trail: ArrayLike | None = None,
    height: int = FRAME_SIZE[0],
    width: int = FRAME_SIZE[1],
) -> np.ndarray:
    """An RGB frame of the drone over the platforms: top view above, side view below; a pure function of the state.

    The platforms are grey (the target orange), the drone a blue cross with red rotors in both
    views, and an optional ``trail`` of earlier positions a light blue line.

    Args:
        position: the drone's ``(x, y, z)`` (m).
        target: the target platform's index, or ``None``.
        trail: optional earlier positions ``[n, 3]``.
        height: frame height in pixels.
        width: frame width in pixels.

    Returns:
        ``uint8 [height, width, 3]``.

    Example:
        >>> frame = drone_frame(START, target=2)
        >>> frame.shape, bool((frame != drone_frame((3.0, -1.5, 1.0), target=2)).any())
        ((480, 480, 3), True)
    """
    p = np.asarray(position, dtype=np.float64).reshape(3)
    span = max(ARENA_HIGH[0] - ARENA_LOW[0], _VIEW_HIGH - ARENA_LOW[2])
    centre = ((ARENA_LOW[0] + ARENA_HIGH[0]) / 2, (ARENA_LOW[2] + _VIEW_HIGH) / 2)
    canvas = Canvas(center=centre, extent=0.52 * span, height=height, width=width)
    (x0, y0, z0), (x1, y1, z1) = ARENA_LOW, ARENA_HIGH
    canvas.box((x0, y0 + _TOP_OFFSET), (x1, y1 + _TOP_OFFSET), color=_ARENA_COLOR, width=0.05)
    canvas.box((x0, z0), (x1, z1), color=_ARENA_COLOR, width=0.05)
    for i, (px, py, top, half) in enumerate(PLATFORMS):
        color = _TARGET_COLOR if i == target else _PLATFORM_COLOR
        canvas.box((px - half, py - half + _TOP_OFFSET), (px + half, py + half + _TOP_OFFSET), color=color)
        canvas.box((px - half, 0.0), (px + half, top), color=color)
    if trail is not None:
        points = np.asarray(trail, dtype=np.float64).reshape(-1, 3)
        canvas.polyline(points[:, :2] + (0.0, _TOP_OFFSET), color=_TRAIL_COLOR, width=0.06)
        canvas.polyline(points[:, [0, 2]], color=_TRAIL_COLOR, width=0.06)
    arm = 0.45  # m, half the drone's span as drawn
    top_view = p[:2] + (0.0, _TOP_OFFSET)
    for dx, dy in ((1, 1), (1, -1)):
        offset = arm * np.array([dx, dy]) / math.sqrt(2)
        canvas.line(top_view - offset, top_view + offset, color=_DRONE_COLOR, width=0.08)
    for dx, dy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        canvas.disc(top_view + arm * np.array([dx, dy]) / math.sqrt(2), 0.14, color=_ROTOR_COLOR)
    side_view = p[[0, 2]]
    canvas.line(side_view - (arm, 0.0), side_view + (arm, 0.0), color=_DRONE_COLOR, width=0.1)
    for rotor in (-arm, arm):
        canvas.box(side_view + (rotor - 0.12, 0.05), side_view + (rotor + 0.12, 0.12), color=_ROTOR_COLOR)
    return canvas.image


class DroneLandingEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """Land a velocity-commanded drone on one of five platforms.

    ## Description

    A simulated stand-in for the paper's drone tele-operation task (section 4.3; the original
    simulator and human data were not released). The drone starts hovering at `(0, 0, 3)` m and
    must land on a target platform, one of five square platforms at increasing distance from the
    start. The operator commands linear velocities; the drone follows them with a first-order
    lag (`tau = 0.4 s`), stepped every `dt = 0.2 s`. An episode ends at touchdown, on a platform
    or on the ground. The target is not part of the observation other than through the distance
    `d` to it, as in the paper.

    | Platform | centre x (m) | centre y (m) | top height (m) | top face (m) |
    |----------|--------------|--------------|----------------|--------------|
    | 0        | 3            | -1.5         | 0.6            | 1 x 1        |
    | 1        | 5            | 1.5          | 1.0            | 1 x 1        |
    | 2        | 7            | -0.5         | 0.8            | 1 x 1        |
    | 3        | 9            | 2            | 1.2            | 1 x 1        |
    | 4        | 11           | -2           | 0.5            | 1 x 1        |

    ## Action Space

    An `ndarray` of shape `(3,)`: the velocity command in m/s, clipped to the box.

    | Num | Action     | Min  | Max |
    |-----|------------|------|-----|
    | 0   | x velocity | -2.0 | 2.0 |
    | 1   | y velocity | -2.0 | 2.0 |
    | 2   | z velocity | -2.0 | 2.0 |

    ## Observation Space

    An `ndarray` of shape `(7,)`, dtype `float32`: the paper's state `x = (p, v, d)`.

    | Num | Observation                                 | Min  | Max  |
    |-----|---------------------------------------------|------|------|
    | 0-2 | position x, y, z (m)                        | (-2, -6, 0) | (14, 6, 6) |
    | 3-5 | velocity x, y, z (m/s)                      | -2.0 | 2.0  |
    | 6   | distance to the target's top centre (m)     | 0    | 20.9 |

    ## Rewards

    Each step gives the progress `d(p) - d(p')` towards the centre of the target's top face. At
    touchdown a successful landing (appendix B.1: height not above the target's top and XY
    within its top face) adds `+10`; any other touchdown adds `-10`.

    ## Starting State

    Hovering at rest at `(0, 0, 3)`; `options={"position": (x, y, z)}` starts elsewhere. The
    target is drawn uniformly from the five platforms with `self.np_random`, or given with
    `options={"target": i}`. `info["target"]` reports it.

    ## Episode End

    Terminates at touchdown (`info["landed_on"]`: the platform index, or -1 for the ground;
    `info["success"]`: the B.1 test). `gymnasium.make("smcd_rl/DroneLanding-v0")` truncates after
    300 steps (60 s).

    ## Arguments

    - `dt`: control period in seconds (default `0.2`).
    - `tau`: velocity time constant in seconds (default `0.4`).
    - `max_speed`: command bound per axis in m/s (default `2.0`).
    - `render_mode`: `None` or `"rgb_array"` (a 480 x 480 frame, top view above side view, of the
      drone and the platforms, the target orange: `drone_frame`).

    ```python
    >>> import gymnasium, numpy as np
    >>> from smcd_rl.envs import register_all
    >>> register_all()
    >>> env = gymnasium.make("smcd_rl/DroneLanding-v0")
    >>> obs, info = env.reset(seed=0, options={"target": 2})
    >>> obs.shape, info["target"]
    ((7,), 2)
    >>> obs, reward, terminated, truncated, info = env.step(np.array([2.0, 0.0, 0.0], dtype=np.float32))
    >>> bool(obs[3] > 0), bool(reward > 0), terminated
    (True, True, False)

    ```

    ## Version History

    * v0: Initial version.
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / DT)}

    def __init__(
        self, dt: float = DT, tau: float = TAU, max_speed: float = MAX_SPEED, render_mode: str | None = None
    ) -> None:
        check_render_mode(render_mode)
        for name, value in (("dt", dt), ("tau", tau), ("max_speed", max_speed)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value!r}.")
        self.dt, self.tau, self.max_speed = float(dt), float(tau), float(max_speed)
        self.render_mode = render_mode
        self.action_space = spaces.Box(-self.max_speed, self.max_speed, (ACTION_DIM,), np.float32)
        span = np.subtract(ARENA_HIGH, ARENA_LOW)
        low = np.array([*ARENA_LOW, *(-self.max_speed,) * 3, 0.0], dtype=np.float32)
        high = np.array([*ARENA_HIGH, *(self.max_speed,) * 3, float(np.linalg.norm(span))], dtype=np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._position: np.ndarray | None = None  # float64 state, set by reset()
        self._velocity = np.zeros(3)
        self._target = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start hovering at rest, with a random (or given) target platform.

        Args:
            seed: seed of ``self.np_random``.
            options: optional ``{"target": i, "position": (x, y, z)}``.

        Raises:
            ValueError: unknown option keys, a target outside ``0..4``, or a start position
                outside the arena or not above the surface.

        Example:
            >>> env = DroneLandingEnv()
            >>> obs, info = env.reset(seed=0, options={"target": 4, "position": (1.0, 0.0, 2.0)})
            >>> obs[:3], info["target"]
            (array([1., 0., 2.], dtype=float32), 4)
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"target", "position"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; use 'target', 'position'.")
        if "target" in options:
            target = options["target"]
            if isinstance(target, bool) or not isinstance(target, (int, np.integer)) or not 0 <= target < NUM_PLATFORMS:
                raise ValueError(f"options['target'] must be a platform index 0..{NUM_PLATFORMS - 1}, got {target!r}.")
            self._target = int(target)
        else:
            self._target = int(self.np_random.integers(NUM_PLATFORMS))
        position = np.asarray(options.get("position", START), dtype=np.float64)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise ValueError(f"options['position'] must be three finite numbers, got {options.get('position')!r}.")
        inside = (position >= ARENA_LOW).all() and (position <= ARENA_HIGH).all()
        above = position[2] > float(surface_height(torch.as_tensor(position[:2])))
        if not (inside and above):
            raise ValueError(
                f"options['position'] {position.tolist()} must lie in the arena {ARENA_LOW}..{ARENA_HIGH} "
                "and above the surface under it."
            )
        self._position, self._velocity = position, np.zeros(3)
        return self._observation(), {"target": self._target}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply a velocity command for ``dt`` seconds.

        Returns:
            ``(observation, reward, terminated, False, info)``; at touchdown ``terminated`` is
            True and ``info`` holds ``landed_on`` and ``success``.
        """
        if self._position is None:
            raise RuntimeError("call reset() before step().")
        command = np.asarray(action, dtype=np.float64)
        if command.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {command.shape}.")
        before = torch.as_tensor(self._position)
        position, velocity, down = drone_transition(
            before,
            torch.as_tensor(self._velocity),
            torch.as_tensor(command),
            dt=self.dt,
            tau=self.tau,
            max_speed=self.max_speed,
        )
        reward = float(drone_reward(before, position, self._target, down))
        self._position, self._velocity = position.numpy(), velocity.numpy()
        info: dict[str, Any] = {"target": self._target}
        terminated = bool(down)
        if terminated:
            info["landed_on"] = int(platform_index(position[:2]))
            info["success"] = bool(landing_success(position, self._target))
        return self._observation(), reward, terminated, False, info

    def render(self) -> np.ndarray | None:
        """The drone and the platforms as ``uint8 [480, 480, 3]`` (``render_mode="rgb_array"``), else None.

        Example:
            >>> env = DroneLandingEnv(render_mode="rgb_array")
            >>> _ = env.reset(seed=0)
            >>> env.render().shape
            (480, 480, 3)
        """
        return render_state(self.render_mode, self._position, lambda position: drone_frame(position, self._target))

    def _observation(self) -> np.ndarray:
        assert self._position is not None
        state = drone_observation(torch.as_tensor(self._position), torch.as_tensor(self._velocity), self._target)
        return state.numpy().astype(np.float32)
