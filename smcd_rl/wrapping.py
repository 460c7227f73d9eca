"""Adapt a network you trained elsewhere: an MLP-shaped torch module as a :class:`~smcd_rl.MaskedMLP`.

:func:`masked_mlp_from` reads an ``nn.Sequential`` of ``nn.Linear`` layers, one kind of activation
and ``nn.Dropout`` layers (torchrl's :class:`~torchrl.modules.MLP` is one) and builds the
:class:`~smcd_rl.MaskedMLP` with its trained weights: with dropout off it predicts exactly what the
module predicts in eval mode, and each hidden layer followed by a ``Dropout`` is a masked layer,
so SMCD's masks are the module's own dropout masks. :func:`adaptive_model_from` wraps it as an
:class:`~smcd_rl.AdaptiveModel` in the module's own units (no standardisation unless you pass
one), declared trained.

What a mask does must be what the module's dropout did in training:

* ``Linear, activation, Dropout`` (dropout after the activation, as :class:`~smcd_rl.MaskedMLP`
  masks) is read as it is;
* ``Linear, Dropout, ReLU`` (dropout before the activation, torchrl's order) is the same
  sub-network: ``relu(m z / keep) = m relu(z) / keep`` for a mask bit ``m`` in ``{0, 1}``. Before
  any other activation (torchrl's default ``Tanh``) it is not, and is refused: train with
  ``activation_class=nn.ReLU``, or with the dropout after the activation.

Every ``Dropout`` must have one probability (:class:`~smcd_rl.MaskedMLP` has one). A network
without any ``Dropout`` is wrapped with dropout 0: the Bayesian last layer, gradient descent and
the combination run on it, and SMCD is refused with a message that says which layers it needs.

Example:
    >>> import torch
    >>> from torch import nn
    >>> module = nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Dropout(0.1), nn.Linear(16, 2)).eval()
    >>> net = masked_mlp_from(module)
    >>> net.hidden, net.dropout, net.masked_layers
    ((16,), 0.1, (0,))
    >>> x = torch.rand(5, 3)
    >>> bool((net.eval()(x) - module(x)).abs().max() < 1e-6)
    True
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict.utils import NestedKey
from torch import nn

from smcd_rl.feature_readout import FeatureReadout
from smcd_rl.masked_mlp import _ACTIVATIONS, MaskedMLP
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies.base import Adaptation

__all__ = ["masked_mlp_from", "adaptive_model_from"]

#: What a FeatureReadout cannot run, said where one is suggested.
_NO_SMCD = "; SMCD needs an MLP of Linear, activation and nn.Dropout layers"

#: Activations whose input a dropout mask may scale as well as their output: ``f(m z / k) = m f(z) / k``.
_HOMOGENEOUS = (nn.ReLU,)


def masked_mlp_from(module: nn.Module) -> MaskedMLP:
    """A :class:`~smcd_rl.MaskedMLP` with ``module``'s trained weights (see the module doc for what it reads).

    Raises:
        TypeError: ``module`` is not an ``nn.Sequential``, or holds a layer that is not a
            ``Linear``, a supported activation or an ``nn.Dropout`` (``Dropout2d``, normalisation
            layers, ...).
        ValueError: the layers do not form an MLP (it must end in a ``Linear``), mix activations or
            dropout probabilities, or put a ``Dropout`` before an activation other than ReLU.
    """
    layers = _flattened(module)
    names = {kind: name for name, kind in _ACTIVATIONS.items()}
    blocks: list[dict[str, Any]] = []  # one per Linear: the layers after it until the next Linear
    for index, layer in enumerate(layers):
        if isinstance(layer, nn.Linear):
            blocks.append({"linear": layer, "after": []})
        elif type(layer) in names or isinstance(layer, nn.Dropout):
            if not blocks:
                raise ValueError(
                    f"layer {index} ({type(layer).__name__}) comes before the first Linear; smcd_rl masks hidden "
                    "units, not inputs: remove it or move it after a Linear"
                )
            blocks[-1]["after"].append(layer)
        elif isinstance(layer, nn.Identity):
            continue
        else:
            raise TypeError(
                f"layer {index} is a {type(layer).__name__}; an MLP to adapt holds nn.Linear layers, one activation "
                f"({', '.join(kind.__name__ for kind in names)}) and nn.Dropout (one mask bit per unit); "
                "Dropout2d/3d, normalisation and other layers have no MaskedMLP form. To adapt its readout only "
                f"(last layer, gradient descent), pass smcd_rl.FeatureReadout.from_sequential(module) "
                f"to adaptive_model_from{_NO_SMCD}"
            )
    if len(blocks) < 2:
        raise ValueError(
            "an MLP to adapt needs at least one hidden layer: Linear, activation, ..., Linear; "
            f"this module has {len(blocks)} Linear layer(s)"
        )
    if blocks[-1]["after"]:
        after = ", ".join(type(layer).__name__ for layer in blocks[-1]["after"])
        raise ValueError(
            f"the module ends in {after} after its last Linear; the strategies adapt a final linear readout, so "
            "the output must be the last Linear's (wrap the rest around the adapted model instead)"
        )
    activations, dropouts, masked = set(), set(), []
    for i, block in enumerate(blocks[:-1]):
        kinds = [layer for layer in block["after"] if not isinstance(layer, nn.Dropout)]
        drops = [layer for layer in block["after"] if isinstance(layer, nn.Dropout)]
        if len(kinds) != 1 or len(drops) > 1:
            raise ValueError(
                f"hidden layer {i} is followed by {[type(layer).__name__ for layer in block['after']]}; each hidden "
                "Linear takes exactly one activation and at most one Dropout"
            )
        activation = kinds[0]
        activations.add(type(activation))
        if drops:
            before = block["after"].index(drops[0]) < block["after"].index(activation)
            if before and not isinstance(activation, _HOMOGENEOUS):
                raise ValueError(
                    f"hidden layer {i} applies Dropout before {type(activation).__name__}: its masks scale the "
                    f"activation's input, and a {type(activation).__name__} of a scaled input is not the scaled "
                    "output that smcd_rl's masks keep; train with the Dropout after the activation, or with "
                    "ReLU (torchrl: MLP(..., activation_class=nn.ReLU))"
                )
            dropouts.add(float(drops[0].p))
            masked.append(i)
    if len(activations) > 1:
        raise ValueError(
            f"the module mixes activations {sorted(kind.__name__ for kind in activations)}; a MaskedMLP has one"
        )
    if len(dropouts) > 1:
        raise ValueError(f"the module's Dropout layers differ in p ({sorted(dropouts)}); a MaskedMLP has one")
    dropout = dropouts.pop() if dropouts else 0.0
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"Dropout(p={dropout}) keeps no unit; a MaskedMLP needs p in [0, 1)")
    linears = [block["linear"] for block in blocks]
    for i, linear in enumerate(linears):
        if isinstance(linear.weight, nn.parameter.UninitializedParameter):
            raise ValueError(
                f"Linear layer {i} is lazy and has no weights yet; run the module once on an input (or train it) first"
            )
    for i, (a, b) in enumerate(zip(linears, linears[1:], strict=False)):
        if a.out_features != b.in_features:
            raise ValueError(
                f"Linear layer {i} gives {a.out_features} values but Linear layer {i + 1} reads {b.in_features}; the "
                "module does not run as it is"
            )
    weight = linears[0].weight
    net = MaskedMLP(
        linears[0].in_features,
        linears[-1].out_features,
        hidden=tuple(linear.out_features for linear in linears[:-1]),
        dropout=dropout,
        activation=names[activations.pop()],  # type: ignore[arg-type]  # a key of _ACTIVATIONS
        masked_layers=masked or None,
        device=weight.device,
        dtype=weight.dtype,
    )
    with torch.no_grad():
        for mine, theirs in zip(net.linears, linears, strict=True):
            assert isinstance(mine, nn.Linear)
            mine.weight.copy_(theirs.weight)
            bias = theirs.bias
            mine.bias.copy_(torch.zeros_like(mine.bias) if bias is None else bias)
    return net.eval()


def adaptive_model_from(
    module: nn.Module,
    *,
    in_keys: Sequence[NestedKey],
    out_key: NestedKey,
    target_key: NestedKey | None = None,
    base_key: NestedKey | None = None,
    adaptation: Adaptation | None = None,
    eval_mode: bool = False,
) -> AdaptiveModel:
    """``module`` (see :func:`masked_mlp_from`) as an :class:`~smcd_rl.AdaptiveModel` in its own units.

    ``module`` is an MLP-shaped ``nn.Sequential``, on which every strategy runs, or a
    :class:`~smcd_rl.FeatureReadout` (any network that ends in a linear layer, as its features
    module and that readout), on which the last layer, gradient descent and the combination run.
    The model is declared trained (``model.fitted``); its inputs and outputs are the module's:
    no standardisation is added (set ``model.input_norm`` / ``model.output_norm`` yourself to add
    one). A module left in training mode is refused, since its predictions are then random: call
    ``module.eval()`` first, or pass ``eval_mode=True`` to have the wrapped copy read as in eval
    mode (the module itself is never changed).

    Example:
        >>> import torch, smcd_rl
        >>> from torch import nn
        >>> from tensordict import TensorDict
        >>> module = nn.Sequential(nn.Linear(2, 8), nn.ReLU(), nn.Dropout(0.2), nn.Linear(8, 2)).eval()
        >>> model = adaptive_model_from(module, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(num_particles=20))
        >>> model.reset()
        >>> model(TensorDict({"q": torch.zeros(2)}, []))["ee"].shape
        torch.Size([2])
    """
    if isinstance(module, nn.Module) and module.training and not eval_mode and not isinstance(module, FeatureReadout):
        raise ValueError(
            "the module is in training mode, so its dropout makes every prediction random; call module.eval() "
            "before wrapping it, or pass eval_mode=True"
        )
    # A FeatureReadout is already a network of the strategies' form, its features held in eval mode.
    net = module if isinstance(module, FeatureReadout) else masked_mlp_from(module)
    model = AdaptiveModel(
        net, in_keys=in_keys, out_key=out_key, target_key=target_key, base_key=base_key, adaptation=adaptation
    )
    model.fitted = True  # trained by its own code; the identity normalisation keeps its units
    return model


def _flattened(module: nn.Module) -> list[nn.Module]:
    """The layers of ``module``, nested ``nn.Sequential`` containers opened."""
    if not isinstance(module, nn.Sequential):
        raise TypeError(
            f"expected an nn.Sequential of Linear, activation and Dropout layers (torchrl's MLP is one), got "
            f"{type(module).__name__}; for another architecture that ends in a linear layer, pass "
            f"smcd_rl.FeatureReadout(features, readout) to adaptive_model_from to adapt its readout (last layer, gradient "
            f"descent){_NO_SMCD}"
        )
    layers: list[nn.Module] = []
    for layer in module:
        layers.extend(_flattened(layer) if isinstance(layer, nn.Sequential) else [layer])
    return layers
