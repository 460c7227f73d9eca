"""The SMCD filter and its resampling: posterior concentration, unbiasedness, flip rates, atomicity."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import smcd_rl
from smcd_rl.filter import flat_particle_index, sample_flip_positions
from smcd_rl.resampling import RESAMPLING_SCHEMES, resample_indices


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_posterior_concentrates_on_the_true_mask() -> None:
    """A network whose correct mask is known: observations come from net(x, mask=m*).

    A single masked hidden layer with a linear read-out of 8 outputs makes each bit identifiable
    from a few random inputs. From a Bernoulli(0.5) prior over 2^12 masks, chance would put the
    MMSE estimate on m* with probability 2^-12; the filter must find it exactly.
    """
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(3, 8, hidden=(12,), dropout=0.5).eval()
    true_mask = torch.rand(12, generator=_gen(1)) < 0.5
    filt = smcd_rl.SMCDFilter(12, num_particles=2000, flip_prob=0.02, keep_prob=0.5, generator=_gen(2))
    filt.reset()
    g = _gen(3)
    for _ in range(40):
        x = torch.randn(3, generator=g)
        z = net(x, mask=true_mask) + 0.01 * torch.randn(8, generator=g)
        with torch.no_grad():
            filt.update(lambda masks, x=x, z=z: -0.5 * ((net.forward_particles(x, masks) - z) / 0.05).square().sum(-1))
    assert torch.equal(filt.mean_mask > 0.5, true_mask)
    assert float((filt.mean_mask - true_mask.float()).abs().max()) < 0.3


@pytest.mark.parametrize("sorted_ancestors", [True, False])
def test_mean_mask_sums_copies_to_the_weighted_mean(sorted_ancestors: bool) -> None:
    """The MMSE mask sums copies of one ancestor first; it must equal the plain weighted mean,
    with weights left non-uniform after resampling and ancestors in any order."""
    filt = smcd_rl.SMCDFilter(16, num_particles=40, generator=_gen(3))
    filt.reset((2,))
    filt.propagate()
    filt.reweight(-((filt.particles.float().sum(-1) - 12) ** 2))  # peaked: few ancestors survive
    ancestors = filt.ancestors
    assert ancestors is not None
    assert 2 * torch.unique(flat_particle_index(ancestors, 40)).numel() <= 80, "the grouped path must run"
    if not sorted_ancestors:
        perm = torch.randperm(40, generator=_gen(4))
        filt.particles = filt.particles[:, perm]
        filt.ancestors = ancestors[:, perm]
    filt.ess_threshold = 0.0  # reweight without resampling: copies keep their ancestors, weights differ
    filt.reweight(torch.randn(2, 40, generator=_gen(5)))
    expected = (filt.weights.unsqueeze(-2) @ filt.particles.float()).squeeze(-2)
    torch.testing.assert_close(filt.mean_mask, expected)


def test_distinct_particles_merge_copies_and_keep_every_weighted_sum() -> None:
    """Copies of one ancestor become one particle with their summed weight, per batch element:
    any weighted sum over the particles (here their bits and a nonlinear function of them) is
    the same, and each merged particle is the particle its member names."""
    filt = smcd_rl.SMCDFilter(16, num_particles=40, generator=_gen(3))
    filt.reset((2,))
    assert filt.distinct() is None  # no resampling yet: copies unknown
    filt.propagate()
    filt.reweight(-((filt.particles.float().sum(-1) - 12) ** 2))  # peaked: few ancestors survive
    filt.ess_threshold = 0.0
    filt.reweight(torch.randn(2, 40, generator=_gen(5)))  # copies keep their ancestors, weights differ
    found = filt.distinct()
    assert found is not None
    particles, weights, streams, members = found
    assert particles.shape[0] <= 40 and weights.shape == streams.shape == members.shape == particles.shape[:1]
    assert torch.equal(filt.particles[streams, members], particles)
    bits = filt.particles.float()
    for f in (lambda b: b, lambda b: b.cumsum(-1).sin()):
        merged = torch.zeros(2, 16).index_add_(0, streams, weights.unsqueeze(-1) * f(particles.float()))
        torch.testing.assert_close(merged, (filt.weights.unsqueeze(-1) * f(bits)).sum(-2))
    assert filt.distinct()[0] is particles  # computed once per filter state


def test_log_evidence_and_weights_match_hand_computation() -> None:
    filt = smcd_rl.SMCDFilter(4, num_particles=3, ess_threshold=0.0, generator=_gen())
    filt.reset()
    ll = torch.tensor([0.0, math.log(2.0), math.log(5.0)])
    filt.reweight(ll)
    assert float(filt.log_evidence) == pytest.approx(math.log((1 + 2 + 5) / 3))
    torch.testing.assert_close(filt.weights, torch.tensor([1 / 8, 2 / 8, 5 / 8]))
    assert float(filt.ess) == pytest.approx(1 / ((1 / 8) ** 2 + (2 / 8) ** 2 + (5 / 8) ** 2))
    expected = (torch.tensor([1.0, 2.0, 5.0]) / 8) @ filt.particles.float()
    torch.testing.assert_close(filt.mean_mask, expected)


@settings(max_examples=50, deadline=None)
@given(
    n=st.integers(1, 64),
    scale=st.floats(0.0, 200.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_ess_stays_between_one_and_n(n: int, scale: float, seed: int) -> None:
    filt = smcd_rl.SMCDFilter(5, num_particles=n, ess_threshold=0.0, generator=_gen(seed))
    filt.reset(batch_shape=(2,))
    filt.reweight(scale * torch.randn(2, n, generator=_gen(seed + 1)))
    ess = filt.ess
    assert bool((ess >= 1 - 1e-4).all()) and bool((ess <= n + 1e-3).all())


@pytest.mark.parametrize("scheme", RESAMPLING_SCHEMES)
def test_resampling_is_unbiased(scheme: str) -> None:
    """Offspring counts average N * w_i over many draws.

    Each particle's count has variance at most N w (1 - w) (multinomial; the others are lower),
    so over R independent draws the mean is within 5 standard errors with probability > 1 - 1e-5
    per particle.
    """
    n, draws = 10, 20_000
    weights = torch.rand(n, generator=_gen(5)) ** 3
    weights = weights / weights.sum()
    idx = resample_indices(weights.log().expand(draws, n), scheme, generator=_gen(6))
    counts = torch.zeros(draws, n).scatter_add_(1, idx, torch.ones(draws, n)).mean(0)
    expected = n * weights
    tolerance = 5 * torch.sqrt(n * weights * (1 - weights) / draws) + 1e-6
    assert bool(((counts - expected).abs() <= tolerance).all()), (counts, expected)
    assert bool((idx[:, 1:] >= idx[:, :-1]).all()), "ancestors come out sorted"


def test_systematic_resampling_of_uniform_weights_keeps_every_particle() -> None:
    idx = resample_indices(torch.zeros(7), "systematic", generator=_gen())
    assert idx.tolist() == list(range(7))


def test_flip_positions_have_the_bernoulli_rate_and_spread() -> None:
    """Sparse sampling (geometric gaps) must match i.i.d. Bernoulli(p) bits.

    Count over 4e6 bits at p = 0.01: mean 4e4, std ~200, tolerance 5 std. Per-row counts of 1000
    rows of 4000 bits are Binomial(4000, p): variance 39.6; the sample variance of 1000 rows has a
    relative std of ~4.5%, tolerance 20%.
    """
    rows, cols, p = 1000, 4000, 0.01
    pos = sample_flip_positions(rows * cols, p, generator=_gen(7))
    assert bool((pos[1:] > pos[:-1]).all()) and int(pos.min()) >= 0 and int(pos.max()) < rows * cols
    mean = rows * cols * p
    assert abs(pos.numel() - mean) < 5 * math.sqrt(mean * (1 - p))
    per_row = torch.bincount(pos // cols, minlength=rows).float()
    assert float(per_row.var()) == pytest.approx(cols * p * (1 - p), rel=0.2)
    per_col = torch.bincount(pos % cols, minlength=cols).float()  # positions are uniform
    assert float(per_col.mean()) == pytest.approx(rows * p, rel=0.05)
    assert float(per_col.var()) == pytest.approx(rows * p * (1 - p), rel=0.2)


@pytest.mark.parametrize("numel", [1, 37, 500, 100_000])
def test_flip_positions_are_the_textbook_geometric_gaps(numel: int) -> None:
    """The in-place sampler draws exactly what floor(log(1 - u) / log(1 - p)) gaps give.

    Pins the random stream: every seeded SMCD result depends on it. Small ``numel`` needs several
    chunks of gaps before one passes the end.
    """
    p = 0.01
    for seed in range(20):
        generator = _gen(seed)
        expected: list[int] = []
        position = -1
        while True:
            u = torch.rand(int(numel * p + 6 * math.sqrt(numel * p) + 16), generator=generator, dtype=torch.float64)
            for gap in torch.floor(torch.log(1.0 - u) / math.log1p(-p)).clamp(max=numel).long().tolist():
                position += gap + 1
                if position >= numel:
                    break
                expected.append(position)
            if position >= numel:
                break
        assert sample_flip_positions(numel, p, generator=_gen(seed)).tolist() == expected


@pytest.mark.parametrize("p", [0.001, 0.02, 0.2])
def test_propagate_flips_bits_at_flip_prob(p: float) -> None:
    filt = smcd_rl.SMCDFilter(256, num_particles=500, flip_prob=p, generator=_gen(8))
    filt.reset()
    before = filt.particles.clone()
    filt.propagate()
    flipped = (before ^ filt.particles).float()
    n = flipped.numel()
    assert abs(float(flipped.sum()) - n * p) < 5 * math.sqrt(n * p * (1 - p))


def test_keep_rate_transition_keeps_the_training_distribution() -> None:
    """With dropout 0.1 the masks must stay 90% kept; symmetric flips drift them towards 50%.

    Expected kept share after t symmetric steps: 0.5 + 0.4 (1 - 2d)^t = 0.501 at t = 300; over
    51,200 bits the keep_rate share has a standard error of about 0.0013, so 0.88-0.92 cannot be
    hit by a drifting chain and cannot be missed by a stationary one.
    """
    shares = {}
    for transition in ("keep_rate", "symmetric"):
        filt = smcd_rl.SMCDFilter(
            256, num_particles=200, flip_prob=0.01, keep_prob=0.9, transition=transition, generator=_gen(4)
        )
        filt.reset()
        for _ in range(300):
            filt.propagate()
        shares[transition] = float(filt.particles.float().mean())
    assert 0.88 < shares["keep_rate"] < 0.92
    assert abs(shares["symmetric"] - 0.5) < 0.02


def test_keep_rate_flips_each_bit_at_its_own_rate() -> None:
    filt = smcd_rl.SMCDFilter(512, num_particles=1000, flip_prob=0.01, keep_prob=0.9, generator=_gen(5))
    assert filt.flip_rates() == pytest.approx((0.002, 0.018))
    filt.reset()
    before = filt.particles.clone()
    filt.propagate()
    flipped = before ^ filt.particles
    for was, rate in ((True, 0.002), (False, 0.018)):
        n = int((before == was).sum())
        count = float((flipped & (before == was)).sum())
        assert abs(count - n * rate) < 5 * math.sqrt(n * rate * (1 - rate)), (was, count / n)
    assert torch.equal(filt.last_flips, flipped.reshape(-1).nonzero().squeeze(-1))


def test_keep_rate_is_the_papers_xor_at_half_dropout() -> None:
    particles = {}
    for transition in ("keep_rate", "symmetric"):
        filt = smcd_rl.SMCDFilter(
            64, num_particles=50, flip_prob=0.03, keep_prob=0.5, transition=transition, generator=_gen(6)
        )
        filt.reset()
        for _ in range(5):
            filt.propagate()
        particles[transition] = filt.particles
    assert torch.equal(particles["keep_rate"], particles["symmetric"])
    with pytest.raises(ValueError, match="too large for the keep_rate transition"):
        smcd_rl.SMCDFilter(8, flip_prob=0.6, keep_prob=0.9)


def test_initial_masks_follow_keep_prob() -> None:
    filt = smcd_rl.SMCDFilter(100, num_particles=1000, keep_prob=0.8, generator=_gen())
    filt.reset(batch_shape=(2,))
    assert filt.particles.shape == (2, 1000, 100) and filt.particles.dtype == torch.bool
    assert float(filt.particles.float().mean()) == pytest.approx(0.8, abs=0.005)


def test_resize_keeps_the_weighted_distribution() -> None:
    filt = smcd_rl.SMCDFilter(3, num_particles=4, ess_threshold=0.0, generator=_gen())
    filt.reset()
    filt.particles = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=torch.bool)
    filt.reweight(torch.log(torch.tensor([0.5, 0.25, 0.25, 0.0])))
    before = filt.mean_mask.clone()
    filt.resize(4000)
    assert filt.particles.shape == (4000, 3) and filt.num_particles == 4000
    torch.testing.assert_close(filt.mean_mask, before, atol=0.01, rtol=0)
    filt.resize(1)
    assert filt.particles.shape == (1, 3)


def test_each_batch_element_resamples_only_when_its_ess_is_low() -> None:
    filt = smcd_rl.SMCDFilter(6, num_particles=8, ess_threshold=0.5, generator=_gen())
    filt.reset(batch_shape=(2,))
    before = filt.particles.clone()
    ll = torch.zeros(2, 8)
    ll[1, 0] = 50.0  # element 1 collapses onto particle 0; element 0 stays uniform
    filt.reweight(ll)
    assert torch.equal(filt.particles[0], before[0])
    assert bool((filt.particles[1] == before[1, 0]).all())
    torch.testing.assert_close(filt.weights, torch.full((2, 8), 1 / 8))


def test_rejected_updates_change_nothing() -> None:
    filt = smcd_rl.SMCDFilter(10, num_particles=20, generator=_gen())
    filt.reset(batch_shape=(3,))
    filt.update(lambda m: torch.zeros(3, 20))
    state = filt.state_dict()
    bad = [
        torch.zeros(3, 19),
        torch.full((3, 20), float("nan")),
        torch.full((3, 20), float("inf")),
        torch.full((3, 20), -float("inf")),
    ]
    for ll in bad:
        with pytest.raises(ValueError):
            filt.reweight(ll)
        with pytest.raises(ValueError):
            filt.update(lambda m, ll=ll: ll)
    with pytest.raises(RuntimeError, match="boom"):
        filt.update(lambda m: (_ for _ in ()).throw(RuntimeError("boom")))
    after = filt.state_dict()
    for key in ("particles", "log_weights", "log_evidence", "generator"):
        assert torch.equal(state[key], after[key]), key


def test_errors_name_the_problem() -> None:
    with pytest.raises(ValueError, match="systematic"):
        smcd_rl.SMCDFilter(4, resampling="bogus")
    with pytest.raises(ValueError, match=r"\[\*batch, N\] = \[5\]"):
        filt = smcd_rl.SMCDFilter(4, num_particles=5)
        filt.reset()
        filt.reweight(torch.zeros(4))
    with pytest.raises(RuntimeError, match="reset"):
        smcd_rl.SMCDFilter(4).propagate()


def test_seeded_runs_repeat() -> None:
    def run() -> torch.Tensor:
        filt = smcd_rl.SMCDFilter(16, num_particles=50, generator=_gen(3))
        filt.reset()
        for _ in range(5):
            filt.update(lambda m: -m.float().sum(-1))
        return filt.particles

    assert torch.equal(run(), run())


def test_last_ess_is_measured_before_resampling() -> None:
    filt = smcd_rl.SMCDFilter(4, num_particles=10, ess_threshold=1.0, generator=_gen())
    filt.reset()
    ll = torch.full((10,), -50.0)
    ll[0] = 0.0
    filt.reweight(ll)
    assert float(filt.ess) == pytest.approx(10.0)  # resampled: uniform weights again
    assert float(filt.last_ess) == pytest.approx(1.0, abs=1e-6)  # what the observation did


def test_restore_rows_puts_back_only_the_chosen_batch_elements() -> None:
    filt = smcd_rl.SMCDFilter(6, num_particles=8, generator=_gen())
    filt.reset(batch_shape=(3,))
    filt.update(lambda m: -m.float().sum(-1))
    saved = filt.state_dict()
    filt.reset(batch_shape=(3,))
    fresh = filt.state_dict()
    filt.restore_rows(saved, torch.tensor([True, False, True]))
    for key in ("particles", "log_weights", "log_evidence", "last_ess"):
        for row, source in ((0, saved), (1, fresh), (2, saved)):
            assert torch.equal(filt.state_dict()[key][row], source[key][row]), (key, row)
    assert torch.equal(filt.state_dict()["generator"], fresh["generator"])  # the generator is not restored


def test_a_log_likelihood_that_overflows_the_weights_dtype_is_refused_and_changes_nothing() -> None:
    """float64 log-likelihoods of -1e40 are finite, but -inf in the float32 weights: the finiteness
    check ran before the cast, so -inf - (-inf) left the weights, ESS and log evidence NaN."""
    filt = smcd_rl.SMCDFilter(10, num_particles=20, generator=_gen())
    filt.reset(batch_shape=(2,))
    filt.update(lambda m: torch.zeros(2, 20))
    state = filt.state_dict()
    overflow = torch.full((2, 20), -1e40, dtype=torch.float64)
    overflow[0] = 0.0  # one batch element is fine: the update is still refused as a whole
    with pytest.raises(ValueError, match="impossible"):
        filt.reweight(overflow)
    with pytest.raises(ValueError, match="impossible"):
        filt.update(lambda m: overflow)
    after = filt.state_dict()
    for key in ("particles", "log_weights", "log_evidence", "last_ess", "generator"):
        assert torch.equal(state[key], after[key]), key
    # Particles whose likelihood overflows alone just get weight 0, as they would in float32.
    some = torch.zeros(2, 20, dtype=torch.float64)
    some[:, 1:] = -1e40
    filt.reweight(some)
    assert torch.isfinite(filt.log_evidence).all() and torch.isfinite(filt.last_ess).all()
    assert not torch.isnan(filt.log_weights).any() and torch.isfinite(filt.mean_mask).all()


def test_a_refused_reweighting_leaves_float64_weights_unchanged() -> None:
    """The reweighting works on a float64 copy of the weights in place: where the weights are
    float64 already the copy must still be made, or a refused step leaves them rewritten."""
    filt = smcd_rl.SMCDFilter(3, num_particles=2, generator=_gen())
    filt.reset(batch_shape=(1,))
    state = filt.state_dict()
    filt.load_state_dict({**state, "log_weights": torch.tensor([[0.0, -math.inf]], dtype=torch.float64)})
    with pytest.raises(ValueError, match="zero likelihood"):  # the only weighted particle is impossible
        filt.reweight(torch.tensor([[-math.inf, 0.0]], dtype=torch.float64))
    assert torch.equal(filt.log_weights, torch.tensor([[0.0, -math.inf]], dtype=torch.float64))


def test_restoring_a_snapshot_puts_back_every_part_of_the_state() -> None:
    """A snapshot holds references: it restores the state exactly as state_dict would, generator,
    ancestors and MMSE mask included, after steps that replaced every one of them."""
    filt = smcd_rl.SMCDFilter(6, num_particles=20, generator=_gen())
    filt.reset(batch_shape=(2,))
    filt.update(lambda m: -m.sum(-1).float())
    saved, snapshot = filt.state_dict(), filt.snapshot()
    for _ in range(3):
        filt.update(lambda m: -(m.sum(-1).float() - 3).square())
    filt.restore(snapshot)
    restored = filt.state_dict()
    assert saved.keys() == restored.keys()
    for key, value in saved.items():
        assert (value is None and restored[key] is None) or torch.equal(value, restored[key]), key


def test_a_log_evidence_that_would_overflow_is_refused_and_changes_nothing() -> None:
    """Each likelihood fits float32, but their sum over steps does not: the evidence would be -inf."""
    filt = smcd_rl.SMCDFilter(10, num_particles=20, generator=_gen())
    filt.reset()
    filt.reweight(torch.full((20,), -3e38))
    state = filt.state_dict()
    with pytest.raises(ValueError, match="log evidence.*reset"):
        filt.reweight(torch.full((20,), -3e38))
    with pytest.raises(ValueError, match="log evidence.*reset"):
        filt.update(lambda m: torch.full((20,), -3e38))
    after = filt.state_dict()
    for key in ("particles", "log_weights", "log_evidence", "last_ess", "generator"):
        assert torch.equal(state[key], after[key]), key
    assert torch.isfinite(filt.log_evidence).all()


def _resampled_state(batch: tuple[int, ...] = (2,)) -> tuple[smcd_rl.SMCDFilter, dict]:
    """A filter whose last update resampled, so that its state names ancestors (copies)."""
    filt = smcd_rl.SMCDFilter(4, num_particles=8, generator=_gen())
    filt.reset(batch_shape=batch)
    filt.update(lambda m: -10.0 * (m.sum(-1).float() - 4).square())
    assert filt.ancestors is not None
    return filt, filt.state_dict()


def _edited(state: dict, **changes: object) -> dict:
    return {**state, **changes}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        # Each was once taken as it was: a state that would go on as wrong numbers, or fail later.
        (lambda s: _edited(s, last_ess=[1.0, 1.0]), r"last_ess is list"),  # once half-loaded, then AttributeError
        (lambda s: _edited(s, ancestors=torch.zeros(2, 8, dtype=torch.long)), "ancestors call particles copies"),
        (lambda s: _edited(s, ancestors=torch.full((2, 8), 99)), r"particle indices in \[0, 8\)"),
        (lambda s: _edited(s, mean_mask=torch.full((2, 4), 7.0)), r"values outside \[0, 1\]"),
        (lambda s: _edited(s, log_weights=torch.zeros(2, 8)), "weights sum to 8, not 1"),
        (lambda s: _edited(s, log_weights=s["log_weights"].long()), "must be float tensors"),
        (lambda s: _edited(s, particles=s["particles"].float()), "particles are torch.float32"),
        (lambda s: _edited(s, log_evidence=torch.full((2,), math.nan)), "log evidence is NaN"),
        (lambda s: _edited(s, last_ess=torch.ones(3)), r"last_ess is \[3\]"),
        (lambda s: _edited(s, last_flips=torch.tensor([10_000])), "last_flips are not positions"),
    ],
)
def test_a_state_that_is_not_one_a_filter_could_be_in_is_refused_and_changes_nothing(edit, message) -> None:
    target, _ = _resampled_state()
    before = target.state_dict()
    with pytest.raises(ValueError, match=message):
        target.load_state_dict(edit(_resampled_state()[1]))
    after = target.state_dict()
    for key, value in before.items():
        assert (value is None and after[key] is None) or torch.equal(value, after[key]), key


def test_a_filter_never_reset_refuses_a_state_of_another_mask_width() -> None:
    """With no particles of its own to compare, it once took 4-bit masks into a 6-bit filter."""
    _, state = _resampled_state()
    with pytest.raises(ValueError, match="masks of 4 bits, this filter's bool masks of 6"):
        smcd_rl.SMCDFilter(6, num_particles=8).load_state_dict(state)


def test_restore_rows_refuses_nan_weights_instead_of_mixing_them_in() -> None:
    filt, state = _resampled_state()
    state["log_weights"][0, 0] = math.nan
    before = filt.state_dict()
    with pytest.raises(ValueError, match="log weights are NaN"):
        filt.restore_rows(state, torch.tensor([True, False]))
    assert torch.equal(filt.state_dict()["log_weights"], before["log_weights"])


def test_restore_takes_only_this_filters_snapshot() -> None:
    """Another filter's snapshot once replaced this one's state and made the two share one generator."""
    a, _ = _resampled_state()
    b, _ = _resampled_state()
    particles = a.particles
    for snapshot in (b.snapshot(), None, ({}, a.generator.get_state())):
        with pytest.raises(ValueError, match="restore takes a snapshot\\(\\) of this same filter"):
            a.restore(snapshot)  # type: ignore[arg-type]
    assert a.particles is particles and a.generator is not b.generator


def test_a_complex_log_likelihood_is_refused_and_a_graph_is_not_kept() -> None:
    filt, _ = _resampled_state()
    with pytest.raises(TypeError, match="log_likelihood is complex"):
        filt.update(lambda m: torch.zeros(2, 8, dtype=torch.complex64))
    scale = torch.tensor(1.0, requires_grad=True)
    filt.update(lambda m: -scale * m.sum(-1).float())  # a likelihood with autograd (a learnt noise, say)
    assert filt.log_weights is not None and filt.log_weights.grad_fn is None
    assert filt.log_evidence is not None and filt.log_evidence.grad_fn is None


def test_the_base_particle_filter_and_a_partial_subclass_are_refused_at_construction() -> None:
    """reset() raised a NotImplementedError with no message; a subclass without _transition failed at the first step."""
    with pytest.raises(TypeError, match="ParticleFilter does not define _initial and _transition.*SMCDFilter"):
        smcd_rl.ParticleFilter(4)

    class NoTransition(smcd_rl.ParticleFilter):
        def _initial(self, batch_shape: tuple[int, ...], num_particles: int) -> torch.Tensor:
            return torch.zeros(*batch_shape, num_particles, 1)

    with pytest.raises(TypeError, match="NoTransition does not define _transition "):
        NoTransition(4)

    class Walk(NoTransition):
        def _transition(self, particles: torch.Tensor) -> torch.Tensor:
            return particles + 1

    walk = Walk(4)
    walk.reset((2,))
    assert walk.particles is not None and walk.particles.shape == (2, 4, 1)


@pytest.mark.parametrize("device", ["meta", "nonsense", *([] if torch.cuda.is_available() else ["cuda"])])
def test_a_device_the_machine_cannot_filter_on_is_refused_by_name(device: str) -> None:
    """They met "META device type not an accelerator" and torch's CUDA-library message."""
    with pytest.raises(ValueError, match="device"):
        smcd_rl.SMCDFilter(4, device=device)
