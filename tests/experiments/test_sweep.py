"""``smcd-rl sweep``: grids, trials on a local Ray equal to in-process trials, resume, statistics, errors, Ray optional.

Ray is a required test dependency (the ``test`` extra): a missing Ray fails the Ray tests, it does not skip them.
"""

import csv
import json
import subprocess
import sys

import pytest
import torch

from smcd_rl import cli
from smcd_rl.experiments.sweep import run as sweep
from tests.experiments.test_stages import planned_stages

TINY_TWO_LINK = ["--tasks", "6", "--episodes", "4", "--cpus", "2"]


def _rows(path) -> list[dict[str, str]]:
    with open(path) as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_training_sweep_on_local_ray_equals_in_process_trials_and_resumes(tmp_path, capsys, monkeypatch) -> None:
    import ray

    assert not ray.is_initialized()
    out = tmp_path / "run"
    grid = ["hidden=8,16", "dropout=0.5", "lr=0.01", "batch_size=64", "epochs=2"]
    assert cli.main(["sweep", "--out", str(out), "--grid", *grid, *TINY_TWO_LINK]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "run") == ["trials", "statistics"]  # starting Ray: the trials take > 1 s
    assert "| train_loss | hidden" in printed and "2 computed, 0 from the cache" in printed
    for name in ("results.csv", "summary.csv", "results.json", "sweep.png", "report.md"):
        assert (out / name).is_file(), name
    # Training losses have no trials to resample: no per-trial scores, no comparisons.
    assert not (out / "trials.csv").exists() and not (out / "comparisons.csv").exists()
    assert not ray.is_initialized(), "the sweep started Ray, so it must shut it down"

    # Determinism: each Ray trial equals the same trial function called here, bit for bit.
    config = cli.make_config("sweep", {"out": str(out), "grid": grid, "tasks": 6, "episodes": 4, "cpus": 2})
    points = sweep.trial_configs(config)
    rows = _rows(out / "results.csv")
    assert [int(r["hidden"]) for r in rows] == [p["hidden"] for p in points] == [8, 16]
    for row, point in zip(rows, points, strict=True):
        assert float(row["train_loss"]) == sweep.trial(point)["train_loss"]
    summary = {(r["parameter"], r["value"]): r for r in _rows(out / "summary.csv")}
    assert set(summary) == {("hidden", "8"), ("hidden", "16")}  # one-valued parameters get no summary row
    payload = json.loads((out / "results.json").read_text())
    assert payload["computed"] == 2 and payload["grid"]["hidden"] == [8, 16]

    # Resume: adding epochs=1 reuses both finished points and reads the new ones off the cached runs'
    # loss histories, so no Ray is needed; the values equal one-epoch trials run from scratch.
    monkeypatch.setattr(ray, "init", lambda *a, **k: pytest.fail("a fully cached sweep must not start Ray"))
    more = [*grid[:-1], "epochs=1,2"]
    assert cli.main(["sweep", "--out", str(out), "--grid", *more, *TINY_TWO_LINK]) == 0
    assert "2 computed, 2 from the cache" in capsys.readouterr().out
    resumed = {(int(r["hidden"]), int(r["epochs"])): float(r["train_loss"]) for r in _rows(out / "results.csv")}
    for row in rows:
        assert resumed[(int(row["hidden"]), 2)] == float(row["train_loss"])
    for point in sweep.trial_configs(cli.make_config("sweep", {"grid": more, "tasks": 6, "episodes": 4})):
        if point["epochs"] == 1:
            assert resumed[(point["hidden"], 1)] == sweep.trial(point)["train_loss"]


