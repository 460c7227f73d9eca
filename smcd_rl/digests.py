"""Digests of content: equal exactly when the content is, so files and caches can be named by what they hold.

Training checkpoints record the digest of their data, and the experiment harness names
checkpoints and cached results by the digests of models, data and settings, so nothing is ever
looked up by a file name that may since hold something else.

Example:
    >>> import torch
    >>> content_digest({"x": torch.ones(3)}) == content_digest({"x": torch.ones(3)})
    True
    >>> content_digest({"x": torch.ones(3)}) == content_digest({"x": torch.ones(3, dtype=torch.float64)})
    False
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

__all__ = ["content_digest", "model_digest", "file_digest", "code_digest"]


def content_digest(value: Any) -> str:
    """A SHA-256 hex digest of tensors, arrays, TensorDicts, mappings, sequences and plain values.

    Tensors and numeric arrays are read by dtype, shape and every byte; mappings by their sorted
    keys; anything else by its ``repr``.

    Example:
        >>> import numpy as np
        >>> a = np.zeros(10_000); b = a.copy(); b[5000] = 1  # their reprs are the same
        >>> content_digest(a) != content_digest(b)
        True
    """
    digest = hashlib.sha256()
    _feed(digest, value)
    return digest.hexdigest()


def model_digest(model: torch.nn.Module) -> str:
    """The digest of a module's class, structure and every parameter and buffer: what it predicts.

    Example:
        >>> import torch
        >>> a, b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)
        >>> model_digest(a) == model_digest(a) != model_digest(b)
        True
    """
    return content_digest({"class": type(model).__qualname__, "repr": repr(model), "state": model.state_dict()})


def file_digest(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes, read in 1 MiB blocks so that a large file is never held whole."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@functools.cache
def code_digest() -> str:
    """The digest of every Python source file of the installed package (``smcd_rl``, its envs and agents).

    Cached results are keyed by it, so any change to the code, an upgrade or a local edit, makes
    them be computed afresh instead of reused from the code that was there before.
    """
    digest = hashlib.sha256()
    for package in ("smcd_rl", "smcd_rl.envs", "smcd_rl.agents"):
        # Found, not imported: the package itself imports this module while it initialises.
        spec = importlib.util.find_spec(package)
        for root in spec.submodule_search_locations or () if spec else ():
            for path in sorted(Path(root).rglob("*.py")):
                digest.update(f"{package}/{path.relative_to(root)}".encode())
                digest.update(path.read_bytes())
    return digest.hexdigest()


def _feed(digest: Any, value: Any) -> None:
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biufc":  # strings, objects: every element by its repr
            digest.update(f"A{value.dtype}{value.shape}{value.tolist()!r}".encode())
            return
        value = torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, torch.Tensor):
        tensor = value.detach().cpu().contiguous()
        digest.update(f"T{tensor.dtype}{tuple(tensor.shape)}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, TensorDictBase):
        digest.update(f"TD{tuple(value.batch_size)}".encode())
        for key in sorted(value.keys(include_nested=True, leaves_only=True), key=repr):
            digest.update(repr(key).encode())
            _feed(digest, value.get(key))
    elif isinstance(value, Mapping):
        digest.update(f"{{{len(value)}".encode())
        for key in sorted(value, key=repr):
            digest.update(repr(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(f"[{len(value)}".encode())
        for item in value:
            _feed(digest, item)
    else:
        digest.update(f"{type(value).__name__}:{value!r}".encode())
