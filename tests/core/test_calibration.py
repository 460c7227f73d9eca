"""smcd_rl.calibrate: the noise and flip probability of highest log evidence, and where they are kept."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl import training
from smcd_rl.calibration import evidence

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
    result = smcd_rl.calibrate(model, episodes, base=small_base(), per_dimension=False, progress=False)
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


def test_the_table_lists_every_candidate_and_marks_the_chosen_one() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    result = smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=32), progress=False)
    table = str(result)
    rows = [line for line in table.splitlines() if line[:6].strip()[:1] in "*0123456789" and line[:6].strip()]
    assert len(rows) == len(result.candidates)
    assert sum(line.startswith("*") for line in table.splitlines()) == 1
    assert "log evidence/ep" in table and "1-step RMSE" in table and "chosen: noise_std=" in table
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
    monkeypatch.setattr(training, "_record_residual_scale", lambda *args: None)
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
    result = smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=32), progress=False)
    assert result.residual_source == "fit" and result.residual_scale == model.residual_scale.double().tolist()
    assert isinstance(result.noise_std, list) and len(result.noise_std) == 2
    ratio = torch.tensor(result.noise_std, dtype=torch.float64) / torch.tensor(result.residual_scale)
    assert torch.allclose(ratio, ratio[0].expand(2)) and math.isclose(float(ratio[0]), result.best.factor)
    # A second fit trains other weights: the calibration of the old ones goes.
    smcd_rl.fit(model, data[:4], epochs=1, batch_size=16, progress=False)
    assert model.calibration is None and model.residual_scale is not None


def test_save_and_load_keep_the_residual_scale_and_calibration(tmp_path) -> None:  # noqa: ANN001
    model, _, data = tiny_fitted(validation=True)
    smcd_rl.calibrate(model, data[4:], base=smcd_rl.SMCD(num_particles=32), progress=False)
    auto = model.with_adaptation(smcd_rl.SMCD(num_particles=32, noise_std="auto", flip_prob="auto"))
    auto.save(tmp_path / "model.pt")
    loaded = smcd_rl.load(tmp_path / "model.pt")
    assert loaded.calibration == model.calibration
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
