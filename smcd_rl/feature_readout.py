"""Any network that ends in a linear layer: a frozen feature module and the readout the strategies adapt.

:class:`FeatureReadout` holds a network you trained elsewhere as two parts, the ``features``
module (anything: convolutions, normalisation, residual blocks, a recurrent encoder's last state)
and the final ``nn.Linear`` that reads its output. It stands where a :class:`~smcd_rl.MaskedMLP`
does, so an :class:`~smcd_rl.AdaptiveModel` and :func:`smcd_rl.tune` take it, and the strategies
that adapt a readout run on it:

* the Bayesian last layer adapts the readout's weights from the features, as on a ``MaskedMLP``;
* gradient descent adapts the readout only, on a window of the features: the features module
  stays as trained (a private copy of every layer of an arbitrary module per stream is what it
  would cost otherwise, and the features of a window do not change while the readout moves);
* the combination mixes them, and ``tune`` chooses their settings.

SMCD and SMCD with a Bayesian readout filter over dropout masks of hidden units that
:class:`~smcd_rl.MaskedMLP` knows how to switch, so they are refused here with a message that says
what they need. The features module is copied and frozen (``requires_grad`` off, always in eval
mode): adapting never changes the module you passed, and its dropout or batch statistics never
make a prediction random.

Example:
    >>> import torch
    >>> from torch import nn
    >>> trunk = nn.Sequential(nn.Linear(3, 16), nn.LayerNorm(16), nn.GELU())
    >>> net = FeatureReadout(trunk, nn.Linear(16, 2))
    >>> net.in_features, net.out_features, net.dropout
    (3, 2, 0.0)
    >>> x = torch.rand(5, 3)
    >>> bool((net(x) - net.readout_layer(trunk(x))).abs().max() < 1e-6)
    True
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any, NoReturn

import torch
from torch import Tensor, nn

from smcd_rl.checks import check_count
from smcd_rl.masked_mlp import MaskedMLP

__all__ = ["FeatureReadout", "NO_MASKS"]


class FeatureReadout(MaskedMLP):
    """A frozen ``features`` module and the linear ``readout`` that reads it, as an adaptable network.

    ``net(x)`` is ``readout(features(x))``. :meth:`features` is the features module's output, what
    the Bayesian last layer reads; :meth:`trunk` is the same (the part no strategy adapts:
    gradient descent steps the readout only). The network has no dropout masks (``mask_dim`` 0):
    SMCD refuses it.

    Args:
        features: the trained module before the readout; any ``nn.Module`` mapping
            ``[..., in_features]`` to ``[..., readout.in_features]``. It is copied (the module
            you pass is never changed), frozen and kept in eval mode.
        readout: the trained final ``nn.Linear``; copied too.
        in_features: the input size; read from the first ``nn.Linear`` inside ``features`` when
            not given.

    Raises:
        TypeError: ``features`` is not an ``nn.Module`` or ``readout`` not an ``nn.Linear``;
            ``in_features`` is not an int; the two compute in different dtypes; or ``features``
            returns something other than one tensor (an RNN's tuple).
        ValueError: the input size cannot be read (pass ``in_features``), or ``features`` does not
            map an input of that size to ``readout.in_features`` values, keeping the batch dims.
    """

    def __init__(self, features: nn.Module, readout: nn.Linear, *, in_features: int | None = None) -> None:
        if not isinstance(features, nn.Module):
            raise TypeError(
                f"features must be an nn.Module (the network before its readout), got {type(features).__name__}"
            )
        if not isinstance(readout, nn.Linear):
            raise TypeError(
                f"readout must be the network's final nn.Linear, got {type(readout).__name__}; the strategies adapt "
                "a linear readout (wrap what comes after it around the adapted model instead)"
            )
        # MaskedMLP's constructor builds its own layers; this network is made of the user's.
        nn.Module.__init__(self)
        # check_count, not int(): int(2.9) is 2 and int(True) is 1, an input size no one meant.
        self.in_features = _input_size(features) if in_features is None else check_count(in_features, "in_features")
        self.out_features = readout.out_features
        self.hidden = (readout.in_features,)
        self.dropout = 0.0
        self.keep_prob = 1.0
        self.activation = "relu"  # unused: no activation follows the trunk here
        self.masked_layers = ()
        self.mask_groups = None
        self.mask_dim = 0
        self.mask_slices = [None]
        self.body = copy.deepcopy(features).requires_grad_(False).eval()
        # linears[0] is the readout: the one layer gradient descent steps, as it steps all of a MaskedMLP's.
        self.linears = nn.ModuleList([copy.deepcopy(readout)])
        self.act = nn.Identity()
        like = readout.weight
        dtypes = sorted({str(p.dtype) for p in self.body.parameters() if p.is_floating_point()} - {str(like.dtype)})
        if dtypes:
            raise TypeError(
                f"the features module's weights are {', '.join(dtypes)} and the readout's {like.dtype}; convert one "
                "with .to(...) so that both compute in one dtype"
            )
        probe = torch.zeros(1, self.in_features, dtype=like.dtype, device=like.device)
        try:
            with torch.no_grad():
                out = self.body(probe)
        except (RuntimeError, ValueError, TypeError) as err:
            raise ValueError(
                f"the features module does not take an input of {self.in_features} values ({err}); pass in_features"
            ) from err
        if not isinstance(out, Tensor):
            raise TypeError(
                f"the features module returns a {type(out).__name__}, not one tensor of features (an nn.GRU or "
                "nn.LSTM returns a tuple); wrap it in a module that returns the features the readout reads"
            )
        if out.shape[:-1] != probe.shape[:-1]:
            raise ValueError(
                f"the features module turns an input of shape {list(probe.shape)} into {list(out.shape)}: it must keep "
                "the batch dims and change only the last (features) dim"
            )
        width = out.shape[-1]
        if width != readout.in_features:
            raise ValueError(
                f"the features module gives {width} values but the readout reads {readout.in_features}; "
                "pass the module that ends where the readout begins"
            )
        self.eval()

    @classmethod
    def from_sequential(cls, module: nn.Sequential) -> FeatureReadout:
        """Split an ``nn.Sequential`` that ends in an ``nn.Linear`` (torchrl's ``MLP`` is one) into features and readout.

        Example:
            >>> from torch import nn
            >>> from torchrl.modules import MLP
            >>> mlp = MLP(in_features=3, out_features=2, num_cells=[16], norm_class=nn.LayerNorm,
            ...           norm_kwargs={"normalized_shape": 16})
            >>> FeatureReadout.from_sequential(mlp).hidden
            (16,)
        """
        if not isinstance(module, nn.Sequential):
            raise TypeError(
                f"from_sequential splits an nn.Sequential, got {type(module).__name__}; name the two parts yourself: "
                "FeatureReadout(features, readout)"
            )
        layers = list(module)  # not module[:-1]: a subclass such as torchrl's MLP cannot be rebuilt from a slice
        if not layers or not isinstance(layers[-1], nn.Linear):
            last = type(layers[-1]).__name__ if layers else "nothing"
            raise ValueError(
                f"the module ends in {last}, not an nn.Linear; the strategies adapt a final linear readout (wrap what "
                "comes after it around the adapted model instead)"
            )
        # A lone nn.Linear reads its inputs directly: the features are the inputs (nn.Sequential() is the identity).
        return cls(
            nn.Sequential(*layers[:-1]), layers[-1], in_features=layers[-1].in_features if len(layers) == 1 else None
        )

    def train(self, mode: bool = True) -> FeatureReadout:
        """Set the mode of the readout; the features module stays in eval mode (it is frozen)."""
        super().train(mode)
        self.body.eval()
        return self

    @property
    def config(self) -> dict[str, Any]:
        """What a checkpoint records: the sizes and the features module's class (rebuilt by passing it back)."""
        kind = type(self.body)
        return {
            "features": f"{kind.__module__}.{kind.__qualname__}",
            "in_features": self.in_features,
            "width": self.hidden[0],
            "out_features": self.out_features,
        }

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, width={self.hidden[0]}, out_features={self.out_features}"

    def forward(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """``readout(features(x))``; a ``mask`` is refused (this network has no dropout masks)."""
        return self.linears[0](self.features(x, mask))

    def features(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """The features module's output, what the readout reads."""
        if mask is not None:
            _no_masks()
        self._check_input(x)
        return self.body(x)

    def trunk(self, x: Tensor) -> Tensor:
        """What :attr:`linears` read: the features (gradient descent adapts the readout on them)."""
        return self.features(x)

    def forward_particles(self, x: Tensor, masks: Tensor, readout: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        _no_masks()

    def group_masks(self, mask_groups: int) -> None:
        _no_masks()


def _input_size(features: nn.Module) -> int:
    """The input width of ``features``: its first ``nn.Linear``'s (refused when it has none)."""
    first = next((m for m in features.modules() if isinstance(m, nn.Linear)), None)
    if first is None:
        raise ValueError(
            f"cannot read the input size of a {type(features).__name__} with no nn.Linear; pass in_features"
        )
    return first.in_features


#: Why SMCD cannot run on a FeatureReadout network, and what it needs instead (SMCD's refusal too).
NO_MASKS = (
    "a FeatureReadout network has no dropout masks: SMCD filters over dropout masks of an MLP's hidden units, "
    "and a FeatureReadout network has none (smcd_rl cannot switch the units of its features module). SMCD needs "
    "an nn.Sequential of Linear, activation and nn.Dropout layers (an nn.Dropout after each hidden layer to mask), "
    "trained with that dropout and wrapped with smcd_rl.adaptive_model_from; the last layer, gradient descent "
    "and the combination adapt this network"
)


def _no_masks() -> NoReturn:
    raise ValueError(NO_MASKS)
