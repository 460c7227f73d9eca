"""The incremental particle forward pass equals the dense one, and SMCD takes it by default.

Equality is exact up to float rounding: the incremental path adds the same terms in another
order. Particles are compared bit for bit: with the same generator both filters must propose,
weigh and resample identically.
"""

import functools

import pytest
import torch

import smcd_rl
from smcd_rl.strategies.particle_forward import Lineage, ParticleForward

#: (hidden widths, masked layers): both layers masked (the paper's), deeper, first / later only.
LAYOUTS = [((48, 40), None), ((32, 32, 24), None), ((32, 40), (0,)), ((32, 40, 24), (1, 2)), ((40,), None)]


def _net(hidden, masked, seed=0, dropout=0.5):
    torch.manual_seed(seed)
    return smcd_rl.MaskedMLP(3, 2, hidden=hidden, dropout=dropout, masked_layers=masked).eval()


def _collapsed(n, dim, flip_rate, generator=None):
    """One parent copied ``n`` times and children with random flips: ``(parents, masks, flips)``."""
    parents = (torch.rand(1, dim, generator=generator) < 0.5).expand(n, dim).clone()
    flips = (torch.rand(n * dim, generator=generator) < flip_rate).nonzero().squeeze(-1)
    masks = parents.clone().reshape(-1)
    masks[flips] ^= True
    return parents, masks.reshape(n, dim), flips


def _run_pair(net, n, batch, flip_prob, steps=12, ess_threshold=1.0, noise=0.05):
    """Run the same SMCD twice, forced incremental and dense; yield both after every step."""
    pair = []
    for path in ("incremental", "dense"):
        smcd = smcd_rl.SMCD(
            num_particles=n,
            flip_prob=flip_prob,
            noise_std=noise,
            ess_threshold=ess_threshold,
            generator=torch.Generator().manual_seed(7),
            forward_path=path,
        )
        smcd.bind(net, torch.ones(2))
        smcd.reset(batch)
        pair.append(smcd)
    g = torch.Generator().manual_seed(3)
    for _ in range(steps):
        x = torch.randn(*batch, 3, generator=g)
        z = torch.randn(*batch, 2, generator=g)
        for smcd in pair:
            smcd.observe(x, z)
        yield pair


