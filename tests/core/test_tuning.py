"""smcd_rl.tune: one criterion for every strategy, a grid that extends itself, a per-step budget."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
import smcd_rl.tuning.held_out
import smcd_rl.tuning.kinds
import smcd_rl.tuning.protocol
import smcd_rl.tuning.search

# Small and fast: a few particles and a small GD grid; each test runs in seconds.
FAST = {"num_particles": 16, "gd_grid": {"lr": (1e-3, 1e-2), "steps": (1,), "window": (1, 5)}, "progress": False}


@pytest.fixture(scope="module")
def model(sine_model) -> smcd_rl.AdaptiveModel:
    return sine_model


def shifted_episodes(shift: float, count: int = 6, steps: int = 12, seed: int = 1) -> TensorDict:
    """Episodes of a task the network never saw: its targets moved by ``shift`` in every output."""
    generator = torch.Generator().manual_seed(seed)
    q = torch.rand(count, steps, 2, generator=generator) * 2 - 1
    return TensorDict({"q": q, "ee": torch.sin(q) + shift}, [count, steps])


@pytest.fixture(scope="module")
def result(model) -> smcd_rl.TuneResult:
    return smcd_rl.tune(model, shifted_episodes(0.5), **FAST)


def test_every_kind_is_scored_by_one_step_error_and_the_best_is_the_lowest(model, result) -> None:
    assert set(result.best_of) == set(smcd_rl.tuning.KINDS)
    lowest = min(c.one_step_rmse for c in result.best_of.values())
    assert result.best_of[result.best_kind].one_step_rmse == lowest
    # A shift of 0.5 in every output is what gradient descent can learn and the frozen network
    # cannot: no adaptation's error is at least the shift's size, GD's must be well below it.
    assert result.best_of["none"].one_step_rmse > 0.4
    assert result.best_of["gradient_descent"].one_step_rmse < 0.8 * result.best_of["none"].one_step_rmse
    # The shift is the readout's bias moving: the Bayesian last layer learns it in a few observations.
    assert result.best_of["last_layer"].one_step_rmse < 0.5 * result.best_of["none"].one_step_rmse
    assert isinstance(result.best, smcd_rl.Adaptation) and isinstance(result.combination, smcd_rl.Combination)
    assert model.tuning["best_kind"] == result.best_kind
    assert "one-step RMSE" in str(result)


def test_the_gd_grid_extends_past_an_edge_where_its_best_point_lies(model) -> None:
    """With learning rates far too small for the shift, the best is the largest: the grid must go on."""
    grid = {"lr": (1e-5, 1e-4), "steps": (1,), "window": (5,)}
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["gradient_descent"], gd_grid=grid, progress=False)
    lrs = sorted({c.settings["lr"] for c in result.candidates})
    assert lrs[-1] > 1e-4, lrs
    assert any("lr" in note and "high edge" in note for note in result.notes)
    assert result.best_of["gradient_descent"].settings["lr"] > 1e-4


def test_gd_limits_stop_the_extension_and_the_result_says_so(model) -> None:
    """The same grid as above, whose best lies on its high edge: a limit at that edge keeps it there."""
    grid = {"lr": (1e-5, 1e-4), "steps": (1,), "window": (5,)}
    result = smcd_rl.tune(
        model,
        shifted_episodes(0.5),
        strategies=["gradient_descent"],
        gd_grid=grid,
        gd_limits={"lr": (None, 1e-4)},
        progress=False,
    )
    assert max(c.settings["lr"] for c in result.candidates) == 1e-4
    assert any("lr" in note and "at gd_limits" in note for note in result.notes), result.notes


def test_a_budget_skips_what_does_not_fit(model) -> None:
    """No strategy takes less than a nanosecond per observation; every one takes less than an hour."""
    with pytest.raises(ValueError, match="no strategy fits"):
        smcd_rl.tune(model, shifted_episodes(0.5), budget_ms=1e-6, **FAST)
    result = smcd_rl.tune(
        model, shifted_episodes(0.5), strategies=["none", "gradient_descent"], budget_ms=3.6e6, **FAST
    )
    assert not [c for c in result.candidates if c.skipped == "over budget"] and len(result.candidates) >= 5
    assert all(c.ms_per_step > 0 for c in result.candidates)


def test_the_same_call_chooses_the_same(model) -> None:
    a = smcd_rl.tune(model, shifted_episodes(0.2), strategies=["smcd"], **FAST)
    b = smcd_rl.tune(model, shifted_episodes(0.2), strategies=["smcd"], **FAST)
    assert {k: c.settings for k, c in a.best_of.items()} == {k: c.settings for k, c in b.best_of.items()}
    assert [c.one_step_rmse for c in a.candidates] == [c.one_step_rmse for c in b.candidates]


def test_tune_leaves_the_calibration_and_the_network_as_they_were(model) -> None:
    before = {k: v.clone() for k, v in model.net.state_dict().items()}
    calibration = model.calibration
    smcd_rl.tune(model, shifted_episodes(0.3), strategies=["gradient_descent", "smcd"], **FAST)
    assert model.calibration == calibration
    assert all(torch.equal(before[k], v) for k, v in model.net.state_dict().items())


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"strategies": ["adam"]}, "unknown"),
        ({"strategies": []}, "unknown"),
        ({"criterion": "rmse"}, "criterion"),
        ({"budget_ms": 0.0}, "budget_ms"),
        ({"gd_grid": {"lr": ()}}, "gd_grid"),
        ({"gd_grid": {"loss": ()}}, "gd_grid"),
        (
            {"gd_grid": {"loss": ("l1",)}},
            r"gd_grid\['loss'\] takes losses from \['mse', 'huber', 'tukey'\], got \['l1'\]",
        ),
        ({"gd_grid": {"loss": "huber"}}, "non-empty sequences"),  # a bare string, not the losses h, u, b, ...
        ({"gd_grid": {"momentum": (0.9,)}}, "gd_grid"),
        ({"flip_probs": (0.01, 2.0)}, r"flip_probs\[1\]"),
        ({"flip_probs": ()}, "at least one flip probability"),
        ({"gd_limits": {"momentum": (None, 1.0)}}, "unknown"),
        ({"gd_limits": {"lr": 0.1}}, "pair"),
        ({"gd_limits": {"lr": (None, 5e-3)}}, r"gd_grid\['lr'\] has \[0.01\] outside"),
    ],
)
def test_bad_options_are_refused_and_change_nothing(model, options, message) -> None:
    before = model.tuning
    with pytest.raises(ValueError, match=message):
        smcd_rl.tune(model, shifted_episodes(0.5), **{**FAST, **options})
    assert model.tuning == before


def test_bad_flip_probabilities_are_refused_before_any_run(model, monkeypatch) -> None:
    """calibrate's own check of the flips runs first: no grid is scored only to fail at SMCD."""
    monkeypatch.setattr(
        smcd_rl.tuning.scoring, "trace_pairs", lambda *a: pytest.fail("a setting ran before the refusal")
    )
    with pytest.raises(TypeError, match="flip_probs must be a sequence of probabilities"):
        smcd_rl.tune(model, shifted_episodes(0.5), **{**FAST, "flip_probs": 0.01})
    with pytest.raises(ValueError, match=r"flip_probs\[0\]"):
        smcd_rl.tune(model, shifted_episodes(0.5), **{**FAST, "flip_probs": (-0.1,)})


