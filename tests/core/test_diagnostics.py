"""smcd_rl.diagnostics.trace: a strategy's one-step error, ESS, evidence and kept share, step by step."""

from __future__ import annotations

import math

import pytest
import torch

import smcd_rl
from smcd_rl.calibration import evidence
from smcd_rl.diagnostics import trace
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


def test_bad_episodes_get_the_calibration_errors() -> None:
    model, episodes, _ = known_mask_episodes(episodes=3, steps=6)
    with pytest.raises(KeyError, match="ee"):
        trace(model, episodes.exclude("ee"), smcd_rl.NoAdaptation())
    with pytest.raises(ValueError, match="at least 2 steps"):
        trace(model, episodes[:, :1], smcd_rl.NoAdaptation())
