"""Independent evaluations side by side in worker processes: what ``--workers`` runs.

Each job is a method's evaluation, ``evaluate(name, factory())``, run in a process of its own
from :mod:`concurrent.futures` with a *spawn* context (a fresh interpreter: no torch or OpenMP
state forked mid-flight), with the run's torch thread count. A job's result depends only on its
inputs, never on what ran before it in the same process, so the results are bit-identical to
one process's (``--workers 1``) for the same seed and threads.

Ctrl-C stops every worker at once (they ignore SIGINT; the parent terminates them), and a
worker ends by itself when the parent dies otherwise (``kill -9``); results
that finished before it were already handed to ``on_result``, which stores them, so the rerun
resumes with the rest.

Example:
    >>> import functools
    >>> jobs = {"a": functools.partial(int, "1"), "b": functools.partial(int, "2")}
    >>> map_jobs(jobs, lambda name, value: f"{name}={value}", workers=1)
    {'a': 'a=1', 'b': 'b=2'}
"""

from __future__ import annotations

import concurrent.futures
import copy
import multiprocessing
import os
import pickle
import signal
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from tqdm.auto import tqdm

from smcd_rl.allocator import keep_freed_memory
from smcd_rl.experiments.shared.orphans import exit_with_parent

__all__ = ["map_jobs", "computed", "auto_workers", "usable_cores", "AUTO_MIN_SECONDS"]

T = TypeVar("T")

#: ``--workers 0`` (auto) starts workers only for at least this much planned evaluation (rough
#: seconds): a spawned worker takes about 3 s to import torch and receive its inputs.
AUTO_MIN_SECONDS = 20.0


def computed(name: str, result: T) -> T:
    """The ``evaluate`` of methods whose factory computes the results itself: returns them as they are.

    A module-level function, not a ``lambda``, so that it can be sent to a worker process.
    """
    return result


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity, where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return os.cpu_count() or 1


def auto_workers(jobs: int, threads: int, planned_seconds: float) -> int:
    """How many workers ``--workers 0`` uses: one per ``threads`` cores, at most one per job.

    One process when the planned work is too short to repay starting workers, or when torch
    already uses every core (``--threads 0``).

    Example:
        >>> auto_workers(jobs=5, threads=1, planned_seconds=100.0) == min(5, usable_cores())
        True
        >>> auto_workers(jobs=5, threads=1, planned_seconds=1.0)
        1
    """
    if threads <= 0 or planned_seconds < AUTO_MIN_SECONDS:
        return 1
    return max(1, min(jobs, usable_cores() // threads))


def map_jobs(
    jobs: Mapping[str, Callable[[], T]],
    call: Callable[[str, T], Any],
    *,
    workers: int,
    threads: int = 1,
    on_result: Callable[[str, Any], None] | None = None,
    progress: bool = False,
    costs: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """Run ``call(name, factory())`` for every ``name -> factory`` job, in ``workers`` processes.

    With ``workers <= 1`` (or a single job) everything runs here, in order. ``on_result(name,
    result)`` is called in this process as each job finishes, in the order they finish. With
    ``progress``, a bar here counts the finished jobs (the workers show none of their own). With
    ``costs`` (name -> expected cost), the workers take the costliest jobs first, so that they
    finish together rather than one waiting for the last long job (the results do not change).

    Raises:
        TypeError: a job cannot be sent to a worker (it holds a lambda or another local
            function); the message names the job.
    """
    results: dict[str, Any] = {}

    def finished(name: str, result: Any) -> None:
        results[name] = result
        if on_result is not None:
            on_result(name, result)

    if workers <= 1 or len(jobs) <= 1:
        for name, factory in jobs.items():
            # On a copy, as a worker would run it: a job that changes its inputs in place must not
            # change the next job's (or the caller's).
            finished(name, call(name, copy.deepcopy(factory)()))
        return results
    # Plain pickle, not multiprocessing's: torch would otherwise move every tensor into shared
    # memory, and a worker that trains a model in place would change the caller's model too.
    payloads = {}
    for name, factory in jobs.items():
        try:
            payloads[name] = pickle.dumps((call, name, factory), protocol=pickle.HIGHEST_PROTOCOL)
        except (pickle.PicklingError, AttributeError, TypeError) as err:
            raise TypeError(
                f"job {name!r} cannot be sent to a worker process ({err}); build it from module-level "
                "functions and functools.partial, or run with --workers 1"
            ) from err
    context = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(
        max_workers=min(workers, len(jobs)),
        mp_context=context,
        initializer=_start_worker,
        initargs=(threads, os.getpid()),
    )
    bar = tqdm(total=len(jobs), desc="jobs", unit="job", disable=not progress)
    try:
        order = sorted(payloads, key=lambda name: -(costs or {}).get(name, 0.0))  # stable: ties keep their order
        futures = {pool.submit(_run_job, payloads[name]): name for name in order}
        for future in concurrent.futures.as_completed(futures):
            try:
                result = future.result()
            except Exception as err:
                if hasattr(err, "add_note"):  # Python 3.11+: the traceback says which job failed
                    err.add_note(f"(in the worker running job {futures[future]!r})")
                raise
            finished(futures[future], pickle.loads(result))
            bar.update()
    except BaseException:  # Ctrl-C or a failed job: stop the others now, keep what finished
        bar.close()  # ends its line, so the message that follows stands on its own
        # The pool's own workers only: any other child process of the caller is not ours to stop.
        processes = list(getattr(pool, "_processes", None) or {})
        pool.shutdown(wait=False, cancel_futures=True)
        for child in multiprocessing.active_children():
            if child.pid in processes:
                child.terminate()
        raise
    bar.close()
    pool.shutdown()
    return {name: results[name] for name in jobs}


def _start_worker(threads: int, parent: int) -> None:
    """A worker: the run's torch threads; Ctrl-C is the parent's to handle; no progress bars of its own.

    It ends when the parent dies, also of ``kill -9``, which no handler of the parent sees.
    """
    import torch

    exit_with_parent(parent)
    keep_freed_memory()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if threads > 0:
        torch.set_num_threads(threads)
    # Two workers' progress bars on one terminal overwrite each other: the parent shows the progress.
    devnull = open(os.devnull, "w")  # noqa: SIM115 - the worker's stderr for as long as it lives
    os.dup2(devnull.fileno(), 2)


def _run_job(payload: bytes) -> bytes:
    """In a worker: unpickle the job, run it, pickle its result (each tensor a copy, not shared memory).

    An error reaches the caller as raised; one that cannot be pickled (an exception class whose
    constructor takes other arguments than its message) as a ``RuntimeError`` with its type and
    message, instead of breaking the pool.
    """
    call, name, factory = pickle.loads(payload)
    try:
        return pickle.dumps(call(name, factory()), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as err:
        try:
            pickle.loads(pickle.dumps(err))
        except Exception:
            raise RuntimeError(f"job {name!r} failed: {type(err).__name__}: {err}") from None
        raise
