"""``smcd-rl ant`` end to end at a tiny scale: files, table with CIs, every cell, resume, bad options."""

import csv
import json
import math
import re

import pytest
import torch

from smcd_rl import cli
from smcd_rl.experiments.ant import prediction
from smcd_rl.experiments.ant import run as ant
from smcd_rl.experiments.shared import stages
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS as SCOREBOARD_COLUMNS
from tests.experiments.test_stages import planned_stages

TINY = [
    "--transitions",
    "400",
    "--data-episode-steps",
    "100",
    "--hidden",
    "16",
    "--mask-groups",
    "4",
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
    "--tuning-episodes",
    "4",
    "--tuning-steps",
    "6",
    "--prediction-episodes",
    "6",
    "--prediction-steps",
    "8",
    "--prediction-horizon",
    "3",
    "--gd-lr",
    "0.01",
    "0.1",
    "--gd-steps",
    "1",
    "--gd-window",
    "5",
]
VARIANTS = ["N", "G", "S", "S(evidence)", "S(paper)", "C"]
ALL_CELLS = ["--planners", "cem", "mppi", "rs", "--adaptations", *VARIANTS]
ADAPTED = ("M+G", "M+S", "M+S(evidence)", "M+S(paper)", "M+C", "M+L", "M+SL")
#: The scoreboard's columns, each a strategy of the primary metric (every strategy's prediction error runs,
#: T+S's on the task-mask network too).
COLUMNS = set(SCOREBOARD_COLUMNS)
#: The default methods of T, the network whose masks were trained to identify the leg.
TASK = ("T+N", "T+G", "T+S", "T+L", "T+SL")
ONE_CELL = ["--planners", "rs", "--adaptations", "N", "--conditions", "crippled"]


