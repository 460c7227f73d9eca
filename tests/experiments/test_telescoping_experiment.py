"""``smcd-rl telescoping`` end to end at a tiny scale: files, table, resume, bad options."""

import csv
import json

import pytest
import torch

from smcd_rl import cli
from smcd_rl.experiments import telescoping

TINY = [
    "--tasks",
    "20",
    "--episodes",
    "5",
    "--hidden",
    "32",
    "--epochs",
    "2",
    "--reptile-epochs",
    "1",
    "--trials",
    "6",
    "--horizon",
    "12",
    "--report-steps",
    "5",
    "12",
    "--particles",
    "50",
    "--oracle-particles",
    "50",
    "--gd-steps",
    "1",
]


def last_table(printed: str) -> list[str]:
    lines = printed.splitlines()
    end = max(i for i, line in enumerate(lines) if line.startswith("|"))
    start = end
    while start > 0 and lines[start - 1].startswith("|"):
        start -= 1
    return lines[start : end + 1]


def test_tiny_run_writes_files_and_a_resumed_run_gives_the_same_table(tmp_path, capsys) -> None:
    whole = tmp_path / "whole"
    assert cli.main(["telescoping", "--out", str(whole), *TINY]) == 0
    uninterrupted = last_table(capsys.readouterr().out)
    assert [line.split("|")[1].strip() for line in uninterrupted[2:]] == list(telescoping.METHODS)
    for name in ("results.csv", "curves.csv", "results.json", "tracking.png", "model.pt", "reptile.pt"):
        assert (whole / name).is_file(), name
    rows = list(csv.DictReader(open(whole / "results.csv")))
    assert {r["method"] for r in rows} == set(telescoping.METHODS)
    assert all(float(r["episode_mean"]) > 0 and float(r["error_k12"]) >= 0 for r in rows)
    curves = list(csv.DictReader(open(whole / "curves.csv")))
    assert len(curves) == len(telescoping.METHODS) * 13  # k = 0..12
    payload = json.loads((whole / "results.json").read_text())
    assert payload["config"]["trials"] == 6 and set(payload["train_loss"]) == {"M", "R"}
    # Every method starts from the same arms and targets: the k = 0 errors agree.
    assert len({c["error_mean"] for c in curves if c["k"] == "0"}) == 1

    # An interrupted run (two methods finished, the rest never started) resumed to the end.
    split = tmp_path / "split"
    assert cli.main(["telescoping", "--out", str(split), *TINY, "--methods", "R+S", "O+P"]) == 0
    first = json.loads((split / "results.json").read_text())["method_seconds"]
    capsys.readouterr()
    assert cli.main(["telescoping", "--out", str(split), *TINY]) == 0
    assert last_table(capsys.readouterr().out) == uninterrupted
    resumed = json.loads((split / "results.json").read_text())["method_seconds"]
    assert resumed["R+S"] == first["R+S"] and resumed["O+P"] == first["O+P"]  # taken from the cache


def test_track_with_true_kinematics_is_better_than_doing_nothing() -> None:
    """The loop itself: the PD law with the true kinematics closes in on the targets.

    Random arms start about 1.6 m from their targets; tracking brings the mean error below
    0.25 m by k = 30 (measured ~0.12 m, the PD law's lag behind the moving target and link).
    """
    config = telescoping.TelescopingConfig(trials=40, horizon=30)
    episodes, noise = telescoping._trials(config, torch.device("cpu"))
    errors = telescoping._track("true", None, episodes, noise, config, progress=False)
    assert errors.shape == (40, 31)
    assert float(errors[:, 0].mean()) > 1.0 and float(errors[:, -1].mean()) < 0.25


def test_full_preset_fills_only_options_not_given() -> None:
    config = cli.make_config("telescoping", {"full": True, "trials": 7})
    assert config.trials == 7 and config.hidden == telescoping.FULL["hidden"] and config.reptile_epochs == 1000
    assert cli.make_config("telescoping", {}).trials == telescoping.TelescopingConfig().trials


def test_help_and_bad_options(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["telescoping", "--help"])
    assert exit_info.value.code == 0 and "--feedback" in capsys.readouterr().out
    never = str(tmp_path / "never")
    assert cli.main(["telescoping", "--methods", "X+Y", "--out", never]) == 2
    assert "unknown method" in capsys.readouterr().err
    assert cli.main(["telescoping", "--feedback", "guessed", "--out", never]) == 2
    assert "feedback" in capsys.readouterr().err
    assert cli.main(["telescoping", "--report-steps", "500", "--out", never]) == 2
    assert "report_steps" in capsys.readouterr().err
    assert cli.main(["telescoping", "--model", str(tmp_path / "missing.pt"), "--out", never]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "notes.pt").write_text("not a model")
    assert cli.main(["telescoping", "--model", str(tmp_path / "notes.pt"), "--out", never]) == 2
    assert "not a saved smcd_rl model" in capsys.readouterr().err