def test_the_strategies_it_returns_adapt(model, result) -> None:
    """The returned strategies work as they are: tuned GD predicts a shifted test episode better than none."""
    test = shifted_episodes(0.5, count=1, steps=20)[0]
    errors = {}
    for kind in ("none", "gradient_descent"):
        adaptive = model.with_adaptation(result.strategy(kind))
        adaptive.reset()
        squared = 0.0
        for t in range(test.shape[0]):
            with torch.no_grad():
                squared += float((adaptive(test[t].clone())["ee"] - test[t]["ee"]).square().sum())
            adaptive.observe(test[t])
        errors[kind] = math.sqrt(squared)
    assert errors["gradient_descent"] < errors["none"]


def test_gd_searches_the_squared_error_and_runs_huber_at_its_best_setting(result) -> None:
    """A ``gd_grid`` without ``"loss"`` (as :data:`FAST`'s) takes both losses from the default grid:
    the grid is searched with the squared error, and the Huber loss runs once, at that search's best."""
    gd = [c for c in result.candidates if c.kind == "gradient_descent"]
    plain = [c for c in gd if c.settings["loss"] == "mse"]
    huber = [c.settings for c in gd if c.settings["loss"] == "huber"]
    assert len(plain) > 1 and len(huber) == 1
    best_plain = min(plain, key=lambda c: c.score).settings
    assert {**huber[0], "loss": "mse"} == best_plain
    assert all(smcd_rl.GradientDescent(**c.settings).config() == c.settings for c in gd)  # the settings are the config


def outlier_episodes() -> TensorDict:
    """The shifted task's episodes with one corrupted target each, 20x the tuned one-step residual (~0.15)."""
    episodes = shifted_episodes(0.5, steps=16)
    episodes["ee"][:, 3] += 3.0
    return episodes


@pytest.mark.parametrize("loss", ["huber", "tukey"])
def test_tune_picks_a_robust_loss_where_an_outlier_makes_the_squared_error_lose(model, loss) -> None:
    """Deterministic data and seeds; measured, the best Huber setting's one-step RMSE is 0.84, Tukey's 0.84 and
    the best squared error's 0.91 (the outlier steps themselves, equal for both, are most of
    each): the test asks for 4 % lower. On the clean episodes the robust loss is close to the squared one."""
    grid = {"lr": (1e-2, 1e-1), "steps": (1,), "window": (5,), "loss": ("mse", loss)}
    result = smcd_rl.tune(model, outlier_episodes(), strategies=["gradient_descent"], gd_grid=grid, progress=False)
    best = {
        form: min(c.one_step_rmse for c in result.candidates if c.settings["loss"] == form) for form in ("mse", loss)
    }
    chosen = result.best_of["gradient_descent"]
    assert chosen.settings["loss"] == loss and chosen.one_step_rmse == best[loss]
    assert best[loss] < 0.96 * best["mse"], best
    strategy = result.best
    assert isinstance(strategy, smcd_rl.GradientDescent) and strategy.loss == loss
    assert f"loss {loss}" in str(result)

    clean = smcd_rl.tune(
        model, shifted_episodes(0.5, steps=16), strategies=["gradient_descent"], gd_grid=grid, progress=False
    )
    scores = {(c.settings["lr"], c.settings["loss"]): c.one_step_rmse for c in clean.candidates if c.skipped == ""}
    # Huber equals the squared loss within its delta; the biweight weighs a residual of its scale
    # at (1 - 1 / 4.685**2)**2 = 0.91 and the larger early ones less: measured 1.9 % above.
    assert math.isclose(scores[(0.1, "mse")], scores[(0.1, loss)], rel_tol=0.01 if loss == "huber" else 0.03), scores


def test_a_grid_of_one_loss_tries_only_that_loss(model) -> None:
    grid = {"lr": (1e-2, 1e-1), "steps": (1,), "window": (5,), "loss": ("mse",)}
    result = smcd_rl.tune(model, outlier_episodes(), strategies=["gradient_descent"], gd_grid=grid, progress=False)
    assert {c.settings["loss"] for c in result.candidates} == {"mse"}
    assert "loss" not in str(result)  # the squared error is the default: the table leaves it out


