"""fit: learning, exact resume after an interruption, and refusing bad data or checkpoints."""

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl


def _data(n: int = 512) -> TensorDict:
    q = torch.rand(n, 2, generator=torch.Generator().manual_seed(0)) * 6 - 3
    return TensorDict({"q": q, "ee": torch.stack([q[:, 0].cos() + q[:, 1].sin(), q[:, 0] * q[:, 1]], -1)}, [n])


def _model(hidden: int = 64) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    return smcd_rl.AdaptiveModel(
        smcd_rl.MaskedMLP(2, 2, hidden=(hidden, hidden), dropout=0.2), in_keys=["q"], out_key="ee"
    )


def test_fit_learns() -> None:
    """Targets are standardised, so predicting the mean scores a loss of 1.0; a smooth target
    that the network fits must fall below 0.2 (dropout noise keeps it above 0)."""
    losses = smcd_rl.fit(_model(), _data(), epochs=40, batch_size=64, lr=3e-3, progress=False)
    assert losses[0] > losses[-1] and losses[-1] < 0.2


class Interrupt(Exception):
    pass


def test_interrupted_training_resumes_to_the_same_result(tmp_path) -> None:
    data = _data()
    straight = _model()
    full = smcd_rl.fit(straight, data, epochs=4, batch_size=64, lr=1e-3, progress=False)

    resumed = _model()

    def stop_after_two(epoch: int, loss: float) -> None:
        if epoch == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        smcd_rl.fit(
            resumed,
            data,
            epochs=4,
            batch_size=64,
            lr=1e-3,
            checkpoint=tmp_path / "c.pt",
            callback=stop_after_two,
            progress=False,
        )
    fresh = _model()  # a new process: nothing but the checkpoint survives
    history = smcd_rl.fit(fresh, data, epochs=4, batch_size=64, lr=1e-3, checkpoint=tmp_path / "c.pt", progress=False)
    assert history == full
    for a, b in zip(straight.state_dict().values(), fresh.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_resume_refuses_another_model_other_settings_or_other_data(tmp_path) -> None:
    smcd_rl.fit(_model(), _data(), epochs=1, checkpoint=tmp_path / "c.pt", progress=False)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="architecture"):
        smcd_rl.fit(_model(hidden=32), _data(), epochs=2, checkpoint=tmp_path / "c.pt", progress=False)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="settings"):
        smcd_rl.fit(_model(), _data(), epochs=2, lr=0.5, checkpoint=tmp_path / "c.pt", progress=False)
    other = _data()
    other["ee"] = other["ee"] * 2  # same keys and shapes, other values
    for data in (other, _data(256)):
        with pytest.raises(smcd_rl.CheckpointMismatchError, match="other data"):
            smcd_rl.fit(_model(), data, epochs=2, checkpoint=tmp_path / "c.pt", progress=False)


def test_empty_or_incomplete_data_is_refused() -> None:
    with pytest.raises(ValueError, match="empty dataset"):
        smcd_rl.fit(_model(), _data()[:0], epochs=1, progress=False)
    with pytest.raises(KeyError, match="no key 'ee'"):
        smcd_rl.fit(_model(), TensorDict({"q": torch.zeros(4, 2)}, [4]), epochs=1, progress=False)
    with pytest.raises(TypeError, match="AdaptiveDynamicsModel"):
        smcd_rl.fit_dynamics(_model(), _data(), epochs=1)


def test_seeded_training_is_repeatable() -> None:
    a, b = _model(), _model()
    smcd_rl.fit(a, _data(), epochs=2, seed=3, progress=False)
    smcd_rl.fit(b, _data(), epochs=2, seed=3, progress=False)
    for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize(
    ("settings", "error", "message"),
    [
        (
            {"lr": math.inf},
            ValueError,
            r"lr must be in \(0, .*got inf",
        ),  # once trained to NaN, then blamed residual_scale
        ({"lr": math.nan}, ValueError, r"lr must be in \(0, "),
        ({"epochs": 1.5}, TypeError, r"epochs must be an int, got 1.5"),  # once Python's raw range() error
        ({"batch_size": 0}, ValueError, "batch_size must be >= 1"),
        ({"weight_decay": -0.1}, ValueError, "weight_decay must be in"),
        # These once failed after the normalisation was fitted (the model then declared trained):
        ({"seed": 0.5}, TypeError, r"seed must be an int, got 0.5"),  # torch's "manual_seed expected a long"
        ({"seed": 2**70}, ValueError, r"seed must be in \[0, 2\*\*64 - 1\]"),
        ({"checkpoint": 5}, TypeError, "fit: checkpoint must be a file path"),
        ({"group_masks": "yes"}, TypeError, "group_masks must be True or False"),
        # ... and these after a whole epoch, or the whole run:
        ({"callback": 5}, TypeError, r"fit: callback must be callable as callback\(epoch, mean_loss\)"),
        ({"validation": TensorDict({"q": torch.rand(8, 2)}, [8])}, KeyError, r"fit\(validation=...\): .*no key 'ee'"),
        (
            {"validation": TensorDict({"q": torch.rand(8, 2), "ee": torch.full((8, 2), math.nan)}, [8])},
            ValueError,
            r"fit\(validation=...\): 'ee' contains NaN",
        ),
    ],
)
def test_bad_training_settings_are_refused_before_any_step(settings, error, message) -> None:
    model = _model()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(error, match=message):
        smcd_rl.fit(model, _data(), **{"epochs": 1, **settings}, progress=False)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
    assert not model.fitted


def test_a_checkpoint_path_that_is_a_directory_is_refused_before_any_step(tmp_path) -> None:
    model = _model()
    with pytest.raises(ValueError, match="is a directory; pass a file path in it"):
        smcd_rl.fit(model, _data(), epochs=1, checkpoint=tmp_path, progress=False)
    assert not model.fitted


def test_a_bare_network_or_a_dict_is_refused_with_the_fix() -> None:
    """They met "'MaskedMLP' object has no attribute 'net'" and "'dict' object has no attribute 'batch_size'"."""
    data = _data(64)
    with pytest.raises(TypeError, match=r"fit trains an smcd_rl.AdaptiveModel, got MaskedMLP; wrap it"):
        smcd_rl.fit(_model().net, data, epochs=1, progress=False)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"fit takes a tensordict.TensorDict, got dict; wrap it"):
        smcd_rl.fit(_model(), dict(data.items()), epochs=1, progress=False)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="fit_reptile trains an smcd_rl.AdaptiveModel"):
        smcd_rl.fit_reptile(_model().net, data.reshape(8, 8), epochs=1, progress=False)  # type: ignore[arg-type]
