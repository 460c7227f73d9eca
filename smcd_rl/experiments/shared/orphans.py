"""Child processes that end when the run that started them dies, however it dies.

A worker process of ``--workers`` waits for jobs on a queue, and Ray's local helpers (its control
store and node manager) serve the driver that started them: after ``kill -9`` of the run, both
would wait forever, holding hundreds of MB each. Ctrl-C and exceptions already stop them; these
two cover the deaths no handler runs for:

* :func:`exit_with_parent`, called in a worker, ends the worker as soon as its parent is gone.
* :func:`reaped`, around the code that starts helper processes, starts a watchdog that kills
  them if this process dies before the block ends. The watchdog holds the read end of a pipe whose
  write end only this process holds: the kernel closes it when this process dies, so the
  watchdog wakes at once, with no polling and whatever killed the process.

Example:
    >>> import os
    >>> with reaped(lambda: []) as watched:  # no helper started: nothing to watch
    ...     watched()
    []
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["exit_with_parent", "reaped", "descendants"]

#: How often a worker checks for its parent (seconds).
POLL_SECONDS = 0.5

# The watchdog: wait for the pipe to close; "done" first means a clean end, anything else a death.
_WATCHDOG = """
import os, signal, sys
said = sys.stdin.read()
if said.strip() != "done":
    for pid in map(int, sys.argv[1:]):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
"""


def exit_with_parent(parent: int) -> None:
    """End this process (exit code 1) once process ``parent`` is gone; a daemon thread watches.

    A process whose parent dies is handed to another parent, so a changed parent id means the
    original one died. Call it first thing in a worker, with the parent's id as the parent saw it.
    """

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def descendants(pid: int | None = None) -> list[int]:
    """The ids of every process below ``pid`` (default: this one), read from ``/proc`` (empty elsewhere)."""
    root = os.getpid() if pid is None else pid
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").glob("[0-9]*/stat"):
        try:
            # The command name (field 2) may hold spaces and parentheses: split after its last ")".
            fields = entry.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # the process ended while being read
        children.setdefault(int(fields[1]), []).append(int(entry.parent.name))
    found, todo = [], [root]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


@contextlib.contextmanager
def reaped(started: Callable[[], list[int]] = descendants) -> Iterator[Callable[[], list[int]]]:
    """Kill the processes ``started()`` names if this process dies inside the block.

    Yields a function to call once the helpers are running: it reads their ids with ``started``
    (by default every process below this one) and hands them to the watchdog, and returns them.
    A block that ends, normally or by an exception, tells the watchdog so and it kills nothing:
    the block's own clean-up (``ray.shutdown()``) stops the helpers then.
    """
    read, write = os.pipe()
    watchdog: subprocess.Popen[bytes] | None = None

    def watch() -> list[int]:
        nonlocal watchdog
        pids = started()
        if pids and watchdog is None:
            watchdog = subprocess.Popen(
                [sys.executable, "-c", _WATCHDOG, *map(str, pids)],
                stdin=read,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,  # out of this process group: a Ctrl-C does not reach it
                pass_fds=(),
            )
        return pids

    try:
        yield watch
    finally:
        try:
            os.write(write, b"done")
        finally:
            os.close(write)
            os.close(read)
            if watchdog is not None:
                watchdog.wait()
