"""The overall progress line: stage k of n, elapsed, and a time left scaled by the run's own speed."""

import io
import re

import pytest

from smcd_rl.experiments.shared import stages
from smcd_rl.experiments.shared.stages import StagePlan

#: One stage line: command, k (or the first and last of stages run side by side), n (if planned),
#: stage, and the times.
STAGE_LINE = re.compile(r"(\S+) \[(\d+)(?:-(\d+))?(?:/(\d+))?\] (.+?) \| (\S.* elapsed.*)")


def planned_stages(err: str, command: str) -> list[str]:
    """The stages ``command`` printed on ``err``, checked: each ``[k/n]`` (``[k-m/n]`` for stages side by
    side in workers) with one n, the stages counting up to n, time left from the 2nd line on.

    A tiny run's stages take well under :data:`~smcd_rl.experiments.shared.stages.RESUMED_SECONDS`, so a
    test that wants the time left sets that to 0 first (``monkeypatch``).
    """
    lines = [m for line in err.splitlines() if (m := STAGE_LINE.fullmatch(line)) and m[1] == command]
    assert lines, err
    assert {m[4] for m in lines} == {lines[0][4]} and lines[0][4] is not None, [m[0] for m in lines]
    counted = [k for m in lines for k in range(int(m[2]), int(m[3] or m[2]) + 1)]
    assert counted == list(range(1, int(lines[0][4]) + 1)), [m[0] for m in lines]
    assert all(", about " in m[6] and m[6].endswith(" left") for m in lines[1:]), [m[0] for m in lines]
    return [name for m in lines for name in _side_by_side(m[5])]


def _side_by_side(stage: str) -> list[str]:
    """A line's stages: ``"tune M, R in 2 workers"`` is ``["tune M", "tune R"]``, any other line one stage."""
    found = re.fullmatch(r"(.+) in \d+ workers", stage)
    if found is None:
        return [stage]
    names = found[1].split(", ")
    kind = names[0].split(" ")[0]
    return [name if name.startswith(kind) else f"{kind} {name}" for name in names]


