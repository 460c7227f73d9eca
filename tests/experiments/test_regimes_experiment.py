"""``smcd-rl regimes`` at a tiny scale: files, every cell, the budgeted view, the regimes' streams and the scoreboard."""

import csv
import json

import pytest
import torch

import smcd_rl
from smcd_rl import cli
from smcd_rl.envs.pendulum_family import pendulum_step
from smcd_rl.experiments.regimes.config import RegimesConfig, regime_names
from smcd_rl.experiments.regimes.families import FAMILIES
from smcd_rl.experiments.regimes.streams import make_plan, regime_errors
from smcd_rl.experiments.scoreboard.config import ScoreboardConfig
from smcd_rl.experiments.scoreboard.run import run as scoreboard

TINY = {
    "tasks": 8,
    "episodes": 4,
    "steps": 5,
    "hidden": 16,
    "epochs": 1,
    "pendulum_tasks": 8,
    "pendulum_episodes": 2,
    "pendulum_steps": 5,
    "trials": 4,
    "tuning_episodes": 3,
    "tuning_steps": 6,
    "burn_in": (1, 3),
    "eval_points": 3,
    "switch_steps": 2,
    "outlier_burn_in": 3,
    "every": 2,
    "every_steps": 4,
    "particles": 16,
    "gd_lr": (0.01,),
    "gd_steps": (1,),
    "gd_window": (2,),
    "calibrate_flips": (0.01,),
    "workers": 1,
}


def options(values: dict) -> list[str]:
    args = []
    for key, value in values.items():
        args.append("--" + key.replace("_", "-"))
        args += [str(v) for v in value] if isinstance(value, tuple) else [str(value)]
    return args


def test_tiny_run_writes_every_cell_with_time_per_step_and_a_scoreboard_reads_it(tmp_path, capsys) -> None:
    out = tmp_path / "regimes"
    assert cli.main(["regimes", "--out", str(out), *options({**TINY, "budget_ms": 1000.0})]) == 0
    printed = capsys.readouterr().out
    for name in ("results.csv", "trials.csv", "comparisons.csv", "results.json", "regimes.png", "report.md"):
        assert (out / name).is_file(), name
    rows = list(csv.DictReader((out / "results.csv").open()))
    methods = ["N", "G", "S", "S(evidence)", "S(paper)", "C", "L", "SL", "G@1000ms", "S@1000ms", "C@1000ms"]
    task = ["T+N", "T+G", "T+S", "T+L", "T+SL"]  # every family's task-mask network (the arm families share one)
    cells = {(r["family"], r["regime"], r["method"]) for r in rows}
    expected = {(f, r, m) for f in FAMILIES for r in regime_names((1, 3), f) for m in (*methods, *task)}
    assert cells == expected | {("pendulum", r, "R+G") for r in regime_names((1, 3), "pendulum")}  # Reptile's
    assert "every n-th" in regime_names((1, 3), "pendulum") and "every n-th" not in regime_names((1, 3), "two-link")
    # every method's time per observation is measured, once per network, and the same in every regime
    for row in rows:
        assert float(row["ms_per_observation"]) > 0, row
    # under a budget no setting exceeds, the budgeted choice is the free one: the same errors
    by = {(r["family"], r["regime"], r["method"]): float(r["rmse_mean"]) for r in rows}
    for family in FAMILIES:
        for regime in regime_names((1, 3), family):
            assert by[(family, regime, "G@1000ms")] == pytest.approx(by[(family, regime, "G")], rel=1e-6)
    result = json.loads((out / "results.json").read_text())
    assert len(result["scoreboard"]) == 3 * 3  # per family T=3, the switch and the outlier (T=30 did not run)
    assert "S vs G" in printed and "Median time per observation" in printed
    assert all(f"| {pair}" in printed or f" {pair} |" in printed for pair in ("L vs G", "L vs S", "SL vs S"))
    assert "pendulum: T+S (masks trained to identify the task) paired with G, R+G, S, T+G, T+N" in printed
    assert "two-link: T+S (masks trained to identify the task) paired with G, S, T+G, T+N" in printed
    # T and R tune only what their methods need: no SMCD for R, no GD budget view for either.
    tuned = result["tuning"]
    assert set(tuned["pendulum-reptile"]["specs"]) == {"G"}
    assert set(tuned["pendulum-task"]["specs"]) == set(tuned["arm-task"]["specs"]) == {"N", "G", "S", "L", "SL"}
    two_link_t3 = [e for e in result["scoreboard"] if e["task"] == "two-link T=3"][0]
    assert two_link_t3["estimates"]["SMCD (task masks)"]["method"] == "T+S"
    pendulum_t3 = [e for e in result["scoreboard"] if e["task"] == "pendulum T=3"][0]
    assert pendulum_t3["estimates"]["SMCD (task masks)"]["method"] == "T+S"
    assert "SMCD (task masks)" in pendulum_t3["ms_per_observation"]

    board = scoreboard(ScoreboardConfig(runs=(str(out),), out=str(tmp_path / "board")), progress=False)
    assert len(board["results"]) == 9
    report = (tmp_path / "board" / "report.md").read_text()
    assert "tuned vs GD" in report and "Median time per observation" in report


