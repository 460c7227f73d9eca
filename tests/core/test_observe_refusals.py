"""Every strategy's ``observe``, called directly, refuses a malformed transition with a clear error and changes nothing.

``AdaptiveModel.observe`` converts what it reads from a TensorDict; these are the calls a planner or
a script makes on ``model.adaptation`` itself. Each strategy once failed its own way: gradient
descent took meta-device tensors as data and answered a float64 target with torch's "Index put
requires the source and destination dtypes match"; SMCD took complex targets (their imaginary part
dropped) and integer ones, and answered a wrong width with a broadcasting error.
"""

from collections.abc import Callable

import pytest
import torch

import smcd_rl

BATCH = (3,)


def _strategies() -> dict[str, Callable[[], smcd_rl.strategies.Adaptation]]:
    def smcd() -> smcd_rl.SMCD:
        return smcd_rl.SMCD(num_particles=20, noise_std=0.1)

    def readout() -> smcd_rl.BayesianLastLayer:
        return smcd_rl.BayesianLastLayer(noise_std=0.1)

    return {
        "none": smcd_rl.NoAdaptation,
        "smcd": smcd,
        "gradient_descent": lambda: smcd_rl.GradientDescent(lr=0.01, steps=2, window=4),
        "last_layer": readout,
        "smcd_last_layer": lambda: smcd_rl.SMCDLastLayer(smcd(), readout()),
        "combination": lambda: smcd_rl.Combination([smcd(), smcd_rl.GradientDescent(lr=0.01)]),
    }


def _model(kind: str) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(16, 16))
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=_strategies()[kind]())
    model.fitted = True  # a random network: the transitions, not the fit, are under test
    model.reset(batch_shape=BATCH)
    return model


GOOD = (torch.rand(3, 2), torch.rand(3, 2))
MALFORMED = {
    "transposed inputs": ((torch.rand(2, 3), GOOD[1]), ValueError, r"inputs of shape \[2, 3\], expected \[3, 2\]"),
    "wide targets": ((GOOD[0], torch.rand(3, 3)), ValueError, r"targets of shape \[3, 3\], expected \[3, 2\]"),
    "inputs with a time axis": ((torch.rand(3, 4, 2), torch.rand(3, 4, 2)), ValueError, r"inputs of shape \[3, 4, 2\]"),
    "a list": (([[0.0, 0.0]] * 3, GOOD[1]), ValueError, r"inputs of shape list"),
    "meta inputs": ((torch.rand(3, 2, device="meta"), GOOD[1]), TypeError, "inputs is on the meta device"),
    "meta targets": ((GOOD[0], torch.rand(3, 2, device="meta")), TypeError, "targets is on the meta device"),
    "float64 inputs": ((GOOD[0].double(), GOOD[1]), TypeError, "inputs of dtype torch.float64, expected"),
    "integer targets": ((GOOD[0], torch.ones(3, 2, dtype=torch.long)), TypeError, "targets of dtype torch.int64"),
    "complex targets": ((GOOD[0], torch.rand(3, 2, dtype=torch.complex64)), TypeError, "targets is complex"),
}


@pytest.mark.parametrize("kind", list(_strategies()))
@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_transition_is_refused_by_name_and_changes_nothing(kind: str, case: str) -> None:
    model = _model(kind)
    strategy = model.adaptation
    strategy.observe(*GOOD)  # a stream under way, so that "unchanged" is not just the reset state
    probe = torch.rand(3, 2)
    before = strategy.predict(probe)
    (inputs, targets), error, message = MALFORMED[case]
    with pytest.raises(error, match=f"{type(strategy).__name__}.observe: {message}"):
        strategy.observe(inputs, targets)
    torch.testing.assert_close(strategy.predict(probe), before, rtol=0.0, atol=0.0)
    strategy.observe(*GOOD)  # and it goes on


@pytest.mark.parametrize("kind", list(_strategies()))
def test_float64_targets_adapt_as_the_same_float32_targets(kind: str) -> None:
    """Targets are real floats of any precision: read in the network's, never refused for it."""
    inputs, targets = torch.rand(3, 2), torch.rand(3, 2)
    probe = torch.rand(3, 2)
    predictions = []
    for precise in (False, True):
        model = _model(kind)
        torch.manual_seed(1)  # the same bit flips for SMCD's particles
        model.adaptation.observe(inputs, targets.double() if precise else targets)
        predictions.append(model.adaptation.predict(probe))
    torch.testing.assert_close(predictions[1], predictions[0], rtol=1e-6, atol=1e-6)


MALFORMED_INPUTS = {
    "meta": (torch.rand(3, 2, device="meta"), TypeError, "inputs is on the meta device"),
    "float64": (torch.rand(3, 2, dtype=torch.float64), TypeError, "inputs of dtype torch.float64, expected"),
    "integer": (torch.ones(3, 2, dtype=torch.long), TypeError, "inputs of dtype torch.int64, expected"),
    "complex": (torch.rand(3, 2, dtype=torch.complex64), TypeError, "inputs is complex"),
    "wide": (torch.rand(3, 3), ValueError, r"inputs of shape \[3, 3\], expected \[..., 2\]"),
    "a list": ([[0.0, 0.0]] * 3, TypeError, "inputs must be a torch.Tensor, got list"),
}


@pytest.mark.parametrize("kind", [kind for kind in _strategies() if kind != "none"])
@pytest.mark.parametrize("case", list(MALFORMED_INPUTS))
def test_predict_refuses_malformed_inputs_by_name(kind: str, case: str) -> None:
    """Gradient descent predicted numbers for meta-device inputs and gave raw dtype errors for the rest."""
    strategy = _model(kind).adaptation
    inputs, error, message = MALFORMED_INPUTS[case]
    for predict in (strategy.predict, strategy.predict_particles):
        with pytest.raises(error, match=f"{type(strategy).__name__}.predict: {message}"):
            predict(inputs)