def test_reuse_takes_an_earlier_calls_scores_without_running_anything(model, result, monkeypatch) -> None:
    """A budgeted call after an unbudgeted one: the same settings, not one filter or GD run again."""

    def refuse(*args, **kwargs):
        raise AssertionError("a setting the earlier call scored was run again")

    monkeypatch.setattr(smcd_rl.tuning.scoring, "trace_pairs", refuse)
    monkeypatch.setattr(smcd_rl.tuning.kinds, "search_noise", refuse)
    again = smcd_rl.tune(model, shifted_episodes(0.5), **FAST, reuse=result)
    assert {k: c.settings for k, c in again.best_of.items()} == {k: c.settings for k, c in result.best_of.items()}
    assert {k: c.one_step_rmse for k, c in again.best_of.items()} == {
        k: c.one_step_rmse for k, c in result.best_of.items()
    }
    # Under a budget that the largest learning rates' settings exceed (a clock of the learning rate,
    # so that no timing noise decides), those are skipped and the rest reused: the leader is within
    # the budget, so the race goes as before and nothing runs.
    monkeypatch.setattr(smcd_rl.tuning.search.Timing, "ms_per_step", lambda timing, s: 1.0 + getattr(s, "lr", 0.0))
    largest = max(c.settings["lr"] for c in result.candidates if c.kind == "gradient_descent")
    assert result.best_of["gradient_descent"].settings["lr"] < largest
    budgeted = smcd_rl.tune(
        model,
        shifted_episodes(0.5),
        **FAST,
        strategies=["none", "gradient_descent"],
        reuse=result,
        budget_ms=0.999 * (1.0 + largest),
    )
    skipped = [c.settings["lr"] for c in budgeted.candidates if c.skipped == "over budget"]
    assert skipped and set(skipped) == {largest}
    assert budgeted.best_of["gradient_descent"].settings == result.best_of["gradient_descent"].settings


def test_reuse_of_other_episodes_is_refused_and_changes_nothing(model, result) -> None:
    before = dict(model.tuning)
    with pytest.raises(ValueError, match="another model, other episodes"):
        smcd_rl.tune(model, shifted_episodes(0.3), **FAST, reuse=result)
    with pytest.raises(TypeError, match="TuneResult"):
        smcd_rl.tune(model, shifted_episodes(0.5), **FAST, reuse=result.to_dict())
    assert model.tuning == before


def test_the_combination_grid_is_scored_as_trace_scores_a_combination(model, result, monkeypatch) -> None:
    """The grid is scored from one recorded run of the members; each score is what trace gives.

    Same operations in the same order, so the scores agree to float rounding (rel 1e-6 is a
    thousand times looser than float32's; a wrong weight update moves them by far more).
    """
    scored = [c for c in result.candidates if c.kind == "combination"]
    assert len(scored) == len(smcd_rl.tuning.COMBINATION_GRID["eta"]) * len(smcd_rl.tuning.COMBINATION_GRID["share"])
    for candidate in scored:
        strategy = smcd_rl.strategies.registry.build("combination", candidate.settings)
        expected = smcd_rl.tuning.diagnostics.trace(model, shifted_episodes(0.5), strategy).rmse
        assert candidate.one_step_rmse == pytest.approx(expected, rel=1e-6)
    # Scoring the grid runs no combination, and no member again: each setting runs once, and the
    # combination takes its members' predictions from their own runs (SMCD's calibration keeps only
    # its trace, so the calibrated SMCD runs once more, to record them; its posterior predictive mean
    # and its Student-t form, once each).
    traced = []
    real_trace = smcd_rl.tuning.scoring.trace_pairs
    monkeypatch.setattr(
        smcd_rl.tuning.scoring,
        "trace_pairs",
        lambda m, x, y, s, **kw: traced.append(type(s).__name__) or real_trace(m, x, y, s, **kw),
    )
    again = smcd_rl.tune(model, shifted_episodes(0.5), **FAST)
    # Each GD setting runs on the first episodes, and those not raced out on the rest.
    settings = [c for c in again.candidates if c.kind == "gradient_descent"]
    ran_on = [c for c in settings if math.isfinite(c.one_step_rmse)]
    assert "Combination" not in traced and traced.count("GradientDescent") == len(settings) + len(ran_on)
    calibration_runs = sum(len(c.candidates) for c in again.calibrations.values())  # calibrate's own filters
    assert traced.count("NoAdaptation") == 1 and traced.count("SMCD") == 3 + calibration_runs
    # Each best strategy's run is kept: what the diagnosis of an experiment shows, without running it again.
    # (GD's, raced, joins the runs on the first episodes and on the rest: the same errors per episode,
    # the per-step RMSEs pooled in another order, equal to float rounding.)
    for kind in ("none", "gradient_descent", "smcd"):
        expected = dataclasses.asdict(
            smcd_rl.tuning.diagnostics.trace(model, shifted_episodes(0.5), again.strategy(kind))
        )
        kept = dataclasses.asdict(again.trace(kind))
        assert kept["per_episode_rmse"] == expected["per_episode_rmse"], kind
        assert kept["one_step_errors"] == expected["one_step_errors"], kind
        for field in ("one_step_rmse", "ess", "log_evidence", "kept"):
            assert kept[field] == pytest.approx(expected[field], rel=1e-12), (kind, field)
        assert kept["rmse"] == pytest.approx(expected["rmse"], rel=1e-12), kind
    assert again.trace("combination").rmse == again.best_of["combination"].one_step_rmse


class _DriftingClock:
    """Times that drift from one measurement to the next, as on a busy machine: each call is 3 % slower."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, strategy: smcd_rl.Adaptation) -> float:
        self.calls += 1
        base = 0.01 if isinstance(strategy, smcd_rl.NoAdaptation) else 4.0 * strategy.config().get("steps", 1)
        if isinstance(strategy, smcd_rl.SMCD):
            base = 0.2 * strategy.num_particles
        return base * 1.03**self.calls


def test_a_budgeted_call_with_reuse_repeats_the_times_and_the_choice(model, monkeypatch) -> None:
    """With a budget the measured times decide what fits; they drift between calls, so the same call could
    choose differently. An earlier result passed as ``reuse`` gives every time, SMCD's particle probes too."""
    clock = _DriftingClock()
    monkeypatch.setattr(smcd_rl.tuning.search.Timing, "ms_per_step", lambda timing, strategy: clock(strategy))
    options = {**FAST, "num_particles": 64, "gd_grid": {"lr": (1e-2,), "steps": (1, 2, 3), "window": (5,)}}
    first = smcd_rl.tune(model, shifted_episodes(0.3), budget_ms=8.0, **options)
    again = smcd_rl.tune(model, shifted_episodes(0.3), budget_ms=8.0, reuse=first, **options)
    assert [(c.kind, c.settings, c.ms_per_step, c.skipped) for c in again.candidates] == [
        (c.kind, c.settings, c.ms_per_step, c.skipped) for c in first.candidates
    ]
    assert {k: c.settings for k, c in again.best_of.items()} == {k: c.settings for k, c in first.best_of.items()}
    assert again.timings == first.timings and any(c.skipped for c in first.candidates)


