"""Argument checks shared by the public entry points, so that bad input fails before any work.

Each check returns the value in its canonical form or raises an error whose message names the
argument, what it got and what it needs: a ``TypeError`` for the wrong kind of value, a
``ValueError`` for a value out of range. Nothing here touches model state.

Example:
    >>> from smcd_rl.checks import check_count
    >>> check_count(5, "num_particles")
    5
    >>> check_count(2.5, "num_particles")
    Traceback (most recent call last):
    ...
    TypeError: num_particles must be an int, got 2.5 (float)
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

__all__ = [
    "check_count",
    "check_seed",
    "check_real",
    "check_shape",
    "checked_rows",
    "check_real_tensor",
    "check_tensordict",
    "check_key",
    "read_tensor",
    "read_inputs",
]


def check_count(value: Any, name: str, *, minimum: int = 1) -> int:
    """``value`` as an ``int`` if it is an integer ``>= minimum``; floats (even ``2.0``) and bools are refused.

    A float count is refused rather than rounded: ``num_particles=2.5`` silently becoming 2 hides a bug.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an int, got {value!r} ({type(value).__name__})")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


#: The largest seed a torch generator takes (``manual_seed`` reads an unsigned 64-bit integer).
MAX_SEED = 2**64 - 1


def check_seed(value: Any, name: str = "seed") -> int:
    """``value`` as an ``int`` if a torch generator can be seeded with it: an integer in ``[0, 2**64 - 1]``.

    Example:
        >>> check_seed(2**70)
        Traceback (most recent call last):
        ...
        ValueError: seed must be in [0, 2**64 - 1] (what a torch generator takes), got 1180591620717411303424
    """
    seed = check_count(value, name, minimum=0)
    if seed > MAX_SEED:
        raise ValueError(f"{name} must be in [0, 2**64 - 1] (what a torch generator takes), got {seed}")
    return seed


def check_real(
    value: Any, name: str, *, low: float = -math.inf, high: float = math.inf, open_low: bool = False
) -> float:
    """``value`` as a ``float`` if it is a real number in ``[low, high]`` (``(low, high]`` with ``open_low``)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {value!r} ({type(value).__name__})")
    number = float(value)
    below = number <= low if open_low else number < low
    if math.isnan(number) or below or number > high:
        bounds = f"{'(' if open_low else '['}{low:g}, {high:g}]"
        raise ValueError(f"{name} must be in {bounds}, got {value}")
    return number


def check_shape(value: Any, name: str) -> tuple[int, ...]:
    """A batch shape: a sequence of ints ``>= 0`` (a ``torch.Size``, tuple or list), as a tuple."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        hint = f"; for {value} elements pass ({value},)" if isinstance(value, numbers.Integral) else ""
        raise TypeError(f"{name} must be a sequence of ints such as (3,), got {value!r}{hint}")
    return tuple(check_count(size, f"{name}[{i}]", minimum=0) for i, size in enumerate(value))


def checked_rows(rows: Any, batch_shape: tuple[int, ...]) -> Tensor:
    """``rows`` of a ``restore_rows`` (the batch elements to put back) as a bool tensor of ``batch_shape``, or a ``ValueError``.

    Example:
        >>> checked_rows(torch.tensor([True, False]), (2,))
        tensor([ True, False])
    """
    if not isinstance(rows, Tensor) or rows.dtype != torch.bool or tuple(rows.shape) != tuple(batch_shape):
        got = f"{rows.dtype} {list(rows.shape)}" if isinstance(rows, Tensor) else type(rows).__name__
        raise ValueError(f"rows must be a bool tensor of the batch shape {list(batch_shape)}, got {got}")
    return rows


def check_real_tensor(value: Any, name: str) -> Tensor:
    """``value`` if it is a torch Tensor of a real dtype (float, int or bool) that holds values.

    Complex, quantized and non-tensors are refused, and so are tensors on the meta device, which
    have a shape but no values (reading one raised torch's ``NotImplementedError`` deep inside).

    Example:
        >>> import torch
        >>> from smcd_rl.checks import check_real_tensor
        >>> check_real_tensor(torch.zeros(2, device="meta"), "observe: 'q'")
        Traceback (most recent call last):
        ...
        TypeError: observe: 'q' is on the meta device, where a tensor has a shape but no values; pass the data itself (e.g. on 'cpu')
    """
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}; convert it with torch.as_tensor")
    if value.device.type == "meta":
        raise TypeError(
            f"{name} is on the meta device, where a tensor has a shape but no values; pass the data itself "
            "(e.g. on 'cpu')"
        )
    if value.is_complex():
        raise TypeError(f"{name} is complex ({value.dtype}); pass real values (e.g. its .real part)")
    if value.dtype in (torch.quint8, torch.qint8, torch.qint32):
        raise TypeError(f"{name} is a quantized tensor ({value.dtype}); pass real values")
    return value


