"""``smcd-rl interpret`` end to end at a tiny scale: files, tables with CIs, --dataset, resume, bad input, tuning."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest
import torch

from smcd_rl import cli
from smcd_rl.envs.drone_operators import save_dataset, simulate_operators
from smcd_rl.experiments.interpret import links as interpret_links
from smcd_rl.experiments.interpret import lookahead as interpret_lookahead
from smcd_rl.experiments.interpret import run as interpret
from smcd_rl.experiments.shared import stages
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, T_COLUMNS, TASK_MASKS
from smcd_rl.interpret import top_k_neighbour_accuracy
from tests.experiments.test_stages import planned_stages

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
    "--tuning-episodes",
    "4",
    "--tuning-steps",
    "5",
    "--tuning-horizon",
    "2",
    "--gd-lr",
    "0.01",
    "0.1",
    "--gd-steps",
    "1",
    "--gd-window",
    "5",
    "--calibrate-flips",
    "0.01",
    # A budget every tiny strategy fits on a loaded machine too: the budgeted choice is then the same every run.
    "--budget-ms",
    "1000",
]
FILES = (
    "results.csv",
    "trials.csv",
    "comparisons.csv",
    "results.json",
    "report.md",
    "fig9.csv",
    "confidence.csv",
    "lookahead.csv",
    "fig9.png",
    "fig4_skill_strategy.png",
    "fig13_phase_success.png",
    "fig14_lookahead.png",
    "dataset.npz",
    "bc_model.pt",
    "reptile_model.pt",
    "tuning-M.png",
)
#: Training checkpoints, named by the harness after the model, trainer, settings and data.
CHECKPOINTS = ("fig9_ld8-*.ckpt", "fig9_ld16-*.ckpt", "bc-*.ckpt", "reptile-*.ckpt")


#: A wall time in the printed text ("0.2 s", "1 min 5 s"): it follows the machine's speed and load, not the results.
WALL_TIME = re.compile(r"\b\d+(?:\.\d+)? (?:s|min|h)\b")
#: The header of a table's column of milliseconds per observation, measured like a wall time.
MS = "ms / observation"


def tables(printed: str) -> list[str]:
    """The printed tables, wall times and ms per observation masked, without the line naming the output directory."""
    lines, column = [], None
    for line in printed.splitlines():
        if line.startswith("wrote "):
            continue
        cells = line.split("|")
        if not line.startswith("|"):
            column = None  # a table ends at its first line that is not a row
        elif column is None and any(c.strip() == MS for c in cells):
            column = next(i for i, c in enumerate(cells) if c.strip() == MS)  # the header row
        elif column is not None and not set(cells[column]) <= set("-: "):
            cells[column] = " <ms> "
            line = "|".join(cells)
        lines.append(WALL_TIME.sub("<time>", line))
    return lines


def test_tables_mask_wall_times_only() -> None:
    first = (
        "Tuning of M on 4 held-out episodes x 5 steps (calibration 12 filter runs, 0.2 s; GD grid 2 runs, 1 min 5 s)"
    )
    again = first.replace("0.2 s", "0.1 s").replace("1 min 5 s", "1 min 7 s")
    assert tables(first) == tables(again) and "4 held-out episodes x 5 steps" in tables(first)[0]
    assert tables(first) != tables(first.replace("12 filter runs", "13 filter runs"))
    table = "| method | RMSE | ms / observation |\n|---|---|---|\n| M+S | 0.25 | 1.23 |\n| R+N | 0.5 | - |\n\nafter 1.5"
    timed_again = table.replace("1.23", "1.31")
    assert tables(table) == tables(timed_again) and "| M+S | 0.25 | <ms> |" in tables(table)
    assert tables(table) != tables(table.replace("0.25", "0.26")) and tables(table)[-1] == "after 1.5"


@pytest.mark.slow
def test_interpret_writes_results_and_an_interrupted_run_resumes_to_the_same_tables(
    tmp_path, capsys, monkeypatch
) -> None:
    first = tmp_path / "first"
    monkeypatch.setattr(stages, "RESUMED_SECONDS", 0.0)  # tiny stages count as timed: the time left shows
    assert cli.main(["interpret", "--out", str(first), *TINY]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "first") == [
        *("train fig9_ld8", "train fig9_ld16", "fig9 ld=8", "fig9 ld=16", "train bc"),
        *("confidence stored", "confidence known", "confidence unknown", "train reptile", "tune M"),
        *("lookahead M+N", "lookahead M+S", "lookahead R+N"),
    ]
    for name in FILES:
        assert (first / name).is_file(), name
    for pattern in CHECKPOINTS:
        assert len(list(first.glob(pattern))) == 1, pattern
    assert "Fig. 9" in printed and "| skill" in printed and "| M+S" in printed and "| R+N" in printed
    assert "M+S paired with M+N, M+G, M+S(evidence), M+S(paper) and M+C" in printed and "[95% CI]" in printed
    assert "Tuning of M on 4 held-out training-task episodes x 5 steps" in printed and MS in printed
    payload = json.loads((first / "results.json").read_text())
    assert (
        payload["dataset"]["train"]["trajectories"]
        + payload["dataset"]["known"]["trajectories"]
        + payload["dataset"]["unknown"]["trajectories"]
        == 24
    )
    for figure, metric in (("fig9", "accuracy"), ("confidence", "confidence"), ("lookahead", "rmse")):
        rows = payload[figure]
        assert rows and all(r[f"{metric}_low"] <= r[f"{metric}_mean"] <= r[f"{metric}_high"] for r in rows), figure
    assert all(0 <= r["confidence_mean"] <= 1 for r in payload["confidence"])
    assert all(0 <= r["accuracy_mean"] <= 1 for r in payload["fig9"])
    assert all(math.isfinite(r["rmse_mean"]) and r["rmse_mean"] > 0 for r in payload["lookahead"])
    # Each method of the tuned network M is timed; R was not tuned (no R method adapts): R+N has no time.
    timed = {r["method"]: r.get("ms_per_observation") for r in payload["lookahead"]}
    assert all(0 < timed[m] < math.inf for m in ("M+N", "M+S")) and timed["R+N"] is None
    # Every adaptive method paired with M+N and with each other on the same trajectories, in each cell.
    pairs = {(c["figure"], c.get("set", ""), c["method"], c["against"]) for c in payload["comparisons"]}
    for set_name in ("known", "unknown"):
        assert {("lookahead", set_name, "M+S", "M+N"), ("lookahead", set_name, "R+N", "M+N")} <= pairs
        assert ("lookahead", set_name, "M+S", "R+N") in pairs
    assert {c["verdict"] for c in payload["comparisons"]} <= {"better", "worse", "no significant difference"}
    with open(first / "results.csv") as handle:
        figures = {row["figure"] for row in csv.DictReader(handle)}
    assert figures == {"fig9", "confidence", "lookahead"}
    with open(first / "trials.csv") as handle:
        trials = list(csv.DictReader(handle))
    lookahead_trials = [t for t in trials if t["figure"] == "lookahead" and t["method"] == "M+S"]
    assert len(lookahead_trials) == sum(r["trials"] for r in payload["lookahead"] if r["method"] == "M+S")
    report = (first / "report.md").read_text()
    assert "Fig. 14" in report and all(f"({name})" in report for name in FILES if name.endswith(".png"))

    # The run is interrupted in its second look-ahead method, and resumes to the same tables.
    second = tmp_path / "second"
    real = interpret_lookahead.evaluate_lookahead
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # M+N known, M+N unknown, then M+S
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(interpret_lookahead, "evaluate_lookahead", interrupted)
    assert cli.main(["interpret", "--out", str(second), *TINY]) == 130
    assert "interrupted; run the same command again to resume" in capsys.readouterr().err

    def counted(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    calls["n"] = 0
    monkeypatch.setattr(interpret_lookahead, "evaluate_lookahead", counted)
    assert cli.main(["interpret", "--out", str(second), *TINY]) == 0
    assert calls["n"] == 4  # M+S and R+N for both sets; M+N came from the cache
    assert tables(capsys.readouterr().out) == tables(printed)

    # The same data as a user's --dataset: Fig. 9 is the same; M and R are fitted without the
    # training flights held out for tuning, so Figs. 4/13/14 are of other networks.
    third = tmp_path / "third"
    assert cli.main(["interpret", "--out", str(third), "--dataset", str(first / "dataset.npz"), *TINY]) == 0
    printed_third = capsys.readouterr().out
    assert tables(printed_third.split("Figs. 4 / 13")[0]) == tables(printed.split("Figs. 4 / 13")[0])
    held_out = json.loads((third / "results.json").read_text())["dataset"]
    assert held_out == payload["dataset"]  # the split is the same; the tuning flights come out of "train"


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
    out = tmp_path / "run"
    missing = ["interpret", "--out", str(out), "--parts", "confidence", "--dataset", str(tmp_path / "none.npz")]
    assert cli.main(missing) == 2
    assert "no such file" in capsys.readouterr().err
    assert not out.exists()  # refused by validate(), before the output directory is made
    path = _user_dataset(tmp_path, drop_label="phase")
    assert cli.main(["interpret", "--out", str(out), "--parts", "confidence", "--dataset", str(path)]) == 2
    error = capsys.readouterr().err
    assert "phase" in error and "--labels" in error
    path = _user_dataset(tmp_path, drop_key="operator")
    assert cli.main(["interpret", "--out", str(out), "--parts", "confidence", "--dataset", str(path)]) == 2
    assert "lacks key" in capsys.readouterr().err
    # A dataset's own faults show only once it is read, but still before it is copied or trained on.
    assert not list(out.glob("*.ckpt")) and not (out / "dataset.npz").exists()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--particles", "-5"], "--particles must be >= 1"),
        (["--epochs", "0"], "--epochs must be >= 1"),
        (["--fig9-epochs", "0"], "--fig9-epochs must be >= 1"),
        (["--fig9-arms", "1"], "--fig9-arms must be >= 2"),
        (["--fig9-ks", "0"], "--fig9-ks must be >= 1"),
        (["--fig9-arms", "10", "--fig9-ks", "20"], "--fig9-ks must be at most --fig9-arms - 1 = 9"),
        (["--methods", "M+X"], "--methods: unknown value 'M+X'"),
        (["--parts", "fig10"], "--parts: unknown value 'fig10'"),
        (["--labels", "colour"], "--labels: the simulated operators have no ['colour']"),
        (["--burn-in", "1.5"], "--burn-in must be < 1.0"),
        (["--horizons", "0"], "--horizons must be > 0.0"),
        (["--dropout", "1"], "--dropout must be < 1.0"),
        (["--flip-prob", "1.5"], "--flip-prob must be <= 1.0"),
        (["--known-fraction", "0.6", "--unknown-fraction", "0.5"], "--known-fraction + --unknown-fraction"),
        (["--operators", "1"], "--operators must be >= 2"),
        (["--k", "0"], "--k must be >= 1"),
        (["--steps", "0"], "--steps must be >= 1"),
        (["--chunk", "0"], "--chunk must be >= 1"),
        (["--noise-scale", "0"], "--noise-scale must be > 0.0"),
        (["--reptile-lr", "-1"], "--reptile-lr must be > 0.0"),
        (["--threads", "-1"], "--threads must be >= 0"),
    ],
)
def test_bad_options_are_refused_before_any_training(tmp_path, capsys, option, message) -> None:
    """Validation runs before any work: nothing is trained, not even the output directory made."""
    out = tmp_path / "run"
    assert cli.main(["interpret", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_empty_lists_are_refused() -> None:
    """The command line cannot give an empty list (nargs="+"), but a config built in Python can."""
    for name in interpret.InterpretConfig.NON_EMPTY:
        with pytest.raises(ValueError, match=f"--{name.replace('_', '-')} needs at least one value"):
            interpret.run(interpret.InterpretConfig(out="/tmp/never", **{name: ()}), progress=False)


def test_overwriting_the_dataset_file_retrains_and_recomputes(tmp_path, capsys, monkeypatch) -> None:
    """Checkpoints and cached results follow the dataset's content, not its path.

    (The command once kept the model in ``bc.ckpt``, which refused to resume on the new data.)
    """
    path, out = tmp_path / "flights.npz", tmp_path / "run"
    save_dataset(simulate_operators(num_operators=4, trajectories_per_operator=3, seed=0), path)
    argv = ["interpret", "--out", str(out), "--dataset", str(path), "--parts", "lookahead", *TINY, "--methods", "M+N"]
    real, calls = interpret_lookahead.evaluate_lookahead, {"n": 0}

    def counted(*args, **kwargs):
        calls["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(interpret_lookahead, "evaluate_lookahead", counted)
    assert cli.main(argv) == 0
    before = json.loads((out / "results.json").read_text())["lookahead"]
    assert calls["n"] == 2  # M+N on the known and the unknown operators
    assert cli.main(argv) == 0 and calls["n"] == 2  # the same file: everything from the cache
    save_dataset(simulate_operators(num_operators=4, trajectories_per_operator=3, seed=1), path)
    assert cli.main(argv) == 0
    capsys.readouterr()
    assert calls["n"] == 4  # the new content: evaluated afresh
    assert len(list(out.glob("bc-*.ckpt"))) == 2  # and trained afresh, beside the first model
    assert json.loads((out / "results.json").read_text())["lookahead"] != before


@pytest.mark.slow
def test_lookahead_tunes_on_held_out_flights_and_writes_a_scoreboard_entry(tmp_path, capsys) -> None:
    """The fair protocol: every method tuned on the tuning flights, timed, six strategies on the scoreboard."""
    out = tmp_path / "run"
    methods = ["--methods", "M+N", "M+G", "M+S", "M+S(evidence)", "M+S(paper)", "M+C", "M+L", "M+SL"]
    assert cli.main(["interpret", "--out", str(out), "--parts", "lookahead", *TINY, *methods]) == 0
    printed = capsys.readouterr().out
    assert all(f"| {m} " in printed for m in methods[1:]) and "Tuning of M on 4" in printed
    assert "tuned under 1000 ms per observation" in printed  # smcd_rl.tune's budgeted table
    payload = json.loads((out / "results.json").read_text())
    assert set(payload["tuning"]) == {"M"}  # no R method ran: only M is tuned
    tuning = payload["tuning"]["M"]
    assert tuning["episodes"] == 4 and tuning["steps"] == 5
    specs = tuning["specs"]
    assert set(specs) == {m[2:] for m in methods[1:]}  # the variants that run, each tuned
    assert specs["G"]["name"] == "gradient_descent" and specs["C"]["name"] == "combination"
    assert specs["S"]["name"] == specs["S(evidence)"]["name"] == "smcd"
    paper = specs["S(paper)"]["settings"]
    assert paper["flip_prob"] == interpret.InterpretConfig().flip_prob
    assert len(paper["noise_std"]) == 3  # noise-scale x M's training RMSE per action dim
    assert all(0 < ms < math.inf for ms in tuning["ms_per_observation"].values())
    # The results table's rows carry each method's time, the one the tuning measured.
    rows = [r for r in payload["lookahead"] if r["method"] in methods]
    assert all(r["ms_per_observation"] == tuning["ms_per_observation"][r["method"][2:]] for r in rows)
    board = payload["scoreboard"]
    assert board["task"] == "drone look-ahead" and board["cell"] == {"set": "unknown", "burn_in": 0.5, "horizon": 0.25}
    ran = set(COLUMNS) - {TASK_MASKS, *T_COLUMNS}  # no task masks here
    assert set(board["estimates"]) == ran == set(board["ms_per_observation"])
    assert {e["method"] for e in board["estimates"].values()} == set(methods[1:])
    assert all(v != "not compared" for v in board["verdicts"].values())
    assert all(0 < ms < math.inf for ms in board["ms_per_observation"].values())
    pairs = {(c["method"], c["against"]) for c in payload["comparisons"]}
    assert {("M+S", m) for m in ("M+N", "M+G", "M+S(evidence)", "M+S(paper)", "M+C")} <= pairs
    assert {("M+C", "M+N"), ("M+C", "M+G"), ("M+S(evidence)", "M+N")} <= pairs
    assert (out / "tuning-M.png").is_file()
    # Without the look-ahead part: no tuning, no scoreboard entry.
    other = tmp_path / "other"
    assert cli.main(["interpret", "--out", str(other), "--parts", "confidence", *TINY]) == 0
    capsys.readouterr()
    assert not {"tuning", "scoreboard"} & set(json.loads((other / "results.json").read_text()))


def test_tuning_flights_are_never_test_flights() -> None:
    """Simulated: fresh operators' flights; a --dataset: training flights held out of the fit, each operator kept."""
    config = interpret.InterpretConfig(tuning_episodes=5, tuning_steps=10)
    flights, fit = interpret_lookahead.tuning_flights(config, None, None)
    assert fit is None and flights.num_trajectories == 5 and (flights.lengths >= 10).all()
    data = simulate_operators(num_operators=6, trajectories_per_operator=4, seed=0)
    assert not any(np.array_equal(flights.state[:10], data.select([i]).state[:10]) for i in range(24))
    split = interpret.drone.split_dataset(data, known_fraction=0.1, unknown_fraction=0.2, seed=0)
    config = interpret.InterpretConfig(tuning_episodes=5, tuning_steps=10, dataset="given.npz")
    flights, fit = interpret_lookahead.tuning_flights(config, data, split)
    assert fit is not None and flights.num_trajectories == 5
    held_out = np.setdiff1d(split["train"], fit)
    assert len(held_out) == 5 and not set(held_out) & (set(split["known"]) | set(split["unknown"]))
    assert set(data.operator[fit]) == set(data.operator[split["train"]])  # every training operator still fitted
    episodes = interpret_lookahead.tuning_episodes(flights, config, torch.device("cpu"))
    assert episodes.batch_size == torch.Size([5, 10]) and set(episodes.keys()) == {"state", "action"}
    with pytest.raises(ValueError, match="--tuning-steps"):
        interpret_lookahead.tuning_episodes(flights.select([0]), config, torch.device("cpu"))


