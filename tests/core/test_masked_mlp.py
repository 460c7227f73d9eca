"""MaskedMLP: explicit masks, particle batches and dropout scaling."""

import math

import pytest
import torch

import smcd_rl


@pytest.fixture
def net() -> smcd_rl.MaskedMLP:
    torch.manual_seed(0)
    return smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), dropout=0.3).eval()


def test_mask_dim_counts_masked_layers_only() -> None:
    assert smcd_rl.MaskedMLP(3, 2, hidden=(16, 8)).mask_dim == 24
    assert smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), masked_layers=[1]).mask_dim == 8


def test_forward_particles_equals_a_loop_over_masks(net: smcd_rl.MaskedMLP) -> None:
    x = torch.randn(5, 3)
    masks = torch.rand(5, 7, net.mask_dim) < 0.7
    batched = net.forward_particles(x, masks)
    looped = torch.stack([torch.stack([net(x[b], mask=masks[b, i]) for i in range(7)]) for b in range(5)])
    assert batched.shape == (5, 7, 2)
    torch.testing.assert_close(batched, looped)


def test_forward_particles_with_one_input_per_particle(net: smcd_rl.MaskedMLP) -> None:
    x = torch.randn(4, 6, 3)
    masks = torch.rand(4, 6, net.mask_dim) < 0.7
    looped = torch.stack([torch.stack([net(x[b, i], mask=masks[b, i]) for i in range(6)]) for b in range(4)])
    torch.testing.assert_close(net.forward_particles(x, masks), looped)


def test_float_mask_is_scaled_like_training(net: smcd_rl.MaskedMLP) -> None:
    """An MMSE mask m in [0, 1] multiplies unit activations by m / keep_prob."""
    x = torch.randn(3)
    m = torch.rand(net.mask_dim)
    l0, l1, l2 = net.linears
    h = torch.relu(l0(x)) * m[:16] / 0.7
    h = torch.relu(l1(h)) * m[16:] / 0.7
    torch.testing.assert_close(net(x, mask=m), l2(h))


def test_mean_mask_reproduces_eval_mode(net: smcd_rl.MaskedMLP) -> None:
    x = torch.randn(10, 3)
    torch.testing.assert_close(net(x, mask=torch.full((net.mask_dim,), net.keep_prob)), net(x))


def test_train_mode_drops_units_at_the_training_rate() -> None:
    net = smcd_rl.MaskedMLP(1, 1, hidden=(1000,), dropout=0.5)
    with torch.no_grad():
        net.linears[0].weight.fill_(1.0)
        net.linears[0].bias.zero_()
        net.linears[1].weight.fill_(1.0)
        net.linears[1].bias.zero_()
    net.train()
    # Every hidden unit is 1; the output sums kept units scaled by 1/keep, so its mean over calls
    # is 1000 and the kept fraction is output * keep / 1000 (std over 1000 units ~ 0.016).
    with torch.no_grad():
        outputs = torch.stack([net(torch.ones(1)) for _ in range(50)]).squeeze(-1)
    kept = outputs * net.keep_prob / 1000
    assert abs(float(kept.mean()) - net.keep_prob) < 0.01
    assert float(outputs.std()) > 0, "train mode must sample a fresh dropout mask per call"
    net.eval()
    assert float(net(torch.ones(1)).detach()) == pytest.approx(1000.0)


def test_bad_shapes_name_the_expected_shape(net: smcd_rl.MaskedMLP) -> None:
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        net(torch.randn(4, 5))
    with pytest.raises(ValueError, match="mask_dim=24"):
        net(torch.randn(3), mask=torch.ones(5))
    with pytest.raises(ValueError, match="N, 24"):
        net.forward_particles(torch.randn(3), torch.ones(24))
    with pytest.raises(ValueError, match="dropout"):
        smcd_rl.MaskedMLP(3, 2, dropout=1.0)


@pytest.mark.parametrize("value", [2.0, -1.0, math.nan, math.inf])
def test_a_mask_value_outside_0_1_is_refused(net: smcd_rl.MaskedMLP, value: float) -> None:
    """A mask of 2 once scaled its units into outputs that looked plausible, and NaN gave NaN."""
    mask = torch.full((3, net.mask_dim), 0.5)
    mask[1, 2] = value
    x = torch.rand(3, net.in_features)
    for forward in (lambda: net(x, mask=mask), lambda: net.forward_particles(x, mask.unsqueeze(0))):
        with pytest.raises(ValueError, match=r"mask values must lie in \[0, 1\]"):
            forward()
    for good in (mask.clamp(0, 1).nan_to_num(0.5), mask.ge(0.5).to(torch.uint8)):
        assert bool(torch.isfinite(net(x, mask=good)).all())


def test_masks_whose_batch_does_not_fit_the_inputs_are_refused_by_name(net: smcd_rl.MaskedMLP) -> None:
    """torch's "The size of tensor a (3) must match the size of tensor b (4)" named neither tensor."""
    x = torch.rand(3, net.in_features)
    with pytest.raises(ValueError, match=r"a mask of shape \[4, \d+\] for inputs of shape \[3, 3\]"):
        net(x, mask=torch.ones(4, net.mask_dim, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"masks of shape \[4, 5, \d+\] for inputs of shape \[3, 3\]"):
        net.forward_particles(x, torch.ones(4, 5, net.mask_dim, dtype=torch.bool))
    assert net.forward_particles(x, torch.ones(3, 5, net.mask_dim, dtype=torch.bool)).shape == (3, 5, 2)
    assert net(x.unsqueeze(1).expand(3, 7, -1), mask=torch.ones(3, 1, net.mask_dim)).shape == (3, 7, 2)
