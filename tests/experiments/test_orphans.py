"""Worker processes and Ray's helpers end when the run that started them is killed, even by SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from smcd_rl.experiments.shared.orphans import descendants

#: How long a child may take to notice that its parent died (the workers poll every 0.5 s).
GRACE_SECONDS = 20.0


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except OSError:
        return False


def _start(script: str) -> tuple[subprocess.Popen[str], list[int]]:
    """Run ``script`` in a fresh interpreter until it prints "ready"; returns it and the processes below it."""
    parent = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script)], stdout=subprocess.PIPE, text=True, cwd=os.getcwd()
    )
    assert parent.stdout is not None
    line = parent.stdout.readline()
    assert line.strip() == "ready", line
    children = descendants(parent.pid)
    assert children, "the script started no child process"
    return parent, children


def _wait_gone(pids: list[int]) -> list[int]:
    deadline = time.monotonic() + GRACE_SECONDS
    while time.monotonic() < deadline and any(_alive(pid) for pid in pids):
        time.sleep(0.2)
    return [pid for pid in pids if _alive(pid)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_their_parent_is_killed() -> None:
    """Before, the workers of a run killed with SIGKILL blocked on their job queue forever (~330 MB each)."""
    parent, workers = _start(
        """
        import functools, threading, time
        from smcd_rl.experiments.shared.workers import computed, map_jobs
        jobs = {name: functools.partial(time.sleep, 120) for name in "ab"}
        threading.Timer(5.0, lambda: print("ready", flush=True)).start()  # the workers have started by then
        map_jobs(jobs, computed, workers=2)
        """
    )
    try:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        assert _wait_gone(workers) == []
    finally:
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_reaped_helpers_die_with_a_killed_parent_and_live_on_after_a_clean_end() -> None:
    script = """
        import subprocess, sys, time
        from smcd_rl.experiments.shared.orphans import reaped
        with reaped() as watch:
            helper = subprocess.Popen(["sleep", "120"])
            watch()
            print("ready", flush=True)
            if sys.argv[-1] == "clean":
                sys.stdin.readline()  # the test says when to end the block
            else:
                time.sleep(120)  # killed inside the block
        time.sleep(120)
        """
    killed, helpers = _start(script)
    try:
        helpers = [pid for pid in helpers if pid != killed.pid]
        killed.send_signal(signal.SIGKILL)
        killed.wait()
        left = _wait_gone(helpers)
        assert left == [], [open(f"/proc/{pid}/cmdline").read() for pid in left]
    finally:
        for pid in helpers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)

    # A block that ends normally leaves the helpers to their owner (ray.shutdown() stops Ray's).
    clean = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(script), "clean"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert clean.stdout is not None and clean.stdin is not None
    assert clean.stdout.readline().strip() == "ready"
    helper = [pid for pid in descendants(clean.pid) if "sleep" in open(f"/proc/{pid}/cmdline").read()]
    try:
        clean.stdin.write("\n")
        clean.stdin.flush()
        time.sleep(1.0)
        clean.send_signal(signal.SIGKILL)
        clean.wait()
        time.sleep(1.0)
        assert helper and all(_alive(pid) for pid in helper)
    finally:
        for pid in helper:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_sweep_leaves_no_ray_process() -> None:
    """The sweep's local Ray: before, two of its helper processes outlived a SIGKILL of the sweep."""
    pytest.importorskip("ray")
    parent, helpers = _start(
        """
        import time
        from smcd_rl.experiments.sweep.config import SweepConfig
        from smcd_rl.experiments.sweep.work import ray_session
        with ray_session(SweepConfig(cpus=1)) as ray:
            print("ready", flush=True)
            time.sleep(120)
        """
    )
    try:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        assert _wait_gone(helpers) == []
    finally:
        for pid in helpers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
