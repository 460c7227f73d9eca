"""Two-link planar arm: forward kinematics under unknown link lengths (paper section 4.1).

The kinematics (eq. 8), the joint integrator (eq. 7), the link-length prior and the
motor-babbling data generator are pure batched torch functions; :class:`TwoLinkArmEnv` calls the
same functions, so the env, the oracle baseline and the planners share one implementation.

Example:
    >>> import torch
    >>> from smcd_rl.envs.two_link_arm import two_link_fk
    >>> two_link_fk(torch.tensor([0.0, 0.0]), torch.tensor([1.0, 1.0]))
    tensor([2., 0.])
"""

from __future__ import annotations

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
    "DEFAULT_DT",
    "TwoLinkArmEnv",
    "integrate_joints",
    "motor_babbling",
    "sample_link_lengths",
    "two_link_fk",
    "two_link_frame",
    "wrap_angle",
]

#: Euler step size in seconds: ``q' = q + DEFAULT_DT * u`` (eq. 7, ``q_dot = u``).
DEFAULT_DT: float = 0.2

# Below this acceptance probability the rejection sampler would loop (nearly) forever.
_MIN_ACCEPTANCE = 1e-4


def wrap_angle(q: Tensor) -> Tensor:
    """Wrap angles to ``[-pi, pi)``.

    Args:
        q: Angles in radians, any shape.

    Returns:
        Tensor of the same shape and dtype with every entry in ``[-pi, pi)``.

    Example:
        >>> import math, torch
        >>> wrap_angle(torch.tensor([math.pi, 3 * math.pi / 2, -0.5]))
        tensor([-3.1416, -1.5708, -0.5000])
    """
    wrapped = torch.remainder(q + math.pi, 2 * math.pi) - math.pi
    # remainder can round up to exactly 2*pi for tiny negative inputs; keep the interval half-open.
    return torch.where(wrapped >= math.pi, wrapped - 2 * math.pi, wrapped)


def two_link_fk(q: Tensor, link_lengths: Tensor) -> Tensor:
    """End-effector position of a planar two-link arm (eq. 8).

    ``x = l1 cos(q1) + l2 cos(q1 + q2)``, ``y = l1 sin(q1) + l2 sin(q1 + q2)``.

    Args:
        q: Joint angles ``[..., 2]`` in radians.
        link_lengths: Link lengths ``[..., 2]``, broadcastable against ``q``.

    Returns:
        End-effector position ``[..., 2]`` (``x, y``); differentiable in both arguments.

    Example:
        >>> import math, torch
        >>> two_link_fk(torch.tensor([math.pi / 2, -math.pi / 2]), torch.tensor([2.0, 1.0])).round()
        tensor([1., 2.])
    """
    q1 = q[..., 0]
    q12 = q1 + q[..., 1]
    l1 = link_lengths[..., 0]
    l2 = link_lengths[..., 1]
    x = l1 * torch.cos(q1) + l2 * torch.cos(q12)
    y = l1 * torch.sin(q1) + l2 * torch.sin(q12)
    return torch.stack((x, y), dim=-1)


def integrate_joints(q: Tensor, action: Tensor, dt: float | Tensor) -> Tensor:
    """One Euler step of ``q_dot = u`` (eq. 7), wrapped to ``[-pi, pi)``.

    Args:
        q: Joint angles ``[..., 2]`` in radians.
        action: Joint velocities ``[..., 2]`` in rad/s, broadcastable against ``q``.
        dt: Step size in seconds.

    Returns:
        Next joint angles ``wrap_angle(q + dt * action)``, shape of the broadcast inputs.

    Example:
        >>> import torch
        >>> integrate_joints(torch.tensor([0.0, 3.0]), torch.tensor([1.0, 1.0]), 0.5)
        tensor([ 0.5000, -2.7832])
    """
    return wrap_angle(q + dt * action)


