"""AdaptiveModel: TensorDict plumbing, batched independent filters, persistence and bad input."""

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.envs.two_link_arm import integrate_joints, sample_link_lengths, two_link_fk


def _stream(lengths: torch.Tensor, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    q = (torch.rand(steps, *lengths.shape[:-1], 2, generator=torch.Generator().manual_seed(seed)) * 2 - 1) * math.pi
    return q, two_link_fk(q, lengths)


def _babbling(lengths: torch.Tensor, steps: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint paths of motor babbling (u ~ N(0, 1)), as in the paper's look-ahead setting."""
    g = torch.Generator().manual_seed(seed)
    q = [(torch.rand(*lengths.shape[:-1], 2, generator=g) * 2 - 1) * math.pi]
    for _ in range(steps - 1):
        q.append(integrate_joints(q[-1], torch.randn(q[-1].shape, generator=g), 0.2))
    path = torch.stack(q)
    return path, two_link_fk(path, lengths)


def _smcd(seed: int = 0, n: int = 500) -> smcd_rl.SMCD:
    return smcd_rl.SMCD(num_particles=n, flip_prob=0.01, noise_std=0.05, generator=torch.Generator().manual_seed(seed))


def test_batched_filters_adapt_each_to_its_own_stream(two_link_model: smcd_rl.AdaptiveModel) -> None:
    """Two arms of very different lengths, one filter each: each mask predicts its own arm better."""
    lengths = torch.tensor([[0.6, 0.6], [1.5, 1.4]])
    model = two_link_model.with_adaptation(_smcd())
    model.reset(batch_shape=(2,))
    q, ee = _stream(lengths, 30, seed=1)
    for t in range(30):
        model.observe(TensorDict({"q": q[t], "ee": ee[t]}, [2]))
    masks = model.mask
    assert masks.shape == (2, model.net.mask_dim)
    q_test, _ = _stream(lengths, 200, seed=2)  # [200, 2 arms, 2]
    errors = torch.empty(2, 2)  # [mask of arm i, arm j]
    with torch.no_grad():
        for i in range(2):
            for j in range(2):
                x = model.input_norm(q_test[:, j])
                pred = model.output_norm.inverse(model.net(x, mask=masks[i]))
                errors[i, j] = (pred - two_link_fk(q_test[:, j], lengths[j])).norm(dim=-1).mean()
    assert errors[0, 0] < errors[1, 0] and errors[1, 1] < errors[0, 1], errors


def test_sequence_batch_equals_step_by_step(two_link_model: smcd_rl.AdaptiveModel) -> None:
    q, ee = _stream(torch.tensor([1.0, 0.8]), 8, seed=3)
    one = two_link_model.with_adaptation(_smcd(5, n=100))
    one.reset()
    one.observe(TensorDict({"q": q, "ee": ee}, [8]))
    two = two_link_model.with_adaptation(_smcd(5, n=100))
    two.reset()
    for t in range(8):
        two.observe(TensorDict({"q": q[t], "ee": ee[t]}, []))
    assert torch.equal(one.mask, two.mask)


def test_smcd_beats_no_adaptation_and_particles_give_the_posterior_predictive(
    two_link_model: smcd_rl.AdaptiveModel,
) -> None:
    """20 held-out arms, 10 babbling steps observed, 10 predicted.

    Measured with these seeds: M+N RMSE 0.52 m, SMCD 0.26 m. The bound 0.75 x M+N leaves a wide
    margin, yet no mask-independent predictor passes it: M+N is the best fixed predictor of
    multi-task training.
    """
    lengths = sample_link_lengths((20,), generator=torch.Generator().manual_seed(9))
    q, ee = _babbling(lengths, 20, seed=4)
    models = {}
    for name, strategy in {"none": smcd_rl.NoAdaptation(), "smcd": _smcd(3)}.items():
        models[name] = model = two_link_model.with_adaptation(strategy)
        model.reset(batch_shape=(20,))
        for t in range(10):
            model.observe(TensorDict({"q": q[t], "ee": ee[t]}, [20]))
    td = TensorDict({"q": q[10:].transpose(0, 1)}, [20, 10])  # extra batch dim: 10 future steps
    with torch.no_grad():
        rmse = {
            k: float((m(td.clone())["ee"] - ee[10:].transpose(0, 1)).square().sum(-1).mean().sqrt())
            for k, m in models.items()
        }
    assert rmse["smcd"] < 0.75 * rmse["none"], rmse
    samples = models["smcd"].predict_particles(td)
    assert samples.shape == (20, 10, 500, 2)
    # Each particle's prediction is the network under that particle's mask.
    m = models["smcd"]
    direct = m.output_norm.inverse(m.net(m.input_norm(td["q"][3, 4]), mask=m.particles[3, 17]))
    torch.testing.assert_close(samples[3, 4, 17], direct)


def test_summary_reports_ess_and_log_evidence(two_link_model: smcd_rl.AdaptiveModel) -> None:
    model = two_link_model.with_adaptation(_smcd(n=50))
    model.reset(batch_shape=(3,))
    q, ee = _stream(torch.ones(3, 2), 1, seed=0)
    model.observe(TensorDict({"q": q[0], "ee": ee[0]}, [3]))
    summary = model.summary()
    assert summary["ess"].shape == (3,) and bool((summary["ess"] >= 1).all())
    assert bool(torch.isfinite(summary["log_evidence"]).all())


def test_gradient_descent_adapts_and_reset_restores_the_trained_weights(
    two_link_model: smcd_rl.AdaptiveModel,
) -> None:
    q, ee = _stream(torch.tensor([1.6, 0.5]), 10, seed=6)
    plain = two_link_model.with_adaptation(smcd_rl.NoAdaptation())
    plain.reset()
    gd = two_link_model.with_adaptation(smcd_rl.GradientDescent(lr=0.05, steps=3, window=5))
    gd.reset()
    td = TensorDict({"q": q}, [10])
    before = plain(td.clone())["ee"]
    torch.testing.assert_close(gd(td.clone())["ee"], before)
    gd.observe(TensorDict({"q": q, "ee": ee}, [10]))
    after = gd(td.clone())["ee"]
    assert (after - ee).norm(dim=-1).mean() < (before - ee).norm(dim=-1).mean()
    gd.reset()
    torch.testing.assert_close(gd(td.clone())["ee"], before)
    torch.testing.assert_close(plain(td.clone())["ee"], before)  # the shared network is untouched


@pytest.mark.parametrize("strategy", ["gd", "smcd"])
def test_reset_where_restarts_only_the_chosen_rows(two_link_model: smcd_rl.AdaptiveModel, strategy: str) -> None:
    """A vector env's finished sub-env restarts its own adaptation; the others keep theirs.

    Row 1 after the partial reset and one more transition must equal a fresh single model that saw
    only that transition (GD: trained weights and an empty window; SMCD: with the same filter
    state, compared through the prior's log evidence of zero before it).
    """

    def make() -> smcd_rl.AdaptiveModel:
        if strategy == "gd":
            return two_link_model.with_adaptation(smcd_rl.GradientDescent(lr=0.05, steps=3, window=5))
        return two_link_model.with_adaptation(_smcd(n=200))

    model = make()
    model.reset(batch_shape=(3,))
    lengths = torch.tensor([[1.0, 0.5], [1.5, 0.8], [0.7, 1.2]])
    q, ee = _stream(lengths, 6, seed=2)
    for t in range(5):
        model.observe(TensorDict({"q": q[t], "ee": ee[t]}, [3]))
    probe = TensorDict({"q": q[5]}, [3])
    before = model(probe.clone())["ee"]
    model.reset(batch_shape=(3,), where=torch.tensor([False, True, False]))
    after = model(probe.clone())["ee"]
    torch.testing.assert_close(after[[0, 2]], before[[0, 2]])
    plain = two_link_model.with_adaptation(smcd_rl.NoAdaptation())
    plain.reset()
    if strategy == "gd":
        torch.testing.assert_close(after[1], plain(probe[1].clone())["ee"])  # trained weights again
        model.observe(TensorDict({"q": q[5], "ee": ee[5]}, [3]))
        fresh = make()
        fresh.reset()
        fresh.observe(TensorDict({"q": q[5, 1], "ee": ee[5, 1]}, []))
        torch.testing.assert_close(model(probe.clone())["ee"][1], fresh(probe[1].clone())["ee"])
    else:
        assert float(model.summary()["log_evidence"][1]) == 0.0
        assert bool((model.summary()["log_evidence"][[0, 2]] != 0).all())
    with pytest.raises(ValueError, match="resets rows of the current batch"):
        model.reset(batch_shape=(2,), where=torch.tensor([True, False]))


def test_dynamics_model_predicts_the_change_of_observation() -> None:
    torch.manual_seed(0)
    obs, act = torch.randn(512, 3), torch.randn(512, 1)
    data = TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + 5.0 + 0.5 * act}, [512])
    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4, 3, hidden=(64,), dropout=0.1))
    smcd_rl.fit_dynamics(model, data, epochs=30, batch_size=64, lr=3e-3, progress=False)
    model.reset()
    td = model(TensorDict({"observation": torch.zeros(3), "action": torch.ones(1)}, []))
    torch.testing.assert_close(td["next", "observation"], torch.full((3,), 5.5), atol=0.15, rtol=0)
    assert model.base_key == "observation"

    # step(): the same prediction from tensors, with the adapted mask or given masks.
    adapted = model.with_adaptation(smcd_rl.SMCD(num_particles=20, generator=torch.Generator().manual_seed(0)))
    adapted.reset()
    adapted.observe(
        TensorDict({"observation": obs[:8], "action": act[:8], ("next", "observation"): obs[:8] + 5.2}, [8])
    )
    states, actions = torch.randn(6, 3), torch.randn(6, 1)
    td = TensorDict({"observation": states, "action": actions}, [6])
    torch.testing.assert_close(adapted.step(states, actions), adapted(td)["next", "observation"])
    masks = adapted.particles[:6]
    torch.testing.assert_close(
        adapted.step(states, actions, mask=masks), adapted(td, mask=masks)["next", "observation"]
    )
    with pytest.raises(ValueError, match=r"action \[..., 1\]"):
        adapted.step(states, torch.randn(6, 2))


