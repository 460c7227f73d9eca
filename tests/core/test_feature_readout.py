"""Any network that ends in a linear layer (FeatureReadout): the readout strategies run on it, SMCD is refused."""

import copy

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

import smcd_rl
from smcd_rl.files import CheckpointMismatchError


class ResidualTrunk(nn.Module):
    """Not an MLP: a normalised residual block, what no MaskedMLP can express."""

    def __init__(self) -> None:
        super().__init__()
        self.inp = nn.Linear(2, 32)
        self.norm = nn.LayerNorm(32)
        self.block = nn.Sequential(nn.Linear(32, 32), nn.GELU(), nn.Dropout(0.3), nn.Linear(32, 32))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = torch.tanh(self.norm(self.inp(x)))
        return torch.tanh(h + self.block(h))


def _network(seed: int = 0) -> tuple[ResidualTrunk, nn.Linear]:
    torch.manual_seed(seed)
    return ResidualTrunk().eval(), nn.Linear(32, 2)


def _episodes(trunk: nn.Module, readout: nn.Linear, shift: torch.Tensor, count: int = 8) -> TensorDict:
    """Episodes of 10 steps whose target is the network's output moved by a per-episode shift (a readout change)."""
    q = torch.rand(count, 10, 2, generator=torch.Generator().manual_seed(3)) * 2 - 1
    with torch.no_grad():
        ee = readout(trunk(q)) + shift.reshape(count, 1, 2)
    return TensorDict({"q": q, "ee": ee}, [count, 10])


def test_a_network_that_ends_in_a_linear_layer_predicts_exactly_what_it_predicts_and_is_left_as_it_was() -> None:
    trunk, readout = _network()
    trunk.train()  # its Dropout must not make the wrapped network's predictions random
    before = copy.deepcopy(trunk.state_dict())
    net = smcd_rl.FeatureReadout(trunk, readout)
    assert (net.in_features, net.out_features, net.hidden, net.mask_dim) == (2, 2, (32,), 0)
    model = smcd_rl.adaptive_model_from(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.GradientDescent(lr=0.5))
    model.train()  # the features module stays in eval mode all the same
    x = torch.randn(16, 2)
    with torch.no_grad():
        expected = readout(trunk.eval()(x))
        torch.testing.assert_close(net(x), expected, rtol=0, atol=1e-6)
        torch.testing.assert_close(net(x), net(x), rtol=0, atol=0)
    model.reset(batch_shape=(16,))
    for _ in range(5):
        model.observe(TensorDict({"q": x, "ee": expected + 1.0}, [16]))
    # Gradient descent stepped the readout (predictions moved toward the shift) and no weight of the module.
    with torch.no_grad():
        moved = model(TensorDict({"q": x}, [16]))["ee"]
    assert float((moved - expected).mean()) > 0.5
    for name, value in trunk.state_dict().items():
        torch.testing.assert_close(value, before[name], rtol=0, atol=0)
    torch.testing.assert_close(net.body.state_dict()["inp.weight"], before["inp.weight"], rtol=0, atol=0)


def test_the_readout_strategies_and_tune_adapt_it_and_smcd_is_refused_by_name() -> None:
    """A per-episode shift of the output is a change of the readout's bias: the last layer learns it
    exactly from the first observation on, so its error must fall well below the unadapted network's,
    whose error is the shift itself (about 0.9 per output here); no setting of no adaptation can."""
    trunk, readout = _network()
    net = smcd_rl.FeatureReadout(trunk, readout)
    model = smcd_rl.adaptive_model_from(net, in_keys=["q"], out_key="ee")
    shift = torch.randn(8, 2, generator=torch.Generator().manual_seed(1))
    episodes = _episodes(trunk, readout, shift)
    grid = {"lr": (1e-2, 1e-1), "steps": (1,), "window": (5,), "loss": ("mse",)}
    result = smcd_rl.tune(model, episodes, gd_grid=grid, progress=False)
    assert set(result.best_of) == {"none", "gradient_descent", "last_layer", "combination"}
    assert any("no dropout" in note for note in result.notes)
    none = result.best_of["none"].one_step_rmse
    assert result.best_of["last_layer"].one_step_rmse < 0.5 * none
    assert result.best_of["gradient_descent"].one_step_rmse < none
    assert result.best_of["combination"].one_step_rmse < none
    for strategy in (
        smcd_rl.SMCD(num_particles=10),
        smcd_rl.SMCDLastLayer(smcd_rl.SMCD(num_particles=10), smcd_rl.BayesianLastLayer()),
    ):
        with pytest.raises(ValueError, match=r"FeatureReadout network has none.*Linear, activation and nn.Dropout"):
            model.with_adaptation(strategy)
    with pytest.raises(ValueError, match="filter over dropout masks"):
        smcd_rl.tune(model, episodes, strategies=["smcd"], progress=False)