def test_neighbour_hits_average_to_the_top_k_accuracy() -> None:
    generator = torch.Generator().manual_seed(0)
    masks, lengths = torch.rand(30, 16, generator=generator).round(), torch.rand(30, 2, generator=generator)
    hits = interpret_links.neighbour_hits(masks, lengths, (1, 3, 10))
    assert hits.shape == (30, 3) and set(hits.unique().tolist()) <= {0.0, 1.0}
    assert torch.allclose(hits.mean(0).float(), top_k_neighbour_accuracy(masks, lengths, [1, 3, 10]))


def test_simulated_labels_are_those_the_simulation_writes() -> None:
    assert set(interpret.SIMULATED_LABELS) == set(
        simulate_operators(num_operators=2, trajectories_per_operator=1).labels
    )


def test_help_and_full_preset(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["interpret", "--help"])
    assert exit_info.value.code == 0 and "--dataset" in capsys.readouterr().out
    config = cli.make_config("interpret", {"full": True, "particles": 7})
    assert config.particles == 7 and config.hidden == interpret.FULL["hidden"] and config.epochs == 400
    assert cli.make_config("interpret", {}).hidden == interpret.InterpretConfig().hidden
    assert interpret.InterpretConfig().threads == 1 and interpret.FULL["threads"] == 0


@pytest.mark.slow
def test_the_task_mask_network_is_trained_on_operators_and_reaches_the_scoreboard(tmp_path) -> None:
    """T+S runs on a network whose masks were trained per operator, tuned like M's methods, paired with M+S."""
    import smcd_rl

    out = tmp_path / "run"
    methods = ["--methods", "M+N", "M+S", "T+S", "--mask-groups", "4"]
    assert cli.main(["interpret", "--out", str(out), "--parts", "lookahead", *TINY, *methods]) == 0
    payload = json.loads((out / "results.json").read_text())
    assert set(payload["tuning"]) == {"M", "T"} and len(payload["task_train_loss"]) == 1  # --epochs 1
    assert smcd_rl.load(out / "task_model.pt").net.mask_dim == 2 * 4  # 4 bits in each of its 2 layers
    board = payload["scoreboard"]
    assert board["estimates"][TASK_MASKS]["method"] == "T+S"
    assert board["verdicts"]["SMCD (task masks) vs SMCD (one-step)"] != "not compared"
