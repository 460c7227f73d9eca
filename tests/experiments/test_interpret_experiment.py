"""``smcd-rl interpret`` end to end at a tiny scale: files, tables, --dataset, resume, bad input."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from smcd_rl import cli
from smcd_rl.envs.drone_operators import save_dataset, simulate_operators
from smcd_rl.experiments import interpret

TINY = [
    "--fig9-latents",
    "8",
    "16",
    "--fig9-tasks",
    "10",
    "--fig9-episodes",
    "4",
    "--fig9-epochs",
    "1",
    "--fig9-arms",
    "12",
    "--fig9-burn-in",
    "3",
    "--fig9-particles",
    "10",
    "--fig9-ks",
    "1",
    "3",
    "--operators",
    "6",
    "--trajectories-per-operator",
    "4",
    "--hidden",
    "16",
    "--epochs",
    "1",
    "--particles",
    "10",
    "--reptile-epochs",
    "1",
    "--steps",
    "1",
    "5",
    "--burn-in",
    "0.5",
    "--horizons",
    "0.25",
    "--methods",
    "M+N",
    "M+S",
    "R+N",
    "--threads",
    "1",
]
FILES = (
    "results.csv",
    "results.json",
    "fig9.csv",
    "confidence.csv",
    "lookahead.csv",
    "fig9.png",
    "fig4_skill_strategy.png",
    "fig13_phase_success.png",
    "fig14_lookahead.png",
    "dataset.npz",
    "bc_model.pt",
)


def tables(printed: str) -> list[str]:
    """The printed tables, without the closing line that names the output directory."""
    return [line for line in printed.splitlines() if not line.startswith("wrote ")]


@pytest.mark.slow
def test_interpret_writes_results_and_an_interrupted_run_resumes_to_the_same_tables(
    tmp_path, capsys, monkeypatch
) -> None:
    first = tmp_path / "first"
    assert cli.main(["interpret", "--out", str(first), *TINY]) == 0
    printed = capsys.readouterr().out
    for name in FILES:
        assert (first / name).is_file(), name
    assert "Fig. 9" in printed and "| skill" in printed and "| M+S" in printed and "| R+N" in printed
    payload = json.loads((first / "results.json").read_text())
    assert (
        payload["dataset"]["train"]["trajectories"]
        + payload["dataset"]["known"]["trajectories"]
        + payload["dataset"]["unknown"]["trajectories"]
        == 24
    )
    assert all(0 <= r["mean"] <= 1 and 0 <= r["chance"] <= 1 for r in payload["confidence"])
    assert all(0 <= r["accuracy"] <= 1 for r in payload["fig9"])
    assert all(math.isfinite(r["rmse_mean"]) and r["rmse_mean"] > 0 for r in payload["lookahead"])
    assert all(r["vs_mn_mean"] == 0 for r in payload["lookahead"] if r["method"] == "M+N")  # paired with itself
    with open(first / "results.csv") as handle:
        figures = {row["figure"] for row in csv.DictReader(handle)}
    assert figures == {"fig9", "confidence", "lookahead"}

    # The same data as a user's --dataset; the run is interrupted in its second look-ahead method.
    second = tmp_path / "second"
    real = interpret._evaluate_lookahead
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # M+N known, M+N unknown, then M+S
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(interpret, "_evaluate_lookahead", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cli.main(["interpret", "--out", str(second), "--dataset", str(first / "dataset.npz"), *TINY])
    capsys.readouterr()

    def counted(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    calls["n"] = 0
    monkeypatch.setattr(interpret, "_evaluate_lookahead", counted)
    assert cli.main(["interpret", "--out", str(second), "--dataset", str(first / "dataset.npz"), *TINY]) == 0
    assert calls["n"] == 4  # M+S and R+N for both sets; M+N came from the cache
    assert tables(capsys.readouterr().out) == tables(printed)


def _user_dataset(tmp_path, drop_label: str | None = None, drop_key: str | None = None):
    path = tmp_path / "user.npz"
    data = simulate_operators(num_operators=4, trajectories_per_operator=3)
    if drop_label:
        data.trajectory_labels.pop(drop_label, None)
        data.step_labels.pop(drop_label, None)
        data.label_names.pop(drop_label, None)
    save_dataset(data, path)
    if drop_key:
        arrays = dict(np.load(path))
        arrays.pop(drop_key)
        np.savez(path, **arrays)
    return path


def test_bad_datasets_are_reported_before_any_training(tmp_path, capsys) -> None:
    out = str(tmp_path / "run")
    assert cli.main(["interpret", "--out", out, "--parts", "confidence", "--dataset", str(tmp_path / "none.npz")]) == 2
    assert "no such file" in capsys.readouterr().err
    path = _user_dataset(tmp_path, drop_label="phase")
    assert cli.main(["interpret", "--out", out, "--parts", "confidence", "--dataset", str(path)]) == 2
    error = capsys.readouterr().err
    assert "phase" in error and "--labels" in error
    path = _user_dataset(tmp_path, drop_key="operator")
    assert cli.main(["interpret", "--out", out, "--parts", "confidence", "--dataset", str(path)]) == 2
    assert "lacks key" in capsys.readouterr().err
    assert not (tmp_path / "run" / "bc.ckpt").exists()


def test_unknown_names_and_bad_settings_are_errors(capsys) -> None:
    assert cli.main(["interpret", "--methods", "M+X", "--out", "/tmp/never"]) == 2
    assert "unknown method" in capsys.readouterr().err
    assert cli.main(["interpret", "--parts", "fig10", "--out", "/tmp/never"]) == 2
    assert "unknown part" in capsys.readouterr().err
    assert cli.main(["interpret", "--burn-in", "1.5", "--out", "/tmp/never"]) == 2
    assert "burn_in" in capsys.readouterr().err
    assert cli.main(["interpret", "--fig9-arms", "10", "--fig9-ks", "20", "--out", "/tmp/never"]) == 2
    assert "fig9_arms" in capsys.readouterr().err


def test_help_and_full_preset(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["interpret", "--help"])
    assert exit_info.value.code == 0 and "--dataset" in capsys.readouterr().out
    config = cli.make_config("interpret", {"full": True, "particles": 7})
    assert config.particles == 7 and config.hidden == interpret.FULL["hidden"] and config.epochs == 400
    assert cli.make_config("interpret", {}).hidden == interpret.InterpretConfig().hidden