def test_the_record_is_json_and_rebuilds_the_result(model) -> None:
    """A skipped candidate's score is inf, which JSON cannot hold; to_dict writes None, from_dict reads it back."""
    import json

    result = smcd_rl.tune(model, shifted_episodes(0.5), budget_ms=3.6e6, **FAST)
    result.candidates.append(smcd_rl.tuning.TuneCandidate("smcd", {"num_particles": 8}, math.inf, 9.0, "over budget"))
    record = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    rebuilt = smcd_rl.TuneResult.from_dict(record)
    assert rebuilt.candidates[-1].one_step_rmse == math.inf and rebuilt.best_kind == result.best_kind
    assert rebuilt.strategy("smcd").config() == result.strategy("smcd").config()
    assert smcd_rl.TuneResult.from_dict(model.tuning).best_kind == model.tuning["best_kind"]
    with pytest.raises(ValueError, match="not a record of TuneResult.to_dict"):
        smcd_rl.TuneResult.from_dict({"gd_lr": 0.01})


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_a_tuning_recorded_on_a_gpu_rebuilds_on_the_cpu(model, result) -> None:
    record = result.to_dict()
    record["best_of"]["smcd"]["settings"]["device"] = "cuda"
    record["best_of"]["smcd_last_layer"]["settings"]["smcd"]["device"] = "cuda"
    for member in record["best_of"]["combination"]["settings"]["members"]:
        if member["name"] == "smcd":
            member["settings"]["device"] = "cuda"
        if member["name"] == "smcd_last_layer":
            member["settings"]["smcd"]["device"] = "cuda"
    gpu = smcd_rl.TuneResult.from_dict(record)
    for kind in ("smcd", "smcd_last_layer", "combination"):
        with pytest.raises(ValueError, match=r"on cuda, which this machine does not have.*device='cpu'"):
            gpu.strategy(kind)
    for kind in ("smcd", "smcd_last_layer", "combination"):
        adaptive = model.with_adaptation(gpu.strategy(kind, device="cpu"))
        adaptive.reset()
    assert gpu.strategy("smcd", device="cpu").config() == result.strategy("smcd").config()


def test_a_combination_tunes_and_mixes_what_it_needs(model) -> None:
    """strategies=["combination", "smcd"] once tuned no combination, and ["combination"] failed with a TypeError;
    then ["combination"] alone was refused. A combination now tunes what it needs (the defaults' NEEDS: no
    adaptation, gradient descent and SMCD) and mixes every kind tuned that adapts."""
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["combination"], **FAST)
    members = [m["name"] for m in result.best_of["combination"].settings["members"]]
    assert members == ["none", "gradient_descent", "smcd"] and "last_layer" not in result.best_of


def test_gradient_descent_that_always_diverges_is_dropped_with_a_note(model) -> None:
    # Tukey's loss is left out: after one step that blows the weights up every residual lies beyond
    # its cut, so it stops pulling and cannot diverge (its setting scores finite and useless).
    grid = {"lr": (1e12, 1e13), "steps": (3,), "window": (5,), "loss": ("mse", "huber")}
    result = smcd_rl.tune(
        model, shifted_episodes(0.5), strategies=["none", "gradient_descent"], gd_grid=grid, progress=False
    )
    assert "gradient_descent" not in result.best_of and result.best_kind == "none"
    assert any("gradient descent: every one of its" in note and "diverged" in note for note in result.notes)


def test_smcd_over_any_budget_says_so_and_is_not_said_to_fit(model, monkeypatch) -> None:
    clock = _DriftingClock()
    monkeypatch.setattr(smcd_rl.tuning.search.Timing, "ms_per_step", lambda timing, strategy: clock(strategy))
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["none", "smcd"], budget_ms=1.0, **FAST)
    assert "smcd" not in result.best_of
    assert any("over the budget even with 8 particles" in note for note in result.notes), result.notes
    assert not any("to fit the budget" in note for note in result.notes)


@pytest.mark.parametrize(
    ("options", "error", "message"),
    [
        ({"gd_grid": {"steps": (1.5,)}}, TypeError, r"gd_grid\['steps'\]\[0\] must be an int, got 1.5"),
        ({"gd_grid": {"window": (0,)}}, ValueError, r"gd_grid\['window'\]\[0\] must be >= 1"),
        ({"gd_grid": {"lr": (0.01, -1.0)}}, ValueError, r"gd_grid\['lr'\]\[1\] must be in \(0, 1e\+30\]"),
        ({"seed": 2**70}, ValueError, r"seed must be in \[0, 2\*\*64 - 1\]"),
        ({"seed": -1}, ValueError, "seed must be >= 0"),
        # A bare string was read as its letters: "unknown ['s', 'm', 'c', 'd']".
        ({"strategies": "smcd"}, TypeError, r"strategies must be a list of kinds .*; for one, pass \['smcd'\]"),
    ],
)
def test_bad_values_are_refused_before_any_run(model, monkeypatch, options, error, message) -> None:
    """Each was found late or not at all: steps=1.5 ran as 1 step, a huge seed failed after the whole GD grid."""
    monkeypatch.setattr(
        smcd_rl.tuning.scoring, "trace_pairs", lambda *a: pytest.fail("a setting ran before the refusal")
    )
    with pytest.raises(error, match=message):
        smcd_rl.tune(model, shifted_episodes(0.5), **{**FAST, **options})


def test_a_model_on_the_meta_device_is_refused_clearly() -> None:
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,))
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    model.fitted = True
    net.to("meta")
    with pytest.raises(ValueError, match="meta device"):
        smcd_rl.tune(model, shifted_episodes(0.5), **FAST)
    with pytest.raises(ValueError, match="meta device"):
        smcd_rl.calibrate(model, shifted_episodes(0.5), progress=False)


