"""``smcd-rl telescoping`` end to end at a tiny scale: files, tables, resume, a cache keyed by content, refused options."""

import csv
import json
import math
import re

import pytest
import torch

import smcd_rl
from smcd_rl import cli
from smcd_rl.envs.two_link_arm import motor_babbling
from smcd_rl.experiments.shared import stages
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS
from smcd_rl.experiments.telescoping import run as telescoping
from smcd_rl.experiments.telescoping.tracking import sample_episodes, track
from tests.experiments.test_stages import planned_stages

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
    "20",
    "--oracle-particles",
    "50",
    "--gd-steps",
    "1",
    # A small tuning (smcd_rl.tune scores GD, SMCD and the combination twice, unbudgeted and budgeted).
    "--tuning-episodes",
    "4",
    "--gd-lr",
    "0.1",
    "--gd-window",
    "5",
    "--calibrate-flips",
    "0.03",
]


def first_table(printed: str) -> list[str]:
    """The first Markdown table printed: the errors (the verdict table follows it)."""
    lines = printed.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return lines[start:end]


def without_times(table: list[str]) -> list[str]:
    """The table without its last column, the ms per observation: wall times differ between runs that tune afresh."""
    return [line.rsplit("|", 2)[0] for line in table]


def test_tiny_run_writes_files_and_a_resumed_run_gives_the_same_table(tmp_path, capsys, monkeypatch) -> None:
    whole = tmp_path / "whole"
    monkeypatch.setattr(stages, "RESUMED_SECONDS", 0.0)  # tiny stages count as timed: the time left shows
    assert cli.main(["telescoping", "--out", str(whole), *TINY]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    trainings = ["train", "train reptile", "train task", "tune M", "tune R", "tune T"]
    expected = [*trainings, *(f"evaluate {m}" for m in telescoping.DEFAULT_METHODS)]
    assert planned_stages(captured.err, "whole") == expected
    uninterrupted = first_table(printed)
    assert [line.split("|")[1].strip() for line in uninterrupted[2:]] == list(telescoping.DEFAULT_METHODS)
    for name in ("M+S(evidence)", "M+C", "R+S(evidence)", "R+C"):
        assert name in telescoping.DEFAULT_METHODS, name
    # The last column: each adapted method's ms per observation; none for the true kinematics and the oracle.
    assert uninterrupted[0].split("|")[-2].strip() == "ms / observation"
    timed = {line.split("|")[1].strip(): line.split("|")[-2].strip() for line in uninterrupted[2:]}
    assert timed["true"] == timed["O+P"] == "-"
    assert all(float(timed[m]) > 0 for m in telescoping.DEFAULT_METHODS if m[0] in "MR")
    # the headline verdicts: M+S against M+N, M+G, M+S(evidence) and M+S(paper)
    for against in (r"M\+N", r"M\+S\(evidence\)", r"M\+S\(paper\)"):
        assert re.search(rf"\| episode \| M\+S +\| {against} +\|", printed), against
    assert "M: tuned under 10 ms per observation" in printed and "R: tuned on " in printed
    for name in ("results.csv", "trials.csv", "comparisons.csv", "curves.csv", "results.json", "tracking.png"):
        assert (whole / name).is_file(), name
    for name in ("report.md", "model.pt", "reptile.pt"):
        assert (whole / name).is_file(), name
    assert len(list(whole.glob("train-*.ckpt"))) == len(list(whole.glob("reptile-*.ckpt"))) == 1
    rows = list(csv.DictReader(open(whole / "results.csv")))
    assert [r["method"] for r in rows] == list(telescoping.DEFAULT_METHODS)
    for r in rows:
        assert 0 <= float(r["episode_low"]) <= float(r["episode_mean"]) <= float(r["episode_high"])
        assert float(r["error_k12_low"]) <= float(r["error_k12"]) <= float(r["error_k12_high"]) and r["trials"] == "6"
        if r["method"] in ("true", "O+P"):
            assert r["ms_per_observation"] == ""
        else:
            assert 0 < float(r["ms_per_observation"]) < math.inf, r
    assert len(list(csv.DictReader(open(whole / "trials.csv")))) == len(telescoping.DEFAULT_METHODS) * 6
    pairs = {(c["k"], c["method"], c["against"]) for c in csv.DictReader(open(whole / "comparisons.csv"))}
    assert {("episode", "M+S", "M+N"), ("episode", "M+S", "M+G"), ("5", "R+S", "R+N"), ("12", "M+S", "true")} <= pairs
    assert {("episode", "M+S", "M+S(evidence)"), ("episode", "M+C", "M+G"), ("5", "R+C", "R+N")} <= pairs
    curves = list(csv.DictReader(open(whole / "curves.csv")))
    assert len(curves) == len(telescoping.DEFAULT_METHODS) * 13  # k = 0..12
    payload = json.loads((whole / "results.json").read_text())
    assert payload["config"]["trials"] == 6 and set(payload["train_loss"]) == {"M", "R", "T"}
    assert set(payload["tuning"]["M"]["specs"]) == {"N", "G", "S", "S(evidence)", "S(paper)", "C", "L", "SL"}
    # The scoreboard's entry: every strategy of M, each with its time per observation.
    board = payload["scoreboard"]
    ran = set(COLUMNS)  # every strategy, the last layers too
    assert set(board["estimates"]) == set(board["ms_per_observation"]) == ran
    assert board["estimates"]["combination"]["method"] == "M+C"
    assert all(0 < ms < math.inf for ms in board["ms_per_observation"].values())
    # Every method starts from the same arms and targets: the k = 0 errors agree.
    assert len({c["error_mean"] for c in curves if c["k"] == "0"}) == 1

    # An interrupted run (two methods finished, the rest never started) resumed to the end.
    split = tmp_path / "split"
    assert cli.main(["telescoping", "--out", str(split), *TINY, "--methods", "R+S", "O+P"]) == 0
    first = json.loads((split / "results.json").read_text())["seconds"]
    capsys.readouterr()
    assert cli.main(["telescoping", "--out", str(split), *TINY]) == 0
    assert without_times(first_table(capsys.readouterr().out)) == without_times(uninterrupted)
    resumed = json.loads((split / "results.json").read_text())["seconds"]
    for name in ("evaluate R+S", "evaluate O+P"):
        assert resumed[name] == first[name]  # taken from the cache


def _save_model(path, seed: int) -> None:
    """A small two-link model q -> ee, trained one epoch from initial weights of ``seed``."""
    data = motor_babbling(10, 5, 5, generator=torch.Generator().manual_seed(0))
    torch.manual_seed(seed)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(32,)), in_keys=["q"], out_key="ee")
    smcd_rl.fit(model, data, epochs=1, batch_size=32, lr=1e-3, progress=False)
    model.save(path)


