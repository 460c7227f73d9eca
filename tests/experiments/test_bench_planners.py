"""``smcd-rl bench planners`` at tiny sizes: it runs, prints ratios, writes files, JSON parses.

No timing is asserted: the numbers depend on the machine and its load.
"""

import csv
import json

import pytest

from smcd_rl import cli
from tests.experiments.test_stages import planned_stages

TINY = [
    "--observation",
    "4",
    "--action",
    "2",
    "--hidden",
    "16",
    "16",
    "--horizon",
    "3",
    "--candidates",
    "20",
    "--top-k",
    "4",
    "--steps",
    "2",
    "--repeats",
    "3",
    "--warmup",
    "1",
    "--device",
    "cpu",
]
NAMES = {
    "torchrl CEMPlanner",
    "ours: CEM + model_reward_objective",
    "ours: CEM + plain objective",
    "floor: bare forwards",
}


def test_bench_planners_prints_ratios_and_writes_files(tmp_path, capsys) -> None:
    out = tmp_path / "bench"
    assert cli.main(["bench", "planners", "--out", str(out), *TINY]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "bench") == ["time"]  # the contenders are timed interleaved: one stage
    assert "torch_threads=" in printed and "torchrl / ours =" in printed and "ours / floor" in printed
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {r["planner"] for r in rows} == NAMES
    assert all(float(r["median_ms"]) > 0 and int(r["repeats"]) == 3 for r in rows)
    payload = json.loads((out / "results.json").read_text())
    assert set(payload["ratios"]) >= {"torchrl_over_ours", "ours_over_floor"}
    assert payload["model"]["forwards_per_plan"] == 6


def test_bench_planners_json_flag_prints_only_json(tmp_path, capsys) -> None:
    assert (
        cli.main(
            ["bench", "planners", "--out", str(tmp_path), *TINY, "--json", "--adaptation", "smcd", "--particles", "5"]
        )
        == 0
    )
    payload = json.loads(capsys.readouterr().out)
    assert {r["planner"] for r in payload["results"]} == NAMES
    assert payload["machine"]["torch_threads"] >= 1 and payload["device"] == "cpu"
    assert isinstance(payload["goals"]["ours_at_least_2x_faster_than_torchrl"], bool)


def test_bench_planners_help_and_bad_options(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["bench", "planners", "--help"])
    assert exit_info.value.code == 0 and "--candidates" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["bench"])  # a group needs its sub-command


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--top-k", "1"], "--top-k must be >= 2, got 1"),
        (["--top-k", "21"], "--top-k must be at most --candidates (20), got 21"),
        (["--hidden", "0"], "--hidden must be >= 1, got 0"),
        (["--adaptation", "gd"], "--adaptation: unknown value 'gd'; choose from ['none', 'smcd']"),
        (["--repeats", "0"], "--repeats must be >= 1"),
        (["--seed", "-3"], "--seed must be >= 0"),
    ],
)
def test_bench_planners_refuses_bad_options_before_any_work(tmp_path, capsys, option, message) -> None:
    """Validation runs before the model is built or anything timed: not even the output directory is made."""
    out = tmp_path / "bench"
    assert cli.main(["bench", "planners", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