def test_the_episodes_and_model_errors_name_the_function_that_was_called(model) -> None:
    """tune, calibrate and trace share their checks; each error names the call the user made."""
    one = shifted_episodes(0.5)[:1]
    unfitted = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    calls = {
        "tune": lambda m, e: smcd_rl.tune(m, e, **FAST),
        "calibrate": lambda m, e: smcd_rl.calibrate(m, e, progress=False),
        "trace": lambda m, e: smcd_rl.tuning.diagnostics.trace(m, e, smcd_rl.SMCD(num_particles=8)),
    }
    for name, call in calls.items():
        with pytest.raises(ValueError, match=rf"^{name} needs at least 2 episodes"):
            call(model, one)
        with pytest.raises(ValueError, match=rf"^{name} needs a fitted model"):
            call(unfitted, shifted_episodes(0.5))
    episode = shifted_episodes(0.5)[0].exclude("ee")
    with pytest.raises(KeyError, match=r"ms_per_observation \(episodes\): the TensorDict has no key 'ee'"):
        smcd_rl.tuning.protocol.ms_per_observation(model, smcd_rl.SMCD(num_particles=8), episode)


def test_racing_drops_settings_by_their_error_alone_and_keeps_the_runs_exact(model) -> None:
    """Every raced-out setting was worse than the leader by more than RACE_MARGIN on the first episodes,
    every setting that ran on has the errors a run on all episodes gives, and the choice is the one
    a search without racing makes (here, where the best is far ahead of the runners-up)."""
    from smcd_rl.tuning.defaults import RACE_MARGIN

    episodes = shifted_episodes(0.5, count=12)
    # One loss: the race alone decides (where two losses tie, the robust-form rule would choose).
    grid = {"lr": (1e-4, 1e-3, 1e-2, 1e-1), "steps": (1, 3), "window": (2, 6), "loss": ("mse",)}
    result = smcd_rl.tune(model, episodes, strategies=["gradient_descent"], gd_grid=grid, progress=False)
    gd = [c for c in result.candidates if c.kind == "gradient_descent"]
    raced_out = [c for c in gd if c.skipped.startswith("raced out")]
    assert raced_out and len(raced_out) < len(gd)
    for candidate in raced_out:
        head, leader = (
            float(v.split(" ")[0])
            for v in candidate.skipped.split(": ")[1].split(" on the first 3 episodes, the best ")
        )
        assert head > (1 + RACE_MARGIN) * leader * (1 - 1e-3)  # printed at 4 digits
    for candidate in gd:
        if math.isfinite(candidate.one_step_rmse):
            full = smcd_rl.tuning.diagnostics.trace(model, episodes, smcd_rl.GradientDescent(**candidate.settings))
            assert candidate.one_step_rmse == pytest.approx(full.rmse, rel=1e-12)
    # The same search with every setting run on all episodes chooses the same.
    unraced = {tuple(sorted(c.settings.items())): c for c in gd}
    scores = {
        key: smcd_rl.tuning.diagnostics.trace(model, episodes, smcd_rl.GradientDescent(**dict(key))).rmse
        for key in unraced
    }
    best = min(scores, key=scores.get)
    assert dict(best) == result.best_of["gradient_descent"].settings


def test_tune_leaves_the_models_calibration_to_calibrate_even_when_both_run_at_once(model, monkeypatch) -> None:
    """tune once saved the calibration and restored it after its own: a calibrate call on the same model in
    between (another thread) was lost. tune no longer writes it: the other call's result stays."""
    real = smcd_rl.tuning.kinds.search_noise
    stored = {}

    def beside(*args, **kwargs):  # a calibrate call on the same model while tune calibrates
        if not stored:
            stored["result"] = smcd_rl.calibrate(
                model, shifted_episodes(0.3), base=smcd_rl.SMCD(num_particles=8), progress=False
            )
        return real(*args, **kwargs)

    monkeypatch.setattr(smcd_rl.tuning.kinds, "search_noise", beside)
    smcd_rl.tune(model, shifted_episodes(0.5), strategies=["smcd"], **FAST)
    assert model.calibration is not None and model.calibration["noise_std"] == stored["result"].noise_std


def test_calibrate_reuses_an_earlier_searchs_runs_and_chooses_the_same(model) -> None:
    """The evidence search starts from the same bracket as the one-step search: reusing the latter's runs,
    it runs fewer filters and chooses exactly what it chooses alone."""
    episodes, base = shifted_episodes(0.2), smcd_rl.SMCD(num_particles=16)
    one_step = smcd_rl.calibrate(model, episodes, base=base, progress=False, store=False)
    alone = smcd_rl.calibrate(model, episodes, base=base, criterion="evidence", progress=False, store=False)
    ran = []
    real = smcd_rl.tuning.calibration._run
    try:
        smcd_rl.tuning.calibration._run = lambda *a: ran.append(1) or real(*a)
        reused = smcd_rl.calibrate(
            model, episodes, base=base, criterion="evidence", progress=False, store=False, reuse=one_step
        )
    finally:
        smcd_rl.tuning.calibration._run = real
    assert (reused.noise_std, reused.flip_prob) == (alone.noise_std, alone.flip_prob)
    assert [c.log_evidence for c in reused.candidates] == [c.log_evidence for c in alone.candidates]
    assert 0 < len(ran) <= len(alone.candidates) - 7  # at least the seven runs of the bracket
    with pytest.raises(ValueError, match="another model, other episodes"):
        smcd_rl.calibrate(model, shifted_episodes(0.3), base=base, progress=False, store=False, reuse=one_step)


def _with_outliers(shift: float) -> TensorDict:
    """:func:`shifted_episodes`, with one reading in the middle of every episode 30 units off."""
    episodes = shifted_episodes(shift)
    episodes["ee"][:, 6] += 30.0
    return episodes


