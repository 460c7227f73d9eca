"""``smcd-rl sweep --study masks``: networks trained for mask adaptation, scored as T+S against T+N and T+G,
with how concentrated their posteriors are on the training arms (per epoch) and on held-out arms."""

import csv
import json

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl import cli
from smcd_rl.experiments.sweep import run as sweep
from smcd_rl.experiments.sweep.posteriors import held_out_posteriors, training_posteriors


def _rows(path) -> list[dict[str, str]]:
    with open(path) as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_masks_sweep_trains_task_networks_reports_posteriors_and_resumes(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "run"
    argv = ["sweep", "--study", "masks", "--out", str(out), "--hidden", "16", "--epochs", "3", "--episodes", "4",
            "--arms", "8", "--burn-in", "1", "3", "--horizons", "2", "--cpus", "2"]  # fmt: skip
    grid = ["--grid", "task_share=0,0.5", "mask_groups=4", "tasks=6", "particles=20"]
    assert cli.main([*argv, *grid]) == 0
    printed = capsys.readouterr().out
    assert "T+S against" in printed and "identity gap" in printed
    for name in ("posteriors.csv", "posteriors.png", "trials.csv", "comparisons.csv", "report.md"):
        assert (out / name).is_file(), name

    # Each training run reports its posteriors at every epoch after the first (epoch 0 trains without them).
    posteriors = _rows(out / "posteriors.csv")
    assert [(r["task_share"], r["epoch"]) for r in posteriors] == [
        ("0.0", "1"),
        ("0.0", "2"),
        ("0.5", "1"),
        ("0.5", "2"),
    ]
    assert all(0 < float(r["ess_share"]) <= 1 for r in posteriors)
    # The held-out arms' posteriors are per-arm trials of the SMCD points only, beside their MSE.
    trials = _rows(out / "trials.csv")
    assert {r["method"] for r in trials} == {"T+S", "T+N", "T+G"}
    assert all(r["test_gap"] != "" for r in trials if r["method"] == "T+S")
    assert all(r["test_gap"] == "" for r in trials if r["method"] != "T+S")
    # The share-0 network is trained as plain random dropout: it is the control, on the same data and seed.
    given = {"study": "masks", "grid": grid[1:], "hidden": 16, "epochs": 3, "episodes": 4, "arms": 8,
             "burn_in": [1, 3], "horizons": [2]}  # fmt: skip
    points = sweep.trial_configs(cli.make_config("sweep", given))
    rows = _rows(out / "results.csv")
    for row, point in zip(rows, points, strict=True):
        assert float(row["mse_T3_H2"]) == pytest.approx(sweep.trial(point)["mse_T3_H2"], rel=1e-6)

    # A rerun reads everything back: no Ray, the same report.
    import ray

    before = {name: (out / name).read_text() for name in ("results.csv", "posteriors.csv")}
    monkeypatch.setattr(ray, "init", lambda *a, **k: pytest.fail("a fully cached sweep must not start Ray"))
    assert cli.main([*argv, *grid]) == 0
    assert "0 computed, 2 from the cache" in capsys.readouterr().out
    assert json.loads((out / "results.json").read_text())["posteriors"][0]["epoch"] == 1
    assert {name: (out / name).read_text() for name in before} == before


def test_training_posteriors_are_means_over_the_arms() -> None:
    found = {
        "log_likelihood": torch.tensor([1.0, 3.0]),
        "shuffled_log_likelihood": torch.tensor([0.0, 2.0]),
        "ess_share": torch.tensor([0.5, 0.25]),
        "distinct_share": torch.tensor([0.5, 0.5]),
    }
    assert training_posteriors(4, found) == {"epoch": 4, "identity_gap": 1.0, "ess_share": 0.375, "distinct_share": 0.5}


def _two_mask_arms(arms: int, *, both: bool) -> tuple[smcd_rl.AdaptiveModel, torch.Tensor, torch.Tensor]:
    """Arms whose positions a known mask of a small network produces: half mask A, half mask B (or all A)."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(32, 32), mask_groups=2)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    data = TensorDict({"q": torch.randn(256, 2), "ee": torch.randn(256, 2)}, [256])
    smcd_rl.fit(model, data, epochs=1, progress=False)  # normalisation statistics; the weights stay random
    a, b = torch.tensor([True, False, True, False]), torch.tensor([False, True, False, True])
    q = torch.randn(arms, 10, 2, generator=torch.Generator().manual_seed(1))
    masks = torch.stack([b if both and k % 2 else a for k in range(arms)])
    model.reset()
    with torch.no_grad():
        ee = torch.stack([model.predict(q[k], mask=masks[k]) for k in range(arms)])
    return model, q, ee


@pytest.mark.parametrize("both", [True, False])
def test_the_identity_gap_is_positive_only_when_arms_need_different_masks(both) -> None:
    """Arms made by two different masks explain their own samples far better than dealt ones (gap > 0);
    arms all made by one mask are explained alike either way (gap about 0)."""
    model, q, ee = _two_mask_arms(20, both=both)
    method = model.with_adaptation(smcd_rl.SMCD(num_particles=64, flip_prob=0.01, noise_std=0.05,
                                                generator=torch.Generator().manual_seed(2)))  # fmt: skip
    found = held_out_posteriors(method, q, ee, chunk=8, generator=torch.Generator().manual_seed(3))
    assert found["test_gap"].shape == found["test_ess_share"].shape == (20,)
    assert bool(((found["test_ess_share"] > 0) & (found["test_ess_share"] <= 1)).all())
    gap = float(found["test_gap"].mean())
    # Over seeds the mean gap was 4 to 7 nats per observation with two masks and within +-0.15 with one.
    if both:  # dealt samples mix the two masks' outputs: no single mask explains them
        assert gap > 2.0 and bool((found["test_gap"] > 0).all())
    else:  # every sample comes from mask A, whichever arm it is dealt to
        assert abs(gap) < 0.5
