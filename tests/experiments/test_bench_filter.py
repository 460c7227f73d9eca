"""``smcd-rl bench filter`` at tiny sizes: it runs, prints ratios and memory, writes files, JSON parses.

No timing is asserted: the numbers depend on the machine and its load.
"""

import csv
import json

import pytest
import torch

from smcd_rl import cli
from smcd_rl.experiments.shared import stages
from tests.experiments.test_stages import planned_stages

TINY = [
    "--particles",
    "20",
    "60",
    "--hidden",
    "32",
    "32",
    "--steps",
    "6",
    "--repeats",
    "3",
    "--warmup",
    "1",
    "--device",
    "cpu",
    "--threads",
    "1",
]


def test_bench_filter_prints_ratios_memory_and_writes_files(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(stages, "RESUMED_SECONDS", 0.0)  # tiny stages count as timed: the time left shows
    out = tmp_path / "bench"
    args = [
        "bench",
        "filter",
        "--out",
        str(out),
        *TINY,
        "--memory-particles",
        "50",
        "--memory-hidden",
        "16",
        "16",
        "16",
    ]
    assert cli.main(args) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "bench") == ["N=20", "N=60", "memory"]
    assert "torch_threads=1" in printed and "naive / ours" in printed and "extra peak memory" in printed
    assert "not measured interleaved, not measured back to back" in printed
    assert (out / "report.md").read_text() == printed  # what a docs page includes is what the command printed
    rows = list(csv.DictReader(open(out / "results.csv")))
    schedules = ["interleaved", "back to back"]
    assert [(int(r["N"]), r["regime"], r["schedule"]) for r in rows] == [
        (n, regime, schedule) for n in (20, 60) for regime in ("realistic", "worst") for schedule in schedules
    ]
    for row in rows:
        assert float(row["ours_ms"]) > 0 and float(row["naive_ms"]) > 0 and float(row["matmul_ms"]) > 0
        assert 1 <= float(row["mean_distinct_parents"]) <= int(row["N"])
    worst = [r for r in rows if r["regime"] == "worst"]
    # Flat weights and systematic resampling keep every particle: nothing for the fast path to share.
    assert all(float(r["mean_distinct_parents"]) == int(r["N"]) for r in worst)
    payload = json.loads((out / "results.json").read_text())
    assert payload["memory"]["ours_peak_extra_mb"] >= 0 and payload["memory"]["particles"] == 50
    assert set(payload["goals"]) == set(schedules)
    for goals in payload["goals"].values():
        # N = 20 and 60 only: the time goals at N = 1000 are not measured; the memory goal is.
        assert goals == {
            "realistic_at_most_1.0x_matmul": None,
            "worst_at_most_1.5x_matmul": None,
            "at_least_10x_faster_than_naive": None,
            "peak_extra_under_200_mb": payload["memory"]["ours_peak_extra_mb"] < 200,
        }


def test_bench_filter_json_flag_prints_only_json(tmp_path, capsys) -> None:
    assert cli.main(["bench", "filter", "--out", str(tmp_path), *TINY, "--memory-particles", "0", "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["memory"] is None and payload["machine"]["torch_threads"] == 1
    assert payload["network"]["mask_dim"] == 64


def test_bench_filter_help_and_bad_options(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["bench", "filter", "--help"])
    assert exit_info.value.code == 0 and "--particles" in capsys.readouterr().out
    if not torch.cuda.is_available():
        assert cli.main(["bench", "filter", "--device", "cuda", "--out", str(tmp_path / "never")]) == 2
        assert "no CUDA device" in capsys.readouterr().err
        assert not (tmp_path / "never").exists()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--particles", "20", "0"], "--particles must be >= 1, got 0"),
        (["--memory-hidden", "-4"], "--memory-hidden must be >= 1, got -4"),
        (["--dropout", "1.0"], "--dropout must be < 1.0, got 1.0"),
        (["--flip-prob", "2"], "--flip-prob must be <= 1.0, got 2.0"),
        (["--noise-std", "0"], "--noise-std must be > 0.0"),
        (["--steps", "0"], "--steps must be >= 1"),
        (["--memory-particles", "-1"], "--memory-particles must be >= 0"),
    ],
)
def test_bench_filter_refuses_bad_options_before_any_work(tmp_path, capsys, option, message) -> None:
    """Validation runs before the network is built or anything timed: not even the output directory is made."""
    out = tmp_path / "bench"
    assert cli.main(["bench", "filter", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