def test_the_last_layer_takes_the_robust_form_where_readings_are_corrupted(model) -> None:
    """After a reading 30 units off, a Gaussian readout predicts tens of units off for the rest of the
    episode; Tukey's biweight ignores it and stays at the shift: the criterion must pick it."""
    result = smcd_rl.tune(model, _with_outliers(0.5), strategies=["last_layer"], progress=False)
    assert result.best_of["last_layer"].settings["likelihood"] == "tukey"
    clean = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["last_layer"], progress=False)
    gaussian = [
        c for c in clean.candidates if c.settings.get("likelihood") == "gaussian" and math.isfinite(c.one_step_rmse)
    ]
    # The Gaussian form's noise is the unadapted residual (the 0.5 shift, in normalised units): it
    # only sets the predictive variance, so model.predictive covers the shift before adapting.
    assert all(v > 0.1 for v in gaussian[0].settings["noise_std"])


def test_smcd_with_a_bayesian_readout_starts_from_the_tuned_smcd_and_last_layer(model) -> None:
    kinds = smcd_rl.tuning.kinds
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["smcd_last_layer"], **FAST)
    assert {"smcd", "last_layer", "smcd_last_layer"} <= set(result.best_of)
    both = [c for c in result.candidates if c.kind == "smcd_last_layer" and "weighing" not in c.settings]
    assert all(c.settings["smcd"] == result.best_of["smcd"].settings for c in both)
    readout = result.best_of["last_layer"].settings["prior_scale"]
    factors = sorted(c.settings["last_layer"]["prior_scale"] / readout for c in both)
    x, _ = smcd_rl.tuning.held_out.pairs(model, shifted_episodes(0.5), "tune")
    quiet = kinds.quiet_readout_scale(model, x, result.best_of["smcd"].settings, result.best_of["last_layer"].settings)
    grid = kinds.smcd_last_layer_factors(quiet / readout)
    assert min(grid) < 1 / 100  # this network's features are large: the old grid's low end swamped the filter
    assert factors[-len(grid) :] == pytest.approx(sorted(grid))
    # below the grid only while the best lies at its low edge, a third each time
    low = len(factors) - len(grid)
    assert factors[:low] == pytest.approx([min(grid) / 3**k for k in range(low, 0, -1)])
    # At the quiet scale the readout barely moves the likelihood: SL weighs the masks as SMCD does.
    quietest = next(c for c in both if c.settings["last_layer"]["prior_scale"] == pytest.approx(readout * min(grid)))
    assert quietest.one_step_rmse == pytest.approx(result.best_of["smcd"].one_step_rmse, rel=0.1)
    strategy = result.strategy("smcd_last_layer")
    assert isinstance(strategy, smcd_rl.SMCDLastLayer)
    # The tuned strategy repeats the scored run: its one-step error on the episodes is the candidate's.
    rerun = smcd_rl.tuning.diagnostics.trace(model, shifted_episodes(0.5), strategy)
    assert rerun.rmse == pytest.approx(result.best_of["smcd_last_layer"].one_step_rmse, rel=1e-6)


def test_clean_episodes_keep_the_robust_form_where_they_cannot_tell_it_from_the_plain_one(model) -> None:
    """Clean tuning episodes once chose the squared loss by a hair, and one corrupted reading then broke it.

    On episodes without outliers Tukey's biweight and the squared loss predict alike (residuals
    well within its scale are squared by both), so tune keeps the biweight and says so. After one
    reading corrupted by 20 (about 40 target standard deviations), which stays in the window for its
    5 steps, the squared loss's gradient pulls the weights 20 times harder than any clean residual;
    the biweight does not pull at all beyond its cut, so its error afterwards is far lower.
    """
    grid = {"lr": (1e-2, 1e-1), "steps": (1,), "window": (5,)}
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["gradient_descent"], gd_grid=grid, progress=False)
    chosen = result.best_of["gradient_descent"].settings
    assert chosen["loss"] == "tukey"
    assert any("kept the robust form (Tukey's biweight loss)" in note for note in result.notes), result.notes
    plain = smcd_rl.GradientDescent(**{**chosen, "loss": "mse"})
    corrupted = shifted_episodes(0.5, count=6, steps=12, seed=7)
    corrupted["ee"][:, 4] += 20.0

    def error_after(strategy: smcd_rl.Adaptation) -> float:
        run = smcd_rl.tuning.diagnostics.trace(model, corrupted, strategy)
        after = run.one_step_rmse[4:]  # steps 6.. (index t - 2): every prediction after the corrupted one
        return math.sqrt(sum(v * v for v in after) / len(after))

    robust, squared = error_after(result.strategy("gradient_descent")), error_after(plain)
    assert robust < 0.5 * squared, (robust, squared)


def _noisy(shift: float, seed: int = 1) -> TensorDict:
    """:func:`shifted_episodes` with measurement noise of 0.1 on every target."""
    episodes = shifted_episodes(shift, seed=seed)
    noise = torch.randn(episodes["ee"].shape, generator=torch.Generator().manual_seed(seed + 100))
    episodes["ee"] = episodes["ee"] + 0.1 * noise
    return episodes


def test_smcd_keeps_the_student_t_form_on_clean_episodes_and_it_ignores_a_corrupted_reading(model) -> None:
    """On noisy but clean episodes a Student-t likelihood of the calibrated scale predicts within the
    episodes' noise of the Gaussian, so tune keeps it and says so. Under one reading 20 units off
    (about 40 target standard deviations) every particle's Gaussian likelihood hinges on it: the
    weights collapse onto the masks that explain it best (measured ESS 0.13 of the particles). The
    Student-t's log-likelihood flattens out that far: every particle explains it alike and the
    weights stay as they were (measured ESS 1.0)."""
    result = smcd_rl.tune(model, _noisy(0.3), strategies=["smcd"], num_particles=64, progress=False)
    chosen = result.best_of["smcd"].settings
    assert chosen["likelihood"] == "student-t"
    assert any("kept the robust form (Student-t likelihood)" in note for note in result.notes), result.notes
    corrupted = _noisy(0.3, seed=7)
    corrupted["ee"][:, 4] += 20.0
    ess = {
        likelihood: smcd_rl.tuning.diagnostics.trace(
            model, corrupted, smcd_rl.strategies.registry.build("smcd", {**chosen, "likelihood": likelihood})
        ).ess[4]  # the update on the corrupted reading
        for likelihood in ("gaussian", "student-t")
    }
    assert ess["student-t"] > 0.9 and ess["gaussian"] < 0.5, ess