def test_a_torchrl_mlp_with_normalisation_is_split_at_its_readout() -> None:
    """torchrl's MLP with LayerNorm has no MaskedMLP form; from_sequential splits it (its slice cannot be rebuilt)."""
    torch.manual_seed(0)
    mlp = MLP(
        in_features=2, out_features=2, num_cells=[16, 16], norm_class=nn.LayerNorm, norm_kwargs={"normalized_shape": 16}
    )
    with pytest.raises(TypeError, match=r"LayerNorm.*FeatureReadout.from_sequential"):
        smcd_rl.adaptive_model_from(mlp.eval(), in_keys=["q"], out_key="ee")
    net = smcd_rl.FeatureReadout.from_sequential(mlp)
    x = torch.randn(5, 2)
    with torch.no_grad():
        torch.testing.assert_close(net(x), mlp(x), rtol=0, atol=1e-6)
    model = smcd_rl.adaptive_model_from(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.BayesianLastLayer())
    model.reset()
    model.observe(TensorDict({"q": x[0], "ee": mlp(x[0]).detach() + 2.0}, []))
    with torch.no_grad():
        assert float((model(TensorDict({"q": x[0]}, []))["ee"] - mlp(x[0])).mean()) > 0.5


def test_it_saves_and_loads_with_its_own_weights_once_the_features_module_is_passed_back(tmp_path) -> None:
    trunk, readout = _network()
    model = smcd_rl.adaptive_model_from(
        smcd_rl.FeatureReadout(trunk, readout), in_keys=["q"], out_key="ee", adaptation=smcd_rl.BayesianLastLayer()
    )
    path = tmp_path / "own.pt"
    model.save(path)
    with pytest.raises(CheckpointMismatchError, match=r"ResidualTrunk.*smcd_rl.load\(path, features="):
        smcd_rl.load(path)
    with pytest.raises(CheckpointMismatchError, match="features= is a torch.nn.modules.container.Sequential"):
        smcd_rl.load(path, features=nn.Sequential(nn.Linear(2, 32)))
    other = _network(seed=5)[0]  # same class and shapes, other weights: the file's weights win
    passed = copy.deepcopy(other.state_dict())
    loaded = smcd_rl.load(path, features=other)
    loaded.reset()
    x = torch.randn(2)
    with torch.no_grad():
        torch.testing.assert_close(loaded(TensorDict({"q": x}, []))["ee"], readout(trunk(x)), rtol=0, atol=1e-6)
    for name, value in other.state_dict().items():  # the module passed back is not changed
        torch.testing.assert_close(value, passed[name], rtol=0, atol=0)
    plain = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    plain.save(tmp_path / "plain.pt")
    with pytest.raises(CheckpointMismatchError, match="without features="):
        smcd_rl.load(tmp_path / "plain.pt", features=other)


@pytest.mark.parametrize(
    ("features", "readout", "error", "message"),
    [
        (
            nn.Sequential(nn.Linear(2, 8), nn.ReLU()),
            nn.Linear(16, 2),
            ValueError,
            "gives 8 values but the readout reads 16",
        ),
        (nn.Sequential(nn.Linear(2, 8), nn.ReLU()), nn.Sequential(nn.Linear(8, 2)), TypeError, "final nn.Linear"),
        (nn.Tanh(), nn.Linear(2, 2), ValueError, "pass in_features"),
        ("not a module", nn.Linear(2, 2), TypeError, "features must be an nn.Module"),
    ],
)
def test_parts_that_do_not_form_a_network_are_refused_with_the_fix(features, readout, error, message) -> None:
    with pytest.raises(error, match=message):
        smcd_rl.FeatureReadout(features, readout)


