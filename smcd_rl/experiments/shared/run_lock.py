"""One run at a time per output directory: ``flock`` on ``<out>/.lock``.

Two runs writing into one ``--out`` would mix their files, and the first would report the
second's; the second is refused with the first's process id and command line.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp())
    >>> handle = lock_out(out)
    >>> try:
    ...     lock_out(out)
    ... except ValueError as err:
    ...     print(str(err).split(" (")[0])
    --out ... is in use by another run
    >>> release(handle)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import IO

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: runs are not locked
    fcntl = None  # type: ignore[assignment]

__all__ = ["LOCK", "lock_out", "release"]


#: The lock file of a run's output directory; it holds the running process's id and command line.
LOCK = ".lock"


def lock_out(out: Path) -> IO[str] | None:
    """Take ``out``'s lock (``flock`` on ``out/.lock``), or refuse: another run is writing into ``out``.

    The operating system releases an ``flock`` when its process ends, however it ends, so a run
    that crashed never leaves ``out`` locked; its stale ``.lock`` file is simply locked again.
    Returns the open lock file (``None`` where there is no ``fcntl``, on Windows: no lock).
    """
    if fcntl is None:  # pragma: no cover - Windows
        return None
    path = out / LOCK
    while True:
        try:
            handle = open(path, "a+")  # not "w": the holder's process id stays readable until we hold the lock
        except OSError as err:
            raise ValueError(
                f"--out {out}: cannot write in the output directory ({err.strerror}); make it writable or pick another"
            ) from err
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.seek(0)
            holder = handle.read().strip()
            handle.close()
            raise ValueError(
                f"--out {out} is in use by another run ({f'process {holder}' if holder else 'process unknown'}); "
                "wait for it to finish, or give this run another --out"
            ) from None
        try:  # the run before us may have removed the file after we opened it: lock the one that is there now
            same = os.path.samestat(os.stat(path), os.fstat(handle.fileno()))
        except FileNotFoundError:
            same = False
        if same:
            break
        handle.close()
    try:  # who holds it, for the message of a run refused
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}: {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}\n")
        handle.flush()
    except OSError as err:  # a full disk: nothing of this run could be saved either
        release(handle)
        raise ValueError(
            f"--out {out}: cannot write in the output directory ({err.strerror}); free some space or pick another"
        ) from err
    return handle


def release(handle: IO[str] | None) -> None:
    """Remove the lock file while still holding its lock, then let it go (see :func:`lock_out`)."""
    if handle is None:  # pragma: no cover - Windows
        return
    try:
        os.unlink(handle.name)
    except OSError:
        pass
    handle.close()
