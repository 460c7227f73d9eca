"""Reliability: all-or-nothing updates, weights that stay normalised, files that fail clearly, checked input.

Each test here pins one way the library used to break: a half-applied sequence, a checkpoint
trained further than asked, weights summing to 200, a pickle traceback for a damaged file, two
runs clobbering one temporary file, inconsistent input failing inside torch, an untrained model
adapting silently, and Ctrl-C printing a traceback.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import warnings
from pathlib import Path
from typing import Any

import pytest
import torch
from hypothesis import event, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

import smcd_rl
from smcd_rl import cli
from smcd_rl.baselines import LatentVariableModel
from smcd_rl.experiments.shared.result_store import ResultStore

pytestmark = pytest.mark.filterwarnings("ignore::smcd_rl.UnfittedModelWarning")  # toy networks, untrained on purpose
PACKAGE = Path(smcd_rl.__file__).parent


def _model(particles: int = 16, noise: float = 0.05, seed: int = 0, **smcd: Any) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(seed)
    adaptation = smcd_rl.SMCD(
        num_particles=particles, noise_std=noise, generator=torch.Generator().manual_seed(seed), **smcd
    )
    return smcd_rl.AdaptiveModel(
        smcd_rl.MaskedMLP(2, 2, hidden=(16, 16)), in_keys=["q"], out_key="ee", adaptation=adaptation
    )


def _dynamics(particles: int = 16) -> smcd_rl.AdaptiveDynamicsModel:
    torch.manual_seed(0)
    smcd = smcd_rl.SMCD(num_particles=particles, generator=torch.Generator().manual_seed(0))
    return smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(16,)), smcd)


def _state(model: smcd_rl.AdaptiveModel) -> dict[str, Any]:
    """Everything an update may change: particles, weights, evidence, ESS, ancestors, generator, MMSE mask."""
    filt = model.adaptation.filter
    return {
        "particles": filt.particles.clone(),
        "log_weights": filt.log_weights.clone(),
        "log_evidence": filt.log_evidence.clone(),
        "last_ess": filt.last_ess.clone(),
        "ancestors": None if filt.ancestors is None else filt.ancestors.clone(),
        "generator": filt.generator.get_state(),
        "mask": model.mask.clone(),
    }


def _assert_same_state(before: dict[str, Any], model: smcd_rl.AdaptiveModel) -> None:
    after = _state(model)
    for key, value in before.items():
        if value is None:
            assert after[key] is None, key
        else:
            assert torch.equal(value, after[key]), f"{key} changed"


def _arm(steps: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    q = torch.rand(steps, 2, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    return q, torch.stack([q[:, 0].cos() + q[:, 1].cos(), q[:, 0].sin() + q[:, 1].sin()], -1)


# ---------------------------------------------------------------------------- observe is all or nothing
def test_a_refused_transition_in_a_sequence_leaves_the_model_as_it_was() -> None:
    """Transition 3 of 5 is an outlier no particle can explain (its likelihood underflows to 0
    everywhere): the whole sequence is refused, and transitions 0..2 must not stay applied."""
    model = _model()
    model.reset()
    q, ee = _arm(8)
    model.observe(TensorDict({"q": q[:3], "ee": ee[:3]}, [3]))
    before = _state(model)
    outlier = ee[3:8].clone()
    outlier[3] = 1e30  # finite, but (1e30 / noise)^2 overflows: every particle's likelihood is 0
    with pytest.raises(ValueError, match=r"transition 3 of the sequence of 5 was refused.*unchanged"):
        model.observe(TensorDict({"q": q[3:8], "ee": outlier}, [5]))
    _assert_same_state(before, model)
    # And the model carries on exactly as if the refused call never happened.
    twin = _model()
    twin.reset()
    twin.observe(TensorDict({"q": q[:3], "ee": ee[:3]}, [3]))
    for m in (model, twin):
        m.observe(TensorDict({"q": q[3:], "ee": ee[3:]}, [5]))
    assert torch.equal(model.mask, twin.mask)


@pytest.mark.parametrize("target", [1e20, 1e25, 1e30])
def test_a_float64_model_refuses_an_outlier_no_particle_can_explain_and_stays_finite(target: float) -> None:
    """A float64 model's likelihood of a 1e20 target is finite (-1e41) but overflows the float32
    weights: the update was accepted and left weights, mask, ESS and evidence NaN until reset."""
    model = _model().to(torch.float64)
    model.reset()
    q, ee = _arm(4)
    q, ee = q.double(), ee.double()
    model.observe(TensorDict({"q": q[:2], "ee": ee[:2]}, [2]))
    before = _state(model)
    with pytest.raises(ValueError, match="impossible"):
        model.observe(TensorDict({"q": q[2], "ee": torch.full((2,), target, dtype=torch.float64)}, []))
    _assert_same_state(before, model)
    model.observe(TensorDict({"q": q[2:], "ee": ee[2:]}, [2]))  # and it carries on
    summary = model.summary()
    assert torch.isfinite(summary["log_evidence"]).all() and torch.isfinite(summary["ess"]).all()
    assert bool(torch.isfinite(model(TensorDict({"q": q}, [4]))["ee"]).all())


# ---------------------------------------------------------------------------- checkpoints and epochs
def _fit_data() -> TensorDict:
    q = torch.rand(128, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    return TensorDict({"q": q, "ee": q.cos()}, [128])


def _fit(epochs: int, checkpoint: Path | None) -> tuple[smcd_rl.AdaptiveModel, list[float]]:
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    losses = smcd_rl.fit(
        model, _fit_data(), epochs=epochs, batch_size=32, lr=1e-3, checkpoint=checkpoint, progress=False
    )
    return model, losses


def test_a_checkpoint_trained_further_than_asked_is_refused_and_more_epochs_train_on(tmp_path: Path) -> None:
    path = tmp_path / "train.ckpt"
    _fit(4, path)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match=r"trained for 4 epochs.*epochs >= 4.*delete it"):
        _fit(2, path)
    resumed, losses = _fit(6, path)  # more epochs: train on from epoch 4, as the longer run would have
    straight, straight_losses = _fit(6, None)
    assert losses == straight_losses
    for a, b in zip(resumed.state_dict().values(), straight.state_dict().values(), strict=True):
        assert torch.equal(a, b)


# ---------------------------------------------------------------------------- normalised weights
def test_a_tiny_likelihood_noise_keeps_the_ess_in_1_to_n_and_the_mask_in_0_to_1() -> None:
    """Noise 1e-4 (and 1e-8) makes log-likelihoods of -1e8 and beyond: float32 normalisation
    reported an ESS of 0.5 and, without resampling, weights summing to 200."""
    q, ee = _arm(6)
    for noise, threshold in ((1e-4, 1.0), (1e-8, 0.0)):
        model = _model(particles=200, noise=noise, ess_threshold=threshold)
        model.reset()
        for t in range(6):
            model.observe(TensorDict({"q": q[t], "ee": ee[t]}, []))
            ess = float(model.summary()["ess"])
            assert 1.0 <= ess <= 200.0, (noise, t, ess)
            weights = model.adaptation.filter.weights
            assert abs(float(weights.sum()) - 1.0) < 1e-5
            assert 0.0 <= float(model.mask.min()) and float(model.mask.max()) <= 1.0
        model.adaptation.filter.resize(300)
        assert 0.0 <= float(model.mask.min()) and float(model.mask.max()) <= 1.0


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(1, 300),
    magnitude=st.sampled_from([1.0, 1e4, 1e8, 1e12, 1e20, 1e30, 3e38]),
    ties=st.integers(0, 300),
    seed=st.integers(0, 2**31 - 1),
)
def test_weights_stay_normalised_for_any_finite_log_likelihood(n: int, magnitude: float, ties: int, seed: int) -> None:
    """Log-likelihoods up to float32's largest, with many exact ties at the maximum (the case
    that made 200 particles each weigh 1)."""
    filt = smcd_rl.SMCDFilter(8, num_particles=n, ess_threshold=0.0, generator=torch.Generator().manual_seed(seed))
    filt.reset(batch_shape=(2,))
    ll = -torch.rand(2, n, generator=torch.Generator().manual_seed(seed + 1)) * magnitude
    ll[0, : min(ties, n)] = -magnitude  # row 0: ties at the bottom
    ll[1, : min(ties, n)] = ll[1].max()  # row 1: ties at the maximum
    filt.reweight(ll)
    assert torch.isfinite(filt.log_weights.exp()).all()
    assert ((filt.weights.sum(-1) - 1.0).abs() < 1e-4).all()
    for ess in (filt.ess, filt.last_ess):
        assert bool((ess >= 1.0).all()) and bool((ess <= n).all()), ess
    assert float(filt.mean_mask.min()) >= 0.0 and float(filt.mean_mask.max()) <= 1.0
    assert torch.isfinite(filt.log_evidence).all()


# ---------------------------------------------------------------------------- unreadable files
def _model_file(path: Path) -> None:
    _model().save(path)


def _training_file(path: Path) -> None:
    _fit(1, path)


def _cache_file(path: Path) -> None:
    ResultStore(path.parent).put("cache", {"seed": 0}, {"rmse": 0.1})


def _latent_file(path: Path) -> None:
    from smcd_rl.files import save_file

    save_file(LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=8).checkpoint(), path)


def _read_model(path: Path) -> None:
    smcd_rl.load(path)


def _read_training(path: Path) -> None:
    _fit(2, path)


def _read_cache(path: Path) -> None:
    ResultStore(path.parent).get("cache", {"seed": 0})


def _read_latent(path: Path) -> None:
    LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=8).load_checkpoint(path)


def _path(directory: Path, kind: str) -> Path:
    """Where the file of ``kind`` goes: a result's path is named by its key."""
    return ResultStore(directory).path("cache", {"seed": 0}) if kind == "cache" else directory / f"{kind}.pt"