class Clock:
    """A perf_counter the test advances by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(stages.time, "perf_counter", clock)
    return clock


def test_time_left_is_the_remaining_cost_at_each_kinds_measured_speed(clock: Clock) -> None:
    """Each stage costs its planned cost plus STAGE_OVERHEAD (0.5); a kind run already has its own speed,
    one not run yet the speed of all finished stages together."""
    costs = {"train": 1.5, "tune M": 0.5, "tune R": 1.5, "evaluate": 3.5}
    plan = StagePlan("run", costs, stream=io.StringIO())
    with plan.stage("train"):
        clock.now += 20.0  # 2 units in 20 s: 10 s per unit
    with plan.stage("tune M"):
        clock.now += 5.0  # tune: 1 unit in 5 s, twice train's speed
    with plan.stage("tune R"):
        clock.now += 10.0
    with plan.stage("evaluate"):
        pass
    lines = plan.stream.getvalue().splitlines()
    assert lines[0] == "run [1/4] train | 0 s elapsed"  # nothing timed yet: no estimate
    assert lines[1] == "run [2/4] tune M | 20 s elapsed, about 1 min 10 s left"  # 7 units at 10 s
    # tune R at tune's 5 s per unit (10 s) and evaluate at the pooled 25 s / 3 units (33 s)
    assert lines[2] == "run [3/4] tune R | 25 s elapsed, about 43 s left"
    assert lines[3] == "run [4/4] evaluate | 35 s elapsed, about 28 s left"  # 4 units at 35 s / 5 units


def test_a_tiny_run_never_extrapolates_its_overhead_to_hours(clock: Clock) -> None:
    """A run whose planned work is next to nothing (tiny settings, or workers whose start dominates) took
    3 s for its first stage: the rest is estimated from that at the stages' overhead, not at 3 s per
    millionth of a unit."""
    plan = StagePlan(
        "run", {"train": 1e-6, "tune": 0.3, **{f"evaluate {i}": 0.2 for i in range(10)}}, stream=io.StringIO()
    )
    with plan.stage("train"):
        clock.now += 3.0
    with plan.stage("tune"):
        pass
    left = plan.stream.getvalue().splitlines()[-1].split("about ")[1]
    assert " h " not in left and left.endswith(" s left") and int(left.split()[0]) < 120, left


def test_resumed_stages_do_not_count_as_fast_work(clock: Clock) -> None:
    plan = StagePlan("run", {"train": 5.0, "tune": 1.0, "evaluate": 1.0}, stream=io.StringIO())
    with plan.stage("train"):
        clock.now += 0.1  # resumed from its checkpoint: says nothing about speed
    with plan.stage("tune"):
        clock.now += 30.0
    with plan.stage("evaluate"):
        pass
    last = plan.stream.getvalue().splitlines()[-1]
    assert last.endswith("about 30 s left"), last  # 20 s per unit (1.5) from tune alone, not 30.1 / 7.5


def test_an_unplanned_stage_still_prints_and_quiet_prints_nothing(clock: Clock) -> None:
    plan = StagePlan("run", {"train": 1.0}, stream=io.StringIO())
    with plan.stage("train"):
        clock.now += 65.0
    with plan.stage("extra"):
        pass
    assert plan.stream.getvalue().splitlines()[-1] == "run [2] extra | 1 min 5 s elapsed, about 0 s left"
    quiet = StagePlan("run", {"train": 1.0}, stream=io.StringIO(), quiet=True)
    with quiet.stage("train"):
        pass
    assert quiet.stream.getvalue() == ""


def test_an_experiment_prints_its_stages_in_plan_order(tmp_path, capsys) -> None:
    from smcd_rl import cli

    options = ["--tasks", "2", "--episodes", "2", "--steps", "2", "--hidden", "8", "--epochs", "1", "--trials", "2"]
    options += ["--burn-in", "1", "--horizons", "1", "--methods", "M+N", "LV+N", "--lv-epochs", "1"]
    assert cli.main(["two-link", "--out", str(tmp_path / "run"), *options]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if re.match(r"run \[\d", line)]
    assert [line.split(" | ")[0] for line in lines] == [
        "run [1/4] train",
        "run [2/4] train latent",
        "run [3/4] evaluate M+N",
        "run [4/4] evaluate LV+N",
    ]


def test_a_report_rounds_its_wall_time_into_the_next_minute(tmp_path) -> None:
    """599.6 s once printed as "9 min 60 s": the seconds were rounded after the minutes were taken."""
    from smcd_rl.experiments.shared.report import write_report

    machine = {"processor": "cpu", "cpus": 2, "torch_threads": 1, "torch": "2"}
    result = {"experiment": "x", "config": {}, "seconds": {"total": 599.6}, "machine": machine}
    write_report(tmp_path / "report.md", result, {}, [])
    assert "Wall time 10 min 0 s on cpu" in (tmp_path / "report.md").read_text()


@pytest.mark.parametrize("cost", [-0.5, float("nan"), float("inf"), "1"])
def test_a_cost_that_is_not_a_finite_number_at_least_0_is_refused_and_the_plan_kept(cost: object) -> None:
    """A negative cost divided the time left by zero, NaN and inf crashed the progress line."""
    plan = StagePlan("demo", {"a": 1.0}, stream=io.StringIO())
    with pytest.raises(ValueError, match=r"stage 'b' has a planned cost of .*; a cost is a finite number >= 0"):
        plan.plan({"b": cost})  # type: ignore[dict-item]
    assert plan.costs == {"a": 1.0}
    with pytest.raises(ValueError, match="stage 'b'"):
        StagePlan("demo", {"a": 1.0, "b": cost}, stream=io.StringIO())  # type: ignore[dict-item]