@pytest.mark.parametrize("hidden, masked", LAYOUTS)
@pytest.mark.parametrize("n, batch, flip_prob", [(1, (), 0.01), (7, (3,), 0.2), (64, (2, 2), 0.01), (300, (), 0.05)])
def test_incremental_and_dense_updates_agree(hidden, masked, n, batch, flip_prob) -> None:
    net = _net(hidden, masked)
    took_incremental = 0
    for fast, dense in _run_pair(net, n, batch, flip_prob):
        assert torch.equal(fast.particles, dense.particles), "resampled particles differ"
        torch.testing.assert_close(fast.filter.log_evidence, dense.filter.log_evidence, rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(fast.filter.last_ess, dense.filter.last_ess, rtol=1e-4, atol=1e-3)
        torch.testing.assert_close(fast.mask, dense.mask)
        took_incremental += fast.particle_forward.last_path == "incremental"
    assert took_incremental >= 10, "the forced incremental path was not taken"


def test_paths_agree_under_the_keep_rate_transition_at_low_dropout() -> None:
    """At dropout 0.1 the transition thins its flips per bit; the lineage must record only real flips."""
    net = _net((48, 40), None, dropout=0.1)
    for fast, dense in _run_pair(net, 80, (2,), 0.05):
        assert torch.equal(fast.particles, dense.particles)
        torch.testing.assert_close(fast.filter.log_evidence, dense.filter.log_evidence, rtol=1e-5, atol=1e-4)


def test_partial_resampling_and_restored_rows_keep_the_paths_equal() -> None:
    """Rows that did not resample, or were restored from a saved state, have no known copies."""
    net = _net((48, 40), None)
    for step, (fast, dense) in enumerate(_run_pair(net, 50, (3,), 0.01, steps=14, ess_threshold=0.5, noise=0.5)):
        assert torch.equal(fast.particles, dense.particles)
        torch.testing.assert_close(fast.filter.log_evidence, dense.filter.log_evidence, rtol=1e-5, atol=1e-4)
        if step == 5:
            saved = [smcd.filter.state_dict() for smcd in (fast, dense)]
        if step == 8:
            rows = torch.tensor([False, True, False])
            for smcd, state in zip((fast, dense), saved, strict=True):
                smcd.filter.restore_rows(state, rows)
            assert fast.filter.ancestors is None or bool((fast.filter.ancestors[1] == torch.arange(50)).all())


@pytest.mark.parametrize("hidden, masked", LAYOUTS)
def test_all_duplicate_particles(hidden, masked) -> None:
    """One parent copied N times (the fully collapsed posterior), children with random flips."""
    net = _net(hidden, masked)
    n, dim = 40, net.mask_dim
    g = torch.Generator().manual_seed(1)
    parents, masks, flips = _collapsed(n, dim, 0.05, g)
    lineage = Lineage(parents, torch.zeros(n, dtype=torch.long), flips)
    x = torch.randn(3, generator=g)
    forward = ParticleForward(net, path="incremental")
    torch.testing.assert_close(forward(x, masks, lineage), net.forward_particles(x, masks), rtol=1e-5, atol=1e-5)
    assert forward.last_path == "incremental" and forward.last_distinct_parents == 1


def test_auto_takes_the_incremental_path_only_when_it_pays() -> None:
    net = _net((256, 256), None)
    n, dim = 200, net.mask_dim
    parents, masks, flips = _collapsed(n, dim, 0.01)
    x = torch.randn(3)
    auto = ParticleForward(net)
    auto(x, masks, Lineage(parents, torch.zeros(n, dtype=torch.long), flips))
    assert auto.last_path == "incremental"
    auto(x, masks, Lineage(parents, torch.arange(n), flips))  # every particle distinct: nothing to share
    assert auto.last_path == "dense"
    auto(x, masks, None)
    assert auto.last_path == "dense"
    last_only = ParticleForward(_net((256, 256), (1,)))  # the next linear is the 2-unit output layer
    last_only(x, masks[:, :256], Lineage(parents[:, :256], torch.zeros(n, dtype=torch.long), flips[flips % dim < 256]))
    assert last_only.last_path == "dense"


def test_incremental_path_follows_weight_changes() -> None:
    """The cached transposed weight must be refreshed when training changes the network."""
    net = _net((48, 40), None)
    forward = ParticleForward(net, path="incremental")
    n, dim = 10, net.mask_dim
    parents = (torch.rand(1, dim) < 0.5).expand(n, dim).clone()
    flips = torch.arange(n) * dim + 3
    masks = parents.clone().reshape(-1)
    masks[flips] ^= True
    masks = masks.reshape(n, dim)
    lineage = Lineage(parents, torch.zeros(n, dtype=torch.long), flips)
    x = torch.randn(3)
    forward(x, masks, lineage)
    with torch.no_grad():
        net.linears[1].weight.mul_(2.0)
    torch.testing.assert_close(forward(x, masks, lineage), net.forward_particles(x, masks), rtol=1e-5, atol=1e-5)


def test_grouped_mean_mask_equals_the_weighted_mean() -> None:
    filt = smcd_rl.SMCDFilter(30, num_particles=100, generator=torch.Generator().manual_seed(0))
    filt.reset((2,))
    filt.propagate()
    filt.reweight(torch.randn(2, 100) * 5)  # concentrated: resampling leaves many copies
    assert filt.ancestors is not None and len(filt.ancestors[0].unique()) < 50
    expected = (filt.weights.unsqueeze(-2) @ filt.particles.float()).squeeze(-2)
    torch.testing.assert_close(filt.mean_mask, expected)


def test_bad_calls_name_the_problem() -> None:
    net = _net((48, 40), None)
    forward = ParticleForward(net, path="incremental")
    masks = torch.rand(5, net.mask_dim) < 0.5
    with pytest.raises(ValueError, match="needs a lineage"):
        forward(torch.randn(3), masks, None)
    with pytest.raises(ValueError, match="do not match"):
        forward(
            torch.randn(3),
            masks,
            Lineage(masks[:4], torch.zeros(4, dtype=torch.long), torch.zeros(0, dtype=torch.long)),
        )
    with pytest.raises(ValueError, match="path must be"):
        ParticleForward(net, path="fast")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="forward_path"):
        smcd_rl.SMCD(forward_path="fast")  # type: ignore[arg-type]