FILES = {
    "model": (_model_file, _read_model),
    "training": (_training_file, _read_training),
    "cache": (_cache_file, _read_cache),
    "latent": (_latent_file, _read_latent),
}


def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "empty":
        path.write_bytes(b"")
    elif how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        path.write_bytes(b"\x80\x02}q\x00(X\x06" + bytes(range(256)))  # a pickle that breaks off
    elif how == "not a dict":
        torch.save([1, 2, 3], path)
    elif how == "entries missing":
        saved = torch.load(path, weights_only=False)
        torch.save({k: v for k, v in saved.items() if k in ("format", "fingerprint")}, path)


@pytest.mark.parametrize("how", ["empty", "truncated", "garbage", "not a dict", "entries missing"])
@pytest.mark.parametrize("kind", sorted(FILES))
def test_a_damaged_file_names_itself_and_the_fix(tmp_path: Path, kind: str, how: str) -> None:
    write, read = FILES[kind]
    path = _path(tmp_path, kind)
    write(path)
    read(path)  # intact, it reads
    _damage(path, how)
    with pytest.raises(ValueError) as caught:
        read(path)
    message = str(caught.value)
    assert str(path) in message and "\n" not in message, message
    if kind == "model" and how == "not a dict":  # a list is no checkpoint of ours, damaged or not
        assert "is not an smcd-rl model checkpoint: it holds a list" in message and "delete" not in message, message
    else:
        assert "delete" in message or "save the model again" in message, message
    assert isinstance(caught.value, smcd_rl.UnreadableFileError | smcd_rl.CheckpointMismatchError)