def test_save_and_load_round_trip(tmp_path, two_link_model: smcd_rl.AdaptiveModel) -> None:
    model = two_link_model.with_adaptation(_smcd(n=64))
    model.save(tmp_path / "m.pt")
    loaded = smcd_rl.load(tmp_path / "m.pt", adaptation=_smcd(n=64))
    assert loaded.net.config == model.net.config and loaded.adaptation.config() == model.adaptation.config()
    q, ee = _stream(torch.tensor([0.9, 1.2]), 5, seed=8)
    for m in (model, loaded):
        m.reset()
        m.observe(TensorDict({"q": q, "ee": ee}, [5]))
    td = TensorDict({"q": q}, [5])
    assert torch.equal(model(td.clone())["ee"], loaded(td.clone())["ee"])
    assert type(smcd_rl.load(tmp_path / "m.pt").adaptation) is smcd_rl.SMCD  # saved strategy rebuilt


def test_checkpoint_of_another_architecture_is_refused(tmp_path, two_link_model) -> None:
    two_link_model.save(tmp_path / "m.pt")
    other = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(64, 64)), in_keys=["q"], out_key="ee")
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="architecture"):
        other.load_checkpoint(tmp_path / "m.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(Exception, match="checkpoint|load"):
        smcd_rl.load(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError):
        smcd_rl.load(tmp_path / "missing.pt")


@pytest.mark.parametrize(
    ("corrupt", "message"),
    [
        (lambda c: c["state_dict"].pop("net.linears.1.bias"), r"missing \['net.linears.1.bias'\]"),
        (lambda c: c["state_dict"].update(extra=torch.zeros(1)), r"unexpected \['extra'\]"),
        (lambda c: c["state_dict"].update({"net.linears.1.bias": torch.zeros(3)}), r"'net.linears.1.bias' is \[3\]"),
        (lambda c: c["state_dict"]["net.linears.0.weight"].fill_(math.nan), "'net.linears.0.weight' holds inf or NaN"),
        (lambda c: c["state_dict"]["output_norm.std"].zero_(), "'output_norm.std' is not positive"),
        (lambda c: c.update(declared_fitted="no"), "declared_fitted is 'no', not True or False"),
        (lambda c: c.update(state_dict=[1.0]), "state_dict is a list"),
    ],
)
def test_a_damaged_checkpoint_is_refused_before_any_weight_changes(corrupt, message) -> None:
    """torch's load_state_dict copies tensor by tensor and raises at the end: a checkpoint missing
    one bias once replaced every other weight and then refused. NaN weights and a normaliser scale
    of 0 loaded silently, the model then predicting NaN or a constant."""

    def model(seed: int) -> smcd_rl.AdaptiveModel:
        torch.manual_seed(seed)
        return smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")

    target, checkpoint = model(0), model(1).checkpoint()
    before = {k: v.clone() for k, v in target.state_dict().items()}
    corrupt(checkpoint)
    with pytest.raises(smcd_rl.CheckpointMismatchError, match=message):
        target.load_checkpoint(checkpoint)
    assert all(torch.equal(before[k], v) for k, v in target.state_dict().items())
    assert not target.fitted


def test_fitted_takes_only_a_bool() -> None:
    """``bool("no")`` is True: a string once declared the model trained."""
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    for value in ("no", 1, torch.tensor(True)):
        with pytest.raises(TypeError, match="model.fitted must be True or False"):
            model.fitted = value  # type: ignore[assignment]
    assert not model.fitted


def test_bad_observations_raise_and_leave_the_filter_unchanged(two_link_model) -> None:
    model = two_link_model.with_adaptation(_smcd(n=32))
    model.reset(batch_shape=(2,))
    q, ee = _stream(torch.ones(2, 2), 2, seed=0)
    model.observe(TensorDict({"q": q[0], "ee": ee[0]}, [2]))
    state = model.adaptation.filter.state_dict()
    nan = ee[1].clone()
    nan[0, 1] = float("nan")
    inf = ee[1].clone()
    inf[1, 0] = float("inf")
    cases = [
        (TensorDict({"q": q[1], "ee": nan}, [2]), ValueError, "NaN or inf"),
        (TensorDict({"q": q[1], "ee": inf}, [2]), ValueError, "NaN or inf"),
        (TensorDict({"q": q[1]}, [2]), KeyError, "no key 'ee'"),
        (TensorDict({"q": q[1, :, :1], "ee": ee[1]}, [2]), ValueError, "network takes 2"),
        (TensorDict({"q": q[1], "ee": ee[1, :, :1]}, [2]), ValueError, r"\[\.\.\., 2\]"),
        (TensorDict({"q": q[:, 0], "ee": ee[:, 0]}, [2]).expand(3, 2), ValueError, "batch_shape"),
    ]
    for td, error, message in cases:
        with pytest.raises(error, match=message):
            model.observe(td)
    after = model.adaptation.filter.state_dict()
    for key in ("particles", "log_weights", "log_evidence", "generator"):
        assert torch.equal(state[key], after[key]), key


def test_configuration_errors_are_clear() -> None:
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,))
    with pytest.raises(ValueError, match="systematic"):
        smcd_rl.SMCD(resampling="bogus")
    with pytest.raises(ValueError, match="noise_std"):
        smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(noise_std=[0.1, 0.1, 0.1]))
    with pytest.raises(ValueError, match="unknown adaptation"):
        smcd_rl.make_adaptation("magic")
    with pytest.raises(RuntimeError, match="reset"):
        smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")(TensorDict({"q": torch.zeros(2)}, []))
    assert isinstance(smcd_rl.make_adaptation("gd", lr=0.1), smcd_rl.GradientDescent)