def _check_link_length_prior(mean: float, std: float, min_length: float) -> None:
    """Raise ValueError if the truncated normal is ill-posed or (nearly) impossible to sample."""
    if not math.isfinite(mean):
        raise ValueError(f"mean must be finite, got {mean}.")
    if not (math.isfinite(std) and std >= 0):
        raise ValueError(f"std must be finite and >= 0, got {std}; pass e.g. std=0.3.")
    if not (math.isfinite(min_length) and min_length >= 0):
        raise ValueError(f"min_length must be finite and >= 0, got {min_length}; pass e.g. 0.1.")
    if std == 0:
        acceptance = 1.0 if mean >= min_length else 0.0
    else:
        acceptance = 0.5 * math.erfc((min_length - mean) / (std * math.sqrt(2)))
    if acceptance < _MIN_ACCEPTANCE:
        raise ValueError(
            f"N(mean={mean}, std={std}) almost never exceeds min_length={min_length} "
            f"(acceptance {acceptance:.2g}); raise mean or std, or lower min_length."
        )


def sample_link_lengths(
    shape: int | Sequence[int],
    *,
    mean: float = 1.0,
    std: float = 0.3,
    min_length: float = 0.1,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Draw link lengths ``l_i ~ N(mean, std^2)``, truncated below at ``min_length``.

    The paper's prior ``N(1, 0.3)`` puts about 0.1 % of its mass below 0.1 (and some below 0),
    which is not a physical arm. Such draws are redrawn until they are ``>= min_length``
    (rejection sampling), so the result is exactly a normal truncated to ``[min_length, inf)``;
    nothing is clamped, so no probability mass piles up at ``min_length``.

    Args:
        shape: Batch shape; the result has shape ``[*shape, 2]``.
        mean: Mean of the untruncated normal.
        std: Standard deviation of the untruncated normal (``>= 0``).
        min_length: Smallest physical link length (``>= 0``).
        generator: Source of randomness; the same seeded generator gives the same lengths.
            It must live on ``device``.
        device: Device of the result (default: the current default device).

    Returns:
        Tensor ``[*shape, 2]`` of the default float dtype, every entry ``>= min_length``.

    Raises:
        ValueError: If ``std`` or ``min_length`` is negative, or the truncated normal is (nearly)
            impossible to sample because ``mean`` lies far below ``min_length``.

    Example:
        >>> import torch
        >>> g = torch.Generator().manual_seed(0)
        >>> lengths = sample_link_lengths((3,), generator=g)
        >>> lengths.shape, bool((lengths >= 0.1).all())
        (torch.Size([3, 2]), True)
    """
    _check_link_length_prior(mean, std, min_length)
    size = (shape,) if isinstance(shape, int) else tuple(shape)
    out = mean + std * torch.randn(*size, 2, generator=generator, device=device)
    rejected = out < min_length
    while bool(rejected.any()):
        redraw = torch.randn(int(rejected.sum()), generator=generator, device=out.device)
        out[rejected] = mean + std * redraw
        rejected = out < min_length
    return out


#: Colours of the two-link frames (links, joints, end effector, goal, the goal's path).
LINK_COLOR, JOINT_COLOR, EE_COLOR = (40, 70, 120), (20, 20, 20), (210, 50, 40)
GOAL_COLOR, PATH_COLOR = (30, 150, 60), (200, 200, 195)


def two_link_frame(
    q: ArrayLike,
    link_lengths: ArrayLike,
    goal: ArrayLike | None = None,
    *,
    path_radius: float | None = None,
    extent: float | None = None,
    height: int = FRAME_SIZE[0],
    width: int = FRAME_SIZE[1],
) -> np.ndarray:
    """An RGB frame of the planar arm at joint angles ``q``: a pure function of the state.

    The base sits at the centre; the links are drawn in blue, the end effector red, a ``goal``
    (if any) as a green ring and a ``path_radius`` (the telescoping task's target circle) as a
    grey circle about the base.

    Args:
        q: joint angles ``(q1, q2)`` (rad).
        link_lengths: ``(l1, l2)`` (m).
        goal: an optional target point ``(x, y)``.
        path_radius: an optional circle about the base to draw (m).
        extent: metres from the centre to the frame's nearer edge; by default 1.15 times the
            farthest of the arm's reach, the goal and the circle, so pass it to keep the scale
            fixed across a video whose lengths change.
        height: frame height in pixels.
        width: frame width in pixels.

    Returns:
        ``uint8 [height, width, 3]``.

    Example:
        >>> frame = two_link_frame((0.0, 0.5), (1.0, 0.8), goal=(1.0, 1.0))
        >>> frame.shape, frame.dtype
        ((480, 480, 3), dtype('uint8'))
        >>> bool((frame != two_link_frame((0.3, 0.5), (1.0, 0.8), goal=(1.0, 1.0))).any())
        True
    """
    q1, q2 = (float(v) for v in np.asarray(q, dtype=np.float64).reshape(2))
    l1, l2 = (float(v) for v in np.asarray(link_lengths, dtype=np.float64).reshape(2))
    elbow = np.array([l1 * math.cos(q1), l1 * math.sin(q1)])
    ee = elbow + l2 * np.array([math.cos(q1 + q2), math.sin(q1 + q2)])
    if extent is None:
        far = [abs(l1) + abs(l2), path_radius or 0.0]
        if goal is not None:
            far.append(float(np.linalg.norm(np.asarray(goal, dtype=np.float64))))
        extent = 1.15 * max(max(far), 0.1)
    canvas = Canvas(extent=extent, height=height, width=width)
    unit = extent / 40  # line widths and marker sizes scale with the view
    if path_radius is not None:
        canvas.ring((0.0, 0.0), path_radius, color=PATH_COLOR, width=0.5 * unit)
    if goal is not None:
        canvas.ring(goal, 1.6 * unit, color=GOAL_COLOR, width=0.7 * unit)
        canvas.disc(goal, 0.5 * unit, color=GOAL_COLOR)
    canvas.box((-1.5 * unit, -1.5 * unit), (1.5 * unit, 1.5 * unit), color=JOINT_COLOR)  # the fixed base
    canvas.polyline(np.stack([np.zeros(2), elbow, ee]), color=LINK_COLOR, width=1.0 * unit)
    canvas.disc(elbow, 0.9 * unit, color=JOINT_COLOR)
    canvas.disc(ee, 1.0 * unit, color=EE_COLOR)
    return canvas.image


def _check_positive_int(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value!r}; pass e.g. {name}=10.")


def _check_non_negative(name: str, value: float) -> None:
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value!r}; pass e.g. {name}=0.0.")


def motor_babbling(
    num_tasks: int,
    episodes_per_task: int,
    steps: int = 10,
    *,
    dt: float = DEFAULT_DT,
    action_std: float = 1.0,
    link_lengths: Tensor | None = None,
    measurement_noise: float = 0.0,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> TensorDict:
    """Motor-babbling transitions of the two-link arm (paper section 4.1).

    Each task has fixed link lengths (drawn by :func:`sample_link_lengths` unless given). Each
    episode starts at ``q0 ~ U(-pi, pi)^2`` and applies ``u ~ N(0, action_std^2)`` for ``steps``
    Euler steps of :func:`integrate_joints`. The paper uses ``motor_babbling(1000, 150, 10)``.

    The end effector is measured once per visited state: ``ee`` at step ``t + 1`` is the very
    same measurement (same noise) as ``("next", "ee")`` at step ``t``.

    Args:
        num_tasks: Number of tasks (arms with different link lengths).
        episodes_per_task: Episodes per task.
        steps: Transitions per episode.
        dt: Euler step size in seconds.
        action_std: Scale of the babbling actions (rad/s).
        link_lengths: Optional fixed link lengths ``[num_tasks, 2]``, all positive.
        measurement_noise: Standard deviation of the Gaussian noise added to measured positions.
        generator: Source of randomness (must live on ``device``); the same seed gives the same
            data.
        device: Device of the result (default: that of ``link_lengths``, else the default device).

    Returns:
        TensorDict with batch size ``[num_tasks, episodes_per_task, steps]`` and keys ``"q"``,
        ``"action"``, ``"ee"``, ``("next", "q")``, ``("next", "ee")``, ``"link_lengths"`` (each
        ``[..., 2]``) and ``"task"`` (int64 task index).

    Raises:
        ValueError: If a count is not positive, ``dt`` is not positive, a standard deviation is
            negative, or ``link_lengths`` has the wrong shape or non-positive entries.

    Example:
        >>> import torch
        >>> data = motor_babbling(4, 3, generator=torch.Generator().manual_seed(0))
        >>> data.batch_size, data["next", "ee"].shape
        (torch.Size([4, 3, 10]), torch.Size([4, 3, 10, 2]))
    """
    _check_positive_int("num_tasks", num_tasks)
    _check_positive_int("episodes_per_task", episodes_per_task)
    _check_positive_int("steps", steps)
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt!r}; pass e.g. dt={DEFAULT_DT}.")
    _check_non_negative("action_std", action_std)
    _check_non_negative("measurement_noise", measurement_noise)

    if link_lengths is None:
        lengths = sample_link_lengths((num_tasks,), generator=generator, device=device)
    else:
        if tuple(link_lengths.shape) != (num_tasks, 2):
            raise ValueError(
                f"link_lengths must have shape (num_tasks, 2) = ({num_tasks}, 2), got "
                f"{tuple(link_lengths.shape)}; pass one (l1, l2) row per task."
            )
        if not bool((link_lengths > 0).all()):
            raise ValueError("link_lengths must all be > 0; a link cannot have length <= 0.")
        dtype = link_lengths.dtype if link_lengths.is_floating_point() else None
        lengths = link_lengths.to(device=device, dtype=dtype or torch.get_default_dtype())
    device, dtype = lengths.device, lengths.dtype

    shape = (num_tasks, episodes_per_task)
    q0 = (2 * torch.rand(*shape, 2, generator=generator, device=device, dtype=dtype) - 1) * math.pi
    actions = action_std * torch.randn(*shape, steps, 2, generator=generator, device=device, dtype=dtype)
    qs = [q0]
    for t in range(steps):
        qs.append(integrate_joints(qs[-1], actions[..., t, :], dt))
    q = torch.stack(qs, dim=-2)  # [tasks, episodes, steps + 1, 2]
    ee = two_link_fk(q, lengths[:, None, None, :])
    if measurement_noise > 0:
        noise = torch.randn(ee.shape, generator=generator, device=device, dtype=dtype)
        ee = ee + measurement_noise * noise

    batch = (*shape, steps)
    task = torch.arange(num_tasks, device=device)[:, None, None].expand(batch)
    return TensorDict(
        {
            "q": q[..., :-1, :],
            "action": actions,
            "ee": ee[..., :-1, :],
            "next": {"q": q[..., 1:, :], "ee": ee[..., 1:, :]},
            "link_lengths": lengths[:, None, None, :].expand(*batch, 2),
            "task": task,
        },
        batch_size=batch,
        device=device,
    )


class TwoLinkArmEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """Planar two-link arm with unknown link lengths, for forward-kinematics prediction.

    ## Description

    A planar arm with two revolute joints and link lengths `l1, l2` (paper section 4.1). The
    joints are velocity controlled, `q_dot = u` (eq. 7), integrated with an Euler step of
    `dt = 0.2 s` by default; angles are wrapped to *[-pi, pi)*. The end effector sits at
    (eq. 8)

    *x = l1 cos(q1) + l2 cos(q1 + q2), y = l1 sin(q1) + l2 sin(q1 + q2)*.

    The link lengths are fixed within an episode and redrawn at every reset, so an agent must
    adapt its forward model online from the measured end-effector positions. This is a
    prediction task: there is no goal and no reward signal.

    ## Action Space

    The action is an `ndarray` with shape `(2,)`: joint velocities in rad/s, clipped to the box.

    | Num | Action              | Min        | Max       |
    |-----|---------------------|------------|-----------|
    | 0   | Joint 1 velocity u1 | -max_speed | max_speed |
    | 1   | Joint 2 velocity u2 | -max_speed | max_speed |

    ## Observation Space

    The observation is an `ndarray` with shape `(4,)` and dtype `float32`.

    | Num | Observation                       | Min  | Max |
    |-----|-----------------------------------|------|-----|
    | 0   | Joint angle q1 (rad)              | -pi  | pi  |
    | 1   | Joint angle q2 (rad)              | -pi  | pi  |
    | 2   | Measured end-effector x           | -Inf | Inf |
    | 3   | Measured end-effector y           | -Inf | Inf |

    The measured position is the true position plus `N(0, measurement_noise^2)` noise; the
    noise-free position is in `info["ee_true"]`.

    ## Rewards

    The reward is always `0.0`: the task is to predict the end-effector position, which is
    scored outside the env (e.g. against `info["ee_true"]`).

    ## Starting State

    Link lengths are drawn per episode from `N(link_length_mean, link_length_std^2)` truncated
    below at `min_link_length` (rejection sampling, see `sample_link_lengths`); joint angles
    from *U(-pi, pi)*. `options={"link_lengths": (l1, l2)}` and/or `options={"q": (q1, q2)}`
    fix either one. `info["link_lengths"]` reports the lengths in use.

    ## Episode End

    The env never terminates. `gymnasium.make("smcd_rl/TwoLinkArm-v0")` truncates after 100
    steps (the paper's babbling episodes are 10 steps: pass `max_episode_steps=10`).

    ## Arguments

    - `dt`: Euler step size in seconds (default `0.2`).
    - `link_length_mean`, `link_length_std`: the link-length prior (default `N(1, 0.3)`).
    - `min_link_length`: smallest physical link length (default `0.1`).
    - `measurement_noise`: std of the Gaussian end-effector measurement noise (default `0`).
    - `max_speed`: joint velocity bound in rad/s (default `3.0`).
    - `render_mode`: `None` or `"rgb_array"` (a 480 x 480 frame of the arm, `two_link_frame`).

    ```python
    >>> import gymnasium
    >>> from smcd_rl.envs import register_all
    >>> register_all()
    >>> env = gymnasium.make("smcd_rl/TwoLinkArm-v0", measurement_noise=0.01)
    >>> obs, info = env.reset(seed=0, options={"link_lengths": (1.0, 0.5), "q": (0.0, 0.0)})
    >>> info["ee_true"], info["link_lengths"]
    (array([1.5, 0. ], dtype=float32), array([1. , 0.5], dtype=float32))
    >>> bool(abs(obs[2:] - info["ee_true"]).max() < 0.1)  # measured = true + small noise
    True

    ```

    ## Version History

    * v0: Initial version (paper section 4.1).
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / DEFAULT_DT)}

    def __init__(
        self,
        dt: float = DEFAULT_DT,
        link_length_mean: float = 1.0,
        link_length_std: float = 0.3,
        min_link_length: float = 0.1,
        measurement_noise: float = 0.0,
        max_speed: float = 3.0,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be finite and > 0, got {dt!r}; pass e.g. dt={DEFAULT_DT}.")
        if not (math.isfinite(max_speed) and max_speed > 0):
            raise ValueError(f"max_speed must be finite and > 0, got {max_speed!r}; pass e.g. 3.0.")
        _check_non_negative("measurement_noise", measurement_noise)
        _check_link_length_prior(link_length_mean, link_length_std, min_link_length)
        self.dt = float(dt)
        self.link_length_mean = float(link_length_mean)
        self.link_length_std = float(link_length_std)
        self.min_link_length = float(min_link_length)
        self.measurement_noise = float(measurement_noise)
        self.max_speed = float(max_speed)
        self.render_mode = render_mode

        self.action_space = spaces.Box(-self.max_speed, self.max_speed, (2,), np.float32)
        high = np.array([np.pi, np.pi, np.inf, np.inf], dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)

        self._q: np.ndarray | None = None  # float64 state, set by reset()
        self._link_lengths = np.zeros(2)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode with new (or given) link lengths and start angles.

        Args:
            seed: Seed for ``self.np_random``.
            options: Optional ``{"link_lengths": (l1, l2), "q": (q1, q2)}``; either key may be
                left out, in which case that part is drawn at random.

        Returns:
            ``(observation, info)`` with ``info["link_lengths"]`` and ``info["ee_true"]``.

        Raises:
            ValueError: On unknown option keys, values that are not two finite numbers, or
                non-positive link lengths.

        Example:
            >>> env = TwoLinkArmEnv()
            >>> obs, info = env.reset(seed=0, options={"link_lengths": (2.0, 1.0)})
            >>> info["link_lengths"]
            array([2., 1.], dtype=float32)
        """
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"link_lengths", "q"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; use 'link_lengths', 'q'.")

        if "link_lengths" in options:
            lengths = _pair("link_lengths", options["link_lengths"])
            if not (lengths > 0).all():
                raise ValueError(f"options['link_lengths'] must be > 0, got {lengths.tolist()}.")
        else:
            # Share sample_link_lengths with the data generator; its torch generator is seeded
            # from self.np_random so gymnasium seeding still controls every draw.
            torch_gen = torch.Generator().manual_seed(int(self.np_random.integers(2**63 - 1)))
            lengths = (
                sample_link_lengths(
                    (),
                    mean=self.link_length_mean,
                    std=self.link_length_std,
                    min_length=self.min_link_length,
                    generator=torch_gen,
                )
                .double()
                .numpy()
            )
        self._link_lengths = lengths

        if "q" in options:
            q = wrap_angle(torch.as_tensor(_pair("q", options["q"]))).numpy()
        else:
            q = self.np_random.uniform(-np.pi, np.pi, size=2)
        self._q = q
        return self._observe()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply joint velocities for ``dt`` seconds.

        Args:
            action: Joint velocities ``(2,)`` in rad/s; clipped to ``[-max_speed, max_speed]``.

        Returns:
            ``(observation, 0.0, False, False, info)``.

        Example:
            >>> import numpy as np
            >>> env = TwoLinkArmEnv(dt=0.5)
            >>> _ = env.reset(seed=0, options={"q": (0.0, 0.0)})
            >>> obs, reward, terminated, truncated, info = env.step(np.array([1.0, -1.0]))
            >>> obs[:2], reward
            (array([ 0.5, -0.5], dtype=float32), 0.0)
        """
        if self._q is None:
            raise RuntimeError("call reset() before step().")
        u = np.asarray(action, dtype=np.float64)
        if u.shape != (2,):
            raise ValueError(f"action must have shape (2,), got {u.shape}.")
        u = np.clip(u, -self.max_speed, self.max_speed)
        self._q = integrate_joints(torch.as_tensor(self._q), torch.as_tensor(u), self.dt).numpy()
        obs, info = self._observe()
        return obs, 0.0, False, False, info

    def render(self) -> np.ndarray | None:
        """The current arm as ``uint8 [480, 480, 3]`` (``render_mode="rgb_array"``), else None with a warning.

        Example:
            >>> env = TwoLinkArmEnv(render_mode="rgb_array")
            >>> _ = env.reset(seed=0)
            >>> env.render().shape
            (480, 480, 3)
        """
        return render_state(self.render_mode, self._q, lambda q: two_link_frame(q, self._link_lengths))

    def _observe(self) -> tuple[np.ndarray, dict[str, Any]]:
        assert self._q is not None
        ee_true = two_link_fk(torch.as_tensor(self._q), torch.as_tensor(self._link_lengths)).numpy()
        ee = ee_true
        if self.measurement_noise > 0:
            ee = ee_true + self.measurement_noise * self.np_random.standard_normal(2)
        obs = np.concatenate([self._q, ee]).astype(np.float32)
        info = {
            "link_lengths": self._link_lengths.astype(np.float32),
            "ee_true": ee_true.astype(np.float32),
        }
        return obs, info


def _pair(name: str, value: object) -> np.ndarray:
    """Parse a reset option into a finite float64 array of shape (2,)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"options[{name!r}] must be two numbers, got {value!r}.") from err
    if arr.shape != (2,) or not np.isfinite(arr).all():
        raise ValueError(f"options[{name!r}] must be two finite numbers, got {value!r}.")
    return arr
