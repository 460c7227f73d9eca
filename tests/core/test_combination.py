"""Combination: exponential weights over strategies follow the best one, within the regret bound, and switch."""

import math

import pytest
import torch
from tensordict import TensorDict
from torch import Tensor

import smcd_rl


class Constant(smcd_rl.NoAdaptation):
    """A member that predicts ``value`` whatever the input: its error on a stream is known exactly."""

    name = "constant"

    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = value

    def predict(self, inputs: Tensor) -> Tensor:
        return inputs.new_full((*inputs.shape[:-1], self.net.out_features), self.value)


def _bound(combination: smcd_rl.Combination) -> smcd_rl.Combination:
    """``combination`` attached to a one-output network in identity units, reset with batch ``()``."""
    net = smcd_rl.MaskedMLP(1, 1, hidden=(4,), dtype=torch.float64)
    combination.bind(net, torch.ones(1, dtype=torch.float64))
    combination.reset(())
    return combination


def _model(seed: int = 0) -> smcd_rl.AdaptiveDynamicsModel:
    torch.manual_seed(seed)
    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(32, 32)))
    model.fitted = True  # a random network on purpose: the task is defined from its predictions
    return model


def _shifted_stream(model: smcd_rl.AdaptiveModel, steps: int, batch: tuple[int, ...], seed: int) -> list[TensorDict]:
    """Transitions whose next observation is the frozen network's prediction plus 1.0 in every dimension."""
    g = torch.Generator().manual_seed(seed)
    frozen = model.with_adaptation(smcd_rl.NoAdaptation())
    frozen.reset(batch_shape=batch)
    stream = []
    for _ in range(steps):
        obs, action = torch.randn(*batch, 3, generator=g), torch.randn(*batch, 1, generator=g)
        with torch.no_grad():
            target = frozen.step(obs, action) + 1.0
        stream.append(TensorDict({"observation": obs, "action": action, ("next", "observation"): target}, batch))
    return stream


def _smcd(seed: int) -> smcd_rl.SMCD:
    return smcd_rl.SMCD(num_particles=50, noise_std=0.5, generator=torch.Generator().manual_seed(seed))


def test_the_weight_concentrates_on_the_member_that_predicts_best() -> None:
    """On a task the frozen network misses by a constant shift, gradient descent learns it and takes the weight."""
    model = _model()
    eta = 1.0
    combination = smcd_rl.Combination([smcd_rl.NoAdaptation(), smcd_rl.GradientDescent(lr=0.1, steps=3)], eta=eta)
    adaptive = model.with_adaptation(combination)
    adaptive.reset()
    for td in _shifted_stream(model, 20, (), seed=1):
        adaptive.observe(td)
    losses, weights = combination.losses, combination.weights
    # share=0: the weights are exactly the exponential weights of the cumulative losses.
    torch.testing.assert_close(weights, torch.softmax(-eta * losses, -1))
    # The frozen network loses 3 (a shift of 1 in 3 outputs) every step. A weight of 0.99 from the
    # uniform 0.5 needs L_none - L_gd > ln(99) / eta = 4.6: gradient descent must beat it by more than
    # one and a half steps' worth of its loss, which only a member that adapts does; the stream and
    # the network are seeded, nothing else is random.
    assert torch.allclose(losses[0], torch.tensor(20 * 3.0), rtol=1e-4), losses
    assert weights[1] > 0.99, weights