def test_the_other_networks_leave_every_other_row_unchanged(tmp_path, capsys) -> None:
    """T and R train from seeds of their own on their base network's data, after it: M's rows do not move."""
    tiny = {**TINY, "families": ("two-link", "pendulum"), "burn_in": (3,)}
    methods = ("N", "G", "S")
    assert cli.main(["regimes", "--out", str(tmp_path / "m"), *options({**tiny, "methods": methods})]) == 0
    with_t = {**tiny, "methods": (*methods, "T+S", "R+G")}
    assert cli.main(["regimes", "--out", str(tmp_path / "t"), *options(with_t)]) == 0

    def rows(run: str) -> dict:
        found = csv.DictReader((tmp_path / run / "results.csv").open())
        return {(r["family"], r["regime"], r["method"]): r["rmse_mean"] for r in found}

    alone, together = rows("m"), rows("t")
    assert all(together[key] == value for key, value in alone.items())
    assert {m for _, _, m in together} - {m for _, _, m in alone} == {"T+S", "R+G"}
    assert not any(f == "two-link" and m == "R+G" for f, _, m in together)  # Reptile's network is the pendulum's
    assert any(f == "two-link" and m == "T+S" for f, _, m in together)  # the arm families have a T of their own
    # T's masks come in mask_groups bits per layer.
    assert smcd_rl.load(tmp_path / "t" / "model-pendulum-task.pt").net.mask_dim == 2 * 16


def test_a_budget_label_with_a_plus_is_no_network_prefix() -> None:
    """``--budget-ms 1e6`` labels G@1e+06ms: once read as a method of a network named 'G@1e'."""
    from smcd_rl.experiments.regimes.families import method_network
    from smcd_rl.experiments.regimes.run import stage_costs

    assert method_network("pendulum", "G@1e+06ms") == ("pendulum", "G@1e+06ms")
    costs = stage_costs(RegimesConfig(budget_ms=1e6))
    assert {"evaluate two-link G@1e+06ms", "evaluate pendulum G@1e+06ms", "evaluate pendulum T+S"} <= set(costs)
    assert "evaluate two-link T+S" in costs and "evaluate two-link R+G" not in costs
    with pytest.raises(ValueError, match="--mask-groups 16 must divide --hidden 24"):
        RegimesConfig(hidden=24).validate()


def test_outlier_regime_moves_one_target_by_the_scale_times_the_residual() -> None:
    residual = torch.tensor([0.1, 0.2])
    clean = make_plan("two-link", RegimesConfig(**TINY, outlier_scale=0.0), residual=residual)
    corrupted = make_plan("two-link", RegimesConfig(**TINY, outlier_scale=20.0), residual=residual)
    differences = []
    for a, b in zip(clean.steps, corrupted.steps, strict=True):
        if a.kind == "observe":
            differences.append((b.td["ee"] - a.td["ee"]).abs())
    moved = [d for d in differences if d.max() > 0]
    assert len(moved) == 1  # exactly one observation is corrupted, for every task
    assert torch.allclose(moved[0], (20.0 * residual).expand(4, 2))


def test_telescoping_tasks_change_with_stream_time_and_two_link_tasks_do_not() -> None:
    g = torch.Generator().manual_seed(0)
    for name, changes in (("two-link", False), ("telescoping", True)):
        family = FAMILIES[name]
        tasks = family.sample(5, g)
        early, late = (family.truth(tasks, 3, at, torch.Generator().manual_seed(1)) for at in (0, 10))
        assert torch.equal(early["q"], late["q"])
        assert (not torch.allclose(early["ee"], late["ee"])) == changes, name