def test_the_cli_reports_a_damaged_file_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    out.mkdir()
    options = ["--tasks", "2", "--episodes", "2", "--steps", "2", "--hidden", "8", "--epochs", "1", "--trials", "2"]
    options += ["--burn-in", "1", "--horizons", "1", "--methods", "M+N"]
    assert cli.main(["two-link", "--out", str(out), *options]) == 0
    capsys.readouterr()
    model = out / "model.pt"
    for damaged in [p for p in out.rglob("*") if p.is_file() and p.suffix in (".pt", ".ckpt")] or [model]:
        damaged.write_bytes(b"")
    assert cli.main(["two-link", "--out", str(out), *options]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line]  # besides the stage's progress line
    assert len(errors) == 1 and "empty" in errors[0] and "Traceback" not in err, err


# ---------------------------------------------------------------------------- writes
def test_a_failed_write_names_the_directory_and_leaves_nothing_behind(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the output directory should be")
    with pytest.raises(smcd_rl.FileWriteError, match=r"not-a-dir.*is a file, not a directory") as caught:
        _model().save(blocker / "model.pt")
    assert isinstance(caught.value, OSError) and isinstance(caught.value, ValueError)

    readonly = tmp_path / "readonly"
    readonly.mkdir()
    readonly.chmod(0o500)
    try:
        if os.access(readonly, os.W_OK):
            pytest.skip("running as root: a read-only directory is still writable")
        with pytest.raises(smcd_rl.FileWriteError, match=r"readonly is read-only or not writable"):
            ResultStore(readonly).put("cache", {}, {"x": 1})
        assert list(readonly.iterdir()) == []
    finally:
        readonly.chmod(0o700)


@pytest.mark.parametrize("kind", ["model", "training", "cache"])
def test_a_save_never_touches_another_writers_temporary_file(tmp_path: Path, kind: str) -> None:
    """Two runs on one output directory used to share the fixed name ``<file>.tmp``: one
    replaced the other's half-written file and died with FileNotFoundError."""
    path = _path(tmp_path, kind)
    other = path.with_suffix(path.suffix + ".tmp")  # the other run's file in progress
    other.write_bytes(b"another run, half-way through its write")
    FILES[kind][0](path)
    assert other.read_bytes() == b"another run, half-way through its write"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, other.name])  # no temporary left
    FILES[kind][1](path)


