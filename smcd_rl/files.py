"""Reading and writing the files smcd_rl saves: one loader and one atomic saver for all of them.

Model checkpoints (:meth:`smcd_rl.AdaptiveModel.save`), training checkpoints (``fit(...,
checkpoint=)``) and the experiments' result caches are all dicts written with :func:`torch.save`.
They go through :func:`save_file` and :func:`load_file`, so that every way a file can be bad gives
one clear error naming the file and the fix, instead of a pickle or zip traceback:

=========================================  ============================================================
what went wrong                            error
=========================================  ============================================================
no such file                               ``FileNotFoundError``
empty, truncated, corrupt (a record        :class:`UnreadableFileError` (a ``ValueError``)
fails its CRC-32), not a dict, keys
missing
another kind of smcd_rl file               :class:`CheckpointMismatchError` (a ``ValueError``)
directory read-only, disk full on write    :class:`FileWriteError` (an ``OSError`` and a ``ValueError``)
=========================================  ============================================================

Writes are atomic: the data goes to a temporary file with a name of its own in the same directory,
is flushed to disk, and replaces the target in one ``os.replace``. An interruption never leaves a
half-written file, and two runs writing into one directory never touch each other's temporary files.
Files in other formats (an ``.npz`` dataset, say) are written the same way by :func:`write_atomic`.

Example:
    >>> import tempfile, torch
    >>> from smcd_rl.files import load_file, save_file
    >>> path = tempfile.mkdtemp() + "/state.pt"
    >>> save_file({"format": "demo/1", "weights": torch.ones(2)}, path, what="demo file")
    >>> load_file(path, what="demo file", expect_format="demo/1", expect_keys=["weights"])["weights"]
    tensor([1., 1.])
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import secrets
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import IO, Any

import torch

__all__ = [
    "load_file",
    "save_file",
    "write_atomic",
    "write_text",
    "UnreadableFileError",
    "FileWriteError",
    "CheckpointMismatchError",
]


class CheckpointMismatchError(ValueError):
    """A checkpoint does not fit the model or the training run it is loaded into."""


class UnreadableFileError(ValueError):
    """A file cannot be read back: it is empty, truncated, corrupt or incomplete.

    Attributes:
        path: the file.
    """

    def __init__(self, message: str, path: Path) -> None:
        super().__init__(message)
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:  # picklable: a worker process's error reaches the caller as it is
        return type(self), (str(self), self.path), self.__dict__


class FileWriteError(OSError, ValueError):
    """A file could not be written (read-only directory, disk full, ...).

    An ``OSError``, since the operating system refused; also a ``ValueError``, so that the
    ``smcd-rl`` command reports it in one line like any other problem with its options.

    Attributes:
        path: the file that was to be written.
    """

    def __init__(self, message: str, path: Path, errno_: int | None = None) -> None:
        super().__init__(message)
        self.path = path
        self.errno = errno_

    def __reduce__(self) -> tuple[Any, ...]:  # picklable, as UnreadableFileError
        return type(self), (str(self), self.path, self.errno), self.__dict__


def load_file(
    path: str | os.PathLike[str],
    *,
    what: str,
    expect_format: str | None = None,
    expect_keys: Iterable[str] = (),
    fix: str | None = None,
) -> dict[str, Any]:
    """Read a dict written by :func:`save_file`, or raise an error that names the file and the fix.

    Args:
        path: the file.
        what: what the file is, for messages (``"model checkpoint"``).
        expect_format: the dict's ``"format"`` entry must be this; another value (another kind of
            smcd_rl file) raises :class:`CheckpointMismatchError`.
        expect_keys: entries the dict must have.
        fix: what to do about an unreadable file (default: delete it and rerun).

    Returns:
        The dict, with tensors on the CPU.

    Raises:
        FileNotFoundError: there is no file at ``path``.
        UnreadableFileError: the file is empty, truncated, corrupt, not a dict or lacks ``expect_keys``.
        CheckpointMismatchError: the file is another kind of smcd_rl file than ``expect_format``.
    """
    path = Path(path)
    fix = fix or "delete it and rerun the command that wrote it"
    if not path.exists():
        raise FileNotFoundError(f"no {what} at {path}")
    if not path.is_file():
        raise UnreadableFileError(f"{what} {path} is not a file; pass the path of a file", path)
    try:
        if path.stat().st_size == 0:
            raise UnreadableFileError(f"{what} {path} is empty (its write was interrupted?); {fix}", path)
        _check_records(path, what=what, fix=fix)
        # weights_only=False: the files hold configs, histories and generator states besides tensors,
        # and are the project's own (never load one from a source you do not trust).
        loaded = torch.load(path, map_location="cpu", weights_only=False)
    except UnreadableFileError:
        raise
    except PermissionError as err:  # the file is there but the system will not let us read it
        raise UnreadableFileError(
            f"cannot read {what} {path}: {err.strerror or err}; check its permissions", path
        ) from err
    # A damaged file can raise almost anything: EOFError, KeyError, RuntimeError from the zip reader,
    # even OSError (EINVAL) when a truncated archive seeks past its end.
    except Exception as err:
        detail = str(err).strip().splitlines()[0] if str(err).strip() else "no detail"
        raise UnreadableFileError(
            f"{what} {path} is corrupt or truncated ({type(err).__name__}: {detail}); {fix}", path
        ) from err
    if not isinstance(loaded, Mapping):
        raise UnreadableFileError(f"{what} {path} holds a {type(loaded).__name__}, not a {what}; {fix}", path)
    if expect_format is not None and loaded.get("format") != expect_format:
        found = loaded.get("format")
        kind = f"a file of format {found!r}" if found is not None else "a file without a format entry"
        raise CheckpointMismatchError(
            f"{path} is not a {what}: it is {kind}, expected {expect_format!r}; pass the right file, or delete it "
            "and rerun to write a new one"
        )
    missing = [key for key in expect_keys if key not in loaded]
    if missing:
        raise UnreadableFileError(f"{what} {path} is incomplete: it has no {missing} entries; {fix}", path)
    return dict(loaded)


def _check_records(path: Path, *, what: str, fix: str) -> None:
    """Raise :class:`UnreadableFileError` if the zip archive ``torch.save`` wrote is damaged.

    ``torch.load`` does not check the checksums ``torch.save`` writes, so a flipped bit in a tensor
    would load as a wrong number, and one in the pickled dict as a missing entry (``KeyError``
    later). A record must match its CRC-32, and its local header the archive's directory (a flipped
    bit in a header's name length shifts where ``torch.load`` reads the data from, which no CRC
    covers); no record may be marked a directory (``torch.save`` writes none, and ``torch.load``
    reads such a record's tensor as uninitialised memory). A file that is not a zip archive is
    left to ``torch.load`` to judge.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError):
        return
    with archive:
        try:
            bad = archive.testzip()  # reads each record through its local header
        except Exception as err:  # a header that does not parse: BadZipFile, UnicodeDecodeError, ...
            raise UnreadableFileError(
                f"{what} {path} is corrupt: a record's header does not match the archive's directory "
                f"({type(err).__name__}); {fix}",
                path,
            ) from err
        if bad is None:
            bad = next((i.filename for i in archive.infolist() if i.is_dir() or i.external_attr & _DIRECTORY), None)
    if bad is not None:
        raise UnreadableFileError(
            f"{what} {path} is corrupt: its record {bad!r} does not match its checksum or header (a flipped bit "
            f"on the disk?); {fix}",
            path,
        )


