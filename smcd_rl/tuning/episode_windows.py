"""Fixed-length episodes cut from a stream of collected transitions, never across a reset.

:func:`smcd_rl.calibrate` and the evaluations take episodes as a TensorDict of batch ``[E, T]``;
collectors return a stream of transitions in which episodes of different lengths follow one
another. :func:`episodes` turns the one into the other.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import Tensor

__all__ = ["episodes", "DONE_KEYS"]

#: The end-of-episode flags :func:`episodes` reads (any of them, joined by "or"), torchrl's layout.
DONE_KEYS = (("next", "done"), ("next", "terminated"), ("next", "truncated"))

#: Marks padding in torchrl collectors' ``split_trajs=True`` output; padded steps are not transitions.
_VALID_KEY = ("collector", "mask")


def episodes(td: TensorDictBase, length: int) -> TensorDictBase:
    """Windows of ``length`` consecutive transitions, each inside one episode, as a TensorDict ``[n, length]``.

    An episode ends at a transition whose ``("next", "done")``, ``("next", "terminated")`` or
    ``("next", "truncated")`` flag is set (any of those present), as
    :func:`smcd_rl.integrations.gymnasium.collect_transitions` and torchrl's collectors write
    them; the next transition starts a new one. Each episode is cut from its first transition
    into consecutive, non-overlapping windows of ``length``; the rest of the episode, shorter
    than ``length``, is dropped (an episode of 7 transitions gives 2 windows of 3 and drops its
    last transition). The transitions after the last flag, an episode still running when the
    collection stopped, count as an episode. The windows keep the order of the stream (row by
    row for a batch ``[E, T]``), every key is kept, and the result is a copy.

    Args:
        td: transitions of batch ``[T]`` (one stream, as ``collect_transitions`` returns it) or
            ``[E, T]`` (one stream per env, as torchrl's collectors return them; no window runs
            from one row into the next). Steps whose ``("collector", "mask")`` is False
            (the padding of ``split_trajs=True``) belong to no episode.
        length: transitions per window, ``>= 1``.

    Returns:
        A TensorDict of batch ``[n, length]``, ``n >= 1``, ready for :func:`smcd_rl.calibrate`.

    Raises:
        TypeError: ``td`` is not a TensorDict, ``length`` not an int, or a flag not bool.
        KeyError: ``td`` has none of the flags above.
        ValueError: ``length < 1``, a batch other than ``[T]`` or ``[E, T]``, a flag of another
            shape than ``[*batch]`` or ``[*batch, 1]``, or no episode with ``length`` transitions.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> done = torch.tensor([0, 0, 1, 0, 0, 0, 0, 1, 0], dtype=torch.bool).unsqueeze(-1)
        >>> data = TensorDict({"observation": torch.arange(9.0), "next": {"done": done}}, [9])
        >>> windows = smcd_rl.episodes(data, 2)  # episodes of 3, 5 and (still running) 1 transitions
        >>> windows.batch_size
        torch.Size([3, 2])
        >>> windows["observation"]
        tensor([[0., 1.],
                [3., 4.],
                [5., 6.]])
    """
    from smcd_rl.checks import check_count, check_tensordict

    check_tensordict(td, "episodes")
    length = check_count(length, "length")
    if td.batch_dims not in (1, 2):
        raise ValueError(
            f"episodes takes transitions of batch [T] (one stream, as collect_transitions returns) or [E, T] (one "
            f"stream per env, as torchrl's collectors return), got batch {list(td.batch_size)}"
            + (f"; flatten the leading dims, e.g. td.reshape(-1, {td.batch_size[-1]})" if td.batch_dims > 2 else "")
        )
    batch = tuple(td.batch_size)
    keys = set(td.keys(include_nested=True))
    present = [key for key in DONE_KEYS if key in keys]
    if not present:
        raise KeyError(
            f"episodes needs end-of-episode flags to know where episodes end: one or more of {list(DONE_KEYS)} "
            f"(bool, [*batch, 1], as collect_transitions and torchrl's collectors write them); the TensorDict has "
            f"{sorted(map(str, keys))}"
        )
    flags = [_flag(td, key, batch) for key in present]
    device = flags[0].device
    ends = torch.stack([flag.to(device) for flag in flags]).any(0)
    valid = _flag(td, _VALID_KEY, batch).to(device) if _VALID_KEY in keys else torch.ones_like(ends)
    # A run is a stretch of valid steps inside one episode. It starts at a row's first step, after an
    # episode's end and after padding; flattened row by row, no run can reach into the next row.
    after_close = torch.ones_like(ends)
    after_close[..., 1:] = ends[..., :-1] | ~valid[..., :-1]
    starts, valid = (valid & after_close).reshape(-1), valid.reshape(-1)
    steps = torch.arange(starts.numel(), device=device)
    run = (torch.cumsum(starts, 0) - 1).clamp(min=0)  # the run of each valid step
    run_start = steps[starts]
    run_length = torch.bincount(run[valid], minlength=run_start.numel())
    position = steps - run_start[run] if run_start.numel() else steps
    first = valid & (position % length == 0)
    if run_start.numel():
        first &= position + length <= run_length[run]
    if not bool(first.any()):
        longest = int(run_length.max()) if run_start.numel() else 0
        if longest == 0:  # nothing to cut: no length would do
            raise ValueError(
                "episodes got no transitions (an empty stream, or every step padding); collect transitions first"
            )
        raise ValueError(
            f"no episode has {length} consecutive transitions (the longest has {longest}; episodes end where "
            f"{' or '.join(map(str, present))} is set): pass length <= {longest}, or collect longer episodes"
        )
    index = steps[first].unsqueeze(-1) + torch.arange(length, device=device)  # [n, length]
    flat = td.reshape(-1) if td.batch_dims == 2 else td
    return flat[index if flat.device is None else index.to(flat.device)]


def _flag(td: TensorDictBase, key: tuple[str, str], batch: tuple[int, ...]) -> Tensor:
    """The bool flag ``td[key]`` of shape ``[*batch]``, or an error naming the key and the shape it needs."""
    value = td.get(key)
    if not isinstance(value, torch.Tensor) or value.dtype != torch.bool:
        kind = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
        raise TypeError(f"episodes: {key!r} must be a bool tensor, got {kind}; convert it with .bool()")
    if tuple(value.shape) == (*batch, 1):
        value = value.squeeze(-1)
    if tuple(value.shape) != batch:
        raise ValueError(
            f"episodes: {key!r} has shape {list(value.shape)} but needs one flag per transition, "
            f"{list(batch)} or {[*batch, 1]}"
        )
    return value