def test_dynamics_model_sizes_and_a_network_too_small_for_observation_plus_action() -> None:
    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(5, 3, hidden=(8,)))
    assert (model.observation_dim, model.action_dim) == (3, 2)
    with pytest.raises(ValueError, match="more inputs than outputs"):
        smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3, 3, hidden=(8,)))


def test_tensors_on_the_meta_device_are_refused_by_name_and_change_nothing() -> None:
    """A meta tensor has a shape but no values: reading it raised torch's NotImplementedError
    ("Cannot copy out of meta tensor") from inside the model, and model.to("meta") threw the
    trained weights away."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8, 8))
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=_smcd(n=16))
    model.fitted = True
    model.reset()
    model.observe(TensorDict({"q": torch.zeros(2), "ee": torch.ones(2)}, []))
    state = model.adaptation.filter.state_dict()
    meta = torch.zeros(2, device="meta")
    calls = {
        "forward": lambda: model(TensorDict({"q": meta}, [])),
        "observe": lambda: model.observe(TensorDict({"q": torch.zeros(2), "ee": meta}, [])),
        "observe a meta TensorDict": lambda: model.observe(
            TensorDict({"q": torch.zeros(2), "ee": meta}, []).to("meta")
        ),
        "predict": lambda: model.predict(meta),
        "mask": lambda: model(TensorDict({"q": torch.zeros(2)}, []), mask=torch.ones(net.mask_dim, device="meta")),
        "predict_particles": lambda: model.predict_particles(TensorDict({"q": meta}, [])),
    }
    for name, call in calls.items():
        with pytest.raises(TypeError, match="meta device.*no values") as caught:
            call()
        assert "NotImplementedError" not in repr(caught.value), name
    after = model.adaptation.filter.state_dict()
    for key in ("particles", "log_weights", "log_evidence", "generator"):
        assert torch.equal(state[key], after[key]), key

    weights = {k: v.clone() for k, v in model.state_dict().items()}
    for move in (lambda: model.to("meta"), lambda: model.to(device=torch.device("meta"))):
        with pytest.raises(ValueError, match="meta device.*no values"):
            move()
    assert all(torch.equal(weights[k], v) for k, v in model.state_dict().items())  # weights kept
    model.to(torch.float64)  # other moves still work
    assert model.net.linears[0].weight.dtype == torch.float64
    with pytest.raises(ValueError, match="meta device.*no values"):
        smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)).to("meta"), in_keys=["q"], out_key="ee")


def test_smcd_rl_save_writes_what_smcd_rl_load_reads(tmp_path) -> None:
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(8,)), adaptation=_smcd(n=16))
    model.fitted = True
    smcd_rl.save(model, tmp_path / "m.pt")
    loaded = smcd_rl.load(tmp_path / "m.pt")
    assert type(loaded) is smcd_rl.AdaptiveDynamicsModel and loaded.adaptation.config() == model.adaptation.config()
    assert all(
        torch.equal(a, b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values(), strict=True)
    )
    with pytest.raises(TypeError, match=r"smcd_rl.save takes an smcd_rl.AdaptiveModel.*torch.save\(net.state_dict"):
        smcd_rl.save(model.net, tmp_path / "net.pt")
    assert not (tmp_path / "net.pt").exists()


def _foreign_files(directory) -> dict[str, tuple[object, str]]:
    """Files a user may pass to smcd_rl.load by mistake: (path, what the error must say about it)."""
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,))
    files = {
        "state_dict": (net.state_dict(), r"a bare state_dict.*net.load_state_dict\(torch.load\(path\)\).*smcd_rl.save"),
        "network": (net, r"holds a MaskedMLP.*smcd_rl.save"),
        "dict": ({"epoch": 3, "loss": 0.1}, r"a dict without a 'format' entry.*smcd_rl.save"),
        "other format": ({"format": "someone.else/1", "x": 1}, r"a file of format 'someone.else/1'.*smcd_rl.save"),
    }
    paths = {}
    for name, (obj, pattern) in files.items():
        path = directory / f"{name.replace(' ', '_')}.pt"
        torch.save(obj, path)
        paths[name] = (path, pattern)
    (directory / "notes.txt").write_text("not a torch file at all\n")
    paths["text"] = (directory / "notes.txt", r"not a file torch.save wrote.*smcd_rl.save")
    import numpy as np

    np.savez(directory / "arrays.npz", x=np.zeros(3))
    paths["npz"] = (directory / "arrays.npz", r"not a file torch.save wrote.*smcd_rl.save")
    import pickle

    (directory / "pickled.pkl").write_bytes(pickle.dumps(net))  # pickle.dump, not torch.save
    paths["pickle"] = (directory / "pickled.pkl", r"a pickle that torch.save did not write.*smcd_rl.save")
    return paths


def test_loading_a_file_that_is_not_a_model_checkpoint_says_so_and_how_to_load_it(tmp_path) -> None:
    """A user's own torch.save(net.state_dict()) file used to get the advice for a damaged cache
    file: "delete it and rerun the command that wrote it"."""
    for name, (path, pattern) in _foreign_files(tmp_path).items():
        with pytest.raises(ValueError) as caught:
            smcd_rl.load(path)
        message = str(caught.value)
        assert str(path) in message and "is not an smcd-rl model checkpoint" in message, (name, message)
        assert "delete" not in message and "corrupt" not in message, (name, message)
        assert __import__("re").search(pattern, message), (name, message)
    # A checkpoint of ours that is damaged keeps the advice for a damaged checkpoint.
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    smcd_rl.save(model, tmp_path / "m.pt")
    data = (tmp_path / "m.pt").read_bytes()
    (tmp_path / "m.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(smcd_rl.UnreadableFileError, match="corrupt or truncated.*save the model again"):
        smcd_rl.load(tmp_path / "m.pt")


def test_a_float64_network_makes_a_float64_model_without_a_cast() -> None:
    net = smcd_rl.MaskedMLP(2, 2, hidden=(16,)).double()  # before: float32 normalisers, torch's dtype error
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(num_particles=20))
    model.fitted = True
    model.reset()
    td = TensorDict({"q": torch.randn(2, dtype=torch.float64), "ee": torch.randn(2, dtype=torch.float64)}, [])
    model.observe(td)
    assert model(td.clone())["ee"].dtype == torch.float64 == model.input_norm.mean.dtype


def _scaled_model(adaptation: smcd_rl.Adaptation) -> smcd_rl.AdaptiveModel:
    """A random network whose outputs are de-normalised by std (2, 0.5) and mean (1, -1)."""
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8, 8)), in_keys=["q"], out_key="ee")
    model.output_norm.std.copy_(torch.tensor([2.0, 0.5]))
    model.output_norm.mean.copy_(torch.tensor([1.0, -1.0]))
    model.fitted = True  # a random network on purpose
    return model.with_adaptation(adaptation)


def _weigh(model: smcd_rl.AdaptiveModel, weights: list[float]) -> None:
    """Give every row of the filter these particle weights (zeros as -inf log weights)."""
    filt = model.adaptation.filter
    row = torch.tensor(weights).log()
    filt.log_weights = row.expand_as(filt.log_weights).clone()


def test_particle_weights_are_the_filters_normalised_weights(two_link_model: smcd_rl.AdaptiveModel) -> None:
    never_resampled = smcd_rl.SMCD(num_particles=32, noise_std=0.2, ess_threshold=0.0)  # else uniform again
    model = two_link_model.with_adaptation(never_resampled)
    model.reset(batch_shape=(2,))
    assert torch.allclose(model.particle_weights, torch.full((2, 32), 1 / 32))  # uniform before any observation
    q, ee = _stream(torch.tensor([[0.6, 0.6], [1.5, 1.4]]), 1, seed=4)
    model.observe(TensorDict({"q": q[0], "ee": ee[0]}, [2]))
    weights = model.particle_weights
    assert weights.shape == (2, 32) and torch.allclose(weights.sum(-1), torch.ones(2))
    assert torch.equal(weights, model.adaptation.filter.weights) and weights.std() > 0
    weights.fill_(0.0)  # a copy: the filter keeps its weights
    assert torch.allclose(model.particle_weights.sum(-1), torch.ones(2))


def test_particle_weights_and_predictive_say_what_is_missing() -> None:
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,))
    td = TensorDict({"q": torch.zeros(2)}, [])
    plain = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    plain.fitted = True
    plain.reset()
    for call in (lambda: plain.particle_weights, lambda: plain.predictive(td)):
        with pytest.raises(TypeError, match=r"needs an SMCD strategy.*NoAdaptation.*with_adaptation\(smcd_rl.SMCD"):
            call()
    unreset = plain.with_adaptation(smcd_rl.SMCD(num_particles=8))
    for call in (lambda: unreset.particle_weights, lambda: unreset.predictive(td)):
        with pytest.raises(RuntimeError, match=r"call model.reset\(\)"):
            call()


def test_predictive_mean_and_variance_in_the_targets_units() -> None:
    """Variance = weighted spread of the particles' predictions + noise_std**2, both in the target's
    units (the outputs are de-normalised by std (2, 0.5), so a slip in units shows by 4x or 1/4)."""
    noise = torch.tensor([0.1, 0.2])
    model = _scaled_model(smcd_rl.SMCD(num_particles=16, noise_std=noise.tolist(), prediction="predictive"))
    model.reset(batch_shape=(2,))
    td = TensorDict({"q": torch.tensor([[0.5, -1.0], [1.5, 0.3]])}, [2])
    mean, variance = model.predictive(td)
    assert mean.shape == variance.shape == (2, 2)
    assert torch.allclose(mean, model(td.clone())["ee"], atol=1e-6)  # forward's prediction="predictive"
    particles = model.predict_particles(td)  # [2, 16, 2], target units
    weights = model.particle_weights.unsqueeze(-1)
    spread = (weights * (particles - mean.unsqueeze(-2)).square()).sum(-2)
    assert torch.allclose(variance, spread + noise.square(), rtol=1e-5)

    _weigh(model, [0.0] * 5 + [1.0] + [0.0] * 10)  # all weight on particle 5
    mean, variance = model.predictive(td)
    assert torch.allclose(mean, particles[:, 5], atol=1e-6)
    assert torch.allclose(mean, model(td.clone(), mask=model.particles[:, 5])["ee"], atol=1e-5)
    assert torch.allclose(variance, noise.square().expand(2, 2), rtol=1e-5)

    filt = model.adaptation.filter
    opposite = filt.particles.clone()
    opposite[:, 1] = ~opposite[:, 0]  # two particles that surely predict differently
    filt.particles = opposite
    _weigh(model, [0.5, 0.5] + [0.0] * 14)
    a, b = model.predict_particles(td)[:, 0], model.predict_particles(td)[:, 1]
    assert (a - b).abs().min() > 1e-3
    mean, variance = model.predictive(td)
    assert torch.allclose(mean, (a + b) / 2, atol=1e-6)
    assert torch.allclose(variance, ((a - b) / 2).square() + noise.square(), rtol=1e-5, atol=1e-7)

    candidates = TensorDict({"q": td["q"].unsqueeze(1).expand(2, 3, 2)}, [2, 3])  # extra dims broadcast
    extra_mean, extra_variance = model.predictive(candidates)
    assert extra_mean.shape == (2, 3, 2) and torch.allclose(extra_mean, mean.unsqueeze(1).expand(2, 3, 2))
    assert torch.allclose(extra_variance, variance.unsqueeze(1).expand(2, 3, 2))


def test_predictive_noise_of_a_student_t_likelihood_and_of_a_dynamics_model() -> None:
    """The Student-t of scale s and dof v has variance s**2 v / (v - 2) (none for v <= 2); a dynamics
    model's mean is the observation plus the mean change, its variance that of the change."""
    model = _scaled_model(smcd_rl.SMCD(num_particles=8, noise_std=0.1, likelihood="student-t", dof=4.0))
    model.reset()
    _weigh(model, [1.0] + [0.0] * 7)
    td = TensorDict({"q": torch.tensor([0.2, 0.4])}, [])
    assert torch.allclose(model.predictive(td)[1], torch.full((2,), 0.1**2 * 4 / 2), rtol=1e-5)
    heavy = model.with_adaptation(smcd_rl.SMCD(num_particles=8, noise_std=0.1, likelihood="student-t", dof=2.0))
    heavy.reset()
    assert torch.isinf(heavy.predictive(td)[1]).all()

    torch.manual_seed(0)
    dynamics = smcd_rl.AdaptiveDynamicsModel(
        smcd_rl.MaskedMLP(3 + 1, 3, hidden=(8,)), adaptation=smcd_rl.SMCD(num_particles=8, noise_std=0.3)
    )
    dynamics.fitted = True
    dynamics.reset()
    _weigh(dynamics, [1.0] + [0.0] * 7)
    state = TensorDict({"observation": torch.tensor([1.0, 2.0, 3.0]), "action": torch.tensor([0.5])}, [])
    mean, variance = dynamics.predictive(state)
    expected = dynamics(state.clone(), mask=dynamics.particles[0])["next", "observation"]
    assert torch.allclose(mean, expected, atol=1e-5) and torch.allclose(variance, torch.full((3,), 0.09), rtol=1e-5)


