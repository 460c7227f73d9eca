"""``smcd-rl bench control`` at tiny sizes: it runs, prints steps/s and ratios, writes files.

No timing is asserted: the numbers depend on the machine and its load.
"""

import csv
import json

import pytest

from smcd_rl import cli
from smcd_rl.experiments.bench.control.run import CONTENDERS
from tests.experiments.test_stages import planned_stages

TINY = [
    "--hidden",
    "16",
    "16",
    "--particles",
    "20",
    "--batch",
    "2",
    "--steps",
    "4",
    "--warmup",
    "1",
    "--gd-steps",
    "1",
    "--device",
    "cpu",
    "--threads",
    "1",
]


def test_bench_control_prints_rates_and_ratios_and_writes_files(tmp_path, capsys) -> None:
    out = tmp_path / "bench"
    assert cli.main(["bench", "control", "--out", str(out), *TINY]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "bench") == ["time"]  # the contenders are timed interleaved: one stage
    assert "torch_threads=1" in printed and "analytic / M+S =" in printed and "M+S / M+G" in printed
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert [r["loop"] for r in rows] == list(CONTENDERS)
    assert all(float(r["steps_per_s"]) > 0 and int(r["steps"]) == 4 for r in rows)
    payload = json.loads((out / "results.json").read_text())
    assert set(payload["ratios"]) == {
        "analytic_over_smcd",
        "smcd_over_gd",
        "no_adaptation_over_smcd",
        "analytic_over_gd",
    }
    assert all(value > 0 for value in payload["ratios"].values())
    assert payload["network"]["mask_dim"] == 32 and payload["network"]["trained"] is False


def test_bench_control_times_a_saved_model_and_prints_json(tmp_path, capsys) -> None:
    import smcd_rl

    path = tmp_path / "model.pt"
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(7, 3, hidden=(8,)), in_keys=["q"], out_key="ee")
    model.fitted = True  # stands in for a trained model: only its timing is measured
    model.save(path)
    assert cli.main(["bench", "control", "--out", str(tmp_path / "b"), *TINY, "--model", str(path), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["network"] == {"in": 7, "hidden": [8], "out": 3, "mask_dim": 8, "trained": True}
    assert payload["device"] == "cpu" and {r["loop"] for r in payload["results"]} == set(CONTENDERS)


def test_bench_control_help_and_bad_options(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["bench", "control", "--help"])
    assert exit_info.value.code == 0 and "--particles" in capsys.readouterr().out
    assert cli.main(["bench", "control", "--model", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "b")]) == 2
    assert "no such file" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--particles", "0"], "--particles must be >= 1, got 0"),
        (["--hidden", "16", "0"], "--hidden must be >= 1, got 0"),
        (["--dropout", "1.0"], "--dropout must be < 1.0, got 1.0"),
        (["--flip-prob", "1.5"], "--flip-prob must be <= 1.0, got 1.5"),
        (["--gd-lr", "0"], "--gd-lr must be > 0.0"),
        (["--warmup", "-1"], "--warmup must be >= 0"),
        (["--threads", "-1"], "--threads must be >= 0"),
        (["--model", "missing.pt"], "no such file"),
    ],
)
def test_bench_control_refuses_bad_options_before_any_work(tmp_path, capsys, option, message) -> None:
    """Validation runs before anything is built or timed: not even the output directory is made."""
    out = tmp_path / "bench"
    assert cli.main(["bench", "control", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
