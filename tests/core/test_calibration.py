"""smcd_rl.calibrate: the noise and flip probability of lowest one-step error or highest evidence, and where they are kept."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.training import fitting
from smcd_rl.tuning import calibration
from smcd_rl.tuning.calibration import evidence
from smcd_rl.tuning.diagnostics import Trace

SIGMA = 0.02  # the known measurement noise of the synthetic episodes


@pytest.fixture(autouse=True)
def one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: on the shared 2-core machine extra threads only wait
    yield
    torch.set_num_threads(threads)


def known_mask_episodes(episodes: int = 8, steps: int = 20) -> tuple[smcd_rl.AdaptiveModel, TensorDict, torch.Tensor]:
    """A random network and episodes of ``net(q, mask=true_mask) + N(0, SIGMA^2)``.

    Eight hidden units make 256 masks, so 256 particles can find the true one and the evidence
    is that of the true noise, not of a mask the filter never proposed.
    """
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,), dropout=0.5)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    model.fitted = True  # a random network on purpose: the truth is its own masked output
    g = torch.Generator().manual_seed(1)
    true_mask = (torch.rand(net.mask_dim, generator=g) < 0.5).float()
    q = torch.rand(episodes, steps, 2, generator=g) * 4 - 2
    with torch.no_grad():
        ee = net(q, mask=true_mask) + SIGMA * torch.randn(episodes, steps, 2, generator=g)
    return model, TensorDict({"q": q, "ee": ee}, [episodes, steps]), true_mask


def small_base() -> smcd_rl.SMCD:
    return smcd_rl.SMCD(num_particles=256)


def test_chosen_noise_is_the_true_noise_and_the_evidence_peaks_there() -> None:
    model, episodes, _ = known_mask_episodes()
    result = smcd_rl.calibrate(
        model, episodes, base=small_base(), per_dimension=False, criterion="evidence", progress=False
    )
    # The search starts at the network's residual with dropout off, which includes the mask it
    # does not know: over 5 x SIGMA in every dimension here, so a search that ignored the evidence
    # would stay far from SIGMA. Ending within 1.5x of it (a window of width log 2.25 in a search
    # spanning log 64 and more) takes the evidence pointing there.
    assert result.residual_source == "episodes" and min(result.residual_scale) > 5 * SIGMA
    assert isinstance(result.noise_std, float)
    assert SIGMA / 1.5 < result.noise_std < 1.5 * SIGMA
    # The table's maximum is the chosen setting, and the evidence falls off on both sides.
    assert result.best.noise_std == result.noise_std and result.best.flip_prob == result.flip_prob
    assert result.best.log_evidence == max(c.log_evidence for c in result.candidates)
    for far in (SIGMA / 4, 4 * SIGMA):
        far_evidence, _ = evidence(model, episodes, noise_std=far, flip_prob=result.flip_prob, base=small_base())
        assert far_evidence < result.best.log_evidence - 10  # nats per episode
    # Few filter runs: bracket 7, flips 3, re-bracket 2, refinement 5, and a few extensions at most.
    assert 15 <= len(result.candidates) <= 25
    assert model.calibration is not None and model.calibration["noise_std"] == result.noise_std
    assert result.criterion == model.calibration["criterion"] == "evidence"


def known_objective(scorer, strategy) -> tuple[float, float, Trace]:  # noqa: ANN001
    """In place of a filter run: an evidence peaked at noise 0.03, flip 0.003 and an RMSE lowest at 0.3, 0.01.

    Pure float64 arithmetic of the setting, so the search's path is the same on every CPU.
    """
    u, f = math.log(strategy.noise_std), math.log(strategy.flip_prob)
    log_evidence = -((u - math.log(0.03)) ** 2) - (f - math.log(0.003)) ** 2
    rmse = 0.1 + (u - math.log(0.3)) ** 2 + (f - math.log(0.01)) ** 2
    return log_evidence, rmse, Trace([], rmse, [], [], [])


#: (stage, factor, flip) of every run of the evidence search on :func:`known_objective` from a
#: residual scale of 0.1, recorded from calibrate as it was before it took a criterion.
EVIDENCE_PATH = [
    *[("bracket", 2.0**k, 0.01) for k in range(-3, 4)],
    *[("flip", 0.25, flip) for flip in (0.001, 0.003, 0.03)],
    ("rebracket", 0.125, 0.003),
    ("rebracket", 0.5, 0.003),
    *[("refine", factor, 0.003) for factor in (0.21226406, 0.294444571, 0.360448249, 0.25984588, 0.3180938)],
]


@pytest.mark.parametrize("criterion", ["evidence", "one-step"])
def test_the_search_finds_the_optimum_of_its_criterion(criterion: str, monkeypatch: pytest.MonkeyPatch) -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=5)
    model.residual_scale = [0.1, 0.1]  # the search starts at noise 0.1
    monkeypatch.setattr(calibration, "_run", known_objective)
    result = smcd_rl.calibrate(
        model, episodes, base=small_base(), per_dimension=False, criterion=criterion, progress=False
    )
    assert isinstance(result.noise_std, float)
    if criterion == "evidence":
        # The search and the choice are the ones calibrate made by evidence before the criterion existed.
        assert [(c.stage, round(c.factor, 9), c.flip_prob) for c in result.candidates] == EVIDENCE_PATH
        assert result.best.log_evidence == max(c.log_evidence for c in result.candidates)
        target, flip = 0.03, 0.003
    else:
        assert result.best.one_step_rmse == min(c.one_step_rmse for c in result.candidates)
        target, flip = 0.3, 0.01
    # At the optimum of its own criterion: the flip exactly, the noise within the refinement's
    # factor 1.22 (the optima are 10x and 3.3x apart, so neither criterion can land on the other's).
    assert result.flip_prob == flip and target / 1.22 < result.noise_std < target * 1.22
    assert (result.noise_std, result.flip_prob) == (result.best.noise_std, result.best.flip_prob)
    assert model.calibration is not None and model.calibration["criterion"] == result.criterion == criterion


def outlier_episodes(outlier: float = 2.0) -> tuple[smcd_rl.AdaptiveModel, TensorDict]:
    """Episodes of ``net(q, mask=true_mask) + N(0, SIGMA^2)`` whose first step is an outlier no mask predicts.

    A third input, 1 at the first step and 0 after, drives every hidden unit below zero: at the
    first step the ReLUs output 0, so every mask predicts the output bias exactly, and the
    observation is that plus ``outlier``.
    """
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(3, 2, hidden=(8,), dropout=0.5)
    with torch.no_grad():
        net.linears[0].weight[:, 2] = -100.0
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    model.fitted = True  # a random network on purpose: the truth is its own masked output
    model.residual_scale = [5 * SIGMA, 5 * SIGMA]  # where a fit on clean data would start the search
    g = torch.Generator().manual_seed(1)
    true_mask = (torch.rand(net.mask_dim, generator=g) < 0.5).float()
    q = torch.rand(8, 20, 3, generator=g) * 4 - 2
    q[..., 2] = 0.0
    q[:, 0, 2] = 1.0
    with torch.no_grad():
        ee = net(q, mask=true_mask) + SIGMA * torch.randn(8, 20, 2, generator=g)
        assert torch.equal(net(q[:, 0], mask=1 - true_mask), net(q[:, 0], mask=true_mask))  # no mask is told apart
    ee[:, 0] += outlier
    return model, TensorDict({"q": q, "ee": ee}, [8, 20])


def test_one_step_chooses_the_lowest_error_where_the_evidence_chooses_otherwise() -> None:
    """Heavy tails: one outlier per episode, at a step that carries no information about the mask.

    Why the two criteria must disagree here. Every mask predicts the first step alike, so the
    filter's weights, and hence its predictions, do not depend on the first step at all, and the
    one-step error never scores the first step: the one-step choice is the noise at which the
    filter finds the mask from the clean steps, near SIGMA. The evidence does score it, with
    ``-outlier^2 / (2 noise^2)`` per output: at noise near SIGMA that is -5000 nats per episode
    and output, far more than the clean steps can gain (at most log(0.5 / SIGMA) = 3.2 nats per
    step and output over a noise of 0.5, about 120 per episode), so the evidence chooses a noise
    near the outlier's own scale, at which the filter barely adapts.
    """
    model, episodes = outlier_episodes()
    one_step = smcd_rl.calibrate(model, episodes, base=small_base(), per_dimension=False, progress=False)
    by_evidence = smcd_rl.calibrate(
        model, episodes, base=small_base(), per_dimension=False, criterion="evidence", progress=False
    )
    assert one_step.criterion == "one-step"  # the default
    assert one_step.best.one_step_rmse == min(c.one_step_rmse for c in one_step.candidates)
    assert by_evidence.best.log_evidence == max(c.log_evidence for c in by_evidence.candidates)
    assert isinstance(one_step.noise_std, float) and isinstance(by_evidence.noise_std, float)
    assert SIGMA / 2 < one_step.noise_std < 2 * SIGMA
    assert by_evidence.noise_std > 8 * one_step.noise_std
    # And the evidence's choice predicts worse, by the error the one-step search minimised: near the
    # unadapted network's error (0.11 here), where the one-step choice finds the mask (0.07).
    assert one_step.best.one_step_rmse < 0.8 * by_evidence.best.one_step_rmse
    # Both searches run every setting alike (common random numbers): the bracket is the same runs.
    assert one_step.candidates[:7] == by_evidence.candidates[:7]


@pytest.mark.parametrize("criterion", ["one-step", "evidence"])
def test_a_filter_that_refuses_the_episodes_under_every_setting_is_an_error(criterion: str) -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=5)
    model.residual_scale = [0.1, 0.1]  # the search starts at noise 0.1 (not at the outlier, as from the episodes)
    episodes["ee"][1, 0, 0] = 1e30  # impossible under every particle and every candidate noise
    with pytest.raises(ValueError, match="refused the episodes under every candidate"):
        smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=8), criterion=criterion, progress=False)
    assert model.calibration is None


@pytest.mark.parametrize("criterion", ["rmse", "Evidence", "one_step", None, 1])
def test_an_unknown_criterion_is_refused_and_changes_nothing(criterion: object) -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=5)
    model.calibration = {"noise_std": [0.03, 0.05], "flip_prob": 0.003, "criterion": "evidence"}
    before = model.calibration
    with pytest.raises(
        ValueError, match=r"criterion must be one of \['one-step', 'evidence', 'lookahead'\] or a callable"
    ):
        smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=8), criterion=criterion, progress=False)  # type: ignore[arg-type]
    assert model.calibration == before


def test_the_table_lists_every_candidate_and_marks_the_chosen_one() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    result = smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=32), progress=False)
    table = str(result)
    rows = [line for line in table.splitlines() if line[:6].strip()[:1] in "*0123456789" and line[:6].strip()]
    assert len(rows) == len(result.candidates)
    assert sum(line.startswith("*") for line in table.splitlines()) == 1
    starred = next(i for i, line in enumerate(rows) if line.startswith("*"))
    assert result.candidates[starred].one_step_rmse == min(c.one_step_rmse for c in result.candidates)
    assert "log evidence/ep" in table and "1-step RMSE" in table
    assert "chosen (lowest 1-step RMSE): noise_std=" in table  # the default criterion, named
    assert ("note: flip_prob" in table) == (result.flip_prob in (0.001, 0.03))  # the grid's ends
    assert all(math.isfinite(c.one_step_rmse) and c.one_step_rmse > 0 for c in result.candidates)


def test_calibration_is_seeded_and_repeatable() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=8)
    base = smcd_rl.SMCD(num_particles=64)
    first = smcd_rl.calibrate(model, episodes, base=base, seed=3, progress=False)
    second = smcd_rl.calibrate(model, episodes, base=base, seed=3, progress=False)
    assert first == second  # every candidate's setting, evidence and error, bit for bit
    assert first.strategy.config() == second.strategy.config()
    other = smcd_rl.calibrate(model, episodes, base=base, seed=4, progress=False)
    assert [c.log_evidence for c in other.candidates] != [c.log_evidence for c in first.candidates]


def test_a_list_of_episodes_is_the_stacked_batch() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    base = smcd_rl.SMCD(num_particles=32)
    stacked = smcd_rl.calibrate(model, episodes, base=base, progress=False)
    listed = smcd_rl.calibrate(model, list(episodes.unbind(0)), base=base, progress=False)
    assert stacked == listed


def bad_episodes() -> dict[str, tuple[object, type[Exception], str]]:
    _, good, _ = known_mask_episodes(episodes=3, steps=5)
    nan = good.clone()
    nan["ee"][1, 2, 0] = math.nan
    return {
        "missing key": (good.exclude("ee"), KeyError, "no key 'ee'"),
        "wrong features": (TensorDict({"q": good["q"], "ee": good["ee"][..., :1]}, [3, 5]), ValueError, "ee"),
        "extra dims": (TensorDict({"q": good["q"], "ee": good["ee"].unsqueeze(-2)}, [3, 5]), ValueError, "ee"),
        "one episode [T]": (good[0], ValueError, "at least 2"),
        "three batch dims": (good.unsqueeze(0), ValueError, "reshape(-1, 5)"),
        "one episode [1, T]": (good[:1], ValueError, "at least 2 episodes"),
        "one step": (good[:, :1], ValueError, "at least 2 steps"),
        "NaN": (nan, ValueError, "NaN"),
        "different lengths": ([good[0], good[1, :3]], ValueError, "different lengths"),
        "different keys": ([good[0], good[1].exclude("ee").set("x", good[1]["ee"])], ValueError, "same keys"),
        "a [T, ...] in a list": ([good, good], ValueError, "batch [T]"),
        "a dict": ({"q": good["q"], "ee": good["ee"]}, TypeError, "TensorDict"),
        "a tensor": (good["q"], TypeError, "TensorDict"),
    }


@pytest.mark.parametrize("case", sorted(bad_episodes()))
def test_bad_episodes_are_refused_before_any_work(case: str) -> None:
    model, _, _ = known_mask_episodes(episodes=3, steps=5)
    episodes, error, message = bad_episodes()[case]
    with pytest.raises(error, match=re.escape(message)):
        smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=8), progress=False)  # type: ignore[arg-type]
    assert model.calibration is None


def test_an_unfitted_model_and_bad_settings_are_refused() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=5)
    unfitted = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    with pytest.raises(ValueError, match="fitted model"):
        smcd_rl.calibrate(unfitted, episodes, progress=False)
    with pytest.raises(ValueError, match="flip_probs"):
        smcd_rl.calibrate(model, episodes, flip_probs=(0.01, 2.0), progress=False)
    with pytest.raises(TypeError, match="base must be a smcd_rl.SMCD"):
        smcd_rl.calibrate(model, episodes, base=smcd_rl.NoAdaptation(), progress=False)  # type: ignore[arg-type]


def tiny_fitted(validation: bool = False) -> tuple[smcd_rl.AdaptiveModel, list[float], TensorDict]:
    """A small q -> ee model fitted on 4 of 6 episodes (the other 2 as ``validation`` if asked)."""
    torch.manual_seed(0)
    q = torch.rand(6, 16, 2) * 2
    data = TensorDict({"q": q, "ee": torch.stack([q[..., 0].cos() + q[..., 1], q.sin().sum(-1)], -1)}, [6, 16])
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    held_out = data[4:] if validation else None
    before = torch.get_rng_state()
    losses = smcd_rl.fit(model, data[:4], epochs=3, batch_size=16, lr=1e-2, progress=False, validation=held_out)
    assert torch.equal(torch.get_rng_state(), before), "fit drew from the global generator"
    return model, losses, data


def test_fit_records_the_residual_scale_without_changing_training(monkeypatch: pytest.MonkeyPatch) -> None:
    model, losses, data = tiny_fitted()
    with_validation, validation_losses, _ = tiny_fitted(validation=True)
    monkeypatch.setattr(fitting, "_record_residual_scale", lambda *args: None)
    without, plain_losses, _ = tiny_fitted()
    assert without.residual_scale is None
    assert losses == validation_losses == plain_losses  # bit for bit
    for other in (with_validation, without):
        for key, value in model.state_dict().items():
            assert torch.equal(value, other.state_dict()[key]), key
    # The residual of the network with dropout off, per output, in the target's units.
    scale, held_out = model.residual_scale, with_validation.residual_scale
    assert scale is not None and held_out is not None and scale.shape == (2,) and not torch.equal(scale, held_out)
    model.reset()
    train = data[:4].reshape(-1)
    expected = (model(train.exclude("ee"))["ee"] - train["ee"]).square().mean(0).sqrt()
    assert torch.allclose(scale, expected.detach(), rtol=1e-4)


def test_calibration_starts_from_the_fit_and_keeps_the_residual_proportions() -> None:
    model, _, data = tiny_fitted(validation=True)
    episodes = data[4:]  # held out from training: [2 episodes, 16 steps]
    result = smcd_rl.calibrate(
        model, episodes, base=smcd_rl.SMCD(num_particles=32), noise_shape="proportional", progress=False
    )
    assert result.residual_source == "fit" and result.residual_scale == model.residual_scale.double().tolist()
    assert isinstance(result.noise_std, list) and len(result.noise_std) == 2
    ratio = torch.tensor(result.noise_std, dtype=torch.float64) / torch.tensor(result.residual_scale)
    assert torch.allclose(ratio, ratio[0].expand(2)) and math.isclose(float(ratio[0]), result.best.factor)
    # A second fit trains other weights: the calibration of the old ones goes.
    smcd_rl.fit(model, data[:4], epochs=1, batch_size=16, progress=False)
    assert model.calibration is None and model.residual_scale is not None


@pytest.mark.parametrize("trainer", ["fit", "fit_reptile"])
def test_a_training_run_stopped_midway_leaves_no_record_of_the_old_weights(trainer: str) -> None:
    """A run stopped after the weights changed (an exception in a callback, Ctrl-C) must not leave the
    calibration, tuning or residual scale of the weights it started from: SMCD(noise_std="auto") would
    then filter the new weights with the old noise."""
    model, _, data = tiny_fitted(validation=True)
    smcd_rl.calibrate(model, data[4:], base=smcd_rl.SMCD(num_particles=32), progress=False)
    model.tuning = {"chosen": "before"}
    weights = {k: v.clone() for k, v in model.state_dict().items()}

    def stop(epoch: int, loss: float) -> None:
        raise KeyboardInterrupt

    train = getattr(smcd_rl, trainer)
    with pytest.raises(KeyboardInterrupt):
        train(model, data[:4], epochs=3, batch_size=16, progress=False, callback=stop)
    assert any(not torch.equal(v, model.state_dict()[k]) for k, v in weights.items()), "the run changed no weight"
    assert model.calibration is None and model.tuning is None and model.residual_scale is None
    with pytest.raises(ValueError, match="has none; run smcd_rl.calibrate"):
        model.with_adaptation(smcd_rl.SMCD(num_particles=8, noise_std="auto", flip_prob="auto")).reset()


def test_save_and_load_keep_the_residual_scale_and_calibration(tmp_path) -> None:  # noqa: ANN001
    model, _, data = tiny_fitted(validation=True)
    smcd_rl.calibrate(model, data[4:], base=smcd_rl.SMCD(num_particles=32), progress=False)
    auto = model.with_adaptation(smcd_rl.SMCD(num_particles=32, noise_std="auto", flip_prob="auto"))
    auto.save(tmp_path / "model.pt")
    loaded = smcd_rl.load(tmp_path / "model.pt")
    assert loaded.calibration == model.calibration and loaded.calibration["criterion"] == "one-step"
    assert torch.equal(loaded.residual_scale, model.residual_scale)
    assert loaded.adaptation.config() == auto.adaptation.config()
    assert loaded.adaptation.config()["noise_std"] == "auto"
    loaded.reset()
    assert loaded.adaptation.filter.flip_prob == model.calibration["flip_prob"]
    # A file written before either was recorded still loads, with neither.
    old = model.checkpoint()
    del old["residual_scale"], old["calibration"]
    fresh = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    fresh.load_checkpoint(old)
    assert fresh.residual_scale is None and fresh.calibration is None
    # A calibration written before the criterion was recorded (it was always the evidence) loads and runs.
    old = model.checkpoint()
    del old["calibration"]["criterion"]
    fresh.load_checkpoint(old)
    assert fresh.calibration == {k: v for k, v in model.calibration.items() if k != "criterion"}
    runner = fresh.with_adaptation(smcd_rl.SMCD(num_particles=8, noise_std="auto", flip_prob="auto"))
    runner.reset()
    assert runner.adaptation.filter.flip_prob == model.calibration["flip_prob"]
    bad = {**model.checkpoint(), "calibration": {"noise_std": [0.1, 0.2, 0.3], "flip_prob": 0.01}}
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="calibration"):
        fresh.load_checkpoint(bad)


def test_auto_smcd_runs_as_the_stored_settings_and_refuses_without_them() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=5)
    auto = model.with_adaptation(smcd_rl.SMCD(num_particles=16, noise_std="auto", flip_prob="auto"))
    with pytest.raises(ValueError, match=r"run smcd_rl\.calibrate\(model, episodes\) first"):
        auto.reset(batch_shape=(3,))
    model.calibration = {"noise_std": [0.03, 0.05], "flip_prob": 0.003}
    runs = {}
    for name, noise, flip in (("auto", "auto", "auto"), ("explicit", [0.03, 0.05], 0.003)):
        strategy = smcd_rl.SMCD(
            num_particles=16, noise_std=noise, flip_prob=flip, generator=torch.Generator().manual_seed(0)
        )
        runner = model.with_adaptation(strategy)  # shares the model's calibration, set after it was built
        runner.reset(batch_shape=(3,))
        for t in range(5):
            runner.observe(episodes[:, t])
        runs[name] = runner.summary()["log_evidence"]
    assert torch.equal(runs["auto"], runs["explicit"])
    noise_only = model.with_adaptation(smcd_rl.SMCD(num_particles=16, noise_std="auto"))
    noise_only.reset()
    assert noise_only.adaptation.filter.flip_prob == 0.01  # the flip probability given (the default)
    model.calibration = None
    with pytest.raises(ValueError, match="has none"):
        auto.reset()


def test_per_dimension_takes_a_bool_not_a_truthy_value() -> None:
    """per_dimension="no" once meant True: any non-empty string is truthy."""
    model, _, data = tiny_fitted(validation=True)
    with pytest.raises(TypeError, match="per_dimension must be True or False, got 'no'"):
        smcd_rl.calibrate(model, data[4:], per_dimension="no", progress=False)
    assert model.calibration is None


def test_the_searched_shape_finds_a_noise_equal_in_every_dimension() -> None:
    """The episodes' noise is SIGMA in both outputs while the network's residual is twice as large in
    the second: the residual's proportions cannot be right in both (they end 1.5x off in one), so the
    evidence must choose the shape, and the search must offer the right one."""
    model, episodes, _ = known_mask_episodes()
    searched = smcd_rl.calibrate(model, episodes, base=small_base(), criterion="evidence", progress=False)
    proportional = smcd_rl.calibrate(
        model, episodes, base=small_base(), criterion="evidence", noise_shape="proportional", progress=False
    )
    assert searched.residual_scale[1] > 1.5 * searched.residual_scale[0]
    assert {c.shape for c in searched.candidates} == {"proportional", "scalar", "sqrt"}
    noise = torch.tensor(searched.noise_std, dtype=torch.float64).expand(2)
    assert bool(((noise / SIGMA).log().abs() < math.log(1.2)).all()), noise
    off = torch.tensor(proportional.noise_std, dtype=torch.float64) / SIGMA
    assert float(off.log().abs().max()) > math.log(1.4), off
    assert searched.best.log_evidence > proportional.best.log_evidence
    table = str(searched)
    assert "shape" in table and f"({searched.noise_shape})" in table


def test_the_search_before_shapes_stays_reachable_and_begins_the_shape_search() -> None:
    """per_dimension=True is noise_shape="proportional", run for run; the shape search starts with
    exactly those runs (the same seeds), so it only adds runs to the old search."""
    model, episodes, _ = known_mask_episodes(episodes=4, steps=10)
    base = smcd_rl.SMCD(num_particles=32)

    def runs(result: calibration.Calibration) -> list[tuple]:
        return [(c.stage, c.noise_std, c.flip_prob, c.log_evidence, c.score) for c in result.candidates]

    old = smcd_rl.calibrate(model, episodes, base=base, per_dimension=True, progress=False, store=False)
    shape = smcd_rl.calibrate(model, episodes, base=base, noise_shape="proportional", progress=False, store=False)
    searched = smcd_rl.calibrate(model, episodes, base=base, progress=False, store=False)
    assert runs(old) == runs(shape) and old.noise_shape == "proportional" and old.shapes == ["proportional"]
    first = [r for r in runs(old) if r[0] in ("bracket", "flip")]
    assert runs(searched)[: len(first)] == first
    with pytest.raises(ValueError, match="noise_shape must be 'search' or one of"):
        smcd_rl.calibrate(model, episodes, base=base, noise_shape="diagonal", progress=False)  # type: ignore[arg-type]