def test_ant_command_writes_every_cell_and_resumes(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "run"
    monkeypatch.setattr(stages, "RESUMED_SECONDS", 0.0)  # tiny stages count as timed: the time left shows
    assert cli.main(["ant", "--out", str(out), *TINY, *ALL_CELLS]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    planned = planned_stages(captured.err, "run")
    assert planned[:6] == ["collect", "train", "tune M", "collect T", "train T", "tune T"]
    assert len(planned) == 6 + 2 * (8 + len(TASK)) + 3 * 6 * 2  # predictions of M and T per condition, then cells
    # The primary table (prediction error) comes first, then its verdicts, the returns and the tuning.
    first = [printed.index(t) for t in ("Prediction error", "M+S paired with M+N", "Episode return", "Tuning of M")]
    assert first == sorted(first)
    assert "| condition" in printed and "| planner" in printed and "healthy" in printed and "crippled" in printed
    assert re.search(r"\| -?\d+\.\d \[-?\d+\.\d, -?\d+\.\d\] +\|", printed)  # mean [95% CI] return cells
    for against in ("M+N", "M+G", "M+S(evidence)", "M+S(paper)", "M+C"):  # the headline verdicts
        assert re.search(rf"\| M\+S +\| {re.escape(against)} +\|", printed), against
    # The primary table shows each strategy's time per observation (every strategy of M was tuned).
    assert "ms / observation" in printed and "| healthy   | M+C " in printed
    names = ("results.csv", "trials.csv", "comparisons.csv", "results.json", "report.md", "model.pt")
    for name in (*names, "task_model.pt", "ant.png", "prediction.png", "tuning-M.png", "tuning-T.png"):
        assert (out / name).is_file(), name
    assert len(list((out / "partial").glob("data-*.pt"))) == 2  # M's healthy data and T's of every condition
    assert len(list(out.glob("train-*.ckpt"))) == len(list(out.glob("T-*.ckpt"))) == 1

    rows = list(csv.DictReader(open(out / "results.csv")))
    returns = [r for r in rows if r["part"] == "return"]
    cells = [(r["planner"], r["method"], r["condition"]) for r in returns]
    assert cells == [(ant.PLANNERS[p], ant.METHOD_LABELS[a], c) for p, a, c in ant.CELLS if a in VARIANTS]
    assert all(float(r["return_low"]) <= float(r["return_mean"]) <= float(r["return_high"]) for r in returns)
    predictions = [r for r in rows if r["part"] == "prediction"]
    assert len(predictions) == 2 * 2 * (8 + len(TASK))  # condition x (one-step, 3-step) x strategy (M's and T's)
    assert {r["method"] for r in predictions} >= set(TASK)
    assert all(float(r["rmse_low"]) <= float(r["rmse_mean"]) <= float(r["rmse_high"]) for r in predictions)
    ms = [float(r["ms_per_observation"]) for r in rows]  # every row's method was tuned, M's and T's
    assert all(math.isfinite(v) and v > 0 for v in ms)
    trials = list(csv.DictReader(open(out / "trials.csv")))
    episodes = [e for e in trials if e["part"] == "return"]
    assert len(episodes) == 36 * 2
    # Episode k is the same episode (seed, leg) in every cell; healthy episodes cripple no leg.
    legs = {(e["condition"], e["episode"]): set() for e in episodes}
    for e in episodes:
        legs[(e["condition"], e["episode"])].add((e["seed"], int(e["leg"])))
    assert all(len(v) == 1 for v in legs.values())
    assert {leg for _, leg in legs[("healthy", "0")]} == {-1}
    assert {leg for _, leg in legs[("crippled", "0")]} <= {0, 1, 2, 3}
    # Per planner and condition: each adaptive method against M+N and against each other.
    comparisons = [c for c in csv.DictReader(open(out / "comparisons.csv")) if c["part"] == "return"]
    pairs = {(c["method"], c["against"]) for c in comparisons}
    assert len(comparisons) == 6 * (5 + 10) and ("M+S", "M+N") in pairs and ("M+S", "M+G") in pairs
    assert ("M+S", "M+S(evidence)") in pairs and ("M+S", "M+C") in pairs and ("M+G", "M+C") in pairs
    assert {c["verdict"] for c in comparisons} <= {"better", "worse", "no significant difference"}
    payload = json.loads((out / "results.json").read_text())
    # returns, then condition x (one-step, 3-step) x strategy predictions
    assert payload["config"]["episodes"] == 2 and len(payload["results"]) == 36 + 2 * 2 * (8 + len(TASK))
    assert len(payload["training"]["paper_noise_std"]) == 41 and payload["machine"]["torch_threads"] == 1
    report = (out / "report.md").read_text()
    assert "mean [95% CI]" in report and "M+S paired with M+N, M+S(evidence), M+S(paper), M+G and M+C" in report
    assert "M: tuned under 10 ms per observation" in report  # smcd_rl.tune's budgeted table
    assert "![tuning-M.png](tuning-M.png)" in report and "![prediction.png](prediction.png)" in report
    # T+S is paired with its own network's methods, which saw the same legs in training, and with M's.
    assert "T+S (masks trained to identify the task) paired with" in report
    assert re.search(r"\| T\+S +\| T\+G +\|", report) and re.search(r"\| T\+S +\| M\+G +\|", report)

    # A rerun finds the training, the tuning, the errors and every cell finished: evaluating one again would raise.
    def never(*args, **kwargs):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(ant, "run_cell", never)
    monkeypatch.setattr(prediction, "prediction_errors", never)
    assert cli.main(["ant", "--out", str(out), *TINY, *ALL_CELLS]) == 0
    assert capsys.readouterr().out.splitlines()[:40] == printed.splitlines()[:40]
    # A subset of the cells is found in the same cache: which cells run is not part of its key.
    options = ["--planners", "rs", "--adaptations", *VARIANTS, "--conditions", "crippled"]
    assert cli.main(["ant", "--out", str(out), *TINY, *options]) == 0
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert len([r for r in rows if r["part"] == "return"]) == 6
    assert len(list(out.glob("train-*.ckpt"))) == 1


def test_results_json_has_the_tuning_and_two_scoreboard_entries(tmp_path) -> None:
    """The fair protocol's record: every strategy's settings and time, and one scoreboard entry per condition
    from the primary metric (one-step prediction error) with every strategy's estimate and time."""
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY, *ONE_CELL, "--conditions", "healthy", "crippled"]) == 0
    payload = json.loads((out / "results.json").read_text())
    tuning = payload["tuning"]["M"]
    assert list(tuning["specs"]) == [*VARIANTS, "L", "SL"] and tuning["episodes"] == 4
    gd = tuning["specs"]["G"]["settings"]  # the grid's point, or one past its edge
    assert gd["lr"] > 0 and gd["steps"] >= 1 and gd["window"] >= 5 and gd["loss"] in ("mse", "huber", "tukey")
    members = [m["name"] for m in tuning["specs"]["C"]["settings"]["members"]]
    assert members == ["none", "gradient_descent", "smcd", "last_layer", "smcd_last_layer"]
    assert len(tuning["specs"]["S(paper)"]["settings"]["noise_std"]) == 41  # 3 x the held-out RMSE per dim
    assert all(math.isfinite(v) and v > 0 for v in tuning["ms_per_observation"].values())
    board = payload["scoreboard"]
    assert [e["task"] for e in board] == ["Ant one-step prediction (healthy)", "Ant one-step prediction (crippled)"]
    for entry, condition in zip(board, ("healthy", "crippled"), strict=True):
        assert entry["cell"] == {"condition": condition, "prediction": "one-step"} and entry["metric"] == "rmse"
        assert entry["unit"] == "observation units" and entry["lower_is_better"] is True
        ran = set(COLUMNS)  # every strategy of both networks
        assert set(entry["estimates"]) == ran and entry["estimates"]["combination"]["method"] == "M+C"
        assert entry["note"] == ant.TASK_NOTE  # T+S's network saw the crippled legs, M's did not
        assert all(e["trials"] == 6 for e in entry["estimates"].values())
        assert set(entry["ms_per_observation"]) == ran
        assert entry["ms_per_observation"]["SMCD (one-step)"] == tuning["ms_per_observation"]["S"]
        # Every verdict between strategies that ran, the last layers' too.
        assert all(v != "not compared" for v in entry["verdicts"].values())