def test_tuning_is_saved_and_loaded_like_the_calibration(tmp_path) -> None:
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    assert model.tuning is None
    tuning = {"tuned": {"gd_lr": 0.01, "noise_std": [0.1, 0.2]}, "episodes": 8, "ok": True, "note": None}
    model.tuning = tuning
    tuning["episodes"] = 9  # the model kept a copy
    model.tuning["episodes"] = 10  # and gives one
    assert model.tuning["episodes"] == 8
    assert model.with_adaptation(smcd_rl.SMCD(num_particles=4)).tuning == model.tuning  # shared like calibration
    model.save(tmp_path / "m.pt")
    expected = {"tuned": {"gd_lr": 0.01, "noise_std": [0.1, 0.2]}, "episodes": 8, "ok": True, "note": None}
    assert smcd_rl.load(tmp_path / "m.pt").tuning == expected
    other = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    other.load_checkpoint(tmp_path / "m.pt")
    assert other.tuning == expected
    # A file written before the tuning was recorded loads without one.
    old = model.checkpoint()
    del old["tuning"]
    from smcd_rl.files import save_file

    save_file(old, tmp_path / "old.pt", what="model checkpoint")
    assert smcd_rl.load(tmp_path / "old.pt").tuning is None
    other.load_checkpoint(old)
    assert other.tuning is None
    with pytest.raises(smcd_rl.CheckpointMismatchError, match="tuning"):
        other.load_checkpoint({**model.checkpoint(), "tuning": ["not", "a", "dict"]})
    assert other.tuning is None  # the refused checkpoint changed nothing


