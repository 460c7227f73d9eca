"""smcd_rl.tuning.diagnostics.trace: a strategy's one-step error, ESS, evidence and kept share, step by step."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.tuning.calibration import evidence
from smcd_rl.tuning.diagnostics import trace
from tests.core.test_calibration import SIGMA, known_mask_episodes


def test_smcd_finds_the_true_mask_and_its_error_falls_to_the_noise() -> None:
    """256 particles over the 256 masks of 8 units: after a few steps the posterior holds the true
    mask, so the one-step error falls from the unadapted network's (over 5 x SIGMA here) to within
    a factor of two of the measurement noise, the floor no strategy can pass."""
    model, episodes, true_mask = known_mask_episodes(episodes=8, steps=20)
    smcd = smcd_rl.SMCD(num_particles=256, noise_std=SIGMA, flip_prob=0.001)
    result = trace(model, episodes, smcd)
    plain = trace(model, episodes, smcd_rl.NoAdaptation())
    assert len(result.one_step_rmse) == 19 and len(result.ess) == len(result.log_evidence) == 20
    assert min(plain.one_step_rmse) > 5 * SIGMA
    assert max(result.one_step_rmse[-5:]) < 2 * SIGMA * math.sqrt(2)  # sqrt 2: per dimension pooled over 2
    assert result.rmse < plain.rmse / 2
    assert all(0 < e <= 1 for e in result.ess) and all(0 <= k <= 1 for k in result.kept)
    assert abs(result.kept[-1] - float(true_mask.mean())) < 0.1  # the MMSE mask keeps the true share
    assert plain.ess == [] and plain.kept == [] and plain.log_evidence == []


def test_the_final_log_evidence_is_the_filters_evidence() -> None:
    model, episodes, _ = known_mask_episodes(episodes=4, steps=6)
    seeded = smcd_rl.SMCD(num_particles=64, noise_std=0.05, flip_prob=0.01, generator=torch.Generator().manual_seed(0))
    final = trace(model, episodes, seeded).log_evidence[-1]
    expected, _ = evidence(model, episodes, noise_std=0.05, flip_prob=0.01, base=smcd_rl.SMCD(num_particles=64), seed=0)
    assert final == pytest.approx(expected, rel=1e-6)


def test_a_strategy_that_refuses_a_step_ends_the_trace_with_an_infinite_error() -> None:
    """Gradient descent at lr 1e30 turns its weights non-finite on the first step and refuses it."""
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    result = trace(model, episodes, smcd_rl.GradientDescent(lr=1e30, steps=3, window=2))
    assert result.rmse == math.inf and len(result.one_step_rmse) < 5
    assert result.per_episode_rmse == [math.inf] * 3  # which episode made it refuse is not known
    assert [len(errors) for errors in result.one_step_errors] == [len(result.one_step_rmse)] * 3


def test_bad_episodes_get_the_calibration_errors() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    with pytest.raises(KeyError, match="ee"):
        trace(model, episodes.exclude("ee"), smcd_rl.NoAdaptation())
    with pytest.raises(ValueError, match="at least 2 steps"):
        trace(model, episodes[:, :1], smcd_rl.NoAdaptation())


def test_predictive_mean_is_the_weighted_mean_of_the_particles_predictions() -> None:
    """With two masked layers the output is nonlinear in the mask, so the mean prediction differs
    from the prediction of the mean mask (with one, before a linear output layer, they coincide)."""
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8, 8)), in_keys=["q"], out_key="ee")
    model.fitted = True  # a random network on purpose
    episodes = TensorDict({"q": torch.rand(2, 3, 2) * 4 - 2, "ee": torch.zeros(2, 3, 2)}, [2, 3])
    smcd = smcd_rl.SMCD(num_particles=64, noise_std=0.5, prediction="predictive", ess_threshold=0.0)
    adapted = model.with_adaptation(smcd)
    adapted.reset(batch_shape=(2,))
    adapted.observe(episodes[:, 0])
    q = episodes["q"][:, 1]
    weights = smcd.filter.weights
    expected = (weights.unsqueeze(-1) * smcd.predict_particles(q)).sum(-2)
    assert torch.allclose(smcd.predict(q), expected, atol=1e-6)
    assert not torch.allclose(expected, smcd.net(q, mask=smcd.mask), atol=1e-3)
    extra = q.unsqueeze(1).expand(2, 5, 2)  # planning candidates broadcast like the MMSE prediction
    assert torch.allclose(smcd.predict(extra), expected.unsqueeze(1).expand(2, 5, 2), atol=1e-6)
    with pytest.raises(ValueError, match="prediction must be 'mask'"):
        smcd_rl.SMCD(prediction="mean")


@pytest.mark.parametrize("readout", [False, True])
def test_the_predictive_mean_of_many_inputs_runs_each_distinct_mask_once_in_pieces(monkeypatch, readout) -> None:
    """A look-ahead of 20 inputs per stream with 1,000 particles once held 20 times an observation's
    activations at once (the two-link look-ahead ran out of memory) and ran every copy resampling
    made. Now each distinct mask runs once, with its copies' weights, in pieces of PREDICTIVE_ROWS
    particle rows; the result is each input's own prediction over every particle. With a readout per
    particle (SMCD with a Bayesian readout) each copy carries its particle's readout: the same holds."""
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8, 8)), in_keys=["q"], out_key="ee")
    model.fitted = True  # a random network on purpose
    # A sharp likelihood and resampling at every step: a few ancestors survive, each many times.
    smcd = smcd_rl.SMCD(num_particles=16, noise_std=0.05, prediction="predictive", ess_threshold=1.0)
    strategy = (
        smcd_rl.SMCDLastLayer(smcd, smcd_rl.BayesianLastLayer(noise_std=0.01, prior_scale=1.0)) if readout else smcd
    )
    model.with_adaptation(strategy).reset(batch_shape=(3,))
    strategy.observe(torch.rand(3, 2), torch.rand(3, 2))
    q = torch.rand(3, 4, 5, 2)
    one_at_a_time = torch.stack([torch.stack([strategy.predict(q[:, i, j]) for j in range(5)], 1) for i in range(4)], 1)
    runs = []
    real = smcd.net.forward_particles
    monkeypatch.setattr(
        smcd.net,
        "forward_particles",
        lambda x, masks, readout: runs.append((x.shape[0], masks.shape[0])) or real(x, masks, readout),
    )
    distinct = smcd.filter.distinct()[0].shape[0]
    assert distinct <= 24  # of the 3 streams' 48 particles: the merged path runs each once
    monkeypatch.setattr(smcd_rl.strategies.smcd, "PREDICTIVE_ROWS", distinct * 6)  # six inputs per stream
    pieces = strategy.predict(q)
    assert runs == [(6, distinct), (6, distinct), (6, distinct), (2, distinct)]  # 20 inputs per stream
    assert pieces.shape == (3, 4, 5, 2)
    assert torch.allclose(pieces, one_at_a_time, atol=1e-6)