def test_prediction_error_is_paired_over_the_same_episodes(tmp_path) -> None:
    """Every strategy is scored on the same logged episodes (episode k, its leg), and each adapted strategy
    is compared with M+N paired over them, per condition and metric.

    Only the structure is asserted, not that adaptation lowers the crippled Ant's error: at this test's
    scale (a 64-unit network fitted for seconds, 8 tuning episodes of 15 steps) the adapted strategies'
    one-step error is not below M+N's (M+S's is higher), so a threshold would test the scale, not the code.
    """
    out = tmp_path / "run"
    options = [*TINY, *ONE_CELL, "--conditions", "healthy", "crippled", "--prediction-episodes", "30"]
    options += ["--prediction-steps", "12"]
    assert cli.main(["ant", "--out", str(out), *options]) == 0
    payload = json.loads((out / "results.json").read_text())
    trials = [e for e in csv.DictReader(open(out / "trials.csv")) if e["part"] == "prediction"]
    for condition in ("healthy", "crippled"):
        by_method: dict[str, list[tuple[str, str]]] = {}
        for e in trials:
            if e["condition"] == condition:
                by_method.setdefault(e["method"], []).append((e["episode"], e["leg"]))
        assert set(by_method) == {"M+N", *ADAPTED, *TASK}
        assert len({tuple(v) for v in by_method.values()}) == 1 and len(by_method["M+N"]) == 30
        legs = {leg for _, leg in by_method["M+N"]}
        assert legs == {"-1"} if condition == "healthy" else legs <= {"0", "1", "2", "3"} and len(legs) > 1
        assert payload["prediction"]["legs"][condition] == [int(leg) for _, leg in by_method["M+N"]]
    pairs = {
        (c["condition"], c["prediction"], c["method"], c["against"])
        for c in payload["comparisons"]
        if c["part"] == "prediction"
    }
    for condition in ("healthy", "crippled"):
        for metric in ("one-step", "3-step"):
            assert all((condition, metric, m, "M+N") in pairs for m in ADAPTED)
            assert all((condition, metric, "M+S", m) in pairs for m in ADAPTED if m != "M+S")


def test_the_task_networks_data_and_tuning_episodes_hold_every_condition() -> None:
    # T trains on the healthy Ant and each crippled leg in equal shares, the condition as its task, and
    # is tuned on healthy and crippled episodes of its own seeds: the crippled legs are its training tasks.
    from smcd_rl.experiments.ant.config import AntConfig
    from smcd_rl.experiments.ant.prediction import random_episodes
    from smcd_rl.experiments.ant.task_network import task_data, task_tuning_episodes

    config = AntConfig(transitions=120, data_episode_steps=10, crippled_legs=(1, 3), tuning_episodes=4, tuning_steps=5)
    data = task_data(config)
    assert data.shape == (120,) and torch.bincount(data["task"]).tolist() == [40, 40, 40]
    m_episodes, _ = random_episodes({}, None, count=4, steps=5, seed=0)
    tuning = task_tuning_episodes(m_episodes, config)
    assert tuning.shape == (4, 5) and torch.equal(tuning[:2]["observation"], m_episodes[:2]["observation"])


