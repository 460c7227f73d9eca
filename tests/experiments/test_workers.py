"""--workers: independent methods in worker processes, the same results, Ctrl-C stops them all."""

from __future__ import annotations

import csv
import functools
import multiprocessing
import time
from pathlib import Path

import pytest
import torch

import smcd_rl.files
from smcd_rl import cli
from smcd_rl.experiments.shared.workers import AUTO_MIN_SECONDS, auto_workers, computed, map_jobs
from tests.experiments.test_two_link_experiment import TINY

METHODS = ["--methods", "M+N", "M+G", "M+S", "R+S", "O+P"]


@pytest.mark.slow
def test_two_workers_give_the_same_files_as_one(tmp_path: Path) -> None:
    """The methods' results do not depend on which process ran them, or in what order."""
    for workers in ("1", "2"):
        assert cli.main(["two-link", "--out", str(tmp_path / workers), *TINY, *METHODS, "--workers", workers]) == 0
    for name in ("trials.csv", "comparisons.csv"):
        assert (tmp_path / "1" / name).read_bytes() == (tmp_path / "2" / name).read_bytes(), name
    # results.csv also holds each method's measured time per observation, which no two runs repeat:
    # every other column must be the same to the last byte.
    untimed = [_without_times(tmp_path / workers / "results.csv") for workers in ("1", "2")]
    assert untimed[0] == untimed[1] and len(untimed[0]) > 1
    # The workers trained M and R to the checkpoints this process then resumed from: one each. (A
    # worker that shared the caller's tensors would have trained its model in place, and the
    # caller would have trained it again under another name.)
    assert sorted(p.name.split("-")[0] for p in (tmp_path / "2").glob("*.ckpt")) == ["reptile", "train"]


def _without_times(path: Path) -> list[list[str]]:
    """The rows of a results.csv without its ``ms_per_observation`` column."""
    rows = list(csv.reader(path.open(newline="")))
    timed = rows[0].index("ms_per_observation")
    return [row[:timed] + row[timed + 1 :] for row in rows]


@pytest.mark.slow
def test_a_rerun_with_other_workers_reuses_every_finished_method(tmp_path: Path, capsys) -> None:
    """--workers is not a setting of the results: the cache and the report's fingerprint ignore it."""
    out = str(tmp_path / "run")
    assert cli.main(["two-link", "--out", out, *TINY, *METHODS, "--workers", "1"]) == 0
    first = (tmp_path / "run" / "report.md").read_text().split("fingerprint `")[1][:12]
    capsys.readouterr()
    assert cli.main(["two-link", "--out", out, *TINY, *METHODS, "--workers", "3"]) == 0
    assert (tmp_path / "run" / "report.md").read_text().split("fingerprint `")[1][:12] == first
    assert " in 3 workers" not in capsys.readouterr().err  # nothing left to evaluate: no workers started


def test_ctrl_c_stops_every_worker_and_keeps_what_finished() -> None:
    """A Ctrl-C in the parent (here: as the first result arrives) ends the slow job at once, not after 60 s."""
    kept = []

    def interrupt(name: str, result: object) -> None:
        kept.append(name)
        raise KeyboardInterrupt

    jobs = {"fast": functools.partial(time.sleep, 0), "slow": functools.partial(time.sleep, 60)}
    started = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        map_jobs(jobs, computed, workers=2, on_result=interrupt)
    assert kept == ["fast"]
    assert time.perf_counter() - started < 50  # the slow job would have taken 60 s
    deadline = time.monotonic() + 10
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not multiprocessing.active_children()


def test_a_job_that_cannot_be_sent_to_a_worker_is_named() -> None:
    with pytest.raises(TypeError, match="job 'local' cannot be sent to a worker process"):
        map_jobs({"local": lambda: 1, "other": functools.partial(int, "2")}, computed, workers=2)


def test_one_process_runs_the_jobs_in_order_without_sending_them() -> None:
    order = []
    result = map_jobs({"b": lambda: 2, "a": lambda: 1}, computed, workers=1, on_result=lambda n, r: order.append(n))
    assert result == {"b": 2, "a": 1} and order == ["b", "a"]


def test_auto_starts_workers_only_for_work_long_enough_to_repay_them() -> None:
    assert auto_workers(jobs=4, threads=1, planned_seconds=AUTO_MIN_SECONDS / 2) == 1
    assert auto_workers(jobs=4, threads=0, planned_seconds=1e6) == 1  # torch already uses every core
    assert auto_workers(jobs=1, threads=1, planned_seconds=1e6) == 1


def _fails_to_read(path: str) -> None:
    smcd_rl.files.load_file(path, what="checkpoint")


def test_a_workers_error_reaches_the_caller_as_raised_and_names_the_job(tmp_path: Path) -> None:
    """The project's file errors take a path besides their message, so a worker could not send them
    back: the caller got "a process in the pool was terminated abruptly" instead of the fix."""
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"garbage")
    jobs = {"reader": functools.partial(_fails_to_read, str(bad)), "other": functools.partial(int, "1")}
    with pytest.raises(smcd_rl.files.UnreadableFileError, match="is corrupt or truncated.*delete it") as raised:
        map_jobs(jobs, computed, workers=2)
    assert raised.value.path == bad and "job 'reader'" in "".join(raised.value.__notes__)


def test_each_job_runs_on_its_own_copy_of_its_inputs_in_one_process_as_in_workers() -> None:
    """A job that changes its input in place changed the next job's and the caller's in one process
    (the result depended on what ran before it), and nothing in worker processes."""
    state = torch.zeros(3)
    job = functools.partial(torch.Tensor.add_, state, 1.0)
    for workers in (1, 2):
        results = map_jobs({"a": job, "b": job}, computed, workers=workers)
        assert [r.tolist() for r in results.values()] == [[1.0] * 3] * 2, workers
    assert state.tolist() == [0.0] * 3


def test_a_failed_job_stops_the_pools_workers_and_no_other_process() -> None:
    """Stopping the workers after a failure terminated every child process of the caller."""
    other = multiprocessing.get_context("spawn").Process(target=time.sleep, args=(30,))
    other.start()
    try:
        with pytest.raises(ValueError, match="invalid literal"):
            map_jobs(
                {"bad": functools.partial(int, "x"), "slow": functools.partial(time.sleep, 5)}, computed, workers=2
            )
        other.join(timeout=3)  # time for a SIGTERM to land
        assert other.is_alive()
    finally:
        other.terminate()
        other.join()