# ---------------------------------------------------------------------------- input checks
def test_inconsistent_input_is_named_before_any_work() -> None:
    model = _model()
    model.reset(batch_shape=(3,))
    q, ee = _arm(3)
    model.observe(TensorDict({"q": q, "ee": ee}, [3]))
    before = _state(model)
    single = _model()
    single.reset()
    cases: list[tuple[Any, Any, type[Exception], str]] = [
        (single, TensorDict({"q": torch.zeros(5, 2), "ee": torch.zeros(5, 2)}, []), ValueError, r"batch_size=\[5\]"),
        (model, q.numpy(), TypeError, "takes a tensordict.TensorDict, got ndarray"),
        (model, {"q": q, "ee": ee}, TypeError, "wrap it: TensorDict"),
        (
            model,
            TensorDict({"q": q.double(), "ee": torch.full((3, 2), 1e39, dtype=torch.float64)}, [3]),
            ValueError,
            "too large for the model's torch.float32",
        ),
        (model, TensorDict({"q": q.to(torch.complex64), "ee": ee}, [3]), TypeError, "complex"),
        (model, TensorDict({"q": q[:, None].expand(3, 4, 2), "ee": ee}, [3]), ValueError, r"batch is \[3\]"),
    ]
    for target, td, error, message in cases:
        with pytest.raises(error, match=message):
            target.observe(td)
    with pytest.raises(ValueError, match=r"one bool per batch element, shape \[3\], got \[2\]"):
        model.reset(batch_shape=(3,), where=torch.tensor([True, False]))
    with pytest.raises(TypeError, match="sequence of ints such as"):
        model.reset(batch_shape=3)  # type: ignore[arg-type]
    _assert_same_state(before, model)

    dynamics = _dynamics()
    dynamics.reset()
    complex_action = {"observation": torch.zeros(3), "action": torch.ones(1, dtype=torch.complex64)}
    with pytest.raises(TypeError, match="'action' is complex"):
        dynamics.observe(TensorDict({**complex_action, ("next", "observation"): torch.zeros(3)}, []))
    with pytest.raises(TypeError, match="action is complex"):
        dynamics.step(torch.zeros(3), torch.ones(1, dtype=torch.complex64))
    with pytest.raises(ValueError, match="same batch dims"):
        dynamics.step(torch.zeros(4, 3), torch.ones(2, 1))


def test_constructors_refuse_what_they_would_silently_change() -> None:
    with pytest.raises(TypeError, match=r"hidden=\(64,\)"):
        smcd_rl.MaskedMLP(2, 2, hidden=64)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="num_particles must be an int, got 2.5"):
        smcd_rl.SMCD(num_particles=2.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="num_particles must be an int"):
        smcd_rl.SMCDFilter(4, num_particles=2.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="in_keys must be a list of keys"):
        smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(4,)), in_keys="q", out_key="ee")
    with pytest.raises(TypeError, match="steps must be an int"):
        smcd_rl.GradientDescent(steps=1.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"ess_threshold must be in \[0, 1\]"):
        smcd_rl.SMCD(ess_threshold=float("nan"))


DTYPES = [torch.float32, torch.float64, torch.float16, torch.int64, torch.int32, torch.bool, torch.complex64]


