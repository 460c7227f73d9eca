"""``smcd-rl two-link`` end to end at a small scale: files, table, ordering of methods, resume."""

import csv
import json

import pytest

import smcd_rl
from smcd_rl import cli
from smcd_rl.experiments.shared import scoreboard_entry
from smcd_rl.experiments.shared.runtime import torch_threads
from smcd_rl.experiments.two_link import run as two_link

SMALL = [
    "--tasks",
    "100",
    "--episodes",
    "20",
    "--hidden",
    "128",
    "--epochs",
    "10",
    "--batch-size",
    "128",
    "--lr",
    "2e-3",
    "--trials",
    "60",
    "--chunk",
    "30",
    "--burn-in",
    "1",
    "10",
    "--horizons",
    "1",
    "10",
    "--particles",
    "300",
    "--oracle-particles",
    "300",
    "--reptile-epochs",
    "3",
    "--lv-epochs",
    "3",
    "--lv-width",
    "64",
]


@pytest.mark.slow
def test_two_link_command_writes_results_and_ranks_methods(tmp_path, capsys) -> None:
    """60 held-out arms after 10 burn-in steps. Measured: O+P ~0.01 m, M+S ~0.2 m, M+N ~0.4 m,
    R+N ~0.9 m, R+S ~0.4 m, R+G ~0.5 m, M+L ~0.06 m at H=1.

    The oracle knows the kinematics, so it must beat M+N by a factor of 5; SMCD must cut M+N's
    error by 25%: a per-trial spread of ~0.2 m gives a standard error of ~0.03 m on 60 trials.
    SMCD adapts the Reptile network too (R+S cuts R+N's error by 25%), and the multi-task
    network adapts better than the Reptile one (M+S below R+S), as in the paper.
    """
    out = tmp_path / "run"
    methods = two_link.FULL["methods"]  # the defaults leave the Reptile network out
    assert cli.main(["two-link", "--out", str(out), *SMALL, "--methods", *methods]) == 0
    printed = capsys.readouterr().out
    assert "| M+S" in printed and "H=10" in printed
    for name in (
        "results.csv",
        "trials.csv",
        "comparisons.csv",
        "results.json",
        "lookahead.png",
        "report.md",
        "model.pt",
    ):
        assert (out / name).is_file(), name
    rows = {
        (r["method"], int(r["burn_in"]), int(r["horizon"])): float(r["rmse_mean"])
        for r in csv.DictReader(open(out / "results.csv"))
    }
    assert rows[("O+P", 10, 10)] < rows[("M+N", 10, 10)] / 5
    assert rows[("M+S", 10, 10)] < 0.75 * rows[("M+N", 10, 10)]
    assert rows[("M+S", 10, 1)] < 0.75 * rows[("M+N", 10, 1)]
    assert rows[("R+S", 10, 1)] < 0.75 * rows[("R+N", 10, 1)]
    assert rows[("M+S", 10, 10)] < rows[("R+S", 10, 10)]
    # The Bayesian last layer adapts the readout to the arm: measured ~0.06 m against M+N's ~0.4 m.
    assert rows[("M+L", 10, 1)] < 0.75 * rows[("M+N", 10, 1)]
    assert {m for m, _, _ in rows} == set(methods)
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["trials"] == 60 and payload["machine"]["torch_threads"] >= 1
    assert len(payload["reptile_train_loss"]) == 3 and len(payload["latent_train_loss"]) == 3

    # The fair protocol: both networks tuned by smcd_rl.tune on the same held-out episodes.
    config = two_link.TwoLinkConfig()
    # Each network is tuned for the variants of its methods that run (--full leaves out R+S(paper)).
    expected = {
        "M": {"N", "G", "S", "S(evidence)", "S(paper)", "C", "L", "SL"},
        "R": {"N", "G", "S", "S(evidence)", "C", "L", "SL"},
    }
    assert payload["tuning"]["M"]["specs"]["S(paper)"]["settings"]["noise_std"] == config.noise_std  # fixed
    for name in ("M", "R"):
        tuning = payload["tuning"][name]
        assert (out / f"tuning-{name}.png").is_file()
        assert set(tuning["specs"]) == expected[name]
        assert all(0 < ms < float("inf") for ms in tuning["ms_per_observation"].values())
        assert any("under 10 ms" in caption for caption in tuning["tune_tables"])
    timed = {r["method"]: r["ms_per_observation"] for r in csv.DictReader(open(out / "results.csv"))}
    assert float(timed["M+S"]) > 0 and timed["O+P"] == "" and "ms / observation" in printed
    board = payload["scoreboard"]
    assert board["cell"] == {"burn_in": 10, "horizon": 1}
    columns = set(scoreboard_entry.COLUMNS)
    assert set(board["estimates"]) == columns == set(board["ms_per_observation"])
    assert board["estimates"]["none"]["mean"] == pytest.approx(rows[("M+N", 10, 1)])
    assert board["verdicts"]["SMCD (calibrated) vs none"].startswith("better")
    assert {"SMCD (one-step) vs GD", "combination vs GD", "SMCD + last layer vs SMCD (one-step)"} <= set(
        board["verdicts"]
    )
    assert "The Bayesian last layer (L) and SMCD with a Bayesian readout (SL) paired" in printed
    # The combination mixes every tuned strategy, the readouts too.
    members = [m["name"] for m in payload["tuning"]["M"]["specs"]["C"]["settings"]["members"]]
    assert members == ["none", "gradient_descent", "smcd", "last_layer", "smcd_last_layer"]

    # A rerun finds the trained model and every method's trials done, and prints the same table.
    assert cli.main(["two-link", "--out", str(out), *SMALL, "--methods", *methods]) == 0
    assert capsys.readouterr().out.splitlines()[-3] == printed.splitlines()[-3]


