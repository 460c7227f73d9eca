"""Keep freed memory in the process: the commands' large temporaries then cost no page faults.

torch allocates CPU tensors with the C library's ``malloc``. glibc serves a block above its mmap
threshold (at most 32 MB by default) from fresh pages of the kernel and returns them on ``free``,
and it trims the top of its heap once 128 KB lie free there. An SMCD update or a gradient step
over many streams allocates and frees tens of MB per call, so each call's temporaries come back
as new pages that the kernel must zero: in ``smcd-rl two-link`` 560 million page faults and
nearly half of the CPU time went to the kernel. :func:`keep_freed_memory` raises both
thresholds, so freed blocks are kept for the next call: an SMCD filter run on the two-link
network takes about 0.6 of the time.

It changes only where memory comes from, never a result, and keeps at most 1 GB of freed memory
in the process. The commands call it at start, and so do their worker processes; importing
``smcd_rl`` does not, since the setting belongs to the process that chooses it: a script of
your own that tunes, calibrates or filters calls it once at its start (``smcd_rl.tune`` on a
2 x 512 network ran 1.5x faster with it: ``scripts/bench_tune.py``).

Example:
    >>> import smcd_rl
    >>> smcd_rl.keep_freed_memory() in (True, False)  # True with glibc (Linux), False elsewhere
    True
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["keep_freed_memory", "KEPT_BYTES"]

#: Blocks up to this size come from the heap, and up to this much free memory stays at its top.
KEPT_BYTES = 1 << 30

_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Tell glibc's ``malloc`` to keep freed memory (up to :data:`KEPT_BYTES`); ``False`` where there is no glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and other C libraries have no mallopt
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, KEPT_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, KEPT_BYTES))
