"""Scores of your own in tune and calibrate: reuse that cannot mix two functions, -inf as the best
possible score, and a clear error where no setting has a usable score."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl

FAST = {"num_particles": 16, "gd_grid": {"lr": (1e-3, 1e-2), "steps": (1,), "window": (1, 5)}, "progress": False}


@pytest.fixture(scope="module")
def model(sine_model) -> smcd_rl.AdaptiveModel:
    return sine_model


def episodes(shift: float = 0.5, count: int = 6, steps: int = 12) -> TensorDict:
    generator = torch.Generator().manual_seed(1)
    q = torch.rand(count, steps, 2, generator=generator) * 2 - 1
    return TensorDict({"q": q, "ee": torch.sin(q) + shift}, [count, steps])


def _mean_error(predicted, observed) -> float:
    return float((predicted - observed).abs().mean())


def test_reuse_refuses_another_score_function_of_the_same_name(model) -> None:
    """Two lambdas (or an edited ``def score``) share a name: reuse once kept the first one's scores and choice."""
    score = lambda p, o: _mean_error(p, o)  # noqa: E731
    other = lambda p, o: -_mean_error(p, o)  # noqa: E731 - the same name, <lambda>, on purpose
    first = smcd_rl.tune(model, episodes(), strategies=["gradient_descent"], criterion=score, horizon=1, **FAST)
    with pytest.raises(ValueError, match="another score function"):
        smcd_rl.tune(
            model, episodes(), strategies=["gradient_descent"], criterion=other, horizon=1, reuse=first, **FAST
        )
    again = smcd_rl.tune(
        model, episodes(), strategies=["gradient_descent"], criterion=score, horizon=1, reuse=first, **FAST
    )
    assert again.best_of["gradient_descent"] == first.best_of["gradient_descent"]


def test_a_score_of_minus_infinity_is_the_best_not_unusable(model) -> None:
    """-inf is the best score there is (a goal reached, say): the setting that earns it wins. It was once
    treated as unusable, so a worse setting won."""
    grid = {"lr": (1e-3, 1e-2, 1e-1), "steps": (1,), "window": (5,), "loss": ("mse",)}
    plain = smcd_rl.tune(
        model,
        episodes(),
        strategies=["gradient_descent"],
        criterion=_mean_error,
        horizon=1,
        gd_grid=grid,
        progress=False,
    )
    reached = math.nextafter(plain.best_of["gradient_descent"].score, math.inf)  # only the best's error is below it

    def goal(predicted, observed) -> float:
        error = _mean_error(predicted, observed)
        return -math.inf if error < reached else error

    result = smcd_rl.tune(
        model, episodes(), strategies=["gradient_descent"], criterion=goal, horizon=1, gd_grid=grid, progress=False
    )
    best = result.best_of["gradient_descent"]
    assert best.score == -math.inf and best.settings == plain.best_of["gradient_descent"].settings
    # JSON has no -inf: the record keeps it as a string, and reads it back as the best possible score.
    again = smcd_rl.TuneResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert again.best_of["gradient_descent"].score == -math.inf


def test_no_usable_score_without_a_budget_is_a_clear_error(model) -> None:
    """A score that is inf everywhere once crashed with a TypeError (formatting a budget of None)."""
    with pytest.raises(ValueError, match=r"no setting of \['none', 'gradient_descent'\] has a usable score"):
        smcd_rl.tune(
            model,
            episodes(),
            strategies=["none", "gradient_descent"],
            criterion=lambda p, o: math.inf,
            horizon=1,
            **FAST,
        )


def test_calibrate_names_the_score_not_the_filter_when_the_score_is_never_usable(model) -> None:
    """Every filter run ran; only the score refused them: the error says so (it blamed the filter)."""
    with pytest.raises(ValueError, match="your score returned inf for every candidate setting"):
        smcd_rl.calibrate(
            model,
            episodes(),
            base=smcd_rl.SMCD(num_particles=8),
            criterion=lambda p, o: math.inf,
            horizon=1,
            progress=False,
            store=False,
        )
