"""fit_reptile: learning, the meaning of the outer step size, exact resume, and refusing bad data."""

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.envs.two_link_arm import motor_babbling
from smcd_rl.experiments.shared.runtime import torch_threads


@pytest.fixture(autouse=True)
def one_thread():
    """Hundreds of SGD steps on tiny batches: one thread is fastest, and stays fast on a busy machine."""
    with torch_threads(1):
        yield


def _data(tasks: int = 16, episodes: int = 8) -> TensorDict:
    """Two-link motor babbling: [tasks, episodes, 10 steps], one arm (link lengths) per task."""
    return motor_babbling(tasks, episodes, 10, measurement_noise=0.01, generator=torch.Generator().manual_seed(0))


def _model(hidden: int = 64) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(hidden, hidden), dropout=0.2)
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")


def _weights(model: smcd_rl.AdaptiveModel) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.net.parameters()]


def test_reptile_learns_two_link_kinematics() -> None:
    """Targets are standardised, so a network that ignores q scores a loss of at least 1.0.
    Below 0.6 it explains 40% of the variance from q: learned kinematics, since the spread of
    link lengths between tasks accounts for under 10% of it. Measured: ~0.9 -> 0.35-0.45."""
    model = _model()
    data = _data(tasks=8, episodes=8)
    losses = smcd_rl.fit_reptile(model, data, epochs=15, batch_size=8, lr=1.0, tasks_per_batch=2, progress=False)
    assert losses[-1] < 0.6 and losses[-1] < 0.7 * losses[0]
    assert not model.net.training  # left ready for prediction, like fit


def test_outer_step_size_is_the_fraction_of_the_way_to_the_adapted_weights() -> None:
    """With every task in one meta step, the adapted weights do not depend on lr (same seed,
    same start), so lr=0.5 must land exactly halfway between the start and lr=1."""
    data = _data(tasks=4, episodes=4)
    start = _weights(_model())
    full, half = _model(), _model()
    smcd_rl.fit_reptile(full, data, epochs=1, batch_size=8, lr=1.0, tasks_per_batch=4, progress=False)
    smcd_rl.fit_reptile(half, data, epochs=1, batch_size=8, lr=0.5, tasks_per_batch=4, progress=False)
    moved = False
    for w0, w1, wh in zip(start, _weights(full), _weights(half), strict=True):
        torch.testing.assert_close(wh, w0 + 0.5 * (w1 - w0))
        moved |= not torch.equal(w1, w0)
    assert moved


class Interrupt(Exception):
    pass


def test_interrupted_reptile_resumes_to_the_same_result(tmp_path) -> None:
    data = _data(tasks=6, episodes=4)
    kwargs = {"epochs": 4, "batch_size": 16, "tasks_per_batch": 2, "seed": 5, "progress": False}
    straight = _model()
    full = smcd_rl.fit_reptile(straight, data, **kwargs)

    def stop_after_two(epoch: int, loss: float) -> None:
        if epoch == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        smcd_rl.fit_reptile(_model(), data, checkpoint=tmp_path / "r.pt", callback=stop_after_two, **kwargs)
    fresh = _model()  # a new process: nothing but the checkpoint survives
    history = smcd_rl.fit_reptile(fresh, data, checkpoint=tmp_path / "r.pt", **kwargs)
    assert history == full
    for a, b in zip(straight.state_dict().values(), fresh.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # Another seed shuffles and masks differently, so it is not the same run.
    other = _model()
    smcd_rl.fit_reptile(other, data, **{**kwargs, "seed": 6})
    assert not torch.equal(other.net.linears[0].weight, straight.net.linears[0].weight)


def test_checkpoint_of_other_settings_or_of_fit_is_refused(tmp_path) -> None:
    data = _data(tasks=4, episodes=2)
    smcd_rl.fit_reptile(_model(), data, epochs=1, checkpoint=tmp_path / "r.pt", progress=False)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="settings"):
        smcd_rl.fit_reptile(_model(), data, epochs=2, inner_lr=0.1, checkpoint=tmp_path / "r.pt", progress=False)
    smcd_rl.fit(_model(), data, epochs=1, checkpoint=tmp_path / "m.pt", progress=False)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="settings"):
        smcd_rl.fit_reptile(_model(), data, epochs=2, checkpoint=tmp_path / "m.pt", progress=False)


def test_bad_data_and_settings_are_refused() -> None:
    data = _data(tasks=4, episodes=2)
    with pytest.raises(ValueError, match="first batch dim indexes tasks"):
        smcd_rl.fit_reptile(_model(), data.reshape(-1), epochs=1, progress=False)
    with pytest.raises(ValueError, match="empty dataset"):
        smcd_rl.fit_reptile(_model(), data[:, :0], epochs=1, progress=False)
    with pytest.raises(ValueError, match="tasks_per_batch=5 exceeds the 4 tasks"):
        smcd_rl.fit_reptile(_model(), data, epochs=1, tasks_per_batch=5, progress=False)
    with pytest.raises(ValueError, match=r"inner_lr must be in \(0, "):
        smcd_rl.fit_reptile(_model(), data, epochs=1, inner_lr=0.0, progress=False)
    with pytest.raises(ValueError, match=r"lr must be in \(0, .*got inf"):
        smcd_rl.fit_reptile(_model(), data, epochs=1, lr=math.inf, progress=False)
    with pytest.raises(TypeError, match=r"epochs must be an int, got 1.5"):
        smcd_rl.fit_reptile(_model(), data, epochs=1.5, progress=False)
    with pytest.raises(KeyError, match="no key 'ee'"):
        smcd_rl.fit_reptile(_model(), TensorDict({"q": torch.zeros(2, 3, 2)}, [2, 3]), epochs=1, progress=False)