def test_the_combined_loss_stays_within_the_exponential_weights_regret_bound() -> None:
    """Squared losses in [0, B]: L_combined(t) <= min_i L_i(t) + ln(K) / eta + eta t B^2 / 8 at every t.

    Exponential weights (share=0) guarantee it for the weighted mean of the members' losses by
    Hoeffding's lemma (Cesa-Bianchi and Lugosi 2006, thm 2.2), for any sequence; the combined
    prediction's squared loss is at most that mean (the loss is convex). So the check is exact:
    it fails only if the weights are wrong, never by chance. Members and targets lie in [0, 1], so
    each loss lies in [0, B = 1].
    """
    members, horizon = (0.1, 0.5, 0.9), 400
    eta = math.sqrt(8 * math.log(len(members)) / horizon)  # the eta that minimises the bound at the horizon
    combination = _bound(smcd_rl.Combination([Constant(c) for c in members], eta=eta))
    targets = 0.3 * torch.rand(horizon, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = torch.zeros(1, dtype=torch.float64)
    combined, best_regret = 0.0, -math.inf
    for t, y in enumerate(targets, start=1):
        combined += float((combination.predict(x) - y).square().sum())
        combination.observe(x, y)
        regret = combined - float(combination.losses.min())
        assert regret <= math.log(len(members)) / eta + eta * t / 8, (t, regret)
        best_regret = max(best_regret, regret)
    # The bound is tight enough to mean something: averaging the members uniformly (predicting 0.5)
    # would lose about (0.5 - 0.15)^2 - (0.1 - 0.15)^2 = 0.12 a step more than the best, 48 over the
    # horizon, three times the bound of 14.8.
    uniform = float((0.5 - targets).square().sum() - (0.1 - targets).square().sum())
    assert uniform > 2 * (math.log(len(members)) / eta + eta * horizon / 8) > 2 * best_regret
    assert combination.weights.argmax() == 0


def test_fixed_share_moves_the_weight_to_the_new_best_member_within_five_steps() -> None:
    """The target jumps from one member's value to the other's after 100 steps."""
    eta, share, switch = 5.0, 0.05, 100
    x = torch.zeros(1, dtype=torch.float64)
    targets = [0.2] * switch + [0.8] * 50
    histories = {}
    for mix in (share, 0.0):
        combination = _bound(smcd_rl.Combination([Constant(0.2), Constant(0.8)], eta=eta, share=mix))
        history = []
        for y in targets:
            combination.observe(x, torch.tensor([y], dtype=torch.float64))
            history.append(float(combination.weights[1]))
        histories[mix] = history
    shared, plain = histories[share], histories[0.0]
    # Fixed share keeps every weight >= share / K = 0.025 (0.030 where the loser settles); after the switch
    # each step multiplies the new best's odds by exp(eta * 0.36) = 6.05 before mixing, so its weight runs
    # 0.030, 0.17, 0.56, 0.86, 0.95: past 0.9 at the 4th step after the switch, and the 5th leaves room
    # for rounding. Nothing is random.
    assert share / 2 <= shared[switch - 1] < 0.05, shared[switch - 1]
    assert shared[switch + 4] > 0.9, shared[switch - 1 : switch + 6]
    # Without share the old best has 100 steps of lead (log odds 180) to lose at 1.8 a step.
    assert plain[switch + 49] < 0.01, plain[switch + 49]


@pytest.mark.parametrize(
    "make", [lambda: smcd_rl.GradientDescent(lr=0.05, steps=2), lambda: _smcd(3)], ids=["gd", "smcd"]
)
def test_one_member_with_share_zero_predicts_exactly_as_that_member(make) -> None:
    """Through the model: TensorDict calls, batched states and planners' extra batch dims."""
    model = _model()
    alone, combined = model.with_adaptation(make()), model.with_adaptation(smcd_rl.Combination([make()], share=0.0))
    g = torch.Generator().manual_seed(4)
    candidates = torch.randn(2, 5, 3, generator=g), torch.randn(2, 5, 1, generator=g)  # [batch, candidates, dim]
    for m in (alone, combined):
        m.reset(batch_shape=(2,))
    for td in _shifted_stream(model, 6, (2,), seed=2):
        for m in (alone, combined):
            m.observe(td.clone())
        assert torch.equal(combined(td.clone())["next", "observation"], alone(td.clone())["next", "observation"])
        assert torch.equal(combined.step(*candidates), alone.step(*candidates))


def test_members_keep_their_own_state_and_the_prediction_is_their_weighted_mean() -> None:
    """Two gradient descents and an SMCD on one network predict as each would on its own model."""
    model = _model()

    def makes() -> list[smcd_rl.Adaptation]:
        return [smcd_rl.GradientDescent(lr=0.1, steps=3), smcd_rl.GradientDescent(lr=0.001), _smcd(5)]

    twins = [model.with_adaptation(m) for m in makes()]
    combination = smcd_rl.Combination(makes(), eta=0.5, share=0.01)
    adaptive = model.with_adaptation(combination)
    for m in (*twins, adaptive):
        m.reset(batch_shape=(3,))
    for td in _shifted_stream(model, 10, (3,), seed=3):
        for m in (*twins, adaptive):
            m.observe(td.clone())
    obs, action = torch.randn(3, 7, 3), torch.randn(3, 7, 1)
    each = torch.stack([twin.step(obs, action) for twin in twins], -1)  # [3, 7, out, K]
    expected = (each * combination.weights.reshape(3, 1, 1, 3)).sum(-1)
    torch.testing.assert_close(adaptive.step(obs, action), expected)
    assert combination.weights[:, 0].min() > combination.weights[:, 1].max()  # the fast learner leads


def test_reset_restores_uniform_weights_for_all_or_only_the_chosen_rows() -> None:
    model = _model()
    combination = smcd_rl.Combination([smcd_rl.NoAdaptation(), smcd_rl.GradientDescent(lr=0.1)], eta=1.0)
    adaptive = model.with_adaptation(combination)
    adaptive.reset(batch_shape=(2,))
    for td in _shifted_stream(model, 5, (2,), seed=4):
        adaptive.observe(td)
    before, obs, action = combination.state_dict(), torch.randn(2, 3), torch.randn(2, 1)
    prediction = adaptive.step(obs, action)
    assert not torch.allclose(combination.weights, torch.full((2, 2), 0.5))
    adaptive.reset(batch_shape=(2,), where=torch.tensor([True, False]))
    assert torch.equal(combination.weights[0], torch.full((2,), 0.5)) and torch.equal(
        combination.losses[0], torch.zeros(2)
    )
    assert torch.equal(combination.losses[1], before["losses"][1])
    assert torch.equal(adaptive.step(obs, action)[1], prediction[1])  # the kept row's members kept their state too
    adaptive.reset(batch_shape=(2,))
    assert torch.equal(combination.weights, torch.full((2, 2), 0.5)) and not combination.losses.any()


def test_a_refused_observation_leaves_every_member_and_the_weights_unchanged() -> None:
    """The second member diverges; the first had adapted already and is put back."""
    model = _model()
    combination = smcd_rl.Combination(
        [smcd_rl.GradientDescent(lr=0.1), smcd_rl.GradientDescent(lr=1e30, steps=3, window=2)]
    )
    adaptive = model.with_adaptation(combination)
    adaptive.reset()
    before = combination.state_dict()
    with pytest.raises(ValueError, match=r"member 1 .* refused the observation, so no member adapted"):
        adaptive.observe(_shifted_stream(model, 1, (), seed=5)[0])
    after = combination.state_dict()
    assert torch.equal(before["log_weights"], after["log_weights"]) and torch.equal(before["losses"], after["losses"])
    for saved, now in zip(before["members"], after["members"], strict=True):
        assert all(torch.equal(saved["params"][k], now["params"][k]) for k in saved["params"])
        assert torch.equal(saved["count"], now["count"])


def test_config_rebuilds_an_unadapted_copy_also_of_a_nested_combination() -> None:
    inner = smcd_rl.Combination([smcd_rl.NoAdaptation(), smcd_rl.SMCD(num_particles=20)], eta=2.0)
    outer = smcd_rl.Combination([smcd_rl.GradientDescent(lr=0.5), inner], share=0.1)
    copy = smcd_rl.Combination(**outer.config())
    assert copy.config() == outer.config() and repr(copy) == repr(outer)
    adaptive = _model().with_adaptation(copy)
    adaptive.reset()
    adaptive.observe(_shifted_stream(adaptive, 1, (), seed=6)[0])
    assert set(copy.summary()) == {
        "weight[0]",
        "weight[1]",
        "weight[0][1]",
        "weight[1][1]",
        "ess[1][1]",
        "log_evidence[1][1]",
    }


def _same() -> list[smcd_rl.Adaptation]:
    member = smcd_rl.NoAdaptation()
    return [member, member]


def _shared_inside() -> list[smcd_rl.Adaptation]:
    member = smcd_rl.NoAdaptation()
    return [member, smcd_rl.Combination([member, smcd_rl.GradientDescent()])]


@pytest.mark.parametrize(
    ("members", "kwargs", "error", "message"),
    [
        (lambda: [], {}, ValueError, "members is empty"),
        (lambda: smcd_rl.NoAdaptation(), {}, TypeError, "wrap a single strategy in a list"),
        (lambda: [smcd_rl.NoAdaptation(), 3], {}, TypeError, r"members\[1\] must be a smcd_rl.Adaptation"),
        (lambda: [smcd_rl.SMCD], {}, TypeError, r"pass an instance, SMCD\(...\), not the class"),
        (lambda: [{"name": "nonsense"}], {}, ValueError, "unknown adaptation 'nonsense'"),
        (_same, {}, ValueError, r"members\[1\] is the same NoAdaptation object as members\[0\]"),
        (_shared_inside, {}, ValueError, r"members\[1\].members\[0\] is the same NoAdaptation object"),
        *[
            (
                lambda: [smcd_rl.NoAdaptation()],
                {"eta": eta},
                ValueError,
                r"eta must be a finite number in \[0, 1e\+100\]",
            )
            for eta in (math.nan, math.inf, -0.5)
        ],
        (
            lambda: [smcd_rl.NoAdaptation()],
            {"eta": 1e101},
            ValueError,
            r"eta must be a finite number in \[0, 1e\+100\]",
        ),
        (lambda: [smcd_rl.NoAdaptation()], {"eta": "1"}, TypeError, "eta must be a real number"),
        *[
            (lambda: [smcd_rl.NoAdaptation()], {"share": share}, ValueError, r"share must be in \[0, 1\)")
            for share in (1.0, -0.1, math.nan)
        ],
    ],
)
def test_bad_arguments_are_refused_with_the_problem_and_the_fix(members, kwargs, error, message) -> None:
    with pytest.raises(error, match=message):
        smcd_rl.Combination(members(), **kwargs)


def test_weights_before_reset_and_unscorable_observations_are_refused() -> None:
    combination = smcd_rl.Combination([smcd_rl.NoAdaptation(), Constant(math.inf)])
    with pytest.raises(RuntimeError, match="call model.reset"):
        combination.weights  # noqa: B018 - the property raises
    _bound(combination)
    x = torch.zeros(1, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"members \[1\] .* predict inf or NaN .* state is unchanged"):
        combination.observe(x, x)
    assert torch.equal(combination.weights, torch.full((2,), 0.5)) and not combination.losses.any()


def test_a_model_saved_with_a_combination_loads_by_name(tmp_path) -> None:
    """smcd_rl.load rebuilds the combination from its config alone, members and weights' settings included."""
    model = _model().with_adaptation(
        smcd_rl.Combination([smcd_rl.NoAdaptation(), smcd_rl.GradientDescent(lr=0.05)], eta=3.0, share=0.01)
    )
    smcd_rl.save(model, tmp_path / "model.pt")
    loaded = smcd_rl.load(tmp_path / "model.pt")
    assert isinstance(loaded.adaptation, smcd_rl.Combination)
    assert loaded.adaptation.config() == model.adaptation.config()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_huge_eta_gives_the_weight_to_the_best_member_instead_of_nan(dtype: torch.dtype) -> None:
    """eta * loss beyond float32's range once made the weights NaN; the limit of a huge eta is all the
    weight on the member with the smallest loss, from the first observation on, and it stays there."""
    net = smcd_rl.MaskedMLP(1, 1, hidden=(4,), dtype=dtype)
    for eta in (1e39, 1e100):
        combination = smcd_rl.Combination([Constant(0.9), Constant(0.2), Constant(0.5)], eta=eta)
        combination.bind(net, torch.ones(1, dtype=dtype))
        combination.reset((2,))
        for target in (0.0, 0.1, 0.6):  # the last target favours another member, whose cumulative loss is larger
            combination.observe(torch.zeros(2, 1, dtype=dtype), torch.full((2, 1), target, dtype=dtype))
            assert torch.equal(combination.weights, torch.tensor([[0.0, 1.0, 0.0]] * 2, dtype=dtype)), eta
        prediction = combination.predict(torch.zeros(2, 1, dtype=dtype))
        assert prediction.dtype == dtype and torch.equal(prediction, torch.full((2, 1), 0.2, dtype=dtype))