#: The MS-DOS "directory" bit of a zip record's external attributes.
_DIRECTORY = 0x10


def save_file(obj: Mapping[str, Any], path: str | os.PathLike[str], *, what: str = "file") -> None:
    """Write ``obj`` to ``path`` atomically with :func:`torch.save`; :func:`load_file` reads it back.

    The parent directories are created. The data goes to a temporary file of a unique name in the
    same directory, reaches the disk, then replaces ``path`` in one step.

    Args:
        obj: the dict to save.
        path: the file to write (replaced if it exists).
        what: what the file is, for messages.

    Raises:
        FileWriteError: the directory cannot be created or written (read-only, disk full, ...);
            ``path`` is then unchanged and no temporary file is left behind.
    """
    write_atomic(path, lambda handle: torch.save(dict(obj), handle), what=what)


def write_atomic(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object], *, what: str = "file") -> None:
    """Write a file of any format atomically: ``write(handle)`` fills a temporary file that then replaces ``path``.

    The parent directories are created. ``write`` gets a binary handle open on a new temporary file
    of a unique name in the same directory; when it returns, the data reaches the disk and replaces
    ``path`` in one step. If anything fails, ``path`` is unchanged and the temporary file is removed.

    Args:
        path: the file to write (replaced if it exists).
        write: writes the file's bytes to the handle it is given (e.g. ``np.savez_compressed``).
        what: what the file is, for messages.

    Raises:
        FileWriteError: the directory cannot be created or written (read-only, disk full, ``path``
            is a directory, ...), or ``write`` raised an ``OSError`` or ``RuntimeError``. Other
            errors of ``write`` propagate as they are, also with ``path`` unchanged.

    Example:
        >>> import tempfile
        >>> from smcd_rl.files import write_atomic
        >>> path = tempfile.mkdtemp() + "/notes.txt"
        >>> write_atomic(path, lambda handle: handle.write(b"hello"), what="notes")
        >>> open(path).read()
        'hello'
    """
    path = Path(path)
    directory = path.parent
    tmp: Path | None = None
    try:
        directory.mkdir(parents=True, exist_ok=True)
        tmp, handle = _create_unique(directory, path.name)
        with handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())  # on disk before the rename, so a crash never leaves an empty file
        os.replace(tmp, path)
    except BaseException as err:  # also KeyboardInterrupt: never leave a stray temporary file
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()
        if isinstance(err, (OSError, RuntimeError)):  # RuntimeError: torch's own writer errors
            cause = _os_error(err)
            code = cause.errno if cause is not None else None
            problem = _write_problem(err, path, lambda: _size_of(write))
            raise FileWriteError(f"cannot write {what} {path}: {problem}", path, code) from err
        raise