def test_the_shortcut_search_repeats_bit_for_bit_and_confirms_its_finalists_at_full_size(model) -> None:
    """With 256 particles tune searches SMCD with 64 and runs its five best settings again with 256;
    every SMCD candidate it keeps is a full-size one. Each search repeats exactly for one seed."""
    episodes = shifted_episodes(0.3)
    common = {"strategies": ["smcd"], "num_particles": 256, "progress": False}
    fast, again = (smcd_rl.tune(model, episodes, **common) for _ in range(2))
    full, full_again = (smcd_rl.tune(model, episodes, shortcuts=False, **common) for _ in range(2))
    for one, other in ((fast, again), (full, full_again)):
        assert [(c.settings, c.score) for c in one.candidates] == [(c.settings, c.score) for c in other.candidates]
    assert fast.calibrations["search"].num_particles == 64 and full.calibrations["search"].num_particles == 256
    plain = [c for c in fast.candidates if c.kind == "smcd" and c.settings["likelihood"] == "gaussian"]
    finalists = [c for c in plain if c.settings["prediction"] == "mask"]
    assert len(finalists) == 5 and all(c.settings["num_particles"] == 256 for c in finalists)
    # then the best finalist predicting with the posterior predictive mean, and the robust form at
    # the setting the prediction rule kept, which the robust-form rule weighs against it
    best = min(finalists, key=lambda c: c.score)
    (mean,) = [c for c in plain if c.settings["prediction"] == "predictive"]
    assert mean.settings == {**best.settings, "prediction": "predictive"}
    (robust,) = [c for c in fast.candidates if c.kind == "smcd" and c.settings["likelihood"] == "student-t"]
    kept = next(c for c in (best, mean) if robust.settings == {**c.settings, "likelihood": "student-t"})
    assert fast.best_of["smcd"] in (kept, robust)
    assert any("searched with 64 particles" in note for note in fast.notes)
    assert set(fast.kind_seconds) == {"smcd"} and fast.kind_seconds["smcd"] > 0


def _search_with_two_runs(model, cheap: list[float], dear: list[float]) -> smcd_rl.tuning.search.Search:
    """A search whose two SMCD settings ran with these one-step RMSEs per episode (the MMSE mask's
    prediction and the posterior predictive mean's), the dearer one the best by its pooled score."""
    scorer = smcd_rl.tuning.scoring.Scorer(
        model,
        shifted_episodes(0.5, count=len(cheap)),
        smcd_rl.tuning.criteria.checked_criterion("one-step", None),
        "tune",
    )
    search = smcd_rl.tuning.search.Search(
        scorer, smcd_rl.tuning.search.Timing(model, scorer.x[0], scorer.y[0], None), False
    )
    for prediction, errors in (("mask", cheap), ("predictive", dear)):
        rmse = math.sqrt(sum(e * e for e in errors) / len(errors))
        settings = {"num_particles": 8, "noise_std": 0.1, "prediction": prediction}
        run = smcd_rl.tuning.diagnostics.Trace([rmse], rmse, [], [], [], list(errors), [[e] for e in errors])
        search.traces[smcd_rl.tuning.search.setting_key("smcd", settings)] = run
        search._add("smcd", settings, rmse)
    assert search.best_of["smcd"].settings["prediction"] == "predictive"
    return search


def test_the_dearer_prediction_is_kept_only_where_its_gain_is_beyond_the_episodes_noise(model) -> None:
    """The posterior predictive mean costs a forward pass per particle: it must earn it.

    Both runs have a lower pooled score for the dearer setting. Where it gains 0.01 on every one of
    six episodes (no spread: the gain is certain) it is kept; where it gains 0.005 on average with
    gains of -0.04 and +0.05 alternating (standard error 0.02, twice that 0.04) the cheaper one is.
    """
    cheap = [0.30, 0.32, 0.28, 0.31, 0.29, 0.30]
    steady = _search_with_two_runs(model, cheap, [e - 0.01 for e in cheap])
    steady.prefer_cheaper("smcd", {"num_particles": 8, "noise_std": 0.1, "prediction": "mask"}, "the mask", "the mean")
    assert steady.best_of["smcd"].settings["prediction"] == "predictive"
    assert any(note.startswith("smcd: kept the mean") and "beyond the episodes' noise" in note for note in steady.notes)
    noisy = _search_with_two_runs(model, cheap, [e + (0.04 if i % 2 else -0.05) for i, e in enumerate(cheap)])
    noisy.prefer_cheaper("smcd", {"num_particles": 8, "noise_std": 0.1, "prediction": "mask"}, "the mask", "the mean")
    assert noisy.best_of["smcd"].settings["prediction"] == "mask"
    assert any(note.startswith("smcd: kept the mask") and "within the episodes' noise" in note for note in noisy.notes)


def test_tune_tries_smcds_posterior_predictive_mean_at_its_best_setting_unless_told_not_to(model) -> None:
    episodes = shifted_episodes(0.3)
    both = smcd_rl.tune(model, episodes, strategies=["smcd"], **FAST)
    plain = [c for c in both.candidates if c.kind == "smcd" and c.settings["likelihood"] == "gaussian"]
    masks = [c for c in plain if c.settings["prediction"] == "mask"]
    (mean,) = [c for c in plain if c.settings["prediction"] == "predictive"]
    assert mean.settings == {**min(masks, key=lambda c: c.score).settings, "prediction": "predictive"}
    # The mean is kept only where it scores lower (and then beyond the noise, by the rule above).
    kept = both.best_of["smcd"].settings.get("prediction")
    assert kept == "mask" or mean.score < min(c.score for c in masks), (kept, mean.score)
    mask_only = smcd_rl.tune(model, episodes, strategies=["smcd"], predictions=("mask",), **FAST)
    assert all(c.settings["prediction"] == "mask" for c in mask_only.candidates if c.kind == "smcd")
    assert not any("predictive" in note for note in mask_only.notes)


