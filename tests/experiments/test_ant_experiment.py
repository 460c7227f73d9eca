"""``smcd-rl ant`` end to end at a tiny scale: files, table with CIs, every cell, resume, bad options."""

import csv
import json
import re

import pytest
import torch

from smcd_rl import cli
from smcd_rl.experiments import ant

TINY = [
    "--transitions",
    "400",
    "--data-episode-steps",
    "100",
    "--hidden",
    "16",
    "--epochs",
    "2",
    "--episodes",
    "2",
    "--episode-steps",
    "4",
    "--horizon",
    "3",
    "--candidates",
    "12",
    "--elites",
    "3",
    "--iterations",
    "2",
    "--particles",
    "8",
    "--threads",
    "1",
]
ONE_CELL = ["--planners", "rs", "--adaptations", "none", "--conditions", "crippled"]


def test_ant_command_writes_every_cell_and_resumes(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY]) == 0
    printed = capsys.readouterr().out
    assert "| planner" in printed and "healthy" in printed and "crippled" in printed
    assert re.search(r"\| -?\d+\.\d \[-?\d+\.\d, -?\d+\.\d\] +\|", printed)  # mean [95% CI] cells
    assert "| SMCD   | none    |" in printed and "| SMCD   | GD      |" in printed  # the headline verdicts
    names = ("results.csv", "trials.csv", "comparisons.csv", "results.json", "report.md", "ant.png", "model.pt")
    for name in names:
        assert (out / name).is_file(), name
    assert len(list((out / "partial").glob("data-*.pt"))) == 1
    assert len(list(out.glob("train-*.ckpt"))) == 1

    rows = list(csv.DictReader(open(out / "results.csv")))
    cells = [(r["planner"], r["adaptation"], r["condition"]) for r in rows]
    assert cells == [(ant.PLANNERS[p], ant.ADAPTATIONS[a], c) for p, a, c in ant.CELLS]
    assert all(float(r["return_low"]) <= float(r["return_mean"]) <= float(r["return_high"]) for r in rows)
    episodes = list(csv.DictReader(open(out / "trials.csv")))
    assert len(episodes) == 18 * 2
    # Episode k is the same episode (seed, leg) in every cell; healthy episodes cripple no leg.
    legs = {(e["condition"], e["episode"]): set() for e in episodes}
    for e in episodes:
        legs[(e["condition"], e["episode"])].add((e["seed"], int(e["leg"])))
    assert all(len(v) == 1 for v in legs.values())
    assert {leg for _, leg in legs[("healthy", "0")]} == {-1} and {leg for _, leg in legs[("crippled", "0")]} <= {
        0,
        1,
        2,
        3,
    }
    # Per planner and condition: SMCD and GD each against no adaptation, and SMCD against GD.
    comparisons = list(csv.DictReader(open(out / "comparisons.csv")))
    pairs = {(c["method"], c["against"]) for c in comparisons}
    assert len(comparisons) == 6 * 3 and pairs == {("SMCD", "none"), ("GD", "none"), ("SMCD", "GD")}
    assert {c["verdict"] for c in comparisons} <= {"better", "worse", "no significant difference"}
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["episodes"] == 2 and len(payload["results"]) == 18
    assert len(payload["training"]["smcd_noise_std"]) == 41 and payload["machine"]["torch_threads"] == 1
    report = (out / "report.md").read_text()
    assert "mean [95% CI]" in report and "SMCD paired with no adaptation and GD" in report

    # A rerun finds the training and every cell finished: evaluating one again would raise.
    def never(*args, **kwargs):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(ant, "run_cell", never)
    assert cli.main(["ant", "--out", str(out), *TINY]) == 0
    assert capsys.readouterr().out.splitlines()[:40] == printed.splitlines()[:40]
    # A subset of the cells is found in the same cache: which cells run is not part of its key.
    assert cli.main(["ant", "--out", str(out), *TINY, "--planners", "rs", "--conditions", "crippled"]) == 0
    assert len(list(csv.DictReader(open(out / "results.csv")))) == 3
    assert len(list(out.glob("train-*.ckpt"))) == 1