def test_pendulum_truth_follows_the_pendulum_physics() -> None:
    g = torch.Generator().manual_seed(0)
    family = FAMILIES["pendulum"]
    tasks = family.sample(4, g)
    truth = family.truth(tasks, 5, 0, g)
    expected = pendulum_step(truth["observation"], truth["action"], tasks[:, :1], tasks[:, 1:])
    torch.testing.assert_close(truth["next", "observation"], expected)


def test_regime_errors_show_squared_error_descent_pulled_by_the_outlier_huber_less_and_none_untouched(
    two_link_model,
) -> None:
    # The conftest's trained arm model, a residual of 0.3 m: the outlier is 6 m off, three times
    # the arm's reach. Seeded data, deterministic strategies: measured, the squared-error descent's
    # error goes from 0.38 m to 0.92 m and the Huber loss's only to 0.45 m, margins far beyond any
    # change of float kernels; the unadapted model's errors cannot depend on what it observes.
    residual = torch.tensor([0.3, 0.3])
    errors = {}
    for scale in (0.0, 20.0):
        config = RegimesConfig(**{**TINY, "trials": 8, "outlier_burn_in": 4, "outlier_scale": scale})
        plan = make_plan("two-link", config, residual=residual)
        for name, strategy in (
            ("N", smcd_rl.NoAdaptation()),
            ("mse", smcd_rl.GradientDescent(lr=0.1, steps=5, window=4)),
            ("huber", smcd_rl.GradientDescent(lr=0.1, steps=5, window=4, loss="huber")),
        ):
            result = regime_errors(two_link_model.with_adaptation(strategy), plan, "ee")
            errors[name, scale] = result["errors"]["outlier"].mean()
    assert errors["N", 0.0] == errors["N", 20.0]
    assert errors["mse", 20.0] > 1.8 * errors["mse", 0.0]
    assert errors["huber", 20.0] < errors["mse", 20.0] - 0.3


def test_the_readout_table_counts_rows_against_the_better_part_and_both() -> None:
    """SL is held against the part of lower mean in each row: worse than it counts, worse than the
    other part alone does not; better than both counts once."""
    from smcd_rl.experiments.regimes.report import readout_table

    def pair(difference: float, low: float, high: float) -> dict:
        verdict = "better" if high < 0 else "worse" if low > 0 else "no significant difference"
        return {"verdict": verdict, "difference": difference, "low": low, "high": high}

    rows = [
        {"family": "f", "regime": r, "method": m, "rmse_mean": v}
        for r, means in (("T=1", {"S": 1.0, "L": 2.0, "SL": 1.5}), ("T=3", {"S": 1.0, "L": 0.9, "SL": 0.5}))
        for m, v in means.items()
    ]
    pairs = {
        ("f", "T=1"): {
            ("SL", "S"): pair(0.5, 0.1, 0.9),
            ("SL", "L"): pair(-0.5, -0.9, -0.1),
        },  # worse than S, the better
        ("f", "T=3"): {("SL", "S"): pair(-0.5, -0.9, -0.1), ("L", "SL"): pair(0.4, 0.1, 0.7)},  # better than both
    }
    table, summary = readout_table(pairs, rows, "f", ["T=1", "T=3"])
    assert summary == "worse than the better part in 1 of 2 rows, better than both in 1"
    assert "| SL vs S " in table and "T+SL" not in table


def test_the_plan_ranks_the_stages_as_the_default_run_measured_them() -> None:
    """The workers take the costliest stages first by this plan. Measured at the defaults, the
    pendulum's combination (its members run again) is the longest evaluation, about twice an arm
    family's, and a network's task-mask twin tunes in about its time, not twice it: a plan that
    priced every combination like 19 s started the 82 s one last."""
    from smcd_rl.experiments.regimes.run import stage_costs

    costs = stage_costs(RegimesConfig())
    evaluations = sorted((cost, name) for name, cost in costs.items() if name.startswith("evaluate "))
    assert evaluations[-1][1] == "evaluate pendulum C"
    assert costs["evaluate pendulum C"] > 1.5 * costs["evaluate two-link C"]
    assert costs["evaluate two-link T+G"] > 3 * costs["evaluate two-link G"]
    assert 0.8 < costs["tune arm-task"] / costs["tune arm"] < 1.25
    assert costs["tune pendulum-reptile"] < 0.25 * costs["tune pendulum"]
