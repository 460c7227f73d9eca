"""Pendulum family: gymnasium's Pendulum-v1 with the pole's mass and length drawn per episode.

The pole's mass ``m ~ U(0.5, 2.0)`` and length ``l ~ U(0.5, 1.5)`` change from episode to episode,
so a dynamics model must adapt online: the same torque swings a light short pole much faster than
a heavy long one. The physics is Pendulum-v1's, unchanged. Its update, its reward, the parameter
prior and a motor-babbling data generator are pure batched torch functions;
:class:`PendulumFamilyEnv` is Pendulum-v1 itself with ``m`` and ``l`` set, and
:func:`pendulum_step` reproduces its step to float precision, so the env, the data and the
planners agree.

Example:
    >>> import torch
    >>> from smcd_rl.envs.pendulum_family import pendulum_step
    >>> upright_at_rest = torch.tensor([1.0, 0.0, 0.0])
    >>> pendulum_step(upright_at_rest, torch.tensor([2.0]), mass=1.0, length=1.0)
    tensor([0.9999, 0.0150, 0.3000])
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, SupportsFloat

import numpy as np
import torch
from gymnasium.envs.classic_control.pendulum import PendulumEnv
from tensordict import TensorDict
from torch import Tensor

from smcd_rl.envs.rendering import FRAME_SIZE, RENDER_MODES, Canvas, check_render_mode, render_state

__all__ = [
    "DEFAULT_DT",
    "DEFAULT_G",
    "LENGTH_RANGE",
    "MASS_RANGE",
    "MAX_SPEED",
    "MAX_TORQUE",
    "PendulumFamilyEnv",
    "pendulum_frame",
    "pendulum_reward",
    "pendulum_step",
    "pendulum_transitions",
    "sample_pendulum_parameters",
]

#: Prior of the pole's mass: ``m ~ U(*MASS_RANGE)``.
MASS_RANGE: tuple[float, float] = (0.5, 2.0)
#: Prior of the pole's length: ``l ~ U(*LENGTH_RANGE)``.
LENGTH_RANGE: tuple[float, float] = (0.5, 1.5)
#: Pendulum-v1's constants: time step (s), gravity, torque bound and angular-velocity bound.
DEFAULT_DT: float = 0.05
DEFAULT_G: float = 10.0
MAX_TORQUE: float = 2.0
MAX_SPEED: float = 8.0


def _check_finite(name: str, value: float, *, positive: bool = False) -> None:
    if not (math.isfinite(value) and (value > 0 or not positive)):
        bound = "finite and > 0" if positive else "finite"
        raise ValueError(f"{name} must be {bound}, got {value!r}.")


def _check_last_dim(name: str, tensor: Tensor, size: int, what: str) -> None:
    if tensor.ndim == 0 or tensor.shape[-1] != size:
        raise ValueError(f"{name} must have shape [..., {size}] ({what}), got {tuple(tensor.shape)}.")


def pendulum_step(
    observation: Tensor,
    action: Tensor,
    mass: Tensor | float,
    length: Tensor | float,
    *,
    g: float = DEFAULT_G,
    dt: float = DEFAULT_DT,
) -> Tensor:
    """One step of Pendulum-v1's dynamics, batched, from observation to next observation.

    With ``th = atan2(sin th, cos th)`` and the torque ``u`` clipped to ``[-2, 2]``:
    ``thdot' = clip(thdot + (3 g / (2 l) sin th + 3 / (m l^2) u) dt, -8, 8)`` and
    ``th' = th + thdot' dt``, the update of ``gymnasium``'s ``PendulumEnv.step`` with
    ``env.m = mass`` and ``env.l = length``. The angle is recovered from its cosine and sine, so
    it may differ from the env's unwrapped angle by a multiple of ``2 pi``, which changes nothing
    of the observation. Mass and length are not checked (no device sync); pass positive ones.

    Args:
        observation: ``[..., 3]`` = ``(cos th, sin th, thdot)``; th = 0 is upright.
        action: Torque ``[..., 1]``, clipped to ``[-MAX_TORQUE, MAX_TORQUE]``.
        mass: Pole mass, a float or ``[...]`` broadcastable against ``observation[..., 0]``.
        length: Pole length, like ``mass``.
        g: Gravity (Pendulum-v1's default ``10.0``).
        dt: Time step in seconds.

    Returns:
        Next observation ``[..., 3]``, the broadcast batch shape; differentiable in every
        tensor input (except where a clip is active).

    Raises:
        ValueError: If ``observation`` or ``action`` has the wrong last dimension, or ``g`` or
            ``dt`` is not finite (``dt`` must be positive too).

    Example:
        >>> import torch
        >>> obs = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # horizontal, at rest
        >>> pendulum_step(obs, torch.zeros(2, 1), torch.tensor([1.0, 1.0]), torch.tensor([1.0, 0.5]))
        tensor([[-0.0375,  0.9993,  0.7500],
                [-0.0749,  0.9972,  1.5000]])
    """
    _check_last_dim("observation", observation, 3, "cos th, sin th, thdot")
    _check_last_dim("action", action, 1, "torque")
    _check_finite("g", g)
    _check_finite("dt", dt, positive=True)
    dtype, device = observation.dtype, observation.device
    m = mass if isinstance(mass, Tensor) else torch.as_tensor(mass, dtype=dtype, device=device)
    l = length if isinstance(length, Tensor) else torch.as_tensor(length, dtype=dtype, device=device)  # noqa: E741 - Pendulum-v1's name
    th = torch.atan2(observation[..., 1], observation[..., 0])
    thdot = observation[..., 2]
    u = action[..., 0].clamp(-MAX_TORQUE, MAX_TORQUE)
    # The same expression, in the same order, as PendulumEnv.step, so that float64 agrees to ~1e-15.
    new_thdot = thdot + (3 * g / (2 * l) * torch.sin(th) + 3.0 / (m * l**2) * u) * dt
    new_thdot = new_thdot.clamp(-MAX_SPEED, MAX_SPEED)
    new_th = th + new_thdot * dt
    return torch.stack(torch.broadcast_tensors(torch.cos(new_th), torch.sin(new_th), new_thdot), dim=-1)


def pendulum_reward(observation: Tensor, action: Tensor, next_observation: Tensor | None = None) -> Tensor:
    """Pendulum-v1's reward of taking ``action`` at ``observation``: ``-(th^2 + 0.1 thdot^2 + 0.001 u^2)``.

    ``th`` in ``[-pi, pi]`` (0 upright) and ``u`` the clipped torque. The reward depends on the
    state before the step only; ``next_observation`` is accepted and ignored, so the function is
    a planner's ``reward_fn(obs, action, next_obs)`` (:data:`smcd_rl.agents.mpc.RewardFn`).

    Args:
        observation: ``[..., 3]`` = ``(cos th, sin th, thdot)``.
        action: Torque ``[..., 1]``.
        next_observation: Ignored.

    Returns:
        Reward ``[...]``, at most 0 (upright at rest without torque).

    Example:
        >>> import torch
        >>> pendulum_reward(torch.tensor([-1.0, 0.0, 1.0]), torch.tensor([3.0]))  # hanging down
        tensor(-9.9736)
    """
    _check_last_dim("observation", observation, 3, "cos th, sin th, thdot")
    _check_last_dim("action", action, 1, "torque")
    th = torch.atan2(observation[..., 1], observation[..., 0])
    u = action[..., 0].clamp(-MAX_TORQUE, MAX_TORQUE)
    return -(th**2 + 0.1 * observation[..., 2] ** 2 + 0.001 * u**2)


def sample_pendulum_parameters(
    shape: int | Sequence[int],
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Draw pole parameters from the task family's prior: mass ``~ U(0.5, 2)``, length ``~ U(0.5, 1.5)``.

    Args:
        shape: Batch shape; the result has shape ``[*shape, 2]``.
        generator: Source of randomness (must live on ``device``); the same seed gives the same
            parameters.
        device: Device of the result (default: the current default device).

    Returns:
        Tensor ``[*shape, 2]`` of the default float dtype: ``[..., 0]`` the mass in
        :data:`MASS_RANGE`, ``[..., 1]`` the length in :data:`LENGTH_RANGE`.

    Raises:
        ValueError: If ``shape`` has a negative size.

    Example:
        >>> import torch
        >>> parameters = sample_pendulum_parameters(4, generator=torch.Generator().manual_seed(0))
        >>> parameters.shape, bool((parameters[:, 0] >= 0.5).all() and (parameters[:, 1] <= 1.5).all())
        (torch.Size([4, 2]), True)
    """
    size = (shape,) if isinstance(shape, int) else tuple(shape)
    if any(isinstance(n, bool) or not isinstance(n, int) or n < 0 for n in size):
        raise ValueError(f"shape must be an int or a sequence of ints >= 0, got {shape!r}.")
    low = torch.tensor([MASS_RANGE[0], LENGTH_RANGE[0]], device=device)
    high = torch.tensor([MASS_RANGE[1], LENGTH_RANGE[1]], device=device)
    return low + (high - low) * torch.rand(*size, 2, generator=generator, device=device)


def _check_positive_int(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value!r}; pass e.g. {name}=10.")


def pendulum_transitions(
    num_tasks: int,
    episodes_per_task: int,
    steps: int,
    *,
    parameters: Tensor | None = None,
    measurement_noise: float = 0.0,
    g: float = DEFAULT_G,
    dt: float = DEFAULT_DT,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> TensorDict:
    """Motor-babbling transitions of the pendulum family: random torques on poles of random mass and length.

    Each task has one pole (mass and length drawn by :func:`sample_pendulum_parameters`, unless
    ``parameters`` gives them). Each episode starts as Pendulum-v1's reset does, ``th ~ U(-pi,
    pi)`` and ``thdot ~ U(-1, 1)``, and applies torques ``u ~ U(-2, 2)`` for ``steps`` steps of
    :func:`pendulum_step`. The draws are made in the order parameters, start states, torques,
    noise.

    Each visited state is measured once: ``N(0, measurement_noise^2)`` noise is added to all
    three components of the observation, and ``"observation"`` at step ``t + 1`` is the very same
    measurement (same noise) as ``("next", "observation")`` at step ``t``. Without noise,
    ``("next", "observation")`` is exactly ``pendulum_step`` of ``"observation"`` and
    ``"action"``.

    Args:
        num_tasks: Number of tasks (poles).
        episodes_per_task: Episodes per task.
        steps: Transitions per episode.
        parameters: Optional ``[num_tasks, 2]`` of (mass, length) per task, all finite and > 0.
        measurement_noise: Standard deviation of the Gaussian noise on the recorded observations.
        g: Gravity.
        dt: Time step in seconds.
        generator: Source of randomness (must live on ``device``); the same seed gives the same
            data.
        device: Device of the result (default: that of ``parameters``, else the default device).

    Returns:
        TensorDict with batch size ``[num_tasks, episodes_per_task, steps]`` and keys
        ``"observation"`` and ``("next", "observation")`` (``[..., 3]``), ``"action"``
        (``[..., 1]``), ``"mass"`` and ``"length"`` (``[...]``, no trailing dimension, so they
        broadcast in :func:`pendulum_step` as they are) and ``"task"`` (``[...]``, int64 task
        index). The float entries have the dtype of ``parameters`` (if floating), else the
        default dtype.

    Raises:
        ValueError: If a count is not a positive int, ``measurement_noise`` is negative or not
            finite, ``g`` or ``dt`` is invalid, or ``parameters`` has the wrong shape or entries
            that are not finite and positive.

    Example:
        >>> import torch
        >>> data = pendulum_transitions(4, 3, 10, generator=torch.Generator().manual_seed(0))
        >>> data.batch_size, data["next", "observation"].shape, data["mass"].shape
        (torch.Size([4, 3, 10]), torch.Size([4, 3, 10, 3]), torch.Size([4, 3, 10]))
        >>> step = pendulum_step(data["observation"], data["action"], data["mass"], data["length"])
        >>> torch.allclose(step, data["next", "observation"], atol=1e-6)
        True
    """
    _check_positive_int("num_tasks", num_tasks)
    _check_positive_int("episodes_per_task", episodes_per_task)
    _check_positive_int("steps", steps)
    if not (math.isfinite(measurement_noise) and measurement_noise >= 0):
        raise ValueError(f"measurement_noise must be finite and >= 0, got {measurement_noise!r}; pass e.g. 0.01.")
    _check_finite("g", g)
    _check_finite("dt", dt, positive=True)

    if parameters is None:
        params = sample_pendulum_parameters(num_tasks, generator=generator, device=device)
    else:
        if tuple(parameters.shape) != (num_tasks, 2):
            raise ValueError(
                f"parameters must have shape (num_tasks, 2) = ({num_tasks}, 2), got "
                f"{tuple(parameters.shape)}; pass one (mass, length) row per task."
            )
        if not bool((torch.isfinite(parameters) & (parameters > 0)).all()):
            raise ValueError("parameters must all be finite and > 0: a pole has positive mass and length.")
        dtype = parameters.dtype if parameters.is_floating_point() else torch.get_default_dtype()
        params = parameters.to(device=device, dtype=dtype)
    device, dtype = params.device, params.dtype
    mass, length = params[:, 0], params[:, 1]

    shape = (num_tasks, episodes_per_task)
    start = 2 * torch.rand(*shape, 2, generator=generator, device=device, dtype=dtype) - 1
    th0, thdot0 = math.pi * start[..., 0], start[..., 1]
    actions = MAX_TORQUE * (2 * torch.rand(*shape, steps, 1, generator=generator, device=device, dtype=dtype) - 1)
    states = [torch.stack((torch.cos(th0), torch.sin(th0), thdot0), dim=-1)]
    for t in range(steps):
        states.append(pendulum_step(states[-1], actions[..., t, :], mass[:, None], length[:, None], g=g, dt=dt))
    observations = torch.stack(states, dim=-2)  # [tasks, episodes, steps + 1, 3]
    if measurement_noise > 0:
        # One draw per visited state, shared by the two transitions that touch it.
        noise = torch.randn(observations.shape, generator=generator, device=device, dtype=dtype)
        observations = observations + measurement_noise * noise

    batch = (*shape, steps)
    return TensorDict(
        {
            "observation": observations[..., :-1, :],
            "action": actions,
            "next": {"observation": observations[..., 1:, :]},
            "mass": mass[:, None, None].expand(batch),
            "length": length[:, None, None].expand(batch),
            "task": torch.arange(num_tasks, device=device)[:, None, None].expand(batch),
        },
        batch_size=batch,
        device=device,
    )


#: Colours of the pendulum frames (pole, pivot, torque arc).
POLE_COLOR, PIVOT_COLOR, TORQUE_COLOR = (204, 77, 77), (20, 20, 20), (40, 70, 120)


def pendulum_frame(
    theta: float,
    length: float = 1.0,
    mass: float = 1.0,
    *,
    torque: float | None = None,
    extent: float | None = None,
    height: int = FRAME_SIZE[0],
    width: int = FRAME_SIZE[1],
) -> np.ndarray:
    """An RGB frame of the pendulum at angle ``theta``: a pure function of the state.

    The pivot sits at the centre, the pole points up at ``theta = 0`` and turns counter-clockwise
    with ``theta``, as in Pendulum-v1's drawing. The pole is ``length`` long and its width grows
    with ``sqrt(mass)`` (a rod of fixed density); a ``torque`` is drawn as an arc about the pivot
    whose sweep grows with ``|torque|``, counter-clockwise for a positive one.

    Args:
        theta: pole angle (rad), 0 upright.
        length: pole length (m).
        mass: pole mass.
        torque: the last torque applied, if any.
        extent: metres from the centre to the frame's nearer edge; by default 1.2 times the
            longer of ``length`` and the prior's longest pole, so poles of the prior share one
            scale and their lengths can be compared across episodes.
        height: frame height in pixels.
        width: frame width in pixels.

    Returns:
        ``uint8 [height, width, 3]``.

    Example:
        >>> frame = pendulum_frame(0.3, 1.2, 1.5, torque=-1.0)
        >>> frame.shape, frame.dtype
        ((480, 480, 3), dtype('uint8'))
        >>> bool((frame != pendulum_frame(0.3, 0.8, 1.5, torque=-1.0)).any())
        True
    """
    if extent is None:
        extent = 1.2 * max(abs(float(length)), LENGTH_RANGE[1])
    canvas = Canvas(extent=extent, height=height, width=width)
    unit = extent / 40  # line widths and marker sizes scale with the view
    if torque is not None and float(torque) != 0:
        sweep = 0.75 * math.pi * max(min(float(torque) / MAX_TORQUE, 1.0), -1.0)
        angles = math.pi / 2 + np.linspace(0.0, sweep, 24)
        radius = 6 * unit
        arc = radius * np.stack((np.cos(angles), np.sin(angles)), axis=-1)
        canvas.polyline(arc, color=TORQUE_COLOR, width=0.6 * unit)
        canvas.disc(arc[-1], 1.0 * unit, color=TORQUE_COLOR)  # the arrow's head: where it turns to
    tip = float(length) * np.array([-math.sin(theta), math.cos(theta)])
    pole_width = 0.1 * math.sqrt(max(float(mass), 0.0))
    canvas.line((0.0, 0.0), tip, color=POLE_COLOR, width=pole_width)
    canvas.disc((0.0, 0.0), 0.8 * unit, color=PIVOT_COLOR)
    return canvas.image


def _positive_number(name: str, value: object) -> float:
    """Parse a reset option into a finite float > 0."""
    if isinstance(value, bool):
        raise ValueError(f"options[{name!r}] must be a finite number > 0, got {value!r}.")
    try:
        number = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"options[{name!r}] must be a finite number > 0, got {value!r}.") from err
    if number.shape != () or not (np.isfinite(number) and number > 0):
        raise ValueError(f"options[{name!r}] must be a finite number > 0, got {value!r}.")
    return float(number)


# A subclass rather than a wrapper: PendulumEnv.step reads self.m and self.l at every step, so
# setting them at reset makes the physics Pendulum-v1's own code, not a copy of it, and
# ``env.unwrapped`` is the pendulum itself (``.m``, ``.l``, ``.state`` where users look for them).
class PendulumFamilyEnv(PendulumEnv):
    """Gymnasium's Pendulum-v1 whose pole has a new mass and length every episode.

    ## Description

    The inverted-pendulum swing-up of gymnasium's `Pendulum-v1`: a rod on a fixed pivot, driven
    by a torque, starts at a random angle and should be swung up and balanced. Here the pole's
    mass `m` and length `l` are drawn anew at every reset: the same torque accelerates the
    lightest, shortest pole 36 times as much as the heaviest, longest one (`3 u / (m l^2)`), so a
    dynamics model has to adapt within the episode. The
    physics is Pendulum-v1's own (this class subclasses its `PendulumEnv` and sets `m` and `l`):

    *thdot' = clip(thdot + (3 g / (2 l) sin(th) + 3 / (m l^2) u) dt, -8, 8), th' = th + thdot' dt*,

    with `dt = 0.05`, the torque `u` clipped to *[-2, 2]*, and `th = 0` upright.
    `pendulum_step` is the same update as a batched torch function.

    ## Action Space

    The action is an `ndarray` with shape `(1,)`: the torque, clipped to the box.

    | Num | Action | Min  | Max |
    |-----|--------|------|-----|
    | 0   | Torque | -2.0 | 2.0 |

    ## Observation Space

    The observation is an `ndarray` with shape `(3,)` and dtype `float32`, as in Pendulum-v1.
    The mass and length are not observed; `info["mass"]` and `info["length"]` report them.

    | Num | Observation      | Min  | Max |
    |-----|------------------|------|-----|
    | 0   | x = cos(theta)   | -1.0 | 1.0 |
    | 1   | y = sin(theta)   | -1.0 | 1.0 |
    | 2   | Angular velocity | -8.0 | 8.0 |

    ## Rewards

    Pendulum-v1's, as a Python float: *r = -(th^2 + 0.1 thdot^2 + 0.001 u^2)* with `th` in
    *[-pi, pi]*, at most 0 (upright at rest); `pendulum_reward` computes it batched.

    ## Starting State

    The angle is drawn from *U(-pi, pi)* and the angular velocity from *U(-1, 1)*, exactly as in
    Pendulum-v1 (the same seed starts from the same state); then the mass from *U(0.5, 2.0)* and
    the length from *U(0.5, 1.5)*, both from the env's `np_random`, so `reset(seed=...)` repeats
    them. `options={"mass": m, "length": l}` fixes either or both (finite and positive);
    fixing one leaves the other's draw as it would be. Pendulum-v1's options `x_init` and
    `y_init` (the bounds of the start angle and velocity) pass through.

    ## Episode End

    The env never terminates. `gymnasium.make("smcd_rl/PendulumFamily-v0")` truncates after
    200 steps, as Pendulum-v1 does.

    ## Arguments

    - `g`: gravity (default `10.0`, as in Pendulum-v1).
    - `render_mode`: `None` or `"rgb_array"` (a 480 x 480 frame of the pole, `pendulum_frame`;
      drawn with numpy, so no pygame and no display are needed).

    ```python
    >>> import gymnasium
    >>> from smcd_rl.envs import register_all
    >>> register_all()
    >>> env = gymnasium.make("smcd_rl/PendulumFamily-v0")
    >>> obs, info = env.reset(seed=0, options={"mass": 2.0})
    >>> info["mass"], 0.5 <= info["length"] <= 1.5, env.unwrapped.m
    (2.0, True, 2.0)
    >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    >>> obs.shape, type(reward), sorted(info)
    ((3,), <class 'float'>, ['length', 'mass'])

    ```

    ## Version History

    * v0: Initial version, on Pendulum-v1.
    """

    metadata: dict[str, Any] = {"render_modes": list(RENDER_MODES), "render_fps": round(1 / DEFAULT_DT)}

    def __init__(self, render_mode: str | None = None, g: float = DEFAULT_G) -> None:
        # Pendulum-v1's own renderer needs pygame, which smcd-rl does not depend on; the frame is
        # drawn by pendulum_frame instead, so "human" (a pygame window) is not offered.
        check_render_mode(render_mode)
        _check_finite("g", g)
        super().__init__(render_mode=render_mode, g=float(g))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode with a new (or given) pole and Pendulum-v1's random start state.

        Args:
            seed: Seed for ``self.np_random``.
            options: Optional ``{"mass": m, "length": l}``, either key may be left out (then that
                one is drawn); Pendulum-v1's ``"x_init"`` and ``"y_init"`` pass through.

        Returns:
            ``(observation, info)`` with ``info["mass"]`` and ``info["length"]``.

        Raises:
            ValueError: On unknown option keys, or a mass or length that is not a finite number
                > 0.

        Example:
            >>> env = PendulumFamilyEnv()
            >>> obs, info = env.reset(seed=0, options={"length": 1.5})
            >>> info["length"], env.l
            (1.5, 1.5)
        """
        options = dict(options or {})
        unknown = set(options) - {"mass", "length", "x_init", "y_init"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; use 'mass', 'length', 'x_init', 'y_init'.")
        # Checked before anything changes, so a rejected reset leaves the env as it was.
        fixed = {key: _positive_number(key, options[key]) for key in ("mass", "length") if key in options}
        initial = {key: options[key] for key in ("x_init", "y_init") if key in options}

        # Pendulum-v1 seeds np_random and draws its start state first, so that a seed starts from
        # the state Pendulum-v1 starts from; the pole is drawn after it, always both values, so
        # that fixing one leaves the other's draw unchanged.
        obs, _ = super().reset(seed=seed, options=initial or None)
        drawn = self.np_random.uniform((MASS_RANGE[0], LENGTH_RANGE[0]), (MASS_RANGE[1], LENGTH_RANGE[1]))
        self.m = fixed.get("mass", float(drawn[0]))
        self.l = fixed.get("length", float(drawn[1]))
        return obs, self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        """Apply a torque for ``dt`` seconds: Pendulum-v1's step with this episode's pole.

        Args:
            action: Torque ``(1,)``; clipped to ``[-2, 2]``.

        Returns:
            ``(observation, reward, False, False, info)``, the reward a Python float and ``info``
            with ``"mass"`` and ``"length"``.

        Raises:
            RuntimeError: Before the first ``reset()``.
            ValueError: If ``action`` does not have shape ``(1,)``.

        Example:
            >>> import numpy as np
            >>> env = PendulumFamilyEnv()
            >>> _ = env.reset(seed=0, options={"mass": 1.0, "length": 1.0, "x_init": 0.0, "y_init": 0.0})
            >>> obs, reward, terminated, truncated, info = env.step(np.array([2.0], dtype=np.float32))
            >>> obs.round(4), round(reward, 6)  # upright at rest, pushed counter-clockwise
            (array([0.9999, 0.015 , 0.3   ], dtype=float32), -0.004)
        """
        if getattr(self, "state", None) is None:
            raise RuntimeError("call reset() before step().")
        if np.shape(action) != (1,):
            raise ValueError(f"action must have shape (1,) (the torque), got {np.shape(action)}.")
        obs, reward, terminated, truncated, _ = super().step(action)
        return obs, float(reward), terminated, truncated, self._info()

    def render(self) -> np.ndarray | None:
        """The current pole as ``uint8 [480, 480, 3]`` (``render_mode="rgb_array"``), else None with a warning.

        Example:
            >>> env = PendulumFamilyEnv(render_mode="rgb_array")
            >>> _ = env.reset(seed=0)
            >>> env.render().shape
            (480, 480, 3)
        """
        return render_state(
            self.render_mode,
            getattr(self, "state", None),
            lambda state: pendulum_frame(float(state[0]), self.l, self.m, torque=self.last_u),
        )

    def _info(self) -> dict[str, Any]:
        return {"mass": float(self.m), "length": float(self.l)}
