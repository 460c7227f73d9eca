"""A multilayer perceptron whose hidden units can be switched off by an explicit dropout mask."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Literal

import torch
from torch import Tensor, nn

from smcd_rl.checks import check_count, check_real, check_real_tensor

__all__ = ["MaskedMLP", "task_mask_groups"]

Activation = Literal["relu", "tanh", "elu", "silu"]
_ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
    "silu": nn.SiLU,
}


class MaskedMLP(nn.Module):
    """MLP with one dropout-mask bit per hidden unit (or per group of units) of its masked layers.

    Dropout sits after each masked hidden layer's activation. A kept unit is scaled by
    ``1 / keep_prob`` exactly as in training, so a mask of ones times ``keep_prob`` (the mean
    mask) gives the ordinary evaluation-mode network.

    * ``net(x)`` in ``train()`` mode drops units at random (ordinary dropout); in ``eval()`` mode
      it drops none.
    * ``net(x, mask=m)`` uses the given mask: ``m`` is ``[..., mask_dim]``, bool or float in
      ``[0, 1]`` (for example an MMSE mask), broadcast against ``x``'s batch dims.
    * ``net.forward_particles(x, masks)`` runs every mask of ``masks [..., N, mask_dim]`` in one
      batched pass; the first layer, which no mask touches, is computed once for all particles.

    Mask bits are laid out layer after layer: bits ``0 .. hidden[i0]-1`` belong to the first
    masked layer, the next ``hidden[i1]`` bits to the second, and so on.

    With ``mask_groups=G`` each masked layer carries ``G`` bits instead, bit ``j`` switching its
    ``j``-th block of ``width / G`` consecutive units on or off together, so ``mask_dim`` is
    ``G`` times the number of masked layers. A small mask space lets a particle filter of a few
    hundred masks cover it, at the price of coarser sub-networks. A kept unit is still scaled
    by ``1 / keep_prob``. (:class:`smcd_rl.SMCD` runs a grouped network's particles from each
    group's contribution to the next layer, ``mask_groups`` multiply-adds per output and particle
    instead of the layer's width: :mod:`smcd_rl.strategies.particle_forward`.)

    Args:
        in_features: input size.
        out_features: output size.
        hidden: widths of the hidden layers.
        dropout: drop probability ``p`` used in training; ``keep_prob = 1 - p``.
        activation: hidden activation.
        masked_layers: indices of the hidden layers that carry mask bits (default: all).
        device: where the parameters live.
        dtype: parameter dtype.
        mask_groups: bits per masked layer, each for ``width / mask_groups`` consecutive units;
            every masked layer's width must be divisible by it. ``None`` (default): one bit per
            unit.

    Example:
        >>> import torch, smcd_rl
        >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(16, 16), dropout=0.5).eval()
        >>> net.mask_dim
        32
        >>> masks = torch.rand(10, net.mask_dim) < 0.5
        >>> net.forward_particles(torch.zeros(2), masks).shape
        torch.Size([10, 2])
        >>> smcd_rl.MaskedMLP(2, 2, hidden=(16, 16), mask_groups=4).mask_dim  # 4 bits per layer
        8
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        hidden: Sequence[int] = (512, 512),
        dropout: float = 0.5,
        activation: Activation = "relu",
        masked_layers: Sequence[int] | None = None,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
        mask_groups: int | None = None,
    ) -> None:
        super().__init__()
        in_features = check_count(in_features, "in_features")
        out_features = check_count(out_features, "out_features")
        if isinstance(hidden, (str, bytes)) or not isinstance(hidden, Sequence):
            hint = f"; for one layer of {hidden} units pass hidden=({hidden},)" if isinstance(hidden, int) else ""
            raise TypeError(f"hidden must be a sequence of layer widths such as (64, 64), got {hidden!r}{hint}")
        if not hidden:
            raise ValueError(f"hidden must list at least one positive width, got {hidden}")
        hidden = tuple(check_count(h, f"hidden[{i}]") for i, h in enumerate(hidden))
        dropout = check_real(dropout, "dropout", low=0.0, high=1.0)
        if dropout == 1.0:
            raise ValueError("dropout must be in [0, 1), got 1.0 (no unit would ever be kept)")
        if activation not in _ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(_ACTIVATIONS)}")
        if masked_layers is not None and (isinstance(masked_layers, str) or not isinstance(masked_layers, Sequence)):
            raise TypeError(
                f"masked_layers must be a sequence of hidden-layer indices such as (0, 1), got {masked_layers!r}"
            )
        chosen = range(len(hidden)) if masked_layers is None else masked_layers
        layers = tuple(sorted({check_count(i, "masked_layers entry", minimum=0) for i in chosen}))
        if not layers or not all(0 <= i < len(hidden) for i in layers):
            raise ValueError(f"masked_layers must index hidden layers 0..{len(hidden) - 1}, got {masked_layers}")
        mask_groups = _checked_groups(mask_groups, hidden, layers)
        if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise TypeError(f"dtype must be a real floating torch dtype such as torch.float32, got {dtype!r}")
        self.in_features = in_features
        self.out_features = out_features
        self.hidden = hidden
        self.dropout = dropout
        self.keep_prob = 1.0 - self.dropout
        self.activation = activation
        self.masked_layers = layers
        widths = (self.in_features, *hidden, self.out_features)
        self.linears = nn.ModuleList(
            nn.Linear(a, b, device=device, dtype=dtype) for a, b in zip(widths[:-1], widths[1:], strict=True)
        )
        self.act = _ACTIVATIONS[activation]()
        self._lay_out_masks(mask_groups)

    def group_masks(self, mask_groups: int) -> None:
        """Give every masked layer ``mask_groups`` bits, each for a block of consecutive units (weights unchanged).

        :func:`smcd_rl.fit` does this with ``mask_training="task"`` to a network with one bit per
        unit (see its doc); a strategy attached before must be attached again
        (``model.with_adaptation(...)``), since the masks' size changes.

        Example:
            >>> net = MaskedMLP(2, 2, hidden=(16, 16))
            >>> net.group_masks(4)
            >>> net.mask_dim, net.config["mask_groups"]
            (8, 4)
        """
        self._lay_out_masks(_checked_groups(mask_groups, self.hidden, self.masked_layers))

    def _lay_out_masks(self, mask_groups: int | None) -> None:
        #: Bits per masked layer, each for a block of consecutive units (``None``: one bit per unit).
        self.mask_groups = mask_groups
        # Where each hidden layer's bits sit in the flat mask (None: the layer is not masked); a
        # layer has one bit per unit, or mask_groups bits with grouped masks.
        self.mask_slices: list[slice | None] = []
        start = 0
        for i, width in enumerate(self.hidden):
            if i in self.masked_layers:
                bits = width if mask_groups is None else mask_groups
                self.mask_slices.append(slice(start, start + bits))
                start += bits
            else:
                self.mask_slices.append(None)
        self.mask_dim = start

    @property
    def config(self) -> dict[str, Any]:
        """The constructor arguments; ``MaskedMLP(**net.config)`` rebuilds the architecture.

        ``mask_groups`` is listed only when set: a network with one bit per unit has the six
        entries above and no more, the config its saved models and training checkpoints (which
        compare configs) record.
        """
        config: dict[str, Any] = {
            "in_features": self.in_features,
            "out_features": self.out_features,
            "hidden": list(self.hidden),
            "dropout": self.dropout,
            "activation": self.activation,
            "masked_layers": list(self.masked_layers),
        }
        if self.mask_groups is not None:
            config["mask_groups"] = self.mask_groups
        return config

    def extra_repr(self) -> str:
        text = f"mask_dim={self.mask_dim}, keep_prob={self.keep_prob}, masked_layers={self.masked_layers}"
        # Only when set: model digests hash the repr, and an ungrouped network's stays as it is.
        return text if self.mask_groups is None else f"{text}, mask_groups={self.mask_groups}"

    def forward(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """Predict with one mask per batch element (or ordinary dropout, see the class docstring)."""
        self._check_input(x)
        if mask is None:
            if not self.training or self.dropout == 0.0:
                return self._run(x, None)
            mask = torch.rand(*x.shape[:-1], self.mask_dim, device=x.device) < self.keep_prob
        return self._run(x, self._scaled(mask, x))

    @property
    def readout_layer(self) -> nn.Linear:
        """The output layer, which reads :meth:`features`."""
        layer = self.linears[-1]
        assert isinstance(layer, nn.Linear)
        return layer

    def features(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """The last hidden layer's activations, what the output layer reads: ``net.readout_layer(net.features(x))``
        is ``net(x)`` with dropout off (with ``mask``, under that mask, its kept units scaled).

        Example:
            >>> import torch, smcd_rl
            >>> net = smcd_rl.MaskedMLP(2, 3, hidden=(8, 6)).eval()
            >>> x = torch.rand(4, 2)
            >>> net.features(x).shape, torch.allclose(net.readout_layer(net.features(x)), net(x))
            (torch.Size([4, 6]), True)
        """
        self._check_input(x)
        return self._hidden(x, None if mask is None else self._scaled(mask, x))

    def trunk(self, x: Tensor) -> Tensor:
        """What :attr:`linears` read, the part of the network before them that no strategy adapts: here the input.

        Gradient descent steps every layer in :attr:`linears` on a window of ``trunk(x)``; a
        :class:`~smcd_rl.feature_readout.FeatureReadout` network's trunk is its frozen features module.
        """
        return x

    def forward_particles(self, x: Tensor, masks: Tensor, readout: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """Predict with every mask of a particle set in one batched pass.

        Args:
            x: inputs ``[..., in_features]`` shared by all particles, or ``[..., N, in_features]``
                with one input per particle (when ``x.dim() == masks.dim()``).
            masks: ``[..., N, mask_dim]``, bool or float in ``[0, 1]``; leading dims broadcast
                against ``x``'s.
            readout: what turns the particles' last hidden activations ``[..., N, width]`` into
                outputs (default: the output layer), e.g. an adapted readout per batch element.

        Returns:
            ``[..., N, out_features]``: one prediction per mask.
        """
        self._check_input(x)
        check_real_tensor(masks, "masks")
        if masks.dim() < 2 or masks.shape[-1] != self.mask_dim:
            raise ValueError(
                f"masks must have shape [..., N, {self.mask_dim}] (mask_dim={self.mask_dim}), got {list(masks.shape)}"
            )
        _check_mask_values(masks)
        shared = x.dim() < masks.dim()
        if not _broadcast(x.shape[:-1] + ((1,) if shared else ()), masks.shape[:-1]):
            raise ValueError(
                f"masks of shape {list(masks.shape)} for inputs of shape {list(x.shape)}: the inputs' batch dims "
                "do not broadcast against the masks' [..., N]; pass inputs [..., in] shared by the particles or "
                "[..., N, in], one per particle"
            )
        h = x
        # list(...)[:-1], not self.linears[:-1]: slicing a ModuleList builds a new Module every call.
        for i, linear in enumerate(list(self.linears)[:-1]):
            h = self.act(linear(h))
            if shared:
                # Everything before the first mask is the same for all particles: add the
                # particle dim only now, so that work is done once instead of N times.
                h = h.unsqueeze(-2)
                shared = False
            sl = self.mask_slices[i]
            if sl is not None:
                # One layer's bits at a time: a float copy of the whole mask set would be the
                # largest temporary of the pass.
                h = self._masked(h, _as_multiplier(masks[..., sl], h.dtype)).mul_(1.0 / self.keep_prob)
        return (readout or self.linears[-1])(h)

    # ------------------------------------------------------------------ helpers
    def _scaled(self, mask: Tensor, x: Tensor) -> Tensor:
        """``mask`` checked against the inputs ``x`` it masks, as the multiplier of the kept units."""
        check_real_tensor(mask, "mask")
        if mask.dim() == 0 or mask.shape[-1] != self.mask_dim:
            raise ValueError(
                f"mask must have shape [..., {self.mask_dim}] (mask_dim={self.mask_dim}), got {list(mask.shape)}"
            )
        if not _broadcast(x.shape[:-1], mask.shape[:-1]):
            raise ValueError(
                f"a mask of shape {list(mask.shape)} for inputs of shape {list(x.shape)}: their batch dims "
                f"{list(mask.shape[:-1])} and {list(x.shape[:-1])} do not broadcast; pass one mask per input, or one for all"
            )
        _check_mask_values(mask)
        return _as_multiplier(mask, x.dtype) * (1.0 / self.keep_prob)

    def _run(self, x: Tensor, scaled: Tensor | None) -> Tensor:
        return self.linears[-1](self._hidden(x, scaled))

    def _hidden(self, x: Tensor, scaled: Tensor | None) -> Tensor:
        h = x
        for i, linear in enumerate(list(self.linears)[:-1]):  # see forward_particles
            h = self.act(linear(h))
            sl = self.mask_slices[i]
            if scaled is not None and sl is not None:
                h = self._masked(h, scaled[..., sl])
        return h

    def _masked(self, h: Tensor, multiplier: Tensor) -> Tensor:
        """``h [..., width]`` times one layer's mask values ``[..., bits]`` (bits = width, or one per group)."""
        if self.mask_groups is None:
            return h * multiplier
        # [..., G, width / G] * [..., G, 1]: every unit of a group takes its group's bit, with no
        # per-unit copy of the mask.
        return (h.unflatten(-1, (self.mask_groups, -1)) * multiplier.unsqueeze(-1)).flatten(-2)

    def _check_input(self, x: Tensor) -> None:
        check_real_tensor(x, "input")
        if not x.is_floating_point():
            raise TypeError(
                f"input must be a float tensor (the network's dtype), got {x.dtype}; convert it with .float()"
            )
        dtype = self.readout_layer.weight.dtype
        if x.dtype != dtype:
            raise TypeError(
                f"input of dtype {x.dtype}, the network's is {dtype}; convert the input with .to({dtype}) "
                f"or the network with .to({x.dtype})"
            )
        if x.dim() < 1 or x.shape[-1] != self.in_features:
            raise ValueError(
                f"input must have shape [..., {self.in_features}] (in_features={self.in_features}), got {list(x.shape)}"
            )


def _broadcast(a: Sequence[int], b: Sequence[int]) -> bool:
    """Whether shapes ``a`` and ``b`` broadcast (``torch.broadcast_shapes`` costs 30x this in a forward)."""
    return all(p == q or p == 1 or q == 1 for p, q in zip(reversed(a), reversed(b), strict=False))


def _check_mask_values(mask: Tensor) -> None:
    """Refuse a mask value outside ``[0, 1]``: a mask keeps a unit (1), drops it (0) or keeps a share
    of it, and a value of 2, -1 or NaN would scale units into outputs that look plausible and mean nothing."""
    if mask.dtype != torch.bool and mask.numel():  # bool masks, the particles' own, cannot be out of range
        low, high = (bound.item() for bound in torch.aminmax(mask))  # one pass; NaN if any is NaN
        if not (low >= 0 and high <= 1):
            outside = ~((mask >= 0) & (mask <= 1))
            raise ValueError(
                "mask values must lie in [0, 1] (bool, or the share of each unit kept, as an MMSE mask), got "
                f"{mask[outside].flatten()[0].item():.3g}"
            )


def _as_multiplier(mask: Tensor, dtype: torch.dtype) -> Tensor:
    """A mask ready to multiply activations of ``dtype``: bool becomes uint8, float is cast.

    Multiplying float activations by a uint8 view of a bool mask promotes to float on the fly and
    is about 2.5x faster than multiplying by the bool mask or converting it to float first.
    """
    return mask.view(torch.uint8) if mask.dtype == torch.bool else mask.to(dtype)


def _checked_groups(mask_groups: int | None, hidden: tuple[int, ...], layers: tuple[int, ...]) -> int | None:
    """``mask_groups`` if it divides every masked layer's width (or ``None``), else a clear error."""
    if mask_groups is None:
        return None
    mask_groups = check_count(mask_groups, "mask_groups")
    uneven = [f"hidden[{i}]={hidden[i]}" for i in layers if hidden[i] % mask_groups]
    if uneven:
        common = math.gcd(*(hidden[i] for i in layers))
        divisors = [g for g in range(1, common + 1) if common % g == 0]
        verb = "is" if len(uneven) == 1 else "are"
        raise ValueError(
            f"mask_groups={mask_groups} must divide the width of every masked layer, but "
            f"{', '.join(uneven)} {verb} not divisible by it; choose one of {divisors}, or change the widths"
        )
    return mask_groups


def task_mask_groups(net: MaskedMLP, target: int = 16) -> int:
    """The mask groups a network with one bit per unit takes for task-trained masks: the divisor of
    every masked layer's width nearest ``target`` (the larger of two equally near).

    Example:
        >>> task_mask_groups(MaskedMLP(2, 2, hidden=(512, 512))), task_mask_groups(MaskedMLP(2, 2, hidden=(200,)))
        (16, 20)
    """
    common = math.gcd(*(net.hidden[i] for i in net.masked_layers))
    divisors = [g for g in range(1, common + 1) if common % g == 0]
    return min(divisors, key=lambda g: (abs(g - target), -g))