@pytest.mark.slow
def test_smcd_sweep_on_a_running_ray_evaluates_each_filter_setting_and_resumes(tmp_path, capsys) -> None:
    import ray

    ray.init(address="local", num_cpus=2, include_dashboard=False)
    try:
        out = tmp_path / "run"
        common = [
            "--study",
            "smcd",
            "--epochs",
            "2",
            "--arms",
            "8",
            "--burn-in",
            "1",
            "3",
            "--horizons",
            "2",
            *TINY_TWO_LINK,
        ]
        grid = ["hidden=16", "dropout=0.5", "flip_prob=0.01", "noise_std=0.05"]
        assert cli.main(["sweep", "--out", str(out), "--grid", *grid, "particles=10,20", *common]) == 0
        assert ray.is_initialized(), "a Ray the sweep did not start must be left running"
        printed = capsys.readouterr().out
        assert "| mse_T3_H2 | particles" in printed and "M+S against" in printed
        assert len(list((out / "partial").glob("train-*.pt"))) == 1  # one training run shared by both filter settings
        assert len(list((out / "partial").glob("reference-*.pt"))) == 2  # M+N and M+G on it, once

        # A third particle count: the saved model is reused (no retraining), the finished points are not redone.
        assert cli.main(["sweep", "--out", str(out), "--grid", *grid, "particles=10,20,30", *common]) == 0
        assert "1 computed, 2 from the cache" in capsys.readouterr().out
        payload = json.loads((out / "results.json").read_text())
        assert payload["train_seconds"] == [] and len(payload["evaluate_seconds"]) == 1
    finally:
        ray.shutdown()

    given = {"study": "smcd", "grid": [*grid, "particles=10,20,30"], "epochs": 2, "arms": 8, "burn_in": [1, 3],
             "horizons": [2], "tasks": 6, "episodes": 4}  # fmt: skip
    rows = _rows(out / "results.csv")
    for row, point in zip(rows, sweep.trial_configs(cli.make_config("sweep", given)), strict=True):
        assert int(row["particles"]) == point["particles"]
        assert {k: float(row[k]) for k in ("mse_T1_H2", "mse_T3_H2")} == sweep.trial(point)
        for k in ("mse_T1_H2", "mse_T3_H2"):  # a 95% CI over the 8 arms around each grid point's mean
            assert float(row[f"{k}_low"]) <= float(row[k]) <= float(row[f"{k}_high"])

    # Every arm of every grid point and reference is a trial; SMCD is paired with both references.
    trials = _rows(out / "trials.csv")
    assert {r["method"] for r in trials} == {"M+S", "M+N", "M+G"} and len(trials) == (3 + 2) * 8
    comparisons = _rows(out / "comparisons.csv")
    pairs = {(r["method"], r["against"]) for r in comparisons}
    assert pairs == {("M+S", "M+N"), ("M+S", "M+G"), ("M+G", "M+N")}
    assert len(comparisons) == (3 * 2 + 1) * 2  # per grid point and (T, H); M+G vs M+N per model and (T, H)
    assert all(r["verdict"] in ("better", "worse", "no significant difference") for r in comparisons)
    report = (out / "report.md").read_text()
    assert "M+S against" in report and "| M+N" in report


def test_grids_factorial_and_one_at_a_time() -> None:
    config = sweep.SweepConfig(study="smcd")
    default = sweep.trial_configs(config)
    assert len(default) == 3 * 3 * 3 * 3 * 2  # every combination of the default grid
    assert {p["particles"] for p in default} == set(sweep.GRIDS["smcd"]["particles"])
    config.design = "one-at-a-time"
    single = sweep.trial_configs(config)
    base = {name: getattr(config, name) for name in sweep.PARAMETERS["smcd"]}
    for point in single:  # every point differs from the base in at most one parameter
        assert sum(point[name] != base[name] for name in base) <= 1
    assert len(single) == 1 + sum(len([v for v in vs if v != base[n]]) for n, vs in sweep.GRIDS["smcd"].items())

    full = cli.make_config("sweep", {"full": True, "arms": 7})
    assert full.arms == 7 and full.tasks == sweep.FULL["tasks"] and full.hidden == sweep.FULL["hidden"]
    assert sweep.resolve_grid(full) == sweep.FULL_GRIDS["training"]