def test_a_tuning_that_is_not_a_json_dict_is_refused_and_the_old_one_kept() -> None:
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    model.tuning = {"lr": 0.1}
    bad = {
        "a list": ([("lr", 0.1)], r"tuning must be a dict.*got list"),
        "a tensor inside": ({"lr": torch.tensor(0.1)}, r"tuning\['lr'\] is a Tensor.*tensor.tolist\(\)"),
        "a key that is no string": ({"grid": [{1: 0.5}]}, r"tuning\['grid'\]\[0\] has the key 1"),
    }
    for name, (value, pattern) in bad.items():
        with pytest.raises(TypeError, match=pattern):
            model.tuning = value
        assert model.tuning == {"lr": 0.1}, name
    model.tuning = None
    assert model.tuning is None


def test_a_float64_model_loads_as_float64(tmp_path) -> None:
    """The saved architecture names no dtype; the weights carry it, so loading keeps a float64 model float64."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(8,), dtype=torch.float64)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    model.fitted = True
    model.save(tmp_path / "m.pt")
    loaded = smcd_rl.load(tmp_path / "m.pt")
    assert {v.dtype for v in loaded.state_dict().values() if v.is_floating_point()} == {torch.float64}
    assert all(
        torch.equal(a, b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values(), strict=True)
    )
    q = torch.rand(3, 2, dtype=torch.float64)
    loaded.reset()
    model.reset()
    assert torch.equal(loaded.predict(q), model.predict(q))


def test_the_predictive_mean_refuses_inputs_that_do_not_start_with_the_batch_shape() -> None:
    """With ``prediction="predictive"`` the batch was never checked: on a batch of (2, 3), inputs
    [3, 2, 4, 2] gave a [2, 3, 4, 2] prediction with the streams mixed up, and [1, 6, 2] on a batch
    of (6,) a raw RuntimeError. The MMSE mask's prediction refused both."""
    for prediction in ("mask", "predictive"):
        smcd = smcd_rl.SMCD(num_particles=8, noise_std=0.1, prediction=prediction)
        model = smcd_rl.AdaptiveModel(
            smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee", adaptation=smcd
        )
        model.fitted = True
        for batch, inputs in (((2, 3), torch.rand(3, 2, 4, 2)), ((6,), torch.rand(1, 6, 2))):
            model.reset(batch_shape=batch)
            with pytest.raises(ValueError, match="do not start with the model's batch shape"):
                smcd.predict(inputs)
        assert smcd.predict(torch.rand(6, 4, 2)).shape == (6, 4, 2)  # extra dims after the batch are fine


