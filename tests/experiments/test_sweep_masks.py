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
    assert all(r["test_specificity"] != "" for r in trials if r["method"] == "T+S")
    assert all(r["test_specificity"] == "" for r in trials if r["method"] != "T+S")
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
        "mean_masks": torch.tensor([[0.8, 0.8], [1.0, 1.0]]),  # one still spread as the prior, one settled
        "ess_share": torch.tensor([0.5, 0.25]),
        "distinct_share": torch.tensor([0.5, 0.5]),
    }
    # each arm's own log likelihood against the dealt mean 1.0: 1 is not ahead, 3 is
    assert training_posteriors(4, found, keep_prob=0.8) == pytest.approx(
        {"epoch": 4, "identity_gap": 1.0, "arms_ahead": 0.5, "spread": 0.5, "ess_share": 0.375, "distinct_share": 0.5}
    )


def _two_mask_arms(arms: int, *, both: bool) -> tuple[smcd_rl.AdaptiveModel, torch.Tensor, torch.Tensor, float]:
    """Arms whose positions a known mask of a small network produces: half mask A, half mask B (or all A),
    and the mean squared difference between A's and B's predictions (the error of the wrong mask)."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(32, 32), mask_groups=2)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    data = TensorDict({"q": torch.randn(256, 2), "ee": torch.randn(256, 2)}, [256])
    smcd_rl.fit(model, data, epochs=1, progress=False)  # normalisation statistics; the weights stay random
    a, b = torch.tensor([1.0, 0.0, 1.0, 0.0]), torch.tensor([0.0, 1.0, 0.0, 1.0])
    q = torch.randn(arms, 15, 2, generator=torch.Generator().manual_seed(1))
    masks = torch.stack([b if both and k % 2 else a for k in range(arms)]).unsqueeze(1).expand(-1, 15, -1)
    model.reset()
    with torch.no_grad():
        ee = model.predict(q, mask=masks)
        wrong = float((model.predict(q, mask=a) - model.predict(q, mask=b)).square().sum(-1).mean())
    return model, q, ee, wrong


@pytest.mark.parametrize("both", [True, False])
def test_mask_specificity_is_positive_only_when_arms_need_different_masks(both) -> None:
    """After 10 observations each arm's MMSE mask is its own: where half the arms need mask B, the other
    arms' masks predict an arm about half as badly as the wrong mask (specificity > 0); where every arm
    needs mask A, every arm's mask predicts alike (specificity about 0)."""
    model, q, ee, wrong = _two_mask_arms(20, both=both)
    method = model.with_adaptation(smcd_rl.SMCD(num_particles=64, flip_prob=0.01, noise_std=0.05,
                                                generator=torch.Generator().manual_seed(2)))  # fmt: skip
    found = held_out_posteriors(method, q, ee, ee, steps=10, chunk=8)
    assert found["test_specificity"].shape == found["test_spread"].shape == found["test_ess_share"].shape == (20,)
    assert bool(((found["test_ess_share"] > 0) & (found["test_ess_share"] <= 1)).all())
    # After 10 observations of a mask's outputs the particles have settled: far less spread than the prior.
    assert float(found["test_spread"].max()) < 0.5
    specificity = float(found["test_specificity"].mean())
    if both:  # ten of the other 19 arms' masks are the wrong one: about 10/19 of the wrong mask's error
        assert specificity > 0.3 * wrong
    else:
        assert abs(specificity) < 0.05 * wrong


def test_the_masks_study_never_scores_on_two_links_test_arms(monkeypatch) -> None:
    """Its result may choose the experiments' T setting, so it is measured on the tuning arms' draws."""
    from smcd_rl.experiments.shared.two_link_family import TUNING_ARMS_SEED
    from smcd_rl.experiments.shared.two_link_lookahead import TEST_ARMS_SEED
    from smcd_rl.experiments.sweep import trials

    seeds = {}

    def record(config, device, *, count, seed):
        seeds[study] = seed
        raise StopIteration

    monkeypatch.setattr(trials, "test_arms", record)
    for study in ("smcd", "masks"):
        point = sweep.trial_configs(sweep.SweepConfig(study=study, hidden=16, mask_groups=4))[0]
        model = trials._model(point, None)
        with pytest.raises(StopIteration):
            trials.evaluate_arms(point, {"checkpoint": model.checkpoint()})
    assert seeds["smcd"] == TEST_ARMS_SEED and seeds["masks"] == TUNING_ARMS_SEED != TEST_ARMS_SEED