def test_subset_of_cells_and_single_condition(tmp_path, capsys) -> None:
    out = tmp_path / "subset"
    options = ["--planners", "rs", "--adaptations", "N", "S", "--conditions", "crippled"]
    assert cli.main(["ant", "--out", str(out), *TINY, *options]) == 0
    rows = [r for r in csv.DictReader(open(out / "results.csv")) if r["part"] == "return"]
    assert {(r["planner"], r["method"], r["condition"]) for r in rows} == {
        ("RS", "M+N", "crippled"),
        ("RS", "M+S", "crippled"),
    }
    comparisons = [c for c in csv.DictReader(open(out / "comparisons.csv")) if c["part"] == "return"]
    assert [(c["planner"], c["condition"], c["method"], c["against"]) for c in comparisons] == [
        ("RS", "crippled", "M+S", "M+N")
    ]
    assert "crippled" in capsys.readouterr().out


def test_other_data_under_the_same_settings_retrains_and_reruns_the_cells(tmp_path, monkeypatch) -> None:
    """The checkpoint is named by the data's digest and the cell cache keyed by the trained model's:
    replacing the cached transitions (same settings, other content) trains a new model and reruns
    its cells instead of resuming the old training or reusing cells of the old model."""
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY, *ONE_CELL]) == 0
    stored = {p: torch.load(p, weights_only=False) for p in (out / "partial").glob("data-*.pt")}
    ((path, saved),) = [(p, s) for p, s in stored.items() if "task" not in s["value"]["data"].keys()]  # M's
    data = saved["value"]["data"]
    data.set("observation", data.get("observation") + 0.1)
    torch.save(saved, path)
    calls = []
    run_cell = ant.run_cell
    monkeypatch.setattr(ant, "run_cell", lambda *args, **kwargs: calls.append(args[1]) or run_cell(*args, **kwargs))
    assert cli.main(["ant", "--out", str(out), *TINY, *ONE_CELL]) == 0
    assert calls == [("rs", "N", "crippled")]
    assert len(list(out.glob("train-*.ckpt"))) == 2 and len(list(out.glob("T-*.ckpt"))) == 1  # T's data is its own


def test_stage_plan_counts_the_combinations_members() -> None:
    """C predicts with N, G and S in the planner's rollouts: its cell is planned at about their sum."""
    from smcd_rl.experiments.ant.plan import stage_costs

    costs = stage_costs(ant.AntConfig(adaptations=tuple(ant.METHOD_LABELS)))
    cell = {v: costs[f"evaluate cem/{v}/crippled"] for v in ant.METHOD_LABELS}
    assert cell["C"] > 0.9 * (cell["N"] + cell["G"] + cell["S"]) and cell["S(evidence)"] == cell["S"]
    assert all(f"prediction-healthy {v}" in costs for v in VARIANTS)


def test_help_lists_every_option(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["ant", "--help"])
    printed = capsys.readouterr().out
    assert exit_info.value.code == 0 and "--crippled-legs" in printed and "--noise-scale" in printed
    assert "--prediction-episodes" in printed and "--tuning-episodes" in printed and "--gd-lr" in printed


def test_full_preset_and_bad_options(capsys) -> None:
    config = cli.make_config("ant", {"full": True, "episodes": 7})
    assert config.episodes == 7 and config.hidden == 1024 and config.depth == 3
    assert config.transitions == 1_000_000 and config.episode_steps == 1000
    assert config.planners == tuple(ant.PLANNERS) and config.adaptations == tuple(ant.METHOD_LABELS)
    assert cli.make_config("ant", {}).hidden == ant.AntConfig().hidden
    assert ant.AntConfig().threads == 1
    for empty in ("planners", "adaptations", "conditions", "crippled_legs", "gd_lr", "calibrate_flips"):
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
        (["--adaptations", "S", "maml"], "--adaptations: unknown value 'maml'"),
        (["--prediction-horizon", "8"], "--prediction-steps (8) must be > --prediction-horizon (8)"),
        (["--calibrate-flips", "0.6"], "--calibrate-flips 0.6 is too large at dropout 0.1"),
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
