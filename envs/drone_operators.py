"""Simulated drone operators and the trajectory-dataset format of the drone analysis.

The paper's human tele-operation data (33 operators x 16 landings, section 4.3) was never
released. :func:`simulate_operators` flies a population of simulated operators through
:func:`~smcd_rl.envs.drone_landing.drone_transition`, with known labels for the four
characteristics of appendix B.1. Users with their own data store it as a
:class:`TrajectoryDataset` (:func:`save_dataset` / :func:`load_dataset`) and run the same analysis
(``smcd-rl interpret --dataset PATH``).

**Operators.** Each operator has a latent skill ``s ~ N(0, 1)`` that sets how they fly: reaction
delay (0-4 steps of 0.2 s: they act on where the drone *was*), proportional gain (novices
over-correct, which with their delay makes them overshoot and oscillate), command noise, cruise
speed, descent speed, and depth misjudgement (the paper's fixed single-point view: the error in
the target's perceived depth grows with its distance). Every operator flies the same task
sequence :data:`TASK_SEQUENCE` (platform indices), 16 landings.

**Labels** (appendix B.1):

* ``strategy`` (per trajectory): ``orthogonal`` (fly over the platform at cruise height, then
  descend) or ``diagonal`` (descend along a glide path while approaching). Each operator prefers
  one with a probability of their own.
* ``phase`` (per step): ``approach`` until the operator judges the drone to be over the platform,
  ``descent`` from then on (the operator's own mode, the simulated counterpart of the paper's
  manual segmentation).
* ``success`` (per trajectory): :func:`~smcd_rl.envs.drone_landing.landing_success` of the final
  position (a timeout is a failure).
* ``skill`` (per operator, stored per trajectory): as the paper did, from the landing record:
  operators ranked by successful landings (ties: smaller mean final distance to the target ranks
  higher); the bottom 10% are ``novice``, the top 10% ``expert``, the rest ``intermediate``.
* ``target`` (per trajectory): the platform index.

**Dataset format** (one ``.npz`` file, :func:`save_dataset`):

============  ==========  ===================================================================
key           shape       meaning
============  ==========  ===================================================================
state         [T, S]      per step: the state (here S = 7: position 3, velocity 3, distance 1)
action        [T, A]      per step: the action (here A = 3: velocity command)
trajectory    [T]         per step: trajectory id in ``0..N-1``; non-decreasing (a trajectory's
                          steps are contiguous and in time order)
operator      [N]         per trajectory: operator id (any integers)
step/NAME     [T]         a per-step label, integers >= 0 (here ``step/phase``)
traj/NAME     [N]         a per-trajectory label, integers >= 0 (here ``traj/skill``,
                          ``traj/strategy``, ``traj/success``, ``traj/target``)
names/NAME    [C]         optional: class names of label NAME (index = label value)
============  ==========  ===================================================================

``T`` is the total number of steps over all trajectories and ``N`` the number of trajectories.

Example:
    >>> from smcd_rl.envs.drone_operators import simulate_operators
    >>> data = simulate_operators(num_operators=4, trajectories_per_operator=3, seed=0)
    >>> data.num_trajectories, data.state.shape[1], data.action.shape[1]
    (12, 7, 3)
    >>> sorted(data.labels)
    ['phase', 'skill', 'strategy', 'success', 'target']
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
import torch

from smcd_rl.envs.drone_landing import (
    MAX_SPEED,
    NUM_PLATFORMS,
    START,
    drone_observation,
    drone_transition,
    landing_success,
    platform_tensor,
)
from smcd_rl.files import write_atomic

__all__ = [
    "SKILLS",
    "STRATEGIES",
    "PHASES",
    "OUTCOMES",
    "TASK_SEQUENCE",
    "TrajectoryDataset",
    "load_dataset",
    "save_dataset",
    "simulate_operators",
    "split_dataset",
]

#: Class names of the labels (index = label value).
SKILLS: tuple[str, ...] = ("novice", "intermediate", "expert")
STRATEGIES: tuple[str, ...] = ("orthogonal", "diagonal")
PHASES: tuple[str, ...] = ("approach", "descent")
OUTCOMES: tuple[str, ...] = ("failure", "success")
#: Target platforms of the 16 landings, in order; the same for every operator (each platform
#: three times, the middle one four).
TASK_SEQUENCE: tuple[int, ...] = (0, 2, 4, 1, 3, 2, 0, 3, 4, 1, 4, 1, 0, 2, 3, 2)

_REQUIRED = ("state", "action", "trajectory", "operator")
_CAPTURE_RADIUS = 0.3  # m: the operator starts descending when they judge the drone this close
_CLEARANCE = 0.3  # m above the platform where the diagonal glide path ends


@dataclass
class TrajectoryDataset:
    """Ragged state-action trajectories with operator ids and labels (the format of the module docstring).

    Arrays are checked and converted on construction (states and actions to float32, ids and
    labels to int64).

    Attributes:
        state: ``[T, S]`` states of all steps, trajectory after trajectory.
        action: ``[T, A]`` actions.
        trajectory: ``[T]`` trajectory id of each step, ``0..N-1``, non-decreasing.
        operator: ``[N]`` operator id of each trajectory.
        step_labels: per-step labels, name -> ``[T]`` integers >= 0.
        trajectory_labels: per-trajectory labels, name -> ``[N]`` integers >= 0.
        label_names: optional class names per label.

    Raises:
        ValueError: shapes or lengths that do not match, ids that are not ``0..N-1`` in
            non-decreasing order, non-finite values, negative labels, a label name used twice.

    Example:
        >>> import numpy as np
        >>> data = TrajectoryDataset(state=np.zeros((5, 7)), action=np.zeros((5, 3)),
        ...                          trajectory=np.array([0, 0, 0, 1, 1]), operator=np.array([7, 8]),
        ...                          trajectory_labels={"skill": np.array([0, 2])})
        >>> data.lengths, data.offsets
        (array([3, 2]), array([0, 3, 5]))
    """

    state: np.ndarray
    action: np.ndarray
    trajectory: np.ndarray
    operator: np.ndarray
    step_labels: dict[str, np.ndarray] = field(default_factory=dict)
    trajectory_labels: dict[str, np.ndarray] = field(default_factory=dict)
    label_names: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.state = np.asarray(self.state, dtype=np.float32)
        self.action = np.asarray(self.action, dtype=np.float32)
        if self.state.ndim != 2 or self.action.ndim != 2:
            raise ValueError(
                f"state and action must be 2-d [steps, features], got {list(self.state.shape)} and {list(self.action.shape)}"
            )
        steps = self.state.shape[0]
        if steps == 0:
            raise ValueError("the dataset has no steps")
        if self.action.shape[0] != steps:
            raise ValueError(
                f"state has {steps} steps but action has {self.action.shape[0]}; they must match row by row"
            )
        if not (np.isfinite(self.state).all() and np.isfinite(self.action).all()):
            raise ValueError("state and action must be finite (no NaN or inf); drop or repair those steps")
        self.trajectory = _integers("trajectory", self.trajectory, steps, "one id per step")
        self.operator = _integers("operator", np.asarray(self.operator).reshape(-1), None, "")
        count = self.operator.shape[0]
        ids = self.trajectory
        if np.any(np.diff(ids) < 0) or ids[0] != 0 or ids[-1] != count - 1 or np.any(np.diff(ids) > 1):
            raise ValueError(
                f"trajectory ids must run 0..N-1 (N = {count}, the length of operator) in non-decreasing order, "
                "each trajectory's steps contiguous; sort the steps by trajectory and renumber the ids"
            )
        self.step_labels = {k: _label(k, v, steps, "per-step") for k, v in dict(self.step_labels).items()}
        self.trajectory_labels = {
            k: _label(k, v, count, "per-trajectory") for k, v in dict(self.trajectory_labels).items()
        }
        clash = set(self.step_labels) & set(self.trajectory_labels)
        if clash:
            raise ValueError(f"label(s) {sorted(clash)} are both per-step and per-trajectory; rename one")
        self.label_names = {k: tuple(str(n) for n in v) for k, v in dict(self.label_names).items()}
        for name, names in self.label_names.items():
            values = self.labels.get(name)
            if values is None:
                raise ValueError(f"label_names has {name!r} but there is no such label; labels: {sorted(self.labels)}")
            if values.size and values.max() >= len(names):
                raise ValueError(
                    f"label {name!r} takes value {values.max()} but label_names lists only {len(names)} names"
                )

    @property
    def num_trajectories(self) -> int:
        return int(self.operator.shape[0])

    @property
    def offsets(self) -> np.ndarray:
        """``[N + 1]``: trajectory ``i`` is steps ``offsets[i]:offsets[i + 1]``."""
        return np.searchsorted(self.trajectory, np.arange(self.num_trajectories + 1))

    @property
    def lengths(self) -> np.ndarray:
        """``[N]`` steps per trajectory."""
        return np.diff(self.offsets)

    @property
    def labels(self) -> dict[str, np.ndarray]:
        """Every label, per-step and per-trajectory, by name."""
        return {**self.step_labels, **self.trajectory_labels}

    def class_name(self, label: str, value: int) -> str:
        """The name of ``value`` of ``label`` (the number itself when no names were given)."""
        names = self.label_names.get(label, ())
        return names[value] if 0 <= value < len(names) else str(value)

    def select(self, trajectories: Sequence[int] | np.ndarray) -> TrajectoryDataset:
        """A dataset of the given trajectories, in the given order, renumbered ``0..len-1``.

        Example:
            >>> data = simulate_operators(num_operators=3, trajectories_per_operator=2)
            >>> data.select([4, 1]).operator.tolist()
            [2, 0]
        """
        ids = np.asarray(trajectories, dtype=np.int64).reshape(-1)
        if ids.size == 0:
            raise ValueError("select needs at least one trajectory id")
        if ids.min() < 0 or ids.max() >= self.num_trajectories:
            raise ValueError(f"trajectory ids must lie in 0..{self.num_trajectories - 1}, got {ids.min()}..{ids.max()}")
        offsets = self.offsets
        rows = np.concatenate([np.arange(offsets[i], offsets[i + 1]) for i in ids])
        return TrajectoryDataset(
            state=self.state[rows],
            action=self.action[rows],
            trajectory=np.repeat(np.arange(ids.size), self.lengths[ids]),
            operator=self.operator[ids],
            step_labels={k: v[rows] for k, v in self.step_labels.items()},
            trajectory_labels={k: v[ids] for k, v in self.trajectory_labels.items()},
            label_names=dict(self.label_names),
        )

    def __repr__(self) -> str:
        return (
            f"TrajectoryDataset(trajectories={self.num_trajectories}, steps={self.state.shape[0]}, "
            f"state_dim={self.state.shape[1]}, action_dim={self.action.shape[1]}, "
            f"operators={np.unique(self.operator).size}, labels={sorted(self.labels)})"
        )


def _integers(name: str, values: object, length: int | None, what: str) -> np.ndarray:
    array = np.asarray(values)
    if array.ndim != 1 or (length is not None and array.shape[0] != length):
        expected = f"[{length}] ({what})" if length is not None else "1-d"
        raise ValueError(f"{name} must have shape {expected}, got {list(array.shape)}")
    if array.size and not np.issubdtype(array.dtype, np.integer):
        if not (np.issubdtype(array.dtype, np.number) and np.all(np.mod(array, 1) == 0)):
            raise ValueError(f"{name} must hold integers, got dtype {array.dtype}")
    return array.astype(np.int64)


def _label(name: str, values: object, length: int, kind: str) -> np.ndarray:
    if not name or "/" in name:
        raise ValueError(f"label names must be non-empty and contain no '/', got {name!r}")
    what = "one value per " + ("step" if kind == "per-step" else "trajectory")
    array = _integers(f"{kind} label {name!r}", values, length, what)
    if array.size and array.min() < 0:
        raise ValueError(f"label {name!r} must be integers >= 0 (class indices), got {array.min()}")
    return array


def save_dataset(dataset: TrajectoryDataset, path: str | os.PathLike[str]) -> None:
    """Write ``dataset`` to a compressed ``.npz`` in the format of the module docstring.

    The write is atomic (:func:`smcd_rl.files.write_atomic`): an interrupted or failed save leaves
    ``path`` as it was, never a truncated file. The parent directories are created.

    Raises:
        smcd_rl.files.FileWriteError: the file cannot be written (read-only directory, disk full,
            ``path`` is a directory, ...); the message names the path and the reason.

    Example:
        >>> import tempfile
        >>> data = simulate_operators(num_operators=2, trajectories_per_operator=2)
        >>> path = tempfile.mkdtemp() + "/drone.npz"
        >>> save_dataset(data, path)
        >>> load_dataset(path).num_trajectories
        4
    """
    arrays: dict[str, np.ndarray] = {
        "state": dataset.state,
        "action": dataset.action,
        "trajectory": dataset.trajectory,
        "operator": dataset.operator,
    }
    arrays.update({f"step/{k}": v for k, v in dataset.step_labels.items()})
    arrays.update({f"traj/{k}": v for k, v in dataset.trajectory_labels.items()})
    arrays.update({f"names/{k}": np.array(v, dtype=str) for k, v in dataset.label_names.items()})

    def write(handle: IO[bytes]) -> None:  # a file handle: np.savez would append .npz to other names
        # mypy matches **arrays against the stubs' allow_pickle: bool; no key here has that name, and
        # passing the flag would store an array named allow_pickle on numpy 1.26, which has no such flag.
        np.savez_compressed(handle, **arrays)  # type: ignore[arg-type]

    write_atomic(path, write, what="dataset")


def load_dataset(path: str | os.PathLike[str]) -> TrajectoryDataset:
    """Read a dataset written by :func:`save_dataset` (or by hand in the same format).

    Raises:
        FileNotFoundError: no file at ``path``.
        KeyError: a required key (state, action, trajectory, operator) is missing.
        ValueError: the file is not an npz, is corrupt, or its arrays break the format (see
            :class:`TrajectoryDataset`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no dataset at {path}; write one with smcd_rl.envs.drone_operators.save_dataset")
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise ValueError(f"{path} is not a readable .npz dataset: {err}") from err
    with archive:
        keys = set(archive.files)
        missing = [k for k in _REQUIRED if k not in keys]
        if missing:
            raise KeyError(
                f"dataset {path} lacks key(s) {missing}; it has {sorted(keys)}. Needed: state [T, S], action [T, A], "
                "trajectory [T] (id per step), operator [N] (id per trajectory); see smcd_rl.envs.drone_operators"
            )
        unknown = [k for k in keys if k not in _REQUIRED and k.split("/")[0] not in ("step", "traj", "names")]
        if unknown:
            raise KeyError(
                f"dataset {path} has unknown key(s) {sorted(unknown)}; labels go under step/NAME or traj/NAME"
            )

        try:  # the zip's members are read (and their CRC-32 checked) only here
            arrays = {k: archive[k] for k in keys}
        except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
            raise ValueError(f"{path} is corrupt ({err}); write it again with save_dataset") from err

        def group(prefix: str) -> dict[str, np.ndarray]:
            return {k.split("/", 1)[1]: arrays[k] for k in keys if k.startswith(prefix + "/")}

        return TrajectoryDataset(
            state=arrays["state"],
            action=arrays["action"],
            trajectory=arrays["trajectory"],
            operator=arrays["operator"],
            step_labels=group("step"),
            trajectory_labels=group("traj"),
            label_names={k: tuple(v.tolist()) for k, v in group("names").items()},
        )


def split_dataset(
    dataset: TrajectoryDataset, *, known_fraction: float = 0.10, unknown_fraction: float = 0.07, seed: int = 0
) -> dict[str, np.ndarray]:
    """The paper's split: training, known-operators testing and unknown-operators testing.

    ``round(unknown_fraction * operators)`` operators (at least one) are held out entirely
    (``"unknown"``); of the other operators' trajectories, ``round(known_fraction * N)`` (at least
    one) are held out at random (``"known"``: their operators are in training), never an
    operator's last training trajectory; the rest is ``"train"``. With 33 operators x 16 this is
    443 / 53 / 32 trajectories (83.9 / 10.0 / 6.1 %).

    Returns:
        ``{"train": ids, "known": ids, "unknown": ids}``, sorted trajectory ids.

    Example:
        >>> data = simulate_operators(num_operators=33, trajectories_per_operator=16)
        >>> {k: len(v) for k, v in split_dataset(data).items()}
        {'train': 443, 'known': 53, 'unknown': 32}
    """
    if not (0 <= known_fraction < 1 and 0 <= unknown_fraction < 1 and known_fraction + unknown_fraction < 1):
        raise ValueError(f"fractions must be in [0, 1) with a sum below 1, got {known_fraction}, {unknown_fraction}")
    operators = np.unique(dataset.operator)
    if operators.size < 2:
        raise ValueError(
            f"the split holds out whole operators, so it needs at least 2 operators; the dataset has {operators.size}"
        )
    rng = np.random.default_rng(seed)
    n_unknown = min(max(1, round(unknown_fraction * operators.size)), operators.size - 1)
    unknown_ops = rng.choice(operators, size=n_unknown, replace=False)
    is_unknown = np.isin(dataset.operator, unknown_ops)
    candidates = np.flatnonzero(~is_unknown)
    n_known = max(1, round(known_fraction * dataset.num_trajectories))
    remaining = {
        int(op): int(n) for op, n in zip(*np.unique(dataset.operator[candidates], return_counts=True), strict=True)
    }
    known: list[int] = []
    for index in rng.permutation(candidates):
        if len(known) == n_known:
            break
        op = int(dataset.operator[index])
        if remaining[op] > 1:  # the operator must stay "known": keep one trajectory in training
            remaining[op] -= 1
            known.append(int(index))
    if len(known) < n_known:
        raise ValueError(
            f"cannot hold out {n_known} known-operator trajectories and keep one per operator in training; "
            "lower known_fraction or add trajectories"
        )
    known_ids = np.sort(np.array(known, dtype=np.int64))
    train = np.setdiff1d(candidates, known_ids)
    return {"train": train, "known": known_ids, "unknown": np.flatnonzero(is_unknown)}


@dataclass(frozen=True)
class _Operators:
    """Per-operator flying parameters (tensors ``[operators]``), from the latent skill."""

    delay: torch.Tensor  # steps the operator's view lags behind the drone
    gain: torch.Tensor  # 1/s: command = gain x perceived error
    noise: torch.Tensor  # m/s std of the command noise
    speed: torch.Tensor  # m/s cruise speed (horizontal command bound)
    descent: torch.Tensor  # m/s fastest descent
    depth_error: torch.Tensor  # std of the perceived target depth, per metre of depth
    diagonal: torch.Tensor  # probability of the diagonal strategy

    @staticmethod
    def from_skill(skill: torch.Tensor, generator: torch.Generator) -> _Operators:
        return _Operators(
            delay=(1.5 - skill).round().clamp(0, 4).long(),
            gain=(1.0 - 0.25 * skill).clamp(0.5, 1.6),
            noise=0.25 * torch.exp(-0.5 * skill),
            speed=(1.2 + 0.3 * skill).clamp(0.6, MAX_SPEED),
            descent=(0.7 - 0.1 * skill).clamp(0.4, 1.2),
            depth_error=0.09 * torch.exp(-0.6 * skill),
            diagonal=0.15 + 0.7 * torch.rand(skill.shape, generator=generator, dtype=skill.dtype),
        )


def simulate_operators(
    num_operators: int = 33,
    trajectories_per_operator: int = 16,
    *,
    seed: int = 0,
    max_steps: int = 300,
) -> TrajectoryDataset:
    """Fly a population of simulated operators; the stand-in for the paper's human data.

    Operator ``o`` flies trajectories ``o * trajectories_per_operator ...``, towards the targets of
    :data:`TASK_SEQUENCE` (repeated if more than 16). See the module docstring for the operator
    model and the labels; :func:`split_dataset` gives the paper's split.

    Args:
        num_operators: operators in the population (the paper had 33).
        trajectories_per_operator: landings per operator (the paper had 16).
        seed: seed of the operators' parameters, strategies, misjudgements and command noise.
        max_steps: a trajectory that has not touched down after this many steps ends (a failure).

    Returns:
        A :class:`TrajectoryDataset` with step label ``phase`` and trajectory labels ``skill``,
        ``strategy``, ``success`` and ``target``.

    Example:
        >>> data = simulate_operators(num_operators=5, trajectories_per_operator=2, seed=1)
        >>> data.class_name("skill", int(data.trajectory_labels["skill"][0])) in SKILLS
        True
    """
    counts = {
        "num_operators": num_operators,
        "trajectories_per_operator": trajectories_per_operator,
        "max_steps": max_steps,
    }
    for name, value in counts.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    generator = torch.Generator().manual_seed(seed)
    dtype = torch.float64
    skill = torch.randn(num_operators, generator=generator, dtype=dtype)
    ops = _Operators.from_skill(skill, generator)
    count = num_operators * trajectories_per_operator
    operator = torch.arange(num_operators).repeat_interleave(trajectories_per_operator)
    sequence = torch.tensor(TASK_SEQUENCE)
    target = sequence[torch.arange(trajectories_per_operator) % len(TASK_SEQUENCE)].repeat(num_operators)
    diagonal = torch.rand(count, generator=generator, dtype=dtype) < ops.diagonal[operator]

    # The perceived target: depth (x) misjudged in proportion to the depth, sideways (y) less.
    table = platform_tensor(dtype=dtype)
    goal = table[target, :3].clone()
    depth = (goal[:, 0] - START[0]).abs()
    misjudged = torch.randn(count, 2, generator=generator, dtype=dtype) * torch.stack([depth, 0.4 * depth], -1)
    goal[:, :2] += ops.depth_error[operator].unsqueeze(-1) * misjudged
    noise = torch.randn(max_steps, count, 3, generator=generator, dtype=dtype) * ops.noise[operator].unsqueeze(-1)

    delay, gain, speed = ops.delay[operator], ops.gain[operator].unsqueeze(-1), ops.speed[operator]
    descent = ops.descent[operator]
    position = torch.tensor(START, dtype=dtype).expand(count, 3).clone()
    velocity = torch.zeros(count, 3, dtype=dtype)
    history = position.new_zeros(max_steps + 1, count, 3)  # positions, for the delayed view
    history[0] = position
    initial_xy = (goal[:, :2] - position[:, :2]).norm(dim=-1)
    descending = torch.zeros(count, dtype=torch.bool)
    active = torch.ones(count, dtype=torch.bool)
    rows = torch.arange(count)
    states, actions, phases, steps = [], [], [], []
    for t in range(max_steps):
        seen = history[(t - delay).clamp(min=0), rows]
        error = goal - seen
        distance_xy = error[:, :2].norm(dim=-1)
        descending = descending | (distance_xy < _CAPTURE_RADIUS)
        horizontal = gain * error[:, :2]
        horizontal = horizontal * (speed / horizontal.norm(dim=-1).clamp(min=1e-9)).clamp(max=1.0).unsqueeze(-1)
        # Cruise height for orthogonal landings; a glide path to just above the platform for diagonal ones.
        glide = (
            goal[:, 2] + _CLEARANCE + (START[2] - goal[:, 2] - _CLEARANCE) * (distance_xy / initial_xy).clamp(max=1.0)
        )
        height_goal = torch.where(diagonal, glide, torch.full_like(glide, START[2]))
        vertical = gain[:, 0] * (height_goal - seen[:, 2])
        sink = -(0.8 * (seen[:, 2] - goal[:, 2]) + 0.15).clamp(min=0.15).minimum(descent)
        vertical = torch.where(descending, sink, vertical)
        command = (torch.cat([horizontal, vertical.unsqueeze(-1)], -1) + noise[t]).clamp(-MAX_SPEED, MAX_SPEED)

        states.append(drone_observation(position, velocity, target))
        actions.append(command)
        phases.append(descending.long())
        steps.append(active.clone())
        next_position, next_velocity, down = drone_transition(position, velocity, command)
        keep = active.unsqueeze(-1)
        position = torch.where(keep, next_position, position)
        velocity = torch.where(keep, next_velocity, velocity)
        history[t + 1] = position
        active = active & ~down
        if not bool(active.any()):
            break

    recorded = torch.stack(steps, 1)  # [count, steps]: which steps belong to a trajectory
    lengths = recorded.sum(1)
    state = torch.stack(states, 1)[recorded]
    action = torch.stack(actions, 1)[recorded]
    phase = torch.stack(phases, 1)[recorded]
    success = landing_success(position, target)
    final_distance = (position[:, :2] - table[target, :2]).norm(dim=-1)
    skill_label = _skill_labels(operator, success, final_distance, num_operators)
    return TrajectoryDataset(
        state=state.numpy(),
        action=action.numpy(),
        trajectory=np.repeat(np.arange(count), lengths.numpy()),
        operator=operator.numpy(),
        step_labels={"phase": phase.numpy()},
        trajectory_labels={
            "skill": skill_label,
            "strategy": diagonal.long().numpy(),
            "success": success.long().numpy(),
            "target": target.numpy(),
        },
        label_names={
            "skill": SKILLS,
            "strategy": STRATEGIES,
            "phase": PHASES,
            "success": OUTCOMES,
            "target": tuple(f"platform {i}" for i in range(NUM_PLATFORMS)),
        },
    )


def _skill_labels(
    operator: torch.Tensor, success: torch.Tensor, final_distance: torch.Tensor, num_operators: int
) -> np.ndarray:
    """Appendix B.1: rank operators by successful landings; bottom 10% novice, top 10% expert."""
    wins = torch.zeros(num_operators).index_add_(0, operator, success.float())
    miss = torch.zeros(num_operators, dtype=final_distance.dtype).index_add_(0, operator, final_distance)
    order = np.lexsort((miss.numpy(), -wins.numpy()))  # best first: most wins, then smallest misses
    tail = max(1, round(0.1 * num_operators)) if num_operators >= 3 else 0
    label = np.ones(num_operators, dtype=np.int64)
    if tail:
        label[order[:tail]] = SKILLS.index("expert")
        label[order[-tail:]] = SKILLS.index("novice")
    return label[operator.numpy()]
