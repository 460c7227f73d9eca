"""The latent-variable baseline (VRNN): training, adapting from burn-in, resume and bad input."""

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.baselines import LatentVariableModel, fit_latent
from smcd_rl.envs.two_link_arm import DEFAULT_DT, integrate_joints, motor_babbling, two_link_fk
from smcd_rl.experiments.shared.runtime import torch_threads


@pytest.fixture(autouse=True)
def one_thread():
    """Hundreds of small Adam steps: one thread is fastest, and stays fast on a busy machine."""
    with torch_threads(1):
        yield


def _data(tasks: int = 50, episodes: int = 10) -> TensorDict:
    return motor_babbling(tasks, episodes, 10, measurement_noise=0.01, generator=torch.Generator().manual_seed(0))


def _model(width: int = 32) -> LatentVariableModel:
    torch.manual_seed(0)
    return LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=width)


@pytest.fixture(scope="module")
def trained() -> tuple[LatentVariableModel, list[float]]:
    """5000 two-step windows from 50 arms, 6 epochs (~3 s)."""
    model = _model()
    with torch_threads(1):
        losses = fit_latent(model, _data(), epochs=6, batch_size=64, lr=3e-3, progress=False)
    return model, losses


def _paths(arms: int = 200, steps: int = 15) -> torch.Tensor:
    """Held-out motor-babbling joint paths ``[arms, steps, 2]`` (a seed the training data never used)."""
    g = torch.Generator().manual_seed(123)
    q = (torch.rand(arms, 2, generator=g) * 2 - 1) * math.pi
    path = [q]
    for _ in range(steps - 1):
        q = integrate_joints(q, torch.randn(arms, 2, generator=g), DEFAULT_DT)
        path.append(q)
    return torch.stack(path, 1)


def _rmse(model: LatentVariableModel, q: torch.Tensor, seen: torch.Tensor, truth: torch.Tensor, burn_in: int) -> float:
    """Observe ``seen`` for ``burn_in`` steps, then predict the next 5 steps of ``truth``."""
    arms = q.shape[0]
    model.reset(batch_shape=(arms,))
    for t in range(burn_in):
        model.observe(TensorDict({"q": q[:, t], "ee": seen[:, t]}, [arms]))
    ahead = slice(burn_in, burn_in + 5)
    predicted = model(TensorDict({"q": q[:, ahead]}, [arms, 5]))["ee"]
    return float((predicted - truth[:, ahead]).square().sum(-1).mean().sqrt())


def test_elbo_improves_and_prediction_uses_the_input(trained) -> None:
    """The negative ELBO falls by more than 2 nats per window (measured ~4 -> -0.8). Before any
    observation, predictions for arms of the mean length must be 3x better than the best guess
    that ignores q (the spread of the end effector, ~1.4 m): measured ~0.2 m."""
    model, losses = trained
    assert losses[-1] < losses[0] - 2.0
    q = _paths()
    ee = two_link_fk(q, torch.tensor([1.0, 1.0]))
    spread = float((ee - ee.mean((0, 1))).square().sum(-1).mean().sqrt())
    assert _rmse(model, q, ee, ee, burn_in=0) < spread / 3


@pytest.mark.parametrize("length, other", [(0.5, 1.5), (1.5, 0.5)])
def test_burn_in_identifies_the_arm(trained, length: float, other: float) -> None:
    """Arms far from the mean length (0.5 m and 1.5 m links, ~1.7 prior std away). Five
    burn-in steps on the arm must cut the error of the next 5 steps by 20% (measured 40-75%).
    That could happen by chance only if any observation moved predictions the right way; so
    the same burn-in with the other arm's measurements (same joints) must do at least 2x worse
    (measured 3-10x): the state carries which arm it saw."""
    model, _ = trained
    q = _paths()
    own = two_link_fk(q, torch.tensor([length, length]))
    foreign = two_link_fk(q, torch.tensor([other, other]))
    before = _rmse(model, q, own, own, burn_in=0)
    after = _rmse(model, q, own, own, burn_in=5)
    misled = _rmse(model, q, foreign, own, burn_in=5)
    assert after < 0.8 * before
    assert misled > 2 * after


class Interrupt(Exception):
    pass


def test_interrupted_training_resumes_to_the_same_result(tmp_path) -> None:
    data = _data(tasks=8, episodes=4)
    straight = _model(width=16)
    full = fit_latent(straight, data, epochs=3, batch_size=32, seed=4, progress=False)

    def stop_after_one(epoch: int, loss: float) -> None:
        if epoch == 0:
            raise Interrupt

    with pytest.raises(Interrupt):
        fit_latent(
            _model(width=16),
            data,
            epochs=3,
            batch_size=32,
            seed=4,
            checkpoint=tmp_path / "lv.pt",
            callback=stop_after_one,
            progress=False,
        )
    fresh = _model(width=16)
    assert (
        fit_latent(fresh, data, epochs=3, batch_size=32, seed=4, checkpoint=tmp_path / "lv.pt", progress=False) == full
    )
    for a, b in zip(straight.state_dict().values(), fresh.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="architecture"):
        fit_latent(
            _model(width=8), data, epochs=4, batch_size=32, seed=4, checkpoint=tmp_path / "lv.pt", progress=False
        )
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="settings"):
        fit_latent(
            _model(width=16), data, epochs=4, batch_size=16, seed=4, checkpoint=tmp_path / "lv.pt", progress=False
        )


def test_bad_input_is_refused() -> None:
    model = _model(width=8)
    data = _data(tasks=2, episodes=2)
    with pytest.raises(KeyError, match="no key .*next.*ee"):
        fit_latent(model, data.exclude(("next", "ee")), epochs=1, progress=False)
    with pytest.raises(ValueError, match="empty dataset"):
        fit_latent(model, data[:0], epochs=1, progress=False)
    with pytest.raises(TypeError, match="LatentVariableModel"):
        fit_latent(smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee"), data)
    with pytest.raises(RuntimeError, match="reset"):
        model.observe(TensorDict({"q": torch.zeros(2), "ee": torch.zeros(2)}, []))
    model.reset(batch_shape=(3,))
    with pytest.raises(ValueError, match="batch_shape=\\[3\\]"):
        model.observe(TensorDict({"q": torch.zeros(4, 2), "ee": torch.zeros(4, 2)}, [4]))
    with pytest.raises(ValueError, match="'ee' must have shape \\[..., 2\\]"):
        model.observe(TensorDict({"q": torch.zeros(3, 2), "ee": torch.zeros(3, 3)}, [3]))
    with pytest.raises(ValueError, match="NaN"):
        model.observe(TensorDict({"q": torch.full((3, 2), math.nan), "ee": torch.zeros(3, 2)}, [3]))
    with pytest.raises(ValueError, match="reset batch shape"):
        model(TensorDict({"q": torch.zeros(4, 2)}, [4]))
    with pytest.raises(ValueError, match="positive ints"):
        LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", state_dim=0)
