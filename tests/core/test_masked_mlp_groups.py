"""MaskedMLP(mask_groups=G): one mask bit per block of units, in every place that takes masks."""

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.strategies.particle_forward import ParticleForward

pytestmark = pytest.mark.usefixtures("one_thread")


def _pair(groups: int = 4) -> tuple[smcd_rl.MaskedMLP, smcd_rl.MaskedMLP]:
    """A grouped network and an ungrouped one with the same weights."""
    torch.manual_seed(0)
    grouped = smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), dropout=0.3, mask_groups=groups).eval()
    plain = smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), dropout=0.3).eval()
    plain.load_state_dict(grouped.state_dict())
    return grouped, plain


def _per_unit(mask: torch.Tensor, groups: int = 4, widths: tuple[int, ...] = (16, 8)) -> torch.Tensor:
    """A grouped mask ``[..., groups * layers]`` as the per-unit mask that means the same."""
    layers = mask.split(groups, dim=-1)
    return torch.cat([m.repeat_interleave(w // groups, dim=-1) for m, w in zip(layers, widths, strict=True)], -1)


def test_mask_dim_is_groups_times_masked_layers() -> None:
    assert smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), mask_groups=4).mask_dim == 8
    assert smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), mask_groups=4, masked_layers=[1]).mask_dim == 4
    # An unmasked layer need not be divisible: only masked widths are split.
    net = smcd_rl.MaskedMLP(3, 2, hidden=(10, 8), mask_groups=4, masked_layers=[1])
    assert net.mask_dim == 4 and net.mask_slices == [None, slice(0, 4)]


def test_a_grouped_mask_acts_as_the_per_unit_mask_it_stands_for() -> None:
    """Bool and float masks, one forward per mask and the batched particle pass, shared and per-particle inputs."""
    grouped, plain = _pair()
    x = torch.randn(5, 3)
    bits = torch.rand(5, 7, grouped.mask_dim) < 0.6
    soft = torch.rand(5, grouped.mask_dim)
    torch.testing.assert_close(grouped(x, mask=soft), plain(x, mask=_per_unit(soft)))
    torch.testing.assert_close(grouped(x[0], mask=bits[0]), plain(x[0], mask=_per_unit(bits[0])))
    torch.testing.assert_close(grouped.forward_particles(x, bits), plain.forward_particles(x, _per_unit(bits)))
    per_particle = torch.randn(5, 7, 3)
    torch.testing.assert_close(
        grouped.forward_particles(per_particle, bits), plain.forward_particles(per_particle, _per_unit(bits))
    )
    # The mean mask is still the evaluation-mode network: kept units scale by 1 / keep_prob.
    mean = torch.full((grouped.mask_dim,), grouped.keep_prob)
    torch.testing.assert_close(grouped(x, mask=mean), grouped(x))


def test_train_mode_drops_whole_groups() -> None:
    """Every hidden unit is 1 and the output sums them scaled by 1/keep: with 2 groups of 4 units
    the output can only be 0, 4/keep or 8/keep, never a count that splits a group."""
    net = smcd_rl.MaskedMLP(1, 1, hidden=(8,), dropout=0.5, mask_groups=2)
    with torch.no_grad():
        for linear in net.linears:
            linear.weight.fill_(1.0)
            linear.bias.zero_()
    net.train()
    with torch.no_grad():
        kept = {round(float(net(torch.ones(1))) * net.keep_prob) for _ in range(200)}
    assert kept == {0, 4, 8}  # all three appear in 200 draws (each has probability >= 1/4)


def test_widths_not_divisible_are_refused_with_the_divisors_that_work() -> None:
    with pytest.raises(ValueError, match=r"hidden\[1\]=12 is not divisible.*\[1, 2, 4\]"):
        smcd_rl.MaskedMLP(3, 2, hidden=(16, 12), mask_groups=8)
    with pytest.raises(TypeError, match="mask_groups must be an int"):
        smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), mask_groups=2.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mask_groups must be >= 1"):
        smcd_rl.MaskedMLP(3, 2, hidden=(16, 8), mask_groups=0)


def test_config_and_repr_name_groups_only_when_set() -> None:
    """An ungrouped network's config and repr are those saved before groups existed: saved models,
    training checkpoints (which compare configs) and model digests (which hash the repr) stay valid."""
    grouped, plain = _pair()
    assert "mask_groups" not in plain.config and "mask_groups" not in repr(plain)
    assert plain.extra_repr() == "mask_dim=24, keep_prob=0.7, masked_layers=(0, 1)"
    assert grouped.config["mask_groups"] == 4 and "mask_groups=4" in repr(grouped)
    assert smcd_rl.MaskedMLP(**grouped.config).mask_dim == grouped.mask_dim


def _model(groups: int | None = 4, **smcd: object) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(32, 32), dropout=0.5, mask_groups=groups)
    adaptation = smcd_rl.SMCD(num_particles=64, noise_std=0.1, generator=torch.Generator().manual_seed(0), **smcd)
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=adaptation)


def _data(n: int = 256) -> TensorDict:
    q = torch.rand(n, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    return TensorDict({"q": q, "ee": torch.cos(q), "task": torch.arange(n) % 4}, [n])


def test_save_and_load_rebuild_the_grouped_network(tmp_path) -> None:
    model = _model()
    smcd_rl.fit(model, _data(), epochs=1, progress=False)
    smcd_rl.save(model, tmp_path / "m.pt")
    loaded = smcd_rl.load(tmp_path / "m.pt")
    assert loaded.net.mask_groups == 4 and loaded.net.mask_dim == 8
    masks = torch.rand(6, 8) < 0.5
    q = torch.randn(2)
    torch.testing.assert_close(loaded.net.forward_particles(q, masks), model.net.forward_particles(q, masks))


def test_smcd_filters_grouped_masks_on_the_grouped_path() -> None:
    model = _model()
    data = _data()
    for epochs, how in ((1, "random"), (2, "task")):  # both trainers draw masks of mask_dim bits
        smcd_rl.fit(model, data, epochs=epochs, progress=False, mask_training=how, mask_particles=16)
    model.reset(batch_shape=(3,))
    for t in range(4):
        model.observe(data[3 * t : 3 * t + 3])
    assert model.mask.shape == (3, 8) and model.particles.shape == (3, 64, 8)
    assert model.adaptation.particle_forward.last_path == "grouped"
    assert model(data[:3].exclude("ee"))["ee"].shape == (3, 2)


def test_the_incremental_path_refuses_a_grouped_network_up_front() -> None:
    with pytest.raises(ValueError, match="mask_groups=4; use path='auto' or 'dense'"):
        _model(forward_path="incremental")
    ParticleForward(_model(groups=None).net, "incremental")  # one bit per unit: allowed as before
