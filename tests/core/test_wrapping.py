"""Networks trained elsewhere: an nn.Sequential MLP (torchrl's MLP included) adapted with its own weights."""

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

import smcd_rl
from smcd_rl.wrapping import adaptive_model_from, masked_mlp_from


def _module(order: str = "after", activation: type[nn.Module] = nn.ReLU, p: float = 0.2) -> nn.Sequential:
    """Two hidden layers of 32 with Dropout ``"after"`` or ``"before"`` the activation, random weights."""
    torch.manual_seed(0)
    layers: list[nn.Module] = []
    for fan_in in (3, 32):
        block = [activation(), nn.Dropout(p)] if order == "after" else [nn.Dropout(p), activation()]
        layers += [nn.Linear(fan_in, 32), *block]
    return nn.Sequential(*layers, nn.Linear(32, 2)).eval()


@pytest.mark.parametrize("order", ["after", "before"])
def test_the_wrapped_network_predicts_what_the_module_predicts_and_masks_as_its_dropout_did(order) -> None:
    """With dropout off the MaskedMLP is the module, to float rounding; under a mask it is the module
    with that mask as its dropout (kept units scaled by 1 / keep), computed here layer by layer."""
    module = _module(order)
    net = masked_mlp_from(module)
    assert net.hidden == (32, 32) and net.masked_layers == (0, 1) and net.dropout == pytest.approx(0.2)
    x = torch.randn(64, 3) * 2
    torch.testing.assert_close(net(x), module(x), rtol=0, atol=1e-5)
    mask = torch.rand(64, net.mask_dim, generator=torch.Generator().manual_seed(1)) < 0.8
    h, bits = x, iter((mask[:, :32], mask[:, 32:]))
    for layer in module:
        if isinstance(layer, nn.Dropout):
            h = h * next(bits) / 0.8  # what the module's own dropout does with this mask
        else:
            h = layer(h)
    torch.testing.assert_close(net(x, mask=mask), h, rtol=0, atol=1e-5)


def test_a_torchrl_mlp_with_relu_is_wrapped_exactly_and_every_strategy_runs_on_it() -> None:
    torch.manual_seed(0)
    module = MLP(in_features=3, out_features=2, num_cells=[32, 32], dropout=0.1, activation_class=nn.ReLU).eval()
    x = torch.randn(4, 3)
    strategies = {
        "none": smcd_rl.NoAdaptation(),
        "gradient descent": smcd_rl.GradientDescent(lr=0.01),
        "SMCD": smcd_rl.SMCD(num_particles=30),
        "last layer": smcd_rl.BayesianLastLayer(),
        "SMCD with a Bayesian readout": smcd_rl.SMCDLastLayer(
            smcd_rl.SMCD(num_particles=30), smcd_rl.BayesianLastLayer()
        ),
    }
    for name, strategy in strategies.items():
        model = adaptive_model_from(module, in_keys=["q"], out_key="ee", adaptation=strategy)
        model.reset(batch_shape=(4,))
        if "SMCD" not in name:  # (SMCD's prediction before any observation is its prior's mean mask's)
            with torch.no_grad():
                torch.testing.assert_close(model(TensorDict({"q": x}, [4]))["ee"], module(x), rtol=0, atol=1e-5)
        for _ in range(3):
            model.observe(TensorDict({"q": x, "ee": module(x).detach() + 0.3}, [4]))
        with torch.no_grad():
            moved = model(TensorDict({"q": x}, [4]))["ee"]
        assert bool(torch.isfinite(moved).all()), name
        if name != "none":
            assert not torch.allclose(moved, module(x)), f"{name} did not adapt"