@st.composite
def _observation(draw: st.DrawFn) -> tuple[tuple[int, ...], Any]:
    """A model batch shape and something passed to observe: mostly TensorDicts, right or subtly wrong."""
    model_batch = draw(st.sampled_from([(), (2,)]))
    kind = draw(st.sampled_from(["tensordict"] * 12 + ["ndarray", "dict", "tensor"]))
    td_batch = draw(st.sampled_from([model_batch] * 4 + [(), (2,), (3,), (2, 2)]))
    entries = {}
    for key in ("q", "ee"):
        if draw(st.booleans()):  # well-formed, so that about half the cases get through the checks
            extra, features, dtype = (), 2, draw(st.sampled_from([torch.float32, torch.float64]))
        else:
            extra = draw(st.sampled_from([(), (1,), (4,)]))  # dims the TensorDict's batch does not declare
            features = draw(st.sampled_from([2, 1, 3]))
            dtype = draw(st.sampled_from(DTYPES))
        shape = (*td_batch, *extra, features)
        scale = draw(st.sampled_from([1.0, 1.0, 1e3, 1e30]))
        generator = torch.Generator().manual_seed(draw(st.integers(0, 1000)))
        values = torch.randn(shape, generator=generator, dtype=torch.float64) * scale  # float64: room for 1e39
        if values.numel() and draw(st.integers(0, 3)) == 0:  # one odd value at a random place
            flat = values.reshape(-1)
            flat[draw(st.integers(0, flat.numel() - 1))] = draw(st.sampled_from([math.nan, math.inf, -math.inf, 1e39]))
        entries[key] = values.to(dtype)
    if kind == "ndarray":
        return model_batch, entries["q"].to(torch.float64).numpy()
    if kind == "dict":
        return model_batch, entries
    if kind == "tensor":
        return model_batch, entries["q"]
    # A TensorDict's tensors must start with its batch dims; pass those that cannot as a batch-[] one.
    fits = all(tuple(v.shape[: len(td_batch)]) == td_batch for v in entries.values())
    return model_batch, TensorDict(entries, list(td_batch) if fits else [])


def _raised_inside_smcd_rl(err: BaseException) -> bool:
    """The error was raised by smcd_rl's own checks, not from inside torch or tensordict."""
    tb = err.__traceback__
    assert tb is not None
    while tb.tb_next is not None:
        tb = tb.tb_next
    return Path(tb.tb_frame.f_code.co_filename).resolve().is_relative_to(PACKAGE.resolve())


@settings(max_examples=200, deadline=None)
@given(case=_observation(), seed=st.integers(0, 3))
def test_observe_either_refuses_clearly_and_changes_nothing_or_stays_finite(case: tuple[Any, Any], seed: int) -> None:
    model_batch, td = case
    model = _model(particles=8, seed=seed)
    model.reset(batch_shape=model_batch)
    q, ee = _arm(2, seed=seed)
    model.observe(TensorDict({"q": q, "ee": ee}, [2]) if model_batch else TensorDict({"q": q[0], "ee": ee[0]}, []))
    before = _state(model)
    try:
        model.observe(td)
    except (ValueError, TypeError) as err:
        event(f"refused: {type(err).__name__}")
        assert _raised_inside_smcd_rl(err), f"{type(err).__name__} from inside torch: {err}"
        assert len(str(err)) > 20  # a message, not a bare name
        _assert_same_state(before, model)
        return
    event("accepted")
    summary = model.summary()
    assert torch.isfinite(summary["log_evidence"]).all()
    assert bool((summary["ess"] >= 1.0).all()) and bool((summary["ess"] <= 8).all())
    assert float(model.mask.min()) >= 0.0 and float(model.mask.max()) <= 1.0
    assert torch.isfinite(model.adaptation.filter.log_weights.exp()).all()


# ---------------------------------------------------------------------------- unfitted models
def test_an_unfitted_model_warns_once_and_a_fitted_or_loaded_one_never(tmp_path: Path) -> None:
    model = _model()
    q, ee = _arm(2)
    with pytest.warns(smcd_rl.UnfittedModelWarning, match="never fitted") as record:
        model.reset()
        model.observe(TensorDict({"q": q, "ee": ee}, [2]))
        model.reset()
    assert len([w for w in record if issubclass(w.category, smcd_rl.UnfittedModelWarning)]) == 1

    trained, _ = _fit(1, None)
    assert trained.fitted
    trained.save(tmp_path / "m.pt")
    mine = _model()
    mine.fitted = True  # trained with one's own loop
    with warnings.catch_warnings():
        warnings.simplefilter("error", smcd_rl.UnfittedModelWarning)
        for m in (trained, smcd_rl.load(tmp_path / "m.pt"), trained.with_adaptation(smcd_rl.SMCD(10)), mine):
            m.reset()
            m.observe(TensorDict({"q": q, "ee": ee}, [2]))