def check_tensordict(td: Any, what: str) -> None:
    """Refuse anything but a TensorDict, with a hint for the usual mistakes (a dict, a bare array)."""
    if not isinstance(td, TensorDictBase):
        hint = ""
        if isinstance(td, dict):
            hint = "; wrap it: TensorDict(that_dict, batch_size=[...])"
        elif isinstance(td, (Tensor, np.ndarray)):
            hint = (
                "; pass a TensorDict that holds it under the model's keys, e.g. TensorDict({'q': x}, batch_size=[...])"
            )
        raise TypeError(f"{what} takes a tensordict.TensorDict, got {type(td).__name__}{hint}")


def check_key(key: Any, name: str, *, optional: bool = False) -> None:
    """A TensorDict key: a non-empty string or a non-empty tuple of them (``None`` if ``optional``)."""
    if key is None and optional:
        return
    plain = isinstance(key, str) and key != ""
    nested = isinstance(key, tuple) and len(key) > 0 and all(isinstance(k, str) and k for k in key)
    if not (plain or nested):
        raise TypeError(f"{name} must be a key (a string, or a tuple of strings for a nested key), got {key!r}")


def read_tensor(
    td: TensorDictBase,
    key: Any,
    size: int | None,
    *,
    what: str,
    like: Tensor,
    check_finite: bool = True,
    exact: bool = False,
) -> Tensor:
    """``td[key]`` checked and converted to ``like``'s dtype and device, before a model uses it.

    It must be a real tensor of shape ``[..., size]`` (``[*td.batch_size, size]`` if ``exact``).
    Finiteness is checked after the conversion: a float64 1e39 is finite, but not in float32.
    The errors name ``what`` (the entry point), the key and the fix.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"q": torch.tensor([[1e39, 0.0]], dtype=torch.float64)}, [1])
        >>> read_tensor(td, "q", 2, what="observe", like=torch.zeros(1))
        Traceback (most recent call last):
        ...
        ValueError: observe: 'q' holds values too large for the model's torch.float32 (they become inf); the adaptation state is unchanged. Rescale or drop the transition before passing it
    """
    value = td.get(key, None)
    if value is None:
        raise KeyError(f"{what}: the TensorDict has no key {key!r}; it has {sorted(map(str, td.keys(True, True)))}")
    value = check_real_tensor(value, f"{what}: {key!r}")
    if value.dim() == 0 or (size is not None and value.shape[-1:] != (size,)):
        raise ValueError(f"{what}: {key!r} must have shape [..., {size or 'features'}], got {list(value.shape)}")
    if exact and tuple(value.shape[:-1]) != tuple(td.batch_size):
        raise ValueError(
            f"{what}: {key!r} has shape {list(value.shape)} but the TensorDict's batch is {list(td.batch_size)}; "
            f"{what} takes one transition per batch element, [*batch, features]: build the TensorDict with "
            f"batch_size={list(value.shape[:-1])}"
        )
    converted = value.to(device=like.device, dtype=like.dtype)
    if check_finite and not bool(torch.isfinite(converted).all()):
        if value.is_floating_point() and bool(torch.isfinite(value).all()):
            raise ValueError(
                f"{what}: {key!r} holds values too large for the model's {converted.dtype} (they become inf); "
                "the adaptation state is unchanged. Rescale or drop the transition before passing it"
            )
        raise ValueError(
            f"{what}: {key!r} contains NaN or inf; the adaptation state is unchanged. "
            "Drop or repair the transition before passing it"
        )
    return converted


def read_inputs(
    td: TensorDictBase,
    keys: Sequence[Any],
    *,
    what: str,
    like: Tensor,
    check_finite: bool = True,
    exact: bool = False,
) -> Tensor:
    """A model's input: ``td``'s ``keys``, each read with :func:`read_tensor`, concatenated along the last dim.

    Each key may hold any number of features; the caller checks their total against its network,
    in its own words.
    """
    parts = [read_tensor(td, key, None, what=what, like=like, check_finite=check_finite, exact=exact) for key in keys]
    try:
        return torch.cat(parts, dim=-1) if len(parts) > 1 else parts[0]
    except RuntimeError as err:
        shapes = {str(k): list(p.shape) for k, p in zip(keys, parts, strict=True)}
        raise ValueError(f"{what}: cannot concatenate inputs {shapes} along the last dim") from err