@pytest.mark.parametrize("hidden, masked", LAYOUTS)
def test_a_later_call_does_not_overwrite_an_earlier_result(hidden, masked) -> None:
    """The incremental path reuses work buffers; what it returns must never be one of them."""
    net = _net(hidden, masked)
    forward = ParticleForward(net, path="incremental")
    parents = (torch.rand(1, net.mask_dim) < 0.5).expand(6, -1).clone()
    lineage = Lineage(parents, torch.zeros(6, dtype=torch.long), torch.zeros(0, dtype=torch.long))
    first = forward(torch.randn(3), parents, lineage)
    kept = first.clone()
    forward(torch.randn(3), parents, lineage)
    assert torch.equal(first, kept)


def test_float_floor_division_is_exact_at_multiples() -> None:
    """The shortcuts for ``index // divisor`` (float, or a shift for powers of two) must not round
    k * divisor - 1 up or k * divisor down."""
    from smcd_rl.strategies.particle_forward import _floor_div

    for divisor in (1, 2, 3, 2048, 1000, 12_345):
        k = torch.tensor([0, 1, 7, 1000, 2**20, 2**27 // divisor + 1])
        index = torch.cat([k * divisor, (k * divisor - 1).clamp(min=0), k * divisor + divisor - 1]).sort().values
        assert torch.equal(_floor_div(index, divisor, 2**40), index // divisor)


@pytest.mark.parametrize(
    ("hidden", "masked", "groups"),
    [((48, 40), None, 8), ((32, 32, 24), None, 4), ((32, 40), (1,), 5), ((40,), None, 10)],
)
@pytest.mark.parametrize("batch", [(), (3,), (2, 2)])
def test_the_grouped_path_equals_the_dense_pass(hidden, masked, groups, batch) -> None:
    """A grouped network's particles from its groups' contributions, for bool and float masks, equal
    the dense pass up to float rounding; a filter on it proposes, weighs and resamples alike."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(3, 2, hidden=hidden, masked_layers=masked, mask_groups=groups).double().eval()
    x = torch.randn(*batch, 3, dtype=torch.float64)
    forward = ParticleForward(net)
    for masks in (
        torch.rand(*batch, 50, net.mask_dim) < 0.5,
        torch.rand(*batch, 50, net.mask_dim, dtype=torch.float64),
    ):
        torch.testing.assert_close(forward(x, masks), net.forward_particles(x, masks), rtol=1e-10, atol=1e-12)
        assert forward.last_path == "grouped"
    filters = []
    for path in ("auto", "dense"):
        smcd = smcd_rl.SMCD(
            num_particles=40, noise_std=0.5, generator=torch.Generator().manual_seed(7), forward_path=path
        )
        smcd.bind(net, torch.ones(2, dtype=torch.float64))
        smcd.reset(batch)
        filters.append(smcd)
    g = torch.Generator().manual_seed(3)
    for _ in range(8):
        x, z = (
            torch.randn(*batch, 3, generator=g, dtype=torch.float64),
            torch.randn(*batch, 2, generator=g, dtype=torch.float64),
        )
        for smcd in filters:
            smcd.observe(x, z)
        assert torch.equal(filters[0].particles, filters[1].particles)
        torch.testing.assert_close(filters[0].filter.log_evidence, filters[1].filter.log_evidence)


@pytest.mark.parametrize(
    ("hidden", "groups", "path"),
    [
        ((16, 12), None, "incremental"),
        ((16, 12), 4, "auto"),
        ((12,), None, "incremental"),
        ((16, 12), None, "dense"),
    ],
)
def test_every_particle_path_reads_out_the_same_last_hidden_features(hidden, groups, path) -> None:
    """Incremental, grouped and dense paths hand the readout the features the network computes per mask."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=hidden, mask_groups=groups).eval()
    n = 24
    mean = torch.randn(1, hidden[-1] + 1, 2)  # one stream's readout, not the network's
    parents, masks, flips = _collapsed(n, net.mask_dim, 0.1)
    x = torch.randn(2)
    readout = functools.partial(smcd_rl.BayesianLastLayer.readout_with, mean)
    forward = ParticleForward(net, path=path)
    got = forward(x, masks, Lineage(parents, torch.zeros(n, dtype=torch.long), flips), readout=readout)
    expected = readout(torch.stack([net.features(x, mask=masks[k]) for k in range(n)]))
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
    assert path != "auto" or forward.last_path == "grouped"