def test_tune_tries_weighing_by_the_readout_mean_at_sls_best_scale_and_the_next_wider_one(model) -> None:
    episodes = shifted_episodes(0.5)
    result = smcd_rl.tune(model, episodes, strategies=["smcd_last_layer"], **FAST)
    both = [c for c in result.candidates if c.kind == "smcd_last_layer" and math.isfinite(c.score)]
    searched = [c for c in both if "weighing" not in c.settings]
    twins = [c for c in both if c.settings.get("weighing") == "mean"]
    best = min(searched, key=lambda c: c.score)
    scale = best.settings["last_layer"]["prior_scale"]
    wider = sorted(s for c in searched if (s := c.settings["last_layer"]["prior_scale"]) > scale * (1 + 1e-9))
    assert [c.settings["last_layer"]["prior_scale"] for c in twins] == pytest.approx([scale, *wider[:1]])
    assert all(c.settings["smcd"] == best.settings["smcd"] for c in twins)
    # The lower score wins, as between the scales, and the note says which.
    assert result.best_of["smcd_last_layer"] == min(both, key=lambda c: c.score)
    kept = "each particle's readout mean" if min(twins, key=lambda c: c.score).score < best.score else "the readout's"
    assert any(
        note.startswith(f"SMCD with a Bayesian readout: weighs its particles by {kept}") for note in result.notes
    )
    assert isinstance(result.strategy("smcd_last_layer"), smcd_rl.SMCDLastLayer)
    alone = smcd_rl.tune(
        model, episodes, strategies=["smcd_last_layer"], weighings=("predictive",), reuse=result, **FAST
    )
    assert not any("weighing" in c.settings for c in alone.candidates if c.kind == "smcd_last_layer")


def test_the_mean_weighing_runs_at_the_best_scale_and_the_next_wider_one_tried(model, monkeypatch) -> None:
    """Without the readout's uncertainty in the likelihood a freer readout no longer blurs the masks:
    the next wider scale tried is the other contender (the search above may end at the widest)."""
    search = _search_with_two_runs(model, [0.30] * 6, [0.29] * 6)
    scored: list[dict] = []
    monkeypatch.setattr(search, "score", lambda kind, settings, **_: scored.append(settings) or 0.5)
    smcd = {"num_particles": 8, "noise_std": 0.1}
    best = {"smcd": smcd, "last_layer": {"prior_scale": 0.2}}
    search.best_of["smcd_last_layer"] = smcd_rl.tuning.search.TuneCandidate("smcd_last_layer", best, 0.1, math.nan)
    factors = [0.01, 0.1, 1.0, 3.0]
    smcd_rl.tuning.kinds._try_mean_weighing(
        search, lambda f: {"smcd": smcd, "last_layer": {"prior_scale": 2.0 * f}}, factors, 2.0
    )
    assert [s["last_layer"]["prior_scale"] for s in scored] == pytest.approx([0.2, 2.0])
    assert all(s["weighing"] == "mean" and s["smcd"] == smcd for s in scored)
    assert search.notes[-1].endswith("(0.1 by the readout's predictive; 0.5 by each particle's readout mean)")


def test_the_mean_weighings_wider_scale_is_the_extension_just_above_the_best(model, monkeypatch) -> None:
    """Where SL's search extends below its grid more than once, the next wider scale tried is the
    previous extension, not the grid's low edge. Scoring SL by its scale alone makes every tighter
    scale win, so the search extends as far as it may and the best is its last extension."""
    score = smcd_rl.tuning.search.Search.score

    def by_scale(self, kind, settings, **kwargs):
        if kind != "smcd_last_layer":
            return score(self, kind, settings, **kwargs)
        return self._add(kind, settings, settings["last_layer"]["prior_scale"])

    contenders: list[list[float]] = []
    monkeypatch.setattr(smcd_rl.tuning.search.Search, "score", by_scale)
    monkeypatch.setattr(smcd_rl.tuning.kinds, "_try_mean_weighing", lambda s, f, factors, c: contenders.append(factors))
    result = smcd_rl.tune(model, shifted_episodes(0.5), strategies=["last_layer", "smcd", "smcd_last_layer"], **FAST)
    scales = sorted(c.settings["last_layer"]["prior_scale"] for c in result.candidates if c.kind == "smcd_last_layer")
    readout = result.best_of["last_layer"].settings["prior_scale"]
    extensions = smcd_rl.tuning.defaults.MAX_EXTENSIONS
    assert len(scales) > len(smcd_rl.tuning.defaults.SMCD_LAST_LAYER_SCALES) + 1  # extended more than once
    (factors,) = contenders
    assert [f * readout for f in factors[: extensions + 1]] == pytest.approx(scales[: extensions + 1])


def test_tunes_weighings_are_the_strategys() -> None:
    assert smcd_rl.tuning.defaults.WEIGHINGS == smcd_rl.strategies.smcd_last_layer.WEIGHINGS


@pytest.mark.parametrize("weighings, error", [("mean", TypeError), (("mean",), ValueError), (("max",), ValueError)])
def test_weighings_that_tune_cannot_try_are_refused_before_any_run(model, monkeypatch, weighings, error) -> None:
    monkeypatch.setattr(smcd_rl.tuning.scoring, "trace_pairs", lambda *a, **k: pytest.fail("ran"))
    with pytest.raises(error, match="weighings must be"):
        smcd_rl.tune(model, shifted_episodes(0.3), strategies=["smcd_last_layer"], weighings=weighings, **FAST)


@pytest.mark.parametrize(
    "predictions, error",
    [("mask", TypeError), (("predictive",), ValueError), (("mask", "median"), ValueError)],
)
def test_predictions_that_tune_cannot_try_are_refused_before_any_run(model, monkeypatch, predictions, error) -> None:
    monkeypatch.setattr(smcd_rl.tuning.scoring, "trace_pairs", lambda *a, **k: pytest.fail("ran"))
    with pytest.raises(error, match="predictions must be"):
        smcd_rl.tune(model, shifted_episodes(0.3), strategies=["smcd"], predictions=predictions, **FAST)