@pytest.mark.parametrize("likelihood", ["gaussian", "student-t"])
def test_first_step_evidence_is_the_mean_likelihood_of_the_prior_particles(likelihood: str) -> None:
    """After one update from uniform weights the log evidence is log mean_i p(z | mask_i), with
    p the Gaussian or the Student-t density of torch.distributions."""
    model, episodes, _ = known_mask_episodes(episodes=2, steps=2)
    smcd = smcd_rl.SMCD(num_particles=32, noise_std=[0.1, 0.2], flip_prob=0.0, likelihood=likelihood, dof=3.0)
    adapted = model.with_adaptation(smcd)
    adapted.reset(batch_shape=(2,))
    prior = smcd.particles.clone()
    adapted.observe(episodes[:, 0])
    with torch.no_grad():
        predicted = smcd.net.forward_particles(episodes["q"][:, 0], prior.float())  # [2, N, 2]
    scale = torch.tensor([0.1, 0.2])
    density = (
        torch.distributions.Normal(predicted, scale)
        if likelihood == "gaussian"
        else torch.distributions.StudentT(3.0, predicted, scale)
    )
    log_p = density.log_prob(episodes["ee"][:, 0].unsqueeze(1)).sum(-1)
    expected = torch.logsumexp(log_p, -1) - math.log(32)
    assert torch.allclose(smcd.summary()["log_evidence"], expected, atol=1e-4)
    with pytest.raises(ValueError, match="likelihood must be"):
        smcd_rl.SMCD(likelihood="laplace")