def write_text(path: str | os.PathLike[str], text: str, *, what: str = "file") -> None:
    """Write ``text`` (UTF-8) atomically through :func:`write_atomic`: a full disk leaves no half file.

    Example:
        >>> import tempfile
        >>> from smcd_rl.files import write_text
        >>> path = Path(tempfile.mkdtemp()) / "notes.md"
        >>> write_text(path, "# notes\\n", what="notes")
        >>> path.read_text()
        '# notes\\n'
    """
    data = text.encode("utf-8")
    write_atomic(path, lambda handle: handle.write(data), what=what)


def _create_unique(directory: Path, name: str) -> tuple[Path, Any]:
    """Create and open a new temporary file for ``name`` in ``directory``, a name no other writer uses.

    Not ``tempfile.mkstemp``: it creates files readable by their owner only, and the replaced file
    would lose the permissions the umask gives every other file the project writes.
    """
    while True:
        tmp = directory / f".{name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
        try:
            raw = _TempFile(tmp, "xb")  # O_CREAT | O_EXCL, permissions 0o666 less the umask
        except FileExistsError:  # astronomically unlikely; draw another name
            continue
        return tmp, io.BufferedWriter(raw)


class _TempFile(io.FileIO):
    """The raw temporary file :func:`write_atomic` fills (a class of its own so that tests can make its disk full)."""


def _size_of(write: Callable[[IO[bytes]], object]) -> int | None:
    """How many bytes ``write`` writes, measured in memory (after a full disk: the space the file needs)."""
    sink = io.BytesIO()
    try:
        write(sink)
    except Exception:  # the writer cannot write twice, or needs a real file: the size stays unknown
        return None
    return sink.getbuffer().nbytes


def _format_bytes(size: int) -> str:
    """``size`` bytes in words: ``"512 bytes"``, ``"3.4 kB"``, ``"1.2 MB"``, ``"2.0 GB"`` (powers of 1000)."""
    if size < 1000:
        return f"{size} bytes"
    for unit, scale in (("kB", 1e3), ("MB", 1e6)):
        if size < 1000 * scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size / 1e9:.1f} GB"


def _os_error(err: BaseException) -> OSError | None:
    """The OSError behind ``err``: itself, or the one torch's writer met (its RuntimeError hides the errno)."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        if isinstance(current, OSError):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def _write_problem(err: BaseException, path: Path, size: Callable[[], int | None] = lambda: None) -> str:
    """Why writing ``path`` failed, and what to do about it, in words (``size``: the file's size, if it can be told)."""
    directory = path.parent
    cause = _os_error(err)
    code = cause.errno if cause is not None else None
    if code == errno.EISDIR or (code is None and path.is_dir()):
        return f"{path} is a directory; pass the path of a file, or remove the directory"
    if code in (errno.EACCES, errno.EPERM, errno.EROFS) or (code is None and not os.access(directory, os.W_OK)):
        return f"the directory {directory} is read-only or not writable; make it writable or write to another directory"
    if code in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
        full = "no space left on the disk of" if code == errno.ENOSPC else "disk quota exceeded for"
        needed = size()
        if needed:
            return (
                f"{full} {directory}: the file needs {_format_bytes(needed)}; free at least that much space "
                "or write to another directory"
            )
        return f"{full} {directory}; free some space or write to another directory"
    if code in (errno.ENOTDIR, errno.EEXIST) or (code is None and directory.exists() and not directory.is_dir()):
        return f"{directory} (or a folder above it) is a file, not a directory; remove it or write elsewhere"
    reason = cause.strerror if cause is not None and cause.strerror else str(err).strip().splitlines()[0]
    return f"{reason} (in {directory}); check the directory, or write to another one"