def test_a_cast_to_a_complex_or_integer_dtype_is_refused_and_changes_nothing() -> None:
    """torch casts only the floating tensors: a complex model was accepted and no forward ran after."""
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    for dtype in (torch.complex64, torch.int64):
        with pytest.raises(ValueError, match=f"model.to\\({dtype}\\): the network computes in a real floating dtype"):
            model.to(dtype)
    assert model.net.readout_layer.weight.dtype == torch.float32
    for dtype in (torch.int64, torch.complex64, "float32"):
        with pytest.raises(TypeError, match="dtype must be a real floating torch dtype"):
            smcd_rl.MaskedMLP(2, 2, hidden=(8,), dtype=dtype)  # type: ignore[arg-type]


def test_particles_of_a_strategy_without_them_says_which_to_use() -> None:
    """An AttributeError raised in the property was swallowed by nn.Module, which reported a missing attribute."""
    model = smcd_rl.AdaptiveModel(
        smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee", adaptation=smcd_rl.NoAdaptation()
    )
    model.fitted = True
    model.reset()
    with pytest.raises(TypeError, match="NoAdaptation keeps no mask particles; use smcd_rl.SMCD"):
        _ = model.particles


def test_a_checkpoint_whose_keys_are_not_a_record_is_unreadable_not_a_raw_error(tmp_path) -> None:
    """Its keys "q" reached the model's constructor: "string indices must be integers"."""
    path = tmp_path / "m.pt"
    smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee").save(path)
    checkpoint = torch.load(path, weights_only=False)
    checkpoint["keys"] = "q"
    torch.save(checkpoint, path)
    with pytest.raises(smcd_rl.files.UnreadableFileError, match="holds a configuration this version of smcd_rl cannot"):
        smcd_rl.load(path)


def test_a_dynamics_model_checks_its_keys_and_flags() -> None:
    """observation_key=5 met "Value after * must be an iterable, not int"."""
    net = smcd_rl.MaskedMLP(4, 3, hidden=(8,))
    for options, error, message in (
        ({"observation_key": 5}, TypeError, "observation_key must be a key"),
        ({"action_key": ""}, TypeError, "action_key must be a key"),
        ({"predict_delta": "yes"}, TypeError, "predict_delta must be True or False"),
    ):
        with pytest.raises(error, match=message):
            smcd_rl.AdaptiveDynamicsModel(net, **options)