def test_a_rerun_with_an_overwritten_model_file_recomputes_its_methods(tmp_path, capsys) -> None:
    """The M methods are cached by the loaded model's digest, not by the --model path: after the
    file is overwritten with another model, the rerun tracks again with the new one (it used to
    print the old model's table); the true kinematics do not depend on it and are reused."""
    path, out = tmp_path / "model.pt", tmp_path / "run"
    command = ["telescoping", "--out", str(out), *TINY, "--model", str(path), "--methods", "true", "M+N"]
    _save_model(path, seed=1)
    assert cli.main(command) == 0
    before = first_table(capsys.readouterr().out)
    seconds = json.loads((out / "results.json").read_text())["seconds"]
    assert not list(out.glob("train-*.ckpt"))  # M was loaded, not trained
    _save_model(path, seed=2)
    assert cli.main(command) == 0
    after = first_table(capsys.readouterr().out)
    rerun = json.loads((out / "results.json").read_text())["seconds"]
    assert after[2] == before[2] and rerun["evaluate true"] == seconds["evaluate true"]
    assert after[3] != before[3] and rerun["evaluate M+N"] != seconds["evaluate M+N"]
    _save_model(path, seed=1)  # the first model again: the same table as its first run
    assert cli.main(command) == 0
    assert first_table(capsys.readouterr().out) == before


def test_track_with_true_kinematics_is_better_than_doing_nothing() -> None:
    """The loop itself: the PD law with the true kinematics closes in on the targets.

    Random arms start about 1.6 m from their targets; tracking brings the mean error below
    0.25 m by k = 30 (measured ~0.12 m, the PD law's lag behind the moving target and link).
    """
    config = telescoping.TelescopingConfig(trials=40, horizon=30)
    episodes, noise = sample_episodes(config, torch.device("cpu"))
    errors = track("true", None, episodes, noise, config, progress=False)
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
    assert cli.make_config("telescoping", {}).threads == 1
    (tmp_path / "notes.pt").write_text("not a model")
    out = tmp_path / "run"
    assert cli.main(["telescoping", "--model", str(tmp_path / "notes.pt"), "--out", str(out), *TINY]) == 2
    error = capsys.readouterr().err
    assert str(tmp_path / "notes.pt") in error and "not an smcd-rl model checkpoint" in error


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--methods", "X+Y"], "--methods: unknown value 'X+Y'"),
        (["--feedback", "guessed"], "--feedback: unknown value 'guessed'"),
        (["--report-steps", "500"], "--report-steps [500] lie beyond --horizon 12"),
        (["--report-steps", "-1"], "--report-steps must be >= 0"),
        (["--particles", "-5"], "--particles must be >= 1"),
        (["--oracle-particles", "0"], "--oracle-particles must be >= 1"),
        (["--epochs", "0"], "--epochs must be >= 1"),
        (["--reptile-epochs", "0"], "--reptile-epochs must be >= 1"),
        (["--trials", "1"], "--trials must be >= 2"),
        (["--dt", "0"], "--dt must be > 0"),
        (["--damping", "-1"], "--damping must be >= 0"),
        (["--dropout", "1"], "--dropout must be < 1"),
        (["--flip-prob", "1.5"], "--flip-prob must be <= 1"),
        (["--model", "missing.pt"], "--model missing.pt: no such file"),
        # Once refused only by the T network's constructor, after M and R had trained.
        (["--hidden", "24", "--mask-groups", "16"], "--mask-groups 16 must divide --hidden 24"),
        (["--task-share", "1.5"], "--task-share must be <= 1"),
    ],
)
def test_bad_options_are_refused_before_any_training(tmp_path, capsys, option, message) -> None:
    """Validation runs before any work: no data, no training, not even the output directory."""
    out = tmp_path / "run"
    assert cli.main(["telescoping", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