def test_subset_of_cells_and_single_condition(tmp_path, capsys) -> None:
    out = tmp_path / "subset"
    options = ["--planners", "rs", "--adaptations", "none", "smcd", "--conditions", "crippled"]
    assert cli.main(["ant", "--out", str(out), *TINY, *options]) == 0
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {(r["planner"], r["adaptation"], r["condition"]) for r in rows} == {
        ("RS", "none", "crippled"),
        ("RS", "SMCD", "crippled"),
    }
    comparisons = list(csv.DictReader(open(out / "comparisons.csv")))
    assert [(c["planner"], c["condition"], c["method"], c["against"]) for c in comparisons] == [
        ("RS", "crippled", "SMCD", "none")
    ]
    assert "crippled" in capsys.readouterr().out


def test_other_data_under_the_same_settings_retrains_and_reruns_the_cells(tmp_path, monkeypatch) -> None:
    """The checkpoint is named by the data's digest and the cell cache keyed by the trained model's:
    replacing the cached transitions (same settings, other content) trains a new model and reruns
    its cells instead of resuming the old training or reusing cells of the old model."""
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY, *ONE_CELL]) == 0
    (path,) = (out / "partial").glob("data-*.pt")
    saved = torch.load(path, weights_only=False)
    data = saved["value"]["data"]
    data.set("observation", data.get("observation") + 0.1)
    torch.save(saved, path)
    calls = []
    run_cell = ant.run_cell
    monkeypatch.setattr(ant, "run_cell", lambda *args, **kwargs: calls.append(args[1]) or run_cell(*args, **kwargs))
    assert cli.main(["ant", "--out", str(out), *TINY, *ONE_CELL]) == 0
    assert calls == [("rs", "none", "crippled")]
    assert len(list(out.glob("train-*.ckpt"))) == 2


def test_help_lists_every_option(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["ant", "--help"])
    printed = capsys.readouterr().out
    assert exit_info.value.code == 0 and "--crippled-legs" in printed and "--noise-scale" in printed


def test_full_preset_and_bad_options(capsys) -> None:
    config = cli.make_config("ant", {"full": True, "episodes": 7})
    assert config.episodes == 7 and config.hidden == 1024 and config.depth == 3
    assert config.transitions == 1_000_000 and config.episode_steps == 1000
    assert cli.make_config("ant", {}).hidden == ant.AntConfig().hidden
    assert ant.AntConfig().threads == 1
    for empty in ("planners", "adaptations", "conditions", "crippled_legs"):
        with pytest.raises(ValueError, match="needs at least one value"):
            ant.AntConfig(**{empty: ()}).validate()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--particles", "-5"], "--particles must be >= 1"),
        (["--epochs", "0"], "--epochs must be >= 1"),
        (["--episodes", "1"], "--episodes must be >= 2"),
        (["--transitions", "0"], "--transitions must be >= 3"),
        (["--planners", "ilqr"], "--planners: unknown value 'ilqr'"),
        (["--adaptations", "smcd", "maml"], "--adaptations: unknown value 'maml'"),
        (["--conditions", "broken"], "--conditions: unknown value 'broken'"),
        (["--crippled-legs", "4"], "--crippled-legs: unknown value 4"),
        (["--data-policy", "expert"], "--data-policy: unknown value 'expert'"),
        (["--task", "hopper"], "--task: unknown value 'hopper'"),
        (["--lr", "0"], "--lr must be > 0.0"),
        (["--mppi-noise", "-1"], "--mppi-noise must be > 0.0"),
        (["--flip-prob", "-0.1"], "--flip-prob must be >= 0.0"),
        (["--flip-prob", "0.6"], "--flip-prob 0.6 is too large at dropout 0.1"),
        (["--dropout", "1"], "--dropout must be < 1"),
        (["--validation", "1.5"], "--validation must be < 1"),
        (["--elites", "13"], "--elites (13) must be <= --candidates (12)"),
        (["--transitions", "3", "--validation", "0.1"], "3 transitions are too few to hold out 10%"),
        (["--device", "tpu"], "unknown device 'tpu'"),
    ],
)
def test_bad_options_are_refused_before_any_data_or_training(tmp_path, capsys, option, message) -> None:
    """Validation runs before any work: no data collected, nothing trained, not even the output directory made."""
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
