"""Finished pieces of a long experiment, one file each, named by the digest of what determines them.

Each piece (a method's results over all trials, a sweep's grid point, collected data) is a file
of its own, ``{kind}-{digest}.pt``, the digest that of the piece's key (every setting and input
digest its result depends on, and the digest of the package's code), so saving one
piece never rewrites another, even among thousands. A changed setting or input gives another file, so a rerun
never reads a stale result, and a grown grid reuses every finished piece; a key that names an
input file holds its :func:`file_digest`, so new data at the same path is never mistaken for the
old. Files are written and read through :mod:`smcd_rl.files` (atomic writes; a damaged file,
down to one flipped bit, is an error naming it and the fix: delete it and rerun).

Example:
    >>> import tempfile
    >>> store = ResultStore(tempfile.mkdtemp(), what="demo result")
    >>> store.get("point", {"lr": 0.1}) is None
    True
    >>> store.put("point", {"lr": 0.1}, {"loss": 0.5})
    >>> store.get("point", {"lr": 0.1}), store.get("point", {"lr": 0.2})
    ({'loss': 0.5}, None)
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from smcd_rl.digests import code_digest, content_digest, file_digest
from smcd_rl.files import UnreadableFileError, load_file, save_file

__all__ = ["ResultStore", "file_digest"]

_FORMAT = "smcd_rl.result_store/1"


class ResultStore:
    """A directory of finished results, each keyed by content (see the module docstring).

    Args:
        directory: where the files go (created on the first :meth:`put`).
        what: what the results are, for error messages (``"sweep result"``).
    """

    def __init__(self, directory: str | os.PathLike[str], *, what: str = "result") -> None:
        self.directory = Path(directory)
        self.what = what

    def path(self, kind: str, key: Mapping[str, Any]) -> Path:
        """The file of the result of ``kind`` (e.g. ``"point"``) determined by ``key``."""
        return self.directory / f"{kind}-{_digest(key)[:16]}.pt"

    def get(self, kind: str, key: Mapping[str, Any]) -> dict[str, Any] | None:
        """The stored result for ``key``, or ``None`` when there is none yet."""
        path = self.path(kind, key)
        if not path.is_file():
            return None
        entry = load_file(path, what=f"{self.what} file", expect_format=_FORMAT, expect_keys=["digest", "value"])
        if entry["digest"] != _digest(key):  # another key with the same 16-digit prefix
            return None
        if not isinstance(entry["value"], Mapping):
            raise UnreadableFileError(
                f"{self.what} file {path} holds a {type(entry['value']).__name__}, not a result; delete it and rerun",
                path,
            )
        return dict(entry["value"])

    def put(self, kind: str, key: Mapping[str, Any], value: Mapping[str, Any]) -> None:
        """Store ``value`` (a dict of tensors, numbers, lists) as the result for ``key``, atomically."""
        entry = {"format": _FORMAT, "digest": _digest(key), "key": dict(key), "value": dict(value)}
        save_file(entry, self.path(kind, key), what=f"{self.what} file")


def _digest(key: Mapping[str, Any]) -> str:
    # The code's digest: after any change to the package's code a result is computed afresh.
    return content_digest({"code": code_digest(), "key": dict(key)})
