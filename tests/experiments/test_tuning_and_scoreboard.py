"""The fair protocol (experiments.tuning) and ``smcd-rl scoreboard``."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from dataclasses import dataclass

import pytest
import torch

import smcd_rl
from smcd_rl import cli
from smcd_rl.experiments.scoreboard import run as scoreboard
from smcd_rl.experiments.shared import references, tuned_methods, tuning
from smcd_rl.experiments.shared.adaptations import AdaptationConfig
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.scoreboard_entry import scoreboard_entry
from smcd_rl.experiments.shared.stats import cell_statistics
from smcd_rl.tuning.calibration import calibrate
from smcd_rl.tuning.diagnostics import trace
from tests.core.test_calibration import SIGMA, known_mask_episodes


@dataclass
class TinyConfig(AdaptationConfig):
    particles: int = 256
    noise_std: float = 0.3  # the "paper" setting: far from the data's true noise on purpose


def test_tune_chooses_from_the_held_out_episodes_and_keeps_the_paper_setting(tmp_path, monkeypatch) -> None:
    model, episodes, _ = known_mask_episodes(episodes=6, steps=12)
    config = TinyConfig(out=str(tmp_path), gd_lr=(1e-4, 0.03), gd_steps=(1, 3), gd_window=(4,))
    with Experiment(config, progress=False) as ex:
        result = tuning.tune(ex, model, episodes, config)
    assert set(result.specs) == set(tuning.VARIANTS)
    # G and S are smcd_rl.tune's choices by one-step error; the model keeps that record.
    best_of = model.tuning["best_of"]
    assert result.specs["G"]["settings"] == best_of["gradient_descent"]["settings"]
    assert result.specs["S"]["settings"] == best_of["smcd"]["settings"]
    assert result.strategy("G", seed=0).lr >= 0.03  # 1e-4 barely moves the weights in 12 steps
    # The evidence lands near the episodes' true noise; the one-step criterion picks the noise that
    # predicts best (its diagnosis repeats the tuned run: same seed) and beats the paper's far-off
    # noise; S(paper) keeps --noise-std exactly.
    noise = result.strategy("S(evidence)", seed=0).noise_std
    rms = math.sqrt(sum(v * v for v in noise) / len(noise)) if isinstance(noise, list) else noise
    assert SIGMA / 2 < rms < 2 * SIGMA
    assert result.traces["S"]["rmse"] == pytest.approx(best_of["smcd"]["one_step_rmse"], rel=1e-6)
    assert result.traces["S"]["rmse"] < result.traces["S(paper)"]["rmse"]
    # The diagnosis takes tuning's own runs where it has them: each equals a fresh run of the variant
    # (G's, raced, joins two runs: the same errors per episode, its means pooled in another order).
    for variant in ("N", "G", "S", "S(evidence)", "S(paper)", "L", "SL"):
        fresh = trace(model, episodes, result.strategy(variant, seed=config.seed + 23)).to_dict()
        kept = result.traces[variant]
        assert kept["one_step_errors"] == fresh["one_step_errors"], variant
        for field, value in fresh.items():
            if field != "one_step_errors":
                assert kept[field] == pytest.approx(value, rel=1e-12), (variant, field)
    paper = result.strategy("S(paper)", seed=0)
    assert isinstance(paper, smcd_rl.SMCD) and paper.noise_std == 0.3 and paper.flip_prob == config.flip_prob
    combination = result.strategy("C", seed=0)
    # It mixes no adaptation and every tuned strategy: G, S, the last layer and SMCD with a readout.
    assert isinstance(combination, smcd_rl.Combination) and len(combination.members) == 5
    # Every variant has a measured time per observation, in the table too.
    assert set(result.ms) == set(tuning.VARIANTS) and all(0 < ms < math.inf for ms in result.ms.values())
    assert "ms / observation" in result.table()
    # The calibrated filter explains the episodes better than the paper's, by its own evidence.
    assert result.traces["S(evidence)"]["log_evidence"][-1] > result.traces["S(paper)"]["log_evidence"][-1]
    tables = result.tables()
    assert "held-out" in result.caption() and any("under 10 ms" in caption for caption in tables)
    # The options are measured on the same episodes, each a finite one-step error.
    assert set(result.options) == {*tuning.OPTIONS, tuning.STUDENT}
    assert all(math.isfinite(t["rmse"]) for t in result.options.values()) and "5x particles" in result.table()
    result.plot(tmp_path / "tuning.png")
    assert (tmp_path / "tuning.png").stat().st_size > 0

    # A rerun reads the stored result: nothing is tuned or calibrated again.
    def refuse(*args, **kwargs):
        raise AssertionError("tuning ran again")

    monkeypatch.setattr(references, "calibrate", refuse)
    monkeypatch.setattr(smcd_rl, "tune", refuse)
    with Experiment(config, progress=False) as ex:
        again = tuning.tune(ex, model, episodes, config)
    assert again.specs == result.specs and again.ms == result.ms
    monkeypatch.undo()

    # Without the options the same choice is made (from a tuning of its own, not the stored one):
    # besides smcd_rl.tune only the evidence calibration runs, Gaussian, and the table lists the variants.
    calls = []
    monkeypatch.setattr(
        references, "calibrate", lambda *a, **k: calls.append(k["base"].likelihood) or calibrate(*a, **k)
    )
    with Experiment(config, progress=False) as ex:
        lean = tuning.tune(ex, model, episodes, config, options=False)
    assert calls == ["gaussian"] and lean.options == {}
    assert {v: s for v, s in lean.specs.items() if v != "C"} == {v: s for v, s in result.specs.items() if v != "C"}
    assert "5x particles" not in lean.table() and len(lean.table().splitlines()) == 2 + len(tuning.VARIANTS)


def test_a_network_that_runs_only_gd_is_tuned_for_gd_only(tmp_path, monkeypatch) -> None:
    """An experiment passes the variants its methods use: no SMCD calibration, reference or option runs for G alone."""
    model, episodes, _ = known_mask_episodes(episodes=4, steps=8)
    config = TinyConfig(out=str(tmp_path), gd_lr=(0.03,), gd_steps=(1,), gd_window=(4,))

    def refuse(*args, **kwargs):
        raise AssertionError("SMCD was calibrated for a network that runs only G")

    monkeypatch.setattr(references, "calibrate", refuse)
    monkeypatch.setattr("smcd_rl.experiments.shared.tuning_options.calibrate", refuse)
    with Experiment(config, progress=False) as ex:
        result = tuning.tune(ex, model, episodes, config, variants=("G",))
    assert set(result.specs) == set(result.ms) == set(result.traces) == {"N", "G"} and result.options == {}
    assert set(model.tuning["best_of"]) == {"none", "gradient_descent"}
    with Experiment(config, progress=False) as ex, pytest.raises(ValueError, match=r"unknown variants \['X'\]"):
        tuning.tune(ex, model, episodes, config, variants=("G", "X"))


@dataclass
class LookaheadConfig(TinyConfig):
    tuning_horizon: int = 1


def test_a_stored_tuning_is_reused_only_for_the_same_horizon(tmp_path, monkeypatch) -> None:
    """The horizon decides what every setting is scored by: a tuning by one-step error is not one by
    a 3-step look-ahead, so a rerun with another ``--tuning-horizon`` must tune again."""
    model, episodes, _ = known_mask_episodes(episodes=4, steps=8)
    config = LookaheadConfig(out=str(tmp_path), gd_lr=(0.03,), gd_steps=(1,), gd_window=(4,))
    criteria = []
    real = smcd_rl.tune
    monkeypatch.setattr(smcd_rl, "tune", lambda *a, **k: criteria.append(k.get("horizon")) or real(*a, **k))
    for horizon in (1, 1, 3):
        with Experiment(dataclasses.replace(config, tuning_horizon=horizon), progress=False) as ex:
            tuning.tune(ex, model, episodes, dataclasses.replace(config, tuning_horizon=horizon), variants=("G",))
    # The first run tunes (free and budgeted), the second reuses it, the third tunes by its horizon.
    assert criteria == [None, None, 3, 3]


def test_unknown_variant_is_refused() -> None:
    specs = {
        "G": {"name": "gradient_descent", "settings": {"lr": 0.1, "steps": 1, "window": 2}},
        "S": {"name": "smcd", "settings": {"num_particles": 8, "noise_std": 0.1, "flip_prob": 0.01, "seed": 0}},
    }
    result = tuning.Tuning("M", specs, {"G": 1.0, "S": 1.0}, {}, {}, {}, {}, episodes=2, steps=2)
    with pytest.raises(ValueError, match="unknown strategy 'X'"):
        result.strategy("X", seed=0)
    # A method's strategy: N needs no tuning; the others come from their network's.
    assert isinstance(tuned_methods.strategy_for("R+N", {}, seed=0), smcd_rl.NoAdaptation)
    assert tuned_methods.strategy_for("M+G", {"M": result}, seed=0).lr == 0.1
    with pytest.raises(ValueError, match="R was not tuned"):
        tuned_methods.strategy_for("R+S", {"M": result}, seed=0)
    # The seed given replaces the tuned one: two seeds, two filters.
    a, b = (result.strategy("S", seed=seed) for seed in (1, 2))
    assert a._generator.initial_seed() == 1 and b._generator.initial_seed() == 2
    assert tuned_methods.ms_column(["M+G", "M+N", "R+S", "O+P"], {"M": result}) == {"M+G": 1.0}


def test_an_empty_grid_is_refused_before_any_work(tmp_path) -> None:
    with pytest.raises(ValueError, match="--gd-lr needs at least one value"):
        TinyConfig(out=str(tmp_path / "x"), gd_lr=()).validate()
    assert not (tmp_path / "x").exists()


def fake_run(
    path, task: str, *, better: bool, adaptive: tuple[str, ...] = ("M+S(evidence)", "M+S(paper)", "M+G")
) -> None:
    """A run directory whose results.json holds a scoreboard entry built from known scores (no one-step SMCD)."""
    torch.manual_seed(0)
    base = torch.rand(40) + 1.0
    shift = -0.5 if better else 0.0
    scores = {
        (10,): {
            "M+N": base,
            "M+G": base - 0.2,
            "M+S(paper)": base - 0.1,
            "M+S(evidence)": base + shift + 0.01 * torch.randn(40),
        }
    }
    rows, comparisons = cell_statistics(scores, cell=("T",), baseline="M+N", adaptive=adaptive, metric="rmse")
    entry = scoreboard_entry(task, rows, comparisons, cell={"T": 10}, metric="rmse", unit="m")
    path.mkdir()
    (path / "results.json").write_text(json.dumps({"scoreboard": entry}))


def test_scoreboard_tables_every_run_with_its_verdicts(tmp_path, capsys) -> None:
    fake_run(tmp_path / "a", "task a", better=True)
    fake_run(
        tmp_path / "b", "task b", better=False, adaptive=("M+G", "M+S(paper)", "M+S(evidence)")
    )  # pairs (M+G, M+S...)
    out = tmp_path / "board"
    assert cli.main(["scoreboard", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 0
    means, verdicts = printed_tables(capsys.readouterr().out)
    # a: calibrated SMCD 0.5 below none and 0.3 below GD; b: it ties none and loses to GD. In both,
    # SMCD (paper) is 0.1 below none and 0.1 above GD. b's pairs are stored as (GD, SMCD): read reversed.
    assert [v.split(" ")[0] for v in verdicts["task a"]] == ["better", "better", "better", "worse"]
    assert verdicts["task a"][3] == "worse 0.100 [0.100, 0.100]"
    b = verdicts["task b"]
    assert b[0].startswith("no significant difference") and b[1].startswith("worse 0.2")
    assert b[2].startswith("better -0.1") and b[3].startswith("worse 0.1")
    assert means["task b"][0] == "rmse (m)" and means["task b"][1] == "T=10"  # the metric and its unit, the cell
    for name in ("results.csv", "results.json", "scoreboard.png", "scoreboard.json", "report.md"):
        assert (out / name).is_file(), name


def printed_tables(printed: str) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """The scoreboard's printed tables, task -> the row's other cells: metric and cell joined to the means, verdicts."""
    tables: list[dict[str, list[str]]] = []
    current: dict[str, list[str]] | None = None
    lines = printed.splitlines() + [""]
    for line, below in itertools.pairwise(lines):
        if below.startswith("|-"):  # a header: a table of tasks, or another (the decision table)
            current = {} if line.startswith("| task ") else None
            if current is not None:
                tables.append(current)
        elif line.startswith("| ") and not line.startswith("|-") and current is not None:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            current[cells[0]] = cells[1:]
    summary, tasks, means, verdicts = tables[:4]  # the compact table first, then the scoreboard's
    assert list(summary) == list(tasks)
    return {task: [*tasks[task], *cells] for task, cells in means.items()}, verdicts


def test_smcd_on_task_masks_has_a_column_and_verdicts_only_where_it_ran(tmp_path, capsys) -> None:
    torch.manual_seed(0)
    base = torch.rand(40) + 1.0
    scores = {(10,): {"M+N": base, "M+G": base - 0.2, "M+S": base - 0.1, "T+S": base - 0.3}}
    adaptive = ("T+S", "M+S", "M+G")
    rows, comparisons = cell_statistics(scores, cell=("T",), baseline="M+N", adaptive=adaptive, metric="rmse")
    note = "T saw the test condition in training"
    entry = scoreboard_entry("with T", rows, comparisons, cell={"T": 10}, metric="rmse", unit="m", note=note)
    assert entry["estimates"]["SMCD (task masks)"]["method"] == "T+S" and entry["note"] == note
    # T+S is 0.1 below GD and 0.2 below one-step SMCD on every trial.
    assert entry["verdicts"]["SMCD (task masks) vs GD"] == "better -0.100 [-0.100, -0.100]"
    assert entry["verdicts"]["SMCD (task masks) vs SMCD (one-step)"] == "better -0.200 [-0.200, -0.200]"
    without = scoreboard_entry("no T", rows[:3], comparisons, cell={"T": 10}, metric="rmse", unit="m")
    assert "SMCD (task masks)" not in without["estimates"] and not any("task masks" in v for v in without["verdicts"])
    for name, e in (("t", entry), ("plain", without)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps({"scoreboard": e}))
    out = tmp_path / "board"
    assert cli.main(["scoreboard", str(tmp_path / "t"), str(tmp_path / "plain"), "--out", str(out)]) == 0
    report = (out / "report.md").read_text()
    table = report.split("(T+S), where it ran")[1]
    assert "| task masks vs GD " in table and "| with T " in table and "| no T " not in table.split("**")[1]
    # A task's note is listed under the tables, beside its task only.
    notes = report.split("Notes: what to know before comparing")[1].split("**")[1]
    assert f"| with T | {note} |" in notes and "| no T " not in notes


def test_two_runs_of_one_experiment_are_labelled_by_their_run_directories(tmp_path, capsys) -> None:
    """Two runs of the same experiment used to print two rows labelled alike."""
    fake_run(tmp_path / "seed0", "task a", better=True)
    fake_run(tmp_path / "seed1", "task a", better=False)
    fake_run(tmp_path / "other", "task b", better=True)
    runs = [str(tmp_path / name) for name in ("seed0", "seed1", "other")]
    assert cli.main(["scoreboard", *runs, "--out", str(tmp_path / "board")]) == 0
    means, verdicts = printed_tables(capsys.readouterr().out)
    expected = [f"task a ({runs[0]})", f"task a ({runs[1]})", "task b"]  # a task only one run has keeps its name
    assert list(means) == list(verdicts) == expected
    assert verdicts[expected[0]][0].startswith("better") and not verdicts[expected[1]][0].startswith("better")


def test_the_scoreboard_is_drawn_again_from_its_scoreboard_json(tmp_path, capsys) -> None:
    fake_run(tmp_path / "a", "task a", better=True)
    fake_run(tmp_path / "b", "task b", better=False)
    first = tmp_path / "board"
    assert cli.main(["scoreboard", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(first)]) == 0
    again = scoreboard.render(first / "scoreboard.json", out=tmp_path / "again", progress=False)
    capsys.readouterr()

    def body(report: str) -> str:  # all but the wall time and the output directory
        return "\n".join(line for line in report.splitlines() if not line.startswith(("Wall time", '  "out"')))

    assert body((tmp_path / "again" / "report.md").read_text()) == body((first / "report.md").read_text())
    assert again["runs"] == [str(tmp_path / "a"), str(tmp_path / "b")]
    assert json.loads((tmp_path / "again" / "scoreboard.json").read_text()) == json.loads(
        (first / "scoreboard.json").read_text()
    )
    with pytest.raises(ValueError, match="holds .*scoreboard.json, which this would replace"):
        scoreboard.render(first / "scoreboard.json", out=first, progress=False)
    (tmp_path / "bad.json").write_text(json.dumps({"format": scoreboard.JSON_FORMAT, "runs": ["a"], "entries": [{}]}))
    with pytest.raises(ValueError, match="bad.json: entry 0 has no run directory 'run'; rerun smcd-rl scoreboard"):
        scoreboard.render(tmp_path / "bad.json", out=tmp_path / "x", progress=False)


def test_scoreboard_names_a_directory_without_results(tmp_path, capsys) -> None:
    assert cli.main(["scoreboard", str(tmp_path), "--out", str(tmp_path / "board")]) == 2
    assert "no results.json" in capsys.readouterr().err
    (tmp_path / "results.json").write_text(json.dumps({"experiment": "bench"}))
    assert cli.main(["scoreboard", str(tmp_path), "--out", str(tmp_path / "board")]) == 2
    assert "no scoreboard entry" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["scoreboard"])  # at least one run directory


def test_scoreboard_never_overwrites_a_run_and_checks_every_entry(tmp_path, capsys) -> None:
    fake_run(tmp_path / "a", "task a", better=True)
    before = (tmp_path / "a" / "results.json").read_text()
    # --out one of the runs: refused before anything is written (it once replaced that run's results)
    assert cli.main(["scoreboard", str(tmp_path / "a"), "--out", str(tmp_path / "a")]) == 2
    assert "is one of the run directories" in capsys.readouterr().err
    assert (tmp_path / "a" / "results.json").read_text() == before
    assert cli.main(["scoreboard", str(tmp_path / "a"), str(tmp_path / "a") + "/", "--out", str(tmp_path / "o")]) == 2
    assert "same directory" in capsys.readouterr().err
    for name, entry, message in [
        ("strings", ["a"], "is a str, not a mapping"),
        ("nocell", {"task": "x"}, "has no dict 'cell'"),
        ("badmean", {**json.loads(before)["scoreboard"], "estimates": {"none": {"mean": "a"}}}, "needs numbers"),
        ("empty", [], "scoreboard list is empty"),
    ]:
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps({"scoreboard": entry}))
        assert cli.main(["scoreboard", str(tmp_path / name), "--out", str(tmp_path / "out")]) == 2, name
        assert message in capsys.readouterr().err, name
    assert not (tmp_path / "out").exists()  # every input is checked before --out is made
    # a scoreboard's own output is not a run, and --out never replaces another command's results
    assert cli.main(["scoreboard", str(tmp_path / "a"), "--out", str(tmp_path / "board")]) == 0
    assert cli.main(["scoreboard", str(tmp_path / "a"), str(tmp_path / "board"), "--out", str(tmp_path / "b2")]) == 2
    assert "a scoreboard's output" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "results.json").write_text(json.dumps({"experiment": "two-link look-ahead"}))
    assert cli.main(["scoreboard", str(tmp_path / "a"), "--out", str(tmp_path / "other")]) == 2
    assert "holds the results of another command" in capsys.readouterr().err


def test_the_scoreboard_refuses_bad_entries_by_file_and_entry_and_keeps_out_as_it_was(tmp_path, capsys) -> None:
    """Each entry once failed only after --out was written (an empty min(), a negative error bar) or
    was dropped without a word (a misspelt column); now each is refused first, by name."""
    fake_run(tmp_path / "a", "task a", better=True)
    good = json.loads((tmp_path / "a" / "results.json").read_text())["scoreboard"]
    out = tmp_path / "board"
    assert cli.main(["scoreboard", str(tmp_path / "a"), "--out", str(out)]) == 0
    before = {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()}
    none = good["estimates"]["none"]
    for name, change, message in [
        ("nan", {"estimates": {c: {**e, "mean": math.nan} for c, e in good["estimates"].items()}}, "is not finite"),
        ("no estimates", {"estimates": {}}, "has no estimates"),
        ("swapped", {"estimates": {"none": {**none, "low": none["high"], "high": none["low"]}}}, "low .* above high"),
        ("misspelt", {"estimates": {**good["estimates"], "last-layer": none}}, "unknown estimate column 'last-layer'"),
        ("verdict", {"verdicts": {"GD vs SMCD": "better"}}, "unknown verdict 'GD vs SMCD'"),
        ("ms", {"ms_per_observation": {"GD": -1.0}}, "milliseconds"),
    ]:
        run = tmp_path / name.replace(" ", "-")
        run.mkdir()
        (run / "results.json").write_text(json.dumps({"scoreboard": {**good, **change}}))
        assert cli.main(["scoreboard", str(tmp_path / "a"), str(run), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err
        assert re.search(message, err) and f"{run}/results.json: scoreboard entry 0" in err, (name, err)
        assert {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()} == before, name


def test_the_summary_answers_both_questions_by_network_from_the_entrys_pairs(tmp_path, capsys) -> None:
    """Known scores per trial: on M, SMCD (0.3 below none) is better than the best of GD and the last
    layer (0.25 below); on T, T+S (0.4 below) is worse than T+L (0.5 below); across both networks
    the best SMCD-family strategy is T+S and the best other T+L. Each verdict is read from the
    entry's pairs, over the same trials."""
    torch.manual_seed(0)
    base = torch.rand(40) + 1.0
    scores = {
        (10,): {
            "M+N": base,
            "M+G": base - 0.2,
            "M+L": base - 0.25,
            "M+S": base - 0.3,
            "T+N": base + 0.1,
            "T+G": base - 0.35,
            "T+L": base - 0.5,
            "T+S": base - 0.4,
        }
    }
    adaptive = ("T+S", "M+S", "M+G", "M+L", "T+N", "T+G", "T+L")
    rows, comparisons = cell_statistics(scores, cell=("T",), baseline="M+N", adaptive=adaptive, metric="rmse")
    entry = scoreboard_entry("by network", rows, comparisons, cell={"T": 10}, metric="rmse", unit="m")
    assert {"T+N", "T+G", "T+L", "SMCD (task masks)"} <= set(entry["estimates"])
    assert entry["pairs"]["SMCD (task masks) vs T+L"].startswith("worse 0.100")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "results.json").write_text(json.dumps({"scoreboard": entry}))
    assert cli.main(["scoreboard", str(tmp_path / "run"), "--out", str(tmp_path / "board")]) == 0
    report = (tmp_path / "board" / "report.md").read_text()
    summary = next(line for line in report.splitlines() if line.startswith("| by network "))
    cells = [c.strip() for c in summary.strip("|").split("|")]
    assert cells[1].startswith("T+L 0.") and cells[2] == "better · worse" and cells[3] == "T+S vs T+L: worse"
    assert "| T+N " in report and "T+L" in report.split("The task-mask network's other strategies")[1]
