"""Two-link arm with a telescoping second link tracking a target on a circle (paper appendix A.4).

The second link's length follows ``l2 = 1 + 0.25 sin(pi k / 20)`` at step ``k`` while the arm
follows a target moving around a circle about its base. The telescoping law, the target path,
the joint integrator, the initial-state sampler and the reward are pure batched torch functions;
:class:`TwoLinkTelescopingEnv` and ``smcd-rl telescoping`` call the same ones. The forward
kinematics, angle wrapping and link-length prior are those of :mod:`smcd_rl.envs.two_link_arm`.

Example:
    >>> import torch
    >>> from smcd_rl.envs.two_link_telescoping import telescoping_length
    >>> telescoping_length(torch.tensor([0, 10, 30]))
    tensor([1.0000, 1.2500, 0.7500])
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

from smcd_rl.envs.rendering import FRAME_SIZE, RENDER_MODES, check_render_mode, render_state
from smcd_rl.envs.two_link_arm import (
    _check_link_length_prior,
    _check_non_negative,
    sample_link_lengths,
    two_link_fk,
    two_link_frame,
    wrap_angle,
)

__all__ = [
    "TELESCOPING_DT",
    "TARGET_ANGULAR_SPEED",
    "RADIUS_RANGE",
    "TwoLinkTelescopingEnv",
    "circle_target",
    "integrate_acceleration",
    "sample_initial_state",
    "telescoping_frame",
    "telescoping_length",
    "telescoping_link_lengths",
    "tracking_reward",
]

#: Step size in seconds of the joint double integrator (100 steps = 10 s).
TELESCOPING_DT: float = 0.1

#: Target speed around the circle in rad/s: half a revolution in a 100-step episode at
#: ``TELESCOPING_DT``. Faster targets make the paper's PD law (no velocity feed-forward) lag
#: behind even with the true kinematics: its steady-state lag on a circle is about
#: ``|w^2 - i K2 w| / |K1 - w^2 + i K2 w|`` of the radius, 8 % here, 16 % at a full revolution.
TARGET_ANGULAR_SPEED: float = math.pi / (100 * TELESCOPING_DT)

#: The target circle's radius is drawn from ``U(*RADIUS_RANGE)`` (paper appendix A.4).
RADIUS_RANGE: tuple[float, float] = (0.3, 1.5)


def _as_tensor(value: Tensor | float | int, like: Tensor | None = None) -> Tensor:
    if isinstance(value, Tensor):
        return value.to(torch.get_default_dtype()) if not value.is_floating_point() else value
    device = like.device if like is not None else None
    dtype = like.dtype if like is not None and like.is_floating_point() else torch.get_default_dtype()
    return torch.as_tensor(value, dtype=dtype, device=device)


def telescoping_length(k: Tensor | float | int) -> Tensor:
    """Length of the telescoping second link at step ``k``: ``1 + 0.25 sin(pi k / 20)`` (period 40 steps).

    Args:
        k: Step index (any shape; integer or float).

    Returns:
        Floating tensor of ``k``'s shape, in ``[0.75, 1.25]``.

    Example:
        >>> telescoping_length(torch.tensor([5, 25]))  # 1 +- 0.25 sin(pi / 4)
        tensor([1.1768, 0.8232])
    """
    steps = _as_tensor(k)
    return 1.0 + 0.25 * torch.sin(math.pi * steps / 20.0)


def telescoping_link_lengths(k: Tensor | float | int, l1: Tensor | float) -> Tensor:
    """Both link lengths at step ``k``: ``(l1, telescoping_length(k))``, broadcast.

    Args:
        k: Step index, broadcastable against ``l1``.
        l1: Length of the fixed first link.

    Returns:
        ``[*broadcast(k, l1), 2]``, ready for :func:`smcd_rl.envs.two_link_arm.two_link_fk`.

    Example:
        >>> import torch
        >>> telescoping_link_lengths(10, torch.tensor([0.8, 1.2]))
        tensor([[0.8000, 1.2500],
                [1.2000, 1.2500]])
    """
    first = _as_tensor(l1)
    second = telescoping_length(k).to(first.device, first.dtype)
    first, second = torch.broadcast_tensors(first, second)
    return torch.stack((first, second), dim=-1)


def circle_target(
    k: Tensor | float | int,
    radius: Tensor | float,
    start_angle: Tensor | float,
    *,
    step_angle: float = TARGET_ANGULAR_SPEED * TELESCOPING_DT,
) -> Tensor:
    """Target position at step ``k`` on a circle about the arm's base, moving counter-clockwise.

    ``x_g(k) = radius (cos a, sin a)`` with ``a = start_angle + step_angle * k``.

    Args:
        k: Step index; ``k``, ``radius`` and ``start_angle`` broadcast together.
        radius: Circle radius (m).
        start_angle: Angle ``phi`` of the target at ``k = 0`` (rad).
        step_angle: Angle travelled per step (rad); the default is half a circle in 100 steps.

    Returns:
        ``[*broadcast, 2]`` positions.

    Example:
        >>> import math, torch
        >>> circle_target(torch.tensor([0, 25]), 2.0, 0.0, step_angle=math.pi / 100)
        tensor([[2.0000, 0.0000],
                [1.4142, 1.4142]])
    """
    r = _as_tensor(radius)
    angle = _as_tensor(start_angle, like=r) + step_angle * _as_tensor(k, like=r)
    return torch.stack((r * torch.cos(angle), r * torch.sin(angle)), dim=-1)


def integrate_acceleration(q: Tensor, q_dot: Tensor, u: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """One semi-implicit Euler step of the double integrator ``q_ddot = u``.

    ``q_dot' = q_dot + dt u``, then ``q' = wrap_angle(q + dt q_dot')``. Updating the velocity first
    keeps the paper's PD law (``K1 = 20, K2 = 5``) stable for ``dt`` up to about 0.26 s.

    Args:
        q: Joint angles ``[..., 2]`` (rad).
        q_dot: Joint velocities ``[..., 2]`` (rad/s).
        u: Joint accelerations ``[..., 2]`` (rad/s^2).
        dt: Step size (s).

    Returns:
        ``(q', q_dot')``.

    Example:
        >>> import torch
        >>> integrate_acceleration(torch.zeros(2), torch.zeros(2), torch.tensor([1.0, -2.0]), 0.5)
        (tensor([ 0.2500, -0.5000]), tensor([ 0.5000, -1.0000]))
    """
    velocity = q_dot + dt * u
    return wrap_angle(q + dt * velocity), velocity


def tracking_reward(ee: Tensor, target: Tensor) -> Tensor:
    """Reward of the tracking task: minus the end-effector's distance to the target, ``[...]``.

    Example:
        >>> import torch
        >>> tracking_reward(torch.tensor([3.0, 0.0]), torch.tensor([0.0, 4.0]))
        tensor(-5.)
    """
    return -(ee - target).norm(dim=-1)


def sample_initial_state(
    shape: tuple[int, ...],
    *,
    link_length_mean: float = 1.0,
    link_length_std: float = 0.3,
    min_link_length: float = 0.1,
    radius_range: tuple[float, float] = RADIUS_RANGE,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> dict[str, Tensor]:
    """Draw episodes: first-link length, start angles, target circle.

    ``l1`` comes from :func:`smcd_rl.envs.two_link_arm.sample_link_lengths` (the prior of the
    training data, ``N(1, 0.3)`` truncated at 0.1); ``q ~ U(-pi, pi)^2``; the target's radius
    ``r ~ U(*radius_range)`` and start angle ``phi ~ U(-pi, pi)``. The arm starts at rest.

    Args:
        shape: Batch shape.
        link_length_mean: Mean of the prior of ``l1``.
        link_length_std: Standard deviation of the prior of ``l1``.
        min_link_length: Truncation of the prior of ``l1`` from below.
        radius_range: ``(low, high)`` of the target circle's radius, ``0 < low <= high``.
        generator: Source of randomness (on ``device``).
        device: Device of the tensors.

    Returns:
        ``{"l1": [*shape], "q": [*shape, 2], "radius": [*shape], "start_angle": [*shape]}``.

    Example:
        >>> import torch
        >>> state = sample_initial_state((3,), generator=torch.Generator().manual_seed(0))
        >>> sorted(state), state["q"].shape
        (['l1', 'q', 'radius', 'start_angle'], torch.Size([3, 2]))
    """
    low, high = radius_range
    if not (0 < low <= high and math.isfinite(high)):
        raise ValueError(f"radius_range must be (low, high) with 0 < low <= high, got {radius_range}; e.g. (0.3, 1.5).")
    shape = tuple(shape)
    l1 = sample_link_lengths(
        shape,
        mean=link_length_mean,
        std=link_length_std,
        min_length=min_link_length,
        generator=generator,
        device=device,
    )[..., 0]
    q = (2 * torch.rand(*shape, 2, generator=generator, device=device) - 1) * math.pi
    radius = low + (high - low) * torch.rand(shape, generator=generator, device=device)
    start_angle = (2 * torch.rand(shape, generator=generator, device=device) - 1) * math.pi
    return {"l1": l1, "q": q, "radius": radius, "start_angle": start_angle}


def telescoping_frame(
    q: ArrayLike,
    l1: float,
    k: int,
    target: ArrayLike,
    radius: float,
    *,
    height: int = FRAME_SIZE[0],
    width: int = FRAME_SIZE[1],
) -> np.ndarray:
    """An RGB frame of the arm at step ``k`` (second link ``telescoping_length(k)``), its target and the circle.

    A pure function of the state, on a scale fixed over the episode (the longest the arm gets,
    ``l1 + 1.25``, or the circle), so the frames of one episode make a steady video.

    Args:
        q: joint angles ``(q1, q2)`` (rad).
        l1: length of the first link (m).
        k: the step, which sets the second link's length.
        target: the target's position ``(x, y)``.
        radius: the target circle's radius (m).
        height: frame height in pixels.
        width: frame width in pixels.

    Returns:
        ``uint8 [height, width, 3]``.

    Example:
        >>> frame = telescoping_frame((0.0, 0.0), 1.0, 0, (1.0, 0.0), 1.0)
        >>> frame.shape, bool((frame != telescoping_frame((0.0, 0.0), 1.0, 10, (1.0, 0.0), 1.0)).any())
        ((480, 480, 3), True)
    """
    lengths = (float(l1), float(telescoping_length(k)))
    extent = 1.15 * max(abs(float(l1)) + 1.25, float(radius))
    return two_link_frame(q, lengths, target, path_radius=radius, extent=extent, height=height, width=width)


class TwoLinkTelescopingEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """Two-link arm with a telescoping second link, following a target around a circle.

    ## Description

    The planar two-link arm of `smcd_rl/TwoLinkArm-v0` (paper appendix A.4, Fig. 7), with end
    effector *x = l1 cos(q1) + l2 cos(q1 + q2), y = l1 sin(q1) + l2 sin(q1 + q2)*, whose second
    link telescopes during the episode: at step `k`

    *l2 = 1 + 0.25 sin(pi k / 20)*

    (period 40 steps, between 0.75 and 1.25 m). A target moves counter-clockwise around a circle
    of radius `r` about the arm's base, starting at angle `phi`: *x_g(k) = r (cos(phi + w dt k),
    sin(phi + w dt k))*, with `w = angular_speed` (half a circle per 100-step episode by
    default). The end effector should stay on the target while the kinematics keep changing.

    The joints are acceleration controlled (a double integrator, integrated by semi-implicit
    Euler with step `dt`): the paper's PD law `u = -K1 J^+ (x - x_g) - K2 q_dot` needs `q_dot` as
    a state that the command changes gradually (see `smcd_rl.agents.pd`).

    ## Action Space

    An `ndarray` of shape `(2,)`: joint accelerations in rad/s^2, clipped to the box.

    | Num | Action                 | Min               | Max              |
    |-----|------------------------|-------------------|------------------|
    | 0   | Joint 1 acceleration   | -max_acceleration | max_acceleration |
    | 1   | Joint 2 acceleration   | -max_acceleration | max_acceleration |

    ## Observation Space

    An `ndarray` of shape `(8,)` and dtype `float32`.

    | Num | Observation                    | Min  | Max |
    |-----|--------------------------------|------|-----|
    | 0   | Joint angle q1 (rad)           | -pi  | pi  |
    | 1   | Joint angle q2 (rad)           | -pi  | pi  |
    | 2   | Joint velocity q1_dot (rad/s)  | -Inf | Inf |
    | 3   | Joint velocity q2_dot (rad/s)  | -Inf | Inf |
    | 4   | Measured end-effector x        | -Inf | Inf |
    | 5   | Measured end-effector y        | -Inf | Inf |
    | 6   | Target x                       | -Inf | Inf |
    | 7   | Target y                       | -Inf | Inf |

    The measured position is the true one plus `N(0, measurement_noise^2)` noise; the noise-free
    position is `info["ee_true"]`, the current link lengths `info["link_lengths"]`, the step
    index `info["k"]`.

    ## Rewards

    Minus the distance from the true end effector to the target after the step,
    `tracking_reward(ee_true, target)`.

    ## Starting State

    `sample_initial_state`: `l1 ~ N(link_length_mean, link_length_std^2)` truncated below at
    `min_link_length`, `q ~ U(-pi, pi)^2`, `q_dot = 0`, `r ~ U(0.3, 1.5)`, `phi ~ U(-pi, pi)`;
    `l2` starts at 1 (k = 0). `options` may fix any of `"l1"`, `"q"` (a pair), `"radius"`,
    `"start_angle"`. Small radii can lie inside the unreachable disc of radius `|l1 - l2|`.

    ## Episode End

    The env never terminates; `gymnasium.make("smcd_rl/TwoLinkTelescoping-v0")` truncates after
    100 steps, the paper's episode.

    ## Arguments

    - `dt`: step size in seconds (default `0.1`).
    - `angular_speed`: target speed around the circle in rad/s (default `pi / 10`).
    - `link_length_mean`, `link_length_std`, `min_link_length`: the prior of `l1` (default
      `N(1, 0.3)` truncated at 0.1, the training prior of the two-link task).
    - `measurement_noise`: std of the Gaussian end-effector measurement noise (default `0`).
    - `max_acceleration`: joint acceleration bound in rad/s^2 (default `100`).
    - `render_mode`: `None` or `"rgb_array"` (a 480 x 480 frame of the arm, its target and the
      circle, `telescoping_frame`).

    ```python
    >>> import gymnasium, numpy as np
    >>> from smcd_rl.envs import register_all
    >>> register_all()
    >>> env = gymnasium.make("smcd_rl/TwoLinkTelescoping-v0")
    >>> obs, info = env.reset(seed=0, options={"l1": 1.0, "q": (0.0, 0.0), "radius": 1.0, "start_angle": 0.0})
    >>> obs[4:6], obs[6:]  # fully stretched arm (l2 = 1 at k = 0) and the target
    (array([2., 0.], dtype=float32), array([1., 0.], dtype=float32))
    >>> obs, reward, terminated, truncated, info = env.step(np.zeros(2, dtype=np.float32))
    >>> info["k"], round(float(info["link_lengths"][1]), 4)
    (1, 1.0391)

    ```

    ## Version History

    * v0: Initial version (paper appendix A.4).
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / TELESCOPING_DT)}

    def __init__(
        self,
        dt: float = TELESCOPING_DT,
        angular_speed: float = TARGET_ANGULAR_SPEED,
        link_length_mean: float = 1.0,
        link_length_std: float = 0.3,
        min_link_length: float = 0.1,
        measurement_noise: float = 0.0,
        max_acceleration: float = 100.0,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt!r}; pass e.g. dt={TELESCOPING_DT}.")
        if not math.isfinite(angular_speed):
            raise ValueError(
                f"angular_speed must be finite, got {angular_speed!r}; pass e.g. {TARGET_ANGULAR_SPEED:.4f}."
            )
        if not (math.isfinite(max_acceleration) and max_acceleration > 0):
            raise ValueError(f"max_acceleration must be finite and > 0, got {max_acceleration!r}; pass e.g. 100.0.")
        _check_non_negative("measurement_noise", measurement_noise)
        _check_link_length_prior(link_length_mean, link_length_std, min_link_length)
        self.dt = float(dt)
        self.angular_speed = float(angular_speed)
        self.link_length_mean = float(link_length_mean)
        self.link_length_std = float(link_length_std)
        self.min_link_length = float(min_link_length)
        self.measurement_noise = float(measurement_noise)
        self.max_acceleration = float(max_acceleration)
        self.render_mode = render_mode

        self.action_space = spaces.Box(-self.max_acceleration, self.max_acceleration, (2,), np.float32)
        high = np.array([np.pi, np.pi] + [np.inf] * 6, dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)

        # float64 state, set by reset()
        self._state: dict[str, Tensor] | None = None
        self._q_dot = torch.zeros(2, dtype=torch.float64)
        self._k = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode: new (or given) ``l1``, start angles and target circle; the arm at rest.

        Args:
            seed: Seed for ``self.np_random``.
            options: Optional ``{"l1": float, "q": (q1, q2), "radius": float, "start_angle": float}``.

        Returns:
            ``(observation, info)``.

        Raises:
            ValueError: On unknown option keys or invalid values.

        Example:
            >>> env = TwoLinkTelescopingEnv()
            >>> obs, info = env.reset(seed=0, options={"radius": 0.5})
            >>> round(float(np.linalg.norm(obs[6:])), 4)
            0.5
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"l1", "q", "radius", "start_angle"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; use 'l1', 'q', 'radius', 'start_angle'.")
        # One sampler for env and experiment; its torch generator is seeded from self.np_random,
        # so gymnasium seeding controls every draw.
        generator = torch.Generator().manual_seed(int(self.np_random.integers(2**63 - 1)))
        state = sample_initial_state(
            (),
            link_length_mean=self.link_length_mean,
            link_length_std=self.link_length_std,
            min_link_length=self.min_link_length,
            generator=generator,
        )
        state = {key: value.double() for key, value in state.items()}
        for key in ("l1", "radius", "start_angle"):
            if key in options:
                value = _finite(key, options[key])
                if key != "start_angle" and value <= 0:
                    raise ValueError(f"options[{key!r}] must be > 0, got {value}.")
                state[key] = torch.tensor(value, dtype=torch.float64)
        if "q" in options:
            q = np.asarray(options["q"], dtype=np.float64) if _is_pair(options["q"]) else None
            if q is None or not np.isfinite(q).all():
                raise ValueError(f"options['q'] must be two finite numbers, got {options['q']!r}.")
            state["q"] = wrap_angle(torch.as_tensor(q))
        self._state = state
        self._q_dot = torch.zeros(2, dtype=torch.float64)
        self._k = 0
        obs, info = self._observe()
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply joint accelerations for ``dt`` seconds; the second link and the target move on.

        Args:
            action: Joint accelerations ``(2,)`` in rad/s^2; clipped to ``[-max_acceleration, max_acceleration]``.

        Returns:
            ``(observation, reward, False, False, info)`` with ``reward = -|ee_true - target|``.

        Example:
            >>> env = TwoLinkTelescopingEnv()
            >>> _ = env.reset(seed=0, options={"q": (0.0, 0.0)})
            >>> obs, reward, *_ = env.step(np.array([10.0, 0.0]))
            >>> obs[:4]  # q_dot = dt * u, then q = dt * q_dot
            array([0.1, 0. , 1. , 0. ], dtype=float32)
        """
        if self._state is None:
            raise RuntimeError("call reset() before step().")
        u = np.asarray(action, dtype=np.float64)
        if u.shape != (2,):
            raise ValueError(f"action must have shape (2,), got {u.shape}.")
        u = np.clip(u, -self.max_acceleration, self.max_acceleration)
        self._state["q"], self._q_dot = integrate_acceleration(
            self._state["q"], self._q_dot, torch.as_tensor(u), self.dt
        )
        self._k += 1
        obs, info = self._observe()
        reward = float(tracking_reward(torch.as_tensor(info["ee_true"], dtype=torch.float64), self._target()))
        return obs, reward, False, False, info

    def render(self) -> np.ndarray | None:
        """The arm, its target and the circle as ``uint8 [480, 480, 3]`` (``render_mode="rgb_array"``), else None.

        Example:
            >>> env = TwoLinkTelescopingEnv(render_mode="rgb_array")
            >>> _ = env.reset(seed=0)
            >>> env.render().shape
            (480, 480, 3)
        """
        return render_state(
            self.render_mode,
            self._state,
            lambda state: telescoping_frame(
                state["q"].numpy(), float(state["l1"]), self._k, self._target().numpy(), float(state["radius"])
            ),
        )

    def _target(self) -> Tensor:
        assert self._state is not None
        return circle_target(
            self._k, self._state["radius"], self._state["start_angle"], step_angle=self.angular_speed * self.dt
        )

    def _observe(self) -> tuple[np.ndarray, dict[str, Any]]:
        assert self._state is not None
        lengths = telescoping_link_lengths(self._k, self._state["l1"])
        ee_true = two_link_fk(self._state["q"], lengths).numpy()
        ee = ee_true
        if self.measurement_noise > 0:
            ee = ee_true + self.measurement_noise * self.np_random.standard_normal(2)
        target = self._target().numpy()
        obs = np.concatenate([self._state["q"].numpy(), self._q_dot.numpy(), ee, target]).astype(np.float32)
        info = {
            "k": self._k,
            "ee_true": ee_true.astype(np.float32),
            "link_lengths": lengths.numpy().astype(np.float32),
            "radius": float(self._state["radius"]),
            "start_angle": float(self._state["start_angle"]),
        }
        return obs, info


def _is_pair(value: object) -> bool:
    try:
        return np.asarray(value, dtype=np.float64).shape == (2,)
    except (TypeError, ValueError):
        return False


def _finite(name: str, value: object) -> float:
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise ValueError(f"options[{name!r}] must be a number, got {value!r}.") from err
    if not math.isfinite(number):
        raise ValueError(f"options[{name!r}] must be finite, got {value!r}.")
    return number