def test_masks_and_smcd_training_are_refused() -> None:
    trunk, readout = _network()
    net = smcd_rl.FeatureReadout(trunk, readout)
    with pytest.raises(ValueError, match="no dropout masks"):
        net(torch.zeros(2), mask=torch.ones(0))
    with pytest.raises(ValueError, match="no dropout masks"):
        net.forward_particles(torch.zeros(2), torch.ones(3, 0))
    with pytest.raises(ValueError, match=r"ends in ReLU, not an nn.Linear"):
        smcd_rl.FeatureReadout.from_sequential(nn.Sequential(nn.Linear(2, 2), nn.ReLU()))
    model = smcd_rl.adaptive_model_from(net, in_keys=["q"], out_key="ee")
    episodes = _episodes(trunk, readout, torch.zeros(8, 2))
    with pytest.raises(TypeError, match="trained by your own code"):
        smcd_rl.fit(model, episodes.reshape(-1), epochs=1, progress=False)


@pytest.mark.parametrize(
    ("build", "error", "message"),
    [
        # in_features went through int(): 2.9 became 2 and True 1; "abc" and -1 gave raw errors.
        (
            lambda: smcd_rl.FeatureReadout(nn.Identity(), nn.Linear(2, 2), in_features=2.9),
            TypeError,
            "in_features must be an int",
        ),
        (
            lambda: smcd_rl.FeatureReadout(nn.Identity(), nn.Linear(2, 2), in_features=-1),
            ValueError,
            "in_features must be >= 1",
        ),
        # An RNN's tuple met "'tuple' object has no attribute 'shape'".
        (
            lambda: smcd_rl.FeatureReadout(nn.GRU(3, 16), nn.Linear(16, 2), in_features=3),
            TypeError,
            "returns a tuple, not one tensor",
        ),
        # Flatten(0) was accepted and every later forward failed with "mat1 and mat2 shapes".
        (
            lambda: smcd_rl.FeatureReadout(nn.Flatten(0), nn.Linear(3, 2), in_features=3),
            ValueError,
            r"turns an input of shape \[1, 3\] into \[3\]",
        ),
        # A float64 trunk was told to "pass in_features".
        (
            lambda: smcd_rl.FeatureReadout(nn.Sequential(nn.Linear(3, 16).double(), nn.ReLU()), nn.Linear(16, 2)),
            TypeError,
            "weights are torch.float64 and the readout's torch.float32",
        ),
    ],
)
def test_a_features_module_that_cannot_feed_the_readout_is_refused_by_name(build, error, message) -> None:
    with pytest.raises(error, match=message):
        build()


def test_from_sequential_reads_a_lone_linear_as_a_readout_of_the_inputs() -> None:
    """It was told to "pass in_features", which from_sequential does not take."""
    linear = nn.Linear(3, 2)
    net = smcd_rl.FeatureReadout.from_sequential(nn.Sequential(linear))
    x = torch.rand(5, 3)
    assert net.in_features == 3 and net.hidden == (3,)
    torch.testing.assert_close(net(x), linear(x))


def test_loading_with_features_of_other_shapes_names_the_features_not_the_file(tmp_path) -> None:
    """It said "save the model again", though the file was sound and the module passed back was not."""
    saved = nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Linear(16, 8), nn.ReLU())
    model = smcd_rl.adaptive_model_from(smcd_rl.FeatureReadout(saved, nn.Linear(8, 2)), in_keys=["q"], out_key="ee")
    model.save(tmp_path / "own.pt")
    other = nn.Sequential(nn.Linear(3, 32), nn.ReLU(), nn.Linear(32, 8), nn.ReLU())  # same class and output width
    with pytest.raises(CheckpointMismatchError, match=r"features module's '0.weight' is \[32, 3\] here but \[16, 3\]"):
        smcd_rl.load(tmp_path / "own.pt", features=other)