def test_full_preset_fills_only_options_not_given() -> None:
    config = cli.make_config("two-link", {"full": True, "trials": 7})
    assert config.trials == 7 and config.hidden == two_link.FULL["hidden"] and config.tasks == 1000
    assert config.burn_in == (1, 5, 10, 20)  # the paper's burn-ins; the default leaves out T = 20
    assert cli.make_config("two-link", {}).hidden == two_link.TwoLinkConfig().hidden


def test_help_and_bad_options(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["two-link", "--help"])
    assert exit_info.value.code == 0 and "--burn-in" in capsys.readouterr().out
    assert cli.main(["two-link", "--methods", "X+Y", "--out", "/tmp/never"]) == 2
    assert "--methods: unknown value 'X+Y'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--particles", "-5"], "--particles must be >= 1"),
        (["--epochs", "0"], "--epochs must be >= 1"),
        (["--hidden", "24", "--mask-groups", "16"], "--mask-groups 16 must divide --hidden 24"),
    ],
)
def test_bad_options_are_refused_before_any_training(tmp_path, capsys, option, message) -> None:
    """Validation runs before any work: nothing is trained, not even the output directory made."""
    out = tmp_path / "run"
    assert cli.main(["two-link", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


TINY = [
    "--tasks",
    "20",
    "--episodes",
    "5",
    "--hidden",
    "32",
    "--epochs",
    "2",
    "--trials",
    "8",
    "--chunk",
    "8",
    "--burn-in",
    "1",
    "3",
    "--horizons",
    "1",
    "2",
    "--particles",
    "50",
    "--oracle-particles",
    "50",
    "--reptile-epochs",
    "1",
    "--lv-epochs",
    "1",
    "--lv-width",
    "16",
]


def _rows(out) -> dict:
    return {
        (r["method"], r["burn_in"], r["horizon"]): r["rmse_mean"] for r in csv.DictReader(open(out / "results.csv"))
    }


def test_reptile_and_latent_methods_leave_the_multitask_rows_unchanged(tmp_path, capsys) -> None:
    """R and LV train their own networks from their own seeds, so M's rows do not depend on them."""
    with torch_threads(1):  # tiny networks: one thread is fastest, and stays fast on a busy machine
        assert cli.main(["two-link", "--out", str(tmp_path / "m"), *TINY, "--methods", "M+N", "M+S"]) == 0
        methods = ["--methods", "R+S", "M+N", "LV+N", "M+S"]
        assert cli.main(["two-link", "--out", str(tmp_path / "all"), *TINY, *methods]) == 0
    alone, together = _rows(tmp_path / "m"), _rows(tmp_path / "all")
    assert alone and all(together[key] == value for key, value in alone.items())
    assert {m for m, _, _ in together} == {"M+N", "M+S", "R+S", "LV+N"}
    assert (
        len(list((tmp_path / "all").glob("reptile-*.ckpt"))) == len(list((tmp_path / "all").glob("latent-*.ckpt"))) == 1
    )
    assert not list((tmp_path / "m").glob("reptile-*.ckpt"))  # no Reptile method, no Reptile training


def test_the_task_mask_network_is_paired_with_m_and_r_and_leaves_their_rows_unchanged(tmp_path, capsys) -> None:
    """T trains its own network (mask_groups bits per layer) from its own seed: M's and R's rows do not move,
    T+S is paired with M+S, M+G and R+G in a table of its own, and the scoreboard entry has its column."""
    with torch_threads(1):
        others = ["M+N", "M+G", "M+S", "R+G"]
        assert cli.main(["two-link", "--out", str(tmp_path / "m"), *TINY, "--methods", *others]) == 0
        methods = ["--methods", *others, "T+N", "T+S", "--mask-groups", "4"]
        assert cli.main(["two-link", "--out", str(tmp_path / "t"), *TINY, *methods]) == 0
    alone, together = _rows(tmp_path / "m"), _rows(tmp_path / "t")
    assert alone and all(together[key] == value for key, value in alone.items())
    task = smcd_rl.load(tmp_path / "t" / "task_model.pt")
    assert task.net.mask_dim == 2 * 4  # two hidden layers of 4 bits
    pairs = {(r["method"], r["against"]) for r in csv.DictReader(open(tmp_path / "t" / "comparisons.csv"))}
    assert {("T+S", against) for against in ("M+S", "M+G", "R+G", "T+N")} <= pairs
    report = (tmp_path / "t" / "report.md").read_text()
    assert "T+S (masks trained to identify the task) paired with M+G, M+S, R+G, T+N" in report
    entry = json.loads((tmp_path / "t" / "results.json").read_text())["scoreboard"]
    assert entry["estimates"]["SMCD (task masks)"]["method"] == "T+S"
    assert "SMCD (task masks) vs GD" in entry["verdicts"]
    # R runs only G, so only GD is tuned for it.
    tuned = json.loads((tmp_path / "t" / "results.json").read_text())["tuning"]
    assert set(tuned["R"]["specs"]) == {"N", "G"} and set(tuned["T"]["specs"]) == {"N", "S"}


def test_mask_groups_that_do_not_divide_the_width_are_accepted_without_t_methods() -> None:
    two_link.TwoLinkConfig(hidden=24, methods=("M+N", "M+S")).validate()
    two_link.TwoLinkConfig(hidden=24, mask_groups=0).validate()  # one bit per unit


def test_a_rerun_with_fewer_epochs_trains_that_many_instead_of_reusing_the_longer_model(tmp_path, capsys) -> None:
    """The checkpoint used to be ``train.ckpt`` whatever the epochs, so ``--epochs 1`` after a
    2-epoch run in the same ``--out`` silently evaluated the 2-epoch model."""
    out = tmp_path / "run"
    methods = ["--methods", "M+N"]
    with torch_threads(1):
        assert cli.main(["two-link", "--out", str(out), *TINY, *methods]) == 0
        assert cli.main(["two-link", "--out", str(out), *TINY, *methods, "--epochs", "1"]) == 0
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["epochs"] == 1 and len(payload["train_loss"]) == 1
    assert len(list(out.glob("train-*.ckpt"))) == 2


def test_the_same_seed_and_thread_count_repeat_every_trial_bit_for_bit(tmp_path, capsys) -> None:
    """Two fresh runs (nothing cached) with the same seed and one thread: identical per-arm errors."""
    with torch_threads(1):
        for name in ("a", "b"):
            assert cli.main(["two-link", "--out", str(tmp_path / name), *TINY, "--methods", "M+G", "M+S", "O+P"]) == 0
    assert (tmp_path / "a" / "trials.csv").read_text() == (tmp_path / "b" / "trials.csv").read_text()


def test_the_combination_from_its_members_runs_equals_running_it(tmp_path, capsys, monkeypatch) -> None:
    """M+C is computed from the recorded runs of M+N, M+G and M+S (its members, same settings and seed)
    when they run too; alone, it runs as a Combination. Both give the same errors, to float rounding:
    the members' predictions are renormalised from the model's output once."""
    from smcd_rl.experiments.two_link import run as two_link_run

    derived = []
    real = two_link_run.combined_errors
    monkeypatch.setattr(two_link_run, "combined_errors", lambda *a, **k: derived.append(1) or real(*a, **k))
    with torch_threads(1):
        both = ["--methods", "M+N", "M+G", "M+S", "M+C"]
        assert cli.main(["two-link", "--out", str(tmp_path / "derived"), *TINY, *both, "--workers", "1"]) == 0
        alone = ["--methods", "M+C"]
        assert cli.main(["two-link", "--out", str(tmp_path / "run"), *TINY, *alone, "--workers", "1"]) == 0
    capsys.readouterr()
    assert derived == [1]  # the first run derived M+C, the second ran it
    trials = {
        where: {
            (r["burn_in"], r["horizon"], r["trial"]): float(r["rmse"])
            for r in csv.DictReader(open(tmp_path / where / "trials.csv"))
            if r["method"] == "M+C"
        }
        for where in ("derived", "run")
    }
    assert trials["derived"].keys() == trials["run"].keys() and len(trials["run"]) == 8 * 2 * 2
    for key, value in trials["run"].items():
        assert trials["derived"][key] == pytest.approx(value, rel=1e-5, abs=1e-7), key


def test_the_plan_ranks_the_evaluations_as_the_default_run_measured_them() -> None:
    """The workers take the costliest evaluations first by this plan. Measured in the default run,
    SMCD with a Bayesian readout on the task-mask network (T+SL) and on M (M+SL) are the two longest,
    and T's SMCD costs more than M's (each of T's forwards samples the arms' posteriors): a plan
    that ranked them below GD started T+SL last, and one worker ran it alone for half a minute."""
    from smcd_rl.experiments.two_link.stages import stage_costs

    costs = stage_costs(two_link.TwoLinkConfig())
    evaluations = sorted((cost, name) for name, cost in costs.items() if name.startswith("evaluate "))
    assert [name for _, name in evaluations[-2:]] == ["evaluate M+SL", "evaluate T+SL"]
    assert costs["evaluate T+S"] > costs["evaluate M+S"]
    assert costs["tune M"] > costs["tune T"] > costs["tune R"]