def test_a_wrapped_model_saves_and_loads_with_its_weights(tmp_path) -> None:
    module = _module()
    model = adaptive_model_from(module, in_keys=["q"], out_key="ee", adaptation=smcd_rl.BayesianLastLayer())
    model.save(tmp_path / "wrapped.pt")
    loaded = smcd_rl.load(tmp_path / "wrapped.pt")
    loaded.reset()
    x = torch.randn(3)
    with torch.no_grad():
        torch.testing.assert_close(loaded(TensorDict({"q": x}, []))["ee"], module(x), rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    ("module", "error", "message"),
    [
        (
            nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Dropout(0.1), nn.Linear(8, 2), nn.ReLU()),
            ValueError,
            "ends in ReLU",
        ),
        (
            nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Dropout2d(0.1), nn.Linear(8, 2)),
            TypeError,
            "layer 2 is a Dropout2d",
        ),
        (nn.Sequential(nn.Linear(3, 8), nn.BatchNorm1d(8), nn.ReLU(), nn.Linear(8, 2)), TypeError, "BatchNorm1d"),
        (_module("before", nn.Tanh), ValueError, "Dropout before Tanh.*activation_class=nn.ReLU"),
        (nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 8), nn.Tanh(), nn.Linear(8, 2)), ValueError, "mixes"),
        (
            nn.Sequential(
                nn.Linear(3, 8),
                nn.ReLU(),
                nn.Dropout(0.1),
                nn.Linear(8, 8),
                nn.ReLU(),
                nn.Dropout(0.3),
                nn.Linear(8, 2),
            ),
            ValueError,
            r"differ in p \(\[0.1, 0.3\]\)",
        ),
        (nn.Linear(3, 2), TypeError, "expected an nn.Sequential"),
        (nn.Sequential(nn.Linear(3, 2)), ValueError, "at least one hidden layer"),
    ],
)
def test_a_module_without_an_mlp_form_is_refused_with_the_layer_named(module, error, message) -> None:
    with pytest.raises(error, match=message):
        masked_mlp_from(module.eval())


def test_a_module_in_training_mode_is_refused_or_read_as_in_eval_mode() -> None:
    module = _module().train()
    with pytest.raises(ValueError, match=r"training mode.*module.eval\(\)"):
        adaptive_model_from(module, in_keys=["q"], out_key="ee")
    model = adaptive_model_from(module, in_keys=["q"], out_key="ee", eval_mode=True)
    assert module.training  # the module itself is left as it was
    model.reset()
    x = torch.randn(3)
    with torch.no_grad():
        torch.testing.assert_close(model(TensorDict({"q": x}, []))["ee"], module.eval()(x), rtol=0, atol=1e-5)


def test_a_target_of_another_size_than_the_modules_output_is_named() -> None:
    model = adaptive_model_from(_module(), in_keys=["q"], out_key="ee", adaptation=smcd_rl.BayesianLastLayer())
    model.reset()
    with pytest.raises(ValueError, match="ee"):
        model.observe(TensorDict({"q": torch.randn(3), "ee": torch.randn(3)}, []))


def test_a_network_without_dropout_runs_the_last_layer_and_gd_and_refuses_smcd_by_name() -> None:
    torch.manual_seed(0)
    module = nn.Sequential(nn.Linear(2, 16), nn.Tanh(), nn.Linear(16, 2)).eval()
    with pytest.raises(ValueError, match=r"trained without dropout.*nn.Dropout after the activation"):
        adaptive_model_from(module, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(num_particles=10))
    model = adaptive_model_from(module, in_keys=["q"], out_key="ee")
    q = torch.rand(6, 10, 2)
    with torch.no_grad():
        episodes = TensorDict({"q": q, "ee": module(q) + 0.5}, [6, 10])
    grid = {"lr": (1e-2, 1e-1), "steps": (1,), "window": (5,), "loss": ("mse",)}
    result = smcd_rl.tune(model, episodes, gd_grid=grid, progress=False)
    assert set(result.best_of) == {"none", "gradient_descent", "last_layer", "combination"}
    assert any("the network has no dropout" in note for note in result.notes)
    # A shift of 0.5 is the readout's bias moving: the last layer learns it, no adaptation cannot.
    assert result.best_of["last_layer"].one_step_rmse < 0.5 * result.best_of["none"].one_step_rmse
    with pytest.raises(ValueError, match=r"\['smcd'\] filter over dropout masks"):
        smcd_rl.tune(model, episodes, strategies=["smcd"], progress=False)


@pytest.mark.parametrize(
    ("module", "message"),
    [
        # torch's "The size of tensor a (16) must match the size of tensor b (8)" at the weight copy.
        (
            nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Linear(8, 2)),
            "Linear layer 0 gives 16 values but Linear layer 1 reads 8",
        ),
        # "in_features must be >= 1, got 0", about a setting the user never passed.
        (
            nn.Sequential(nn.LazyLinear(16), nn.ReLU(), nn.Linear(16, 2)),
            "Linear layer 0 is lazy and has no weights yet",
        ),
    ],
)
def test_a_module_that_does_not_run_as_it_is_is_refused_by_name(module, message) -> None:
    with pytest.raises(ValueError, match=message):
        smcd_rl.masked_mlp_from(module)