def test_gradient_descent_refuses_an_observation_that_makes_its_weights_non_finite() -> None:
    """A finite but huge target used to turn the weights NaN for good, and every later prediction with them."""
    model = _model().with_adaptation(smcd_rl.GradientDescent(lr=0.1, steps=2, window=4))
    model.reset(batch_shape=(3,))
    q, ee = _arm(3)
    model.observe(TensorDict({"q": q, "ee": ee}, [3]))
    before = model.adaptation.state_dict()
    with pytest.raises(ValueError, match="diverged on this observation"):
        model.observe(TensorDict({"q": q, "ee": torch.full((3, 2), 1e20)}, [3]))
    after = model.adaptation.state_dict()
    assert all(torch.equal(before["params"][k], after["params"][k]) for k in before["params"])
    assert torch.equal(before["inputs"], after["inputs"]) and torch.equal(before["count"], after["count"])
    assert bool(torch.isfinite(model.predict(q)).all())


@pytest.mark.parametrize(
    ("lr", "target"),
    [(0.01, 1e18), (1e3, None)],  # an outlier target; a learning rate far too large on ordinary input
    ids=["outlier", "large lr"],
)
def test_gradient_descent_never_accepts_an_observation_that_makes_it_predict_inf(lr: float, target: Any) -> None:
    """One step on a 1e18 target (or two with lr=1e3) kept the weights finite but made them
    predict inf: the step was accepted, and the model predicted inf until the next observe refused."""
    model = _model().with_adaptation(smcd_rl.GradientDescent(lr=lr, steps=1, window=4))
    model.reset(batch_shape=(3,))
    q, ee = _arm(6)
    model.observe(TensorDict({"q": q[:3], "ee": ee[:3]}, [3]))
    outlier = ee[3:] if target is None else torch.full((3, 2), target)
    for _ in range(5):  # with lr=1e3 the predictions grow by 1e14 and more per step: inf within 5
        before = model.adaptation.state_dict()
        try:
            model.observe(TensorDict({"q": q[3:], "ee": outlier}, [3]))
        except ValueError as err:
            assert "diverged on this observation" in str(err) and "unchanged" in str(err), err
            after = model.adaptation.state_dict()
            assert all(torch.equal(before["params"][k], after["params"][k]) for k in before["params"])
            for key in ("inputs", "targets", "count"):
                assert torch.equal(before[key], after[key]), key
            assert bool(torch.isfinite(model.predict(q[3:])).all())
            return
        assert bool(torch.isfinite(model.predict(q[3:])).all()), "accepted an observation, then predicted inf"
    raise AssertionError("gradient descent never refused the diverging observations")


def test_declaring_a_model_fitted_keeps_the_normalisation_unfitted_and_survives_a_save(tmp_path: Path) -> None:
    """``model.fitted = True`` used to mark the normalisers fitted too, so a later fit skipped
    standardising the data and trained on raw units."""
    model = _model()
    model.fitted = True
    assert model.fitted and not bool(model.input_norm.fitted)
    model.save(tmp_path / "declared.pt")
    assert smcd_rl.load(tmp_path / "declared.pt").fitted
    q, ee = _arm(64)
    smcd_rl.fit(model, TensorDict({"q": q, "ee": 10 + ee}, [64]), epochs=1, batch_size=16, progress=False)
    assert bool(model.output_norm.fitted) and float(model.output_norm.mean.min()) > 5


# ---------------------------------------------------------------------------- Ctrl-C
def test_ctrl_c_prints_one_line_and_exits_130(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A real SIGINT, 1.5 s into a two-link run that takes minutes.

    The test gives SIGINT the handler a terminal's Ctrl-C meets, for its own duration: a suite
    started as a background job (``nohup bash -c ... &``) inherits SIGINT ignored, and run so,
    after the tests before it, the signal was dropped and the command ran for minutes."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        status = cli.main(["two-link", "--out", str(tmp_path / "run"), "--threads", "1"])
    except KeyboardInterrupt:
        pytest.fail("KeyboardInterrupt escaped cli.main")
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert status == 130
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "interrupted" in line]
    assert lines == ["smcd-rl two-link: interrupted; run the same command again to resume (finished work is kept)"]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