def test_summary_is_mean_std_min_over_the_other_parameters() -> None:
    rows = [
        {"hidden": 8, "lr": 0.1, "loss": 4.0},
        {"hidden": 8, "lr": 0.01, "loss": 2.0},
        {"hidden": 16, "lr": 0.1, "loss": 1.0},
        {"hidden": 16, "lr": 0.01, "loss": 1.0},
    ]
    summary = {(r["parameter"], r["value"]): r for r in sweep.summarise(rows, ["hidden", "lr"], ["loss"])}
    assert summary[("hidden", 8)] == {
        "metric": "loss", "parameter": "hidden", "value": 8, "trials": 2, "mean": 3.0, "std": 1.0, "min": 2.0,
    }  # fmt: skip
    assert (summary[("lr", 0.1)]["mean"], summary[("lr", 0.1)]["min"]) == (2.5, 1.0)
    assert summary[("hidden", 16)]["std"] == 0.0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["--study", "ablation"],
            "--study: unknown value 'ablation'; choose from ['training', 'smcd', 'drone', 'masks']",
        ),
        (["--grid", "latent=64"], "unknown parameter 'latent' for study 'training'; its parameters: hidden, dropout"),
        (["--grid", "particles=10"], "unknown parameter 'particles' for study 'training'"),
        (["--study", "smcd", "--grid", "lr=0.1"], "unknown parameter 'lr' for study 'smcd'"),
        (["--grid", "hidden"], "must read NAME=V1,V2"),
        (["--grid", "hidden=8", "hidden=16"], "given twice"),
        (["--grid", "hidden=8.5"], "values of hidden must be ints"),
        (["--grid", "dropout=1.5"], "--grid dropout=1.5: --dropout must be < 1.0, got 1.5"),
        (["--grid", "lr=0.1,-0.1"], "--grid lr=-0.1: --lr must be > 0.0, got -0.1"),
        (["--study", "smcd", "--grid", "particles=10,0"], "--grid particles=0: --particles must be >= 1, got 0"),
        (["--design", "random"], "--design: unknown value 'random'"),
        (["--cpus", "2", "--cpus-per-trial", "3"], "exceeds the local Ray's 2 CPUs"),
        (["--particles", "-5"], "--particles must be >= 1, got -5"),
        (["--epochs", "0"], "--epochs must be >= 1, got 0"),
        (["--flip-prob", "1.5"], "--flip-prob must be <= 1.0, got 1.5"),
        (["--arms", "1"], "--arms must be >= 2, got 1"),
        (["--burn-in", "1", "0"], "--burn-in must be >= 1, got 0"),
        (["--cpus-per-trial", "0"], "--cpus-per-trial must be >= 1, got 0"),
        (["--gpus-per-trial", "-1"], "--gpus-per-trial must be >= 0.0"),
        pytest.param(  # once hung: Ray waited for a GPU that does not exist
            ["--gpus-per-trial", "1"],
            "exceeds the local Ray's 0 GPUs",
            marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU"),
        ),
        (["--threads", "-2"], "--threads must be >= 0"),
        (["--study", "drone", "--dataset", "missing.npz"], "--dataset missing.npz: no such file"),
        (["--study", "masks", "--grid", "mask_groups=0,3"], "mask_groups 3 does not divide --hidden 256"),
        (["--study", "masks", "--mask-groups", "5", "--grid", "mask_groups=5"], "mask_groups 5 does not divide"),
        (["--study", "masks", "--grid", "task_share=0,1.5"], "--grid task_share=1.5: --task-share must be <= 1.0"),
        (["--study", "masks", "--grid", "hidden=8"], "unknown parameter 'hidden' for study 'masks'"),
        (["--study", "masks", "--grid", "tasks=1,25"], "tasks 1: the masks study ties masks to training arms"),
        (["--study", "masks", "--dropout", "0"], "the masks study needs --dropout > 0"),
        (["--study", "masks", "--epochs", "1"], "the masks study needs --epochs 2 or more"),
        (["--study", "masks", "--design", "one-at-a-time", "--mask-groups", "24"], "mask_groups 24 does not divide"),
        (["--study", "masks", "--design", "one-at-a-time", "--tasks", "1"], "tasks 1: the masks study ties masks"),
        # Once neither checked nor used: a factorial grid sweeps mask_groups over its own values.
        (["--study", "masks", "--mask-groups", "7"], "--mask-groups 7 is not used: the masks study's factorial grid"),
        (["--study", "smcd", "--particles", "300"], "--grid particles=300 to sweep it"),
    ],
)
def test_bad_options_are_refused_before_any_work(tmp_path, capsys, argv, message) -> None:
    """Validation names the problem before any data, Ray or training: not even the output directory is made."""
    out = tmp_path / "never"
    assert cli.main(["sweep", "--out", str(out), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match="--horizons needs at least one value"):
        sweep.SweepConfig(study="smcd", horizons=()).validate()


@pytest.mark.slow
def test_overwriting_the_drone_dataset_makes_the_rerun_recompute(tmp_path, capsys) -> None:
    """Stored results are keyed by the dataset's content, not its path: new data at the same path is retrained."""
    from smcd_rl.envs import drone_operators

    dataset = tmp_path / "landings.npz"
    drone_operators.save_dataset(drone_operators.simulate_operators(4, 3, seed=1, max_steps=60), dataset)
    out = tmp_path / "run"
    argv = ["sweep", "--study", "drone", "--out", str(out), "--dataset", str(dataset), "--subset", "0", "--cpus", "2"]
    grid = ["--grid", "hidden=8", "dropout=0.5", "lr=0.01", "batch_size=64", "epochs=1"]
    assert cli.main([*argv, *grid]) == 0
    assert "1 computed, 0 from the cache" in capsys.readouterr().out
    first = float(_rows(out / "results.csv")[0]["train_loss"])
    assert cli.main([*argv, *grid]) == 0  # same file: the stored result is reused
    assert "0 computed, 1 from the cache" in capsys.readouterr().out

    drone_operators.save_dataset(drone_operators.simulate_operators(4, 3, seed=2, max_steps=60), dataset)
    assert cli.main([*argv, *grid]) == 0
    assert "1 computed, 0 from the cache" in capsys.readouterr().out
    assert float(_rows(out / "results.csv")[0]["train_loss"]) != first


@pytest.mark.slow
def test_without_ray_the_sweep_says_how_to_install_it_and_the_rest_still_imports(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ImportError
    config = sweep.SweepConfig(out=str(tmp_path / "run"), grid=("hidden=8", "epochs=1"), tasks=4, episodes=2)
    with pytest.raises(ImportError, match=r'pip install -e "\.\[ray\]"'):
        sweep.run(config, progress=False)

    # A fresh interpreter without Ray imports the package and builds every command's parser.
    code = "import sys; sys.modules['ray'] = None; import smcd_rl; from smcd_rl import cli; cli.build_parser(); print('ok')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