def test_student_t_with_many_degrees_of_freedom_is_the_gaussian() -> None:
    """Its normalising constant stays exact where lgamma(v/2) is huge: at v = 1e9 the Student-t
    density is the Gaussian to about 1e-8, so the evidence must agree (it was off by nats once)."""
    model, episodes, _ = known_mask_episodes(episodes=3, steps=4)
    results = []
    for likelihood in ("gaussian", "student-t"):
        smcd = smcd_rl.SMCD(num_particles=16, noise_std=0.1, likelihood=likelihood, dof=1e9)
        smcd._generator = torch.Generator().manual_seed(0)
        results.append(trace(model, episodes, smcd).log_evidence[-1])
    assert results[1] == pytest.approx(results[0], abs=1e-3)
    with pytest.raises(ValueError, match="dof"):
        smcd_rl.SMCD(likelihood="student-t", dof=float("inf"))


def test_trace_refuses_a_strategy_attached_to_a_model() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=4)
    live = model.with_adaptation(smcd_rl.SMCD(num_particles=8, noise_std=0.1))
    live.reset(batch_shape=(7,))
    with pytest.raises(ValueError, match="fresh strategy"):
        trace(model, episodes, live.adaptation)
    assert live.batch_shape == (7,)  # untouched
    with pytest.raises(TypeError, match="strategy"):
        trace(model, episodes, None)


def test_per_episode_errors_single_out_the_worse_episode_and_pool_to_the_rmse() -> None:
    """Episode 2's targets are shifted by 2 (the frozen network's RMSE per episode is 0.2-0.35 here):
    its errors are the largest by far. The episodes have equal lengths T, so with D outputs
    ``rmse**2 = sum_e sum_t sum_d err**2 / (E (T-1) D) = mean_e per_episode_rmse[e]**2``, and per step
    ``one_step_rmse[t]**2 = mean_e one_step_errors[e][t]**2``."""
    model, episodes, _ = known_mask_episodes(episodes=4, steps=6)
    episodes["ee"][2] += 2.0
    result = trace(model, episodes, smcd_rl.NoAdaptation())
    assert len(result.per_episode_rmse) == 4 and [len(errors) for errors in result.one_step_errors] == [5] * 4
    assert max(range(4), key=result.per_episode_rmse.__getitem__) == 2
    assert all(result.per_episode_rmse[2] > 2 * r for e, r in enumerate(result.per_episode_rmse) if e != 2)
    assert result.rmse == pytest.approx(math.sqrt(sum(r**2 for r in result.per_episode_rmse) / 4), rel=1e-12)
    for t, pooled in enumerate(result.one_step_rmse):
        assert pooled == pytest.approx(math.sqrt(sum(e[t] ** 2 for e in result.one_step_errors) / 4), rel=1e-12)
    # The values themselves: the frozen network (identity normalisation here) against the targets.
    with torch.no_grad():
        squared = (model.net.eval()(episodes["q"][:, 1:]) - episodes["ee"][:, 1:]).double().square()  # [E, T-1, D]
    expected_steps = squared.mean(-1).sqrt()
    for e in range(4):
        assert result.one_step_errors[e] == pytest.approx(expected_steps[e].tolist(), rel=1e-5)
        assert result.per_episode_rmse[e] == pytest.approx(float(squared[e].mean().sqrt()), rel=1e-5)
    assert result.rmse == pytest.approx(float(squared.mean().sqrt()), rel=1e-5)  # the pooled field as before
