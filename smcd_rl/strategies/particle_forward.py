"""Exact incremental forward passes for a resampled, bit-flipped particle set.

The cost of an SMCD update is the particle forward pass, and most of that is the linear layer right
after the first masked layer: a dense ``(N x width) @ (width x fan_out)`` matmul. That layer's
pre-activation is linear in the particle's mask bits ``a``, and the activations ``h`` it masks are
shared by every particle (no mask acts before them), so for particle ``i``::

    pre_i = W (h * a_i / keep) + b
          = pre_parent(i) + sum over the bits j flipped in i of  (+-h_j / keep) * W[:, j]

with ``+`` where the flip turned the bit on. After resampling many particles are copies of one
parent, and a transition flips only a few bits, so :class:`ParticleForward` computes the
pre-activations once per distinct parent (each batch element's first parent from its kept live
units, the others as that row plus their differing columns) and every child's as its parent's row
plus its flipped columns: one weighted ``embedding_bag`` over the rows of ``W.t()``, a few rows per
particle. Later layers are computed per particle as usual. The result equals
:meth:`MaskedMLP.forward_particles` up to float rounding.

Which path an update takes (``ParticleForward(net, path="auto")``, what :class:`smcd_rl.SMCD` uses):

=====================================================================  ===========
case                                                                   path
=====================================================================  ===========
shared input, duplicates known from the last resampling, and           incremental
``U * width + SPARSE_COST * flips < N * width``
no resampling since the last reset, ``propagate()``, state load or    dense
``restore_rows`` (the filter cannot tell which particles are copies)
weights so flat that (almost) every particle is distinct               dense
masks on the last hidden layer only (the next linear is the small      dense
output layer: nothing worth saving)
one input per particle (``x`` has a particle dim)                      dense
grouped masks (``MaskedMLP(mask_groups=...)``: a bit is a block of     grouped
columns), one input per batch element
a float (MMSE) mask                                                    one ordinary forward, no particles
=====================================================================  ===========

Deeper networks take the incremental path for the first masked layer's successor and the dense path
for every layer after it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from smcd_rl.filter import flat_particle_index, group_copies, group_members
from smcd_rl.masked_mlp import MaskedMLP

__all__ = ["Lineage", "ParticlePath", "ParticleForward", "SPARSE_COST", "check_path"]

ParticlePath = Literal["auto", "incremental", "dense"]

#: Cost of one sparse multiply-add (a weighted row of an embedding bag) relative to one multiply-add
#: of a dense matmul. Measured on a 2-core x86 CPU: 2.4 to 4.6 (5k rows of 1024 in 0.12 ms with warm
#: caches, 0.23 ms with cold ones; a dense 1000 x 1024 x 1024 matmul in 10.6 ms); rounded up so that
#: borderline cases keep the simpler dense path.
SPARSE_COST = 8.0


class Lineage(NamedTuple):
    """How a proposed particle set descends from the previous one.

    Attributes:
        parents: the particles before the transition, bool ``[*B, N, D]``.
        ancestors: ``[*B, N]``; parents with the same ancestor index are identical copies (the
            indices of the last resampling).
        flips: sorted flat positions into ``parents.reshape(-1)`` that the transition flipped.
    """

    parents: Tensor
    ancestors: Tensor
    flips: Tensor


def check_path(path: str, what: str = "path") -> ParticlePath:
    """Return ``path`` if it names a :data:`ParticlePath`, else raise a ValueError naming ``what``."""
    if path not in ("auto", "incremental", "dense"):
        raise ValueError(f"{what} must be 'auto', 'incremental' or 'dense', got {path!r}")
    return path  # type: ignore[return-value]


class ParticleForward:
    """Runs a particle set of masks through one network, incrementally where that is exact and cheaper.

    Args:
        net: the network.
        path: ``"auto"`` picks the cheaper path per call (module table), ``"dense"`` always runs
            :meth:`MaskedMLP.forward_particles`, ``"incremental"`` takes the incremental path
            whenever it is valid (for tests and benchmarks).

    Example:
        >>> import torch, smcd_rl
        >>> from smcd_rl.strategies.particle_forward import Lineage, ParticleForward
        >>> net = smcd_rl.MaskedMLP(3, 2, hidden=(64, 64)).eval()
        >>> parents = (torch.rand(1, 64 + 64) < 0.5).expand(50, -1)   # 50 copies of one mask
        >>> masks = parents.clone(); masks[:, 5] ^= True               # every child flips bit 5
        >>> lineage = Lineage(parents, torch.zeros(50, dtype=torch.long), flips=torch.arange(50) * 128 + 5)
        >>> x = torch.randn(3)
        >>> fast = ParticleForward(net, path="incremental")(x, masks, lineage)
        >>> torch.allclose(fast, net.forward_particles(x, masks), atol=1e-5)
        True
    """

    def __init__(self, net: MaskedMLP, path: ParticlePath = "auto") -> None:
        self.net = net
        self.path = check_path(path)
        # The incremental sums add one weight column per flipped bit: a grouped bit would be a
        # block of columns, which the gain table below does not model.
        self._grouped_masks = net.mask_groups is not None
        if self._grouped_masks and self.path == "incremental":
            raise ValueError(
                f"the incremental path needs one mask bit per unit, but this network has mask_groups="
                f"{net.mask_groups}; use path='auto' or 'dense' (a grouped network always runs dense)"
            )
        #: The path the last call took: ``"incremental"``, ``"grouped"`` or ``"dense"``.
        self.last_path: str | None = None
        #: Distinct parents of the last call's particle set (``None`` after a dense call without lineage).
        self.last_distinct_parents: int | None = None
        self._layer = min(net.masked_layers)
        self._table_cache: tuple[tuple[int, int], Tensor] | None = None
        self._buffers: dict[int, Tensor] = {}

    def __call__(
        self,
        x: Tensor,
        masks: Tensor,
        lineage: Lineage | None = None,
        readout: Callable[[Tensor], Tensor] | None = None,
    ) -> Tensor:
        """Predictions ``[*B, N, out]`` for inputs ``x [*B, in]`` and masks ``[*B, N, D]`` (no gradients).

        ``readout`` turns the particles' last hidden activations ``[*B, N, width]`` into outputs
        instead of the network's output layer (:meth:`MaskedMLP.forward_particles`).
        """
        with torch.no_grad():
            return self._forward(x, masks, lineage, readout)

    def _forward(
        self, x: Tensor, masks: Tensor, lineage: Lineage | None, readout: Callable[[Tensor], Tensor] | None = None
    ) -> Tensor:
        self.last_path, self.last_distinct_parents = "dense", None
        valid = (
            lineage is not None and masks.dtype == torch.bool and x.dim() == masks.dim() - 1 and not self._grouped_masks
        )
        if self.path == "incremental" and not valid:
            raise ValueError("the incremental path needs a lineage, bool masks and one input [*B, in] per particle set")
        if readout is not None and self._layer == len(self.net.hidden) - 1:
            # The first masked layer feeds the output layer: no later layer for the readout to replace.
            return self.net.forward_particles(x, masks, readout)
        if self.path == "auto" and self._grouped_masks and x.dim() == masks.dim() - 1:
            return self._grouped(x, masks, readout)
        if self.path == "dense" or not valid:
            return self.net.forward_particles(x, masks, readout)
        assert lineage is not None
        self._check(x, masks, lineage)
        n = masks.shape[-2]
        total = masks[..., 0].numel()
        groups, child_group = group_copies(flat_particle_index(lineage.ancestors, n))
        self.last_distinct_parents = groups.numel()
        if self.path == "auto" and not self._pays(groups.numel(), total, lineage.flips.numel()):
            return self.net.forward_particles(x, masks, readout)
        self.last_path = "incremental"
        return self._incremental(x, masks, lineage, groups, child_group, readout)

    def _grouped(self, x: Tensor, masks: Tensor, readout: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """A grouped network's particles: the layer after the first masked one from its groups' contributions.

        With ``G`` bits on the first masked layer, each bit switches a block of units, so that
        layer's successor sees ``pre = b + sum_g bit_g * c_g``, where ``c_g`` is the block's
        contribution ``W[:, block_g] @ h[block_g] / keep``, the same for every particle of a batch
        element. The contributions cost one dense row per batch element; each particle then costs
        ``G`` multiply-adds per output instead of the layer's width. Later layers run per particle.
        """
        net, layer = self.net, self._layer
        batch, n, dim = masks.shape[:-2], masks.shape[-2], masks.shape[-1]
        elements = masks[..., 0, 0].numel()
        h = x
        for linear in list(net.linears)[: layer + 1]:  # slicing a ModuleList builds a new Module
            h = net.act(linear(h))
        groups = net.mask_groups
        assert groups is not None
        following = _linear(net, layer + 1)
        blocks = h.reshape(elements, groups, -1) * (1.0 / net.keep_prob)  # [B, G, width / G]
        weight = following.weight.reshape(following.out_features, groups, -1)  # [out, G, width / G]
        contributions = torch.einsum("bgk,ogk->bgo", blocks, weight)  # [B, G, out]
        sl = net.mask_slices[layer]
        assert sl is not None
        bits = masks.reshape(elements, n, dim)[..., sl].to(h.dtype)  # [B, N, G], 0 and 1 for bools
        pre = torch.baddbmm(following.bias, bits, contributions)  # [B, N, out]
        flat_masks = masks.reshape(elements * n, dim)
        h = pre.reshape(elements * n, -1)
        self.last_path = "grouped"
        for i in range(layer + 1, len(net.hidden)):
            h = net.act(h)
            later = net.mask_slices[i]
            if later is not None:
                h = net._masked(h, flat_masks[:, later].to(h.dtype) * (1.0 / net.keep_prob))
            if i == len(net.hidden) - 1 and readout is not None:
                return readout(h.reshape(*batch, n, h.shape[-1]))
            h = _linear(net, i + 1)(h)
        return h.reshape(*batch, n, h.shape[-1])

    def _pays(self, distinct: int, total: int, flips: int) -> bool:
        if self._layer == len(self.net.hidden) - 1:
            return False  # the next linear is the small output layer: nothing worth saving
        width = self.net.hidden[self._layer]
        # Flips outside the first masked layer's bits cost nothing; counting all of them errs dense.
        return distinct * width + SPARSE_COST * flips < total * width

    def _incremental(
        self,
        x: Tensor,
        masks: Tensor,
        lineage: Lineage,
        groups: Tensor,
        child_group: Tensor,
        readout: Callable[[Tensor], Tensor] | None = None,
    ) -> Tensor:
        net, layer = self.net, self._layer
        batch, n, dim = masks.shape[:-2], masks.shape[-2], masks.shape[-1]
        total = child_group.numel()
        inv_keep = 1.0 / net.keep_prob
        # The shared part: every layer up to the first masked one, once per batch element.
        h = x
        for linear in list(net.linears)[: layer + 1]:  # slicing a ModuleList builds a new Module
            h = net.act(linear(h))
        h = h.reshape(-1, h.shape[-1]) * inv_keep  # [B, width], scaled like a kept unit
        sl = net.mask_slices[layer]
        assert sl is not None
        width = sl.stop - sl.start
        following = _linear(net, layer + 1)

        # Once per distinct parent: ``representative`` is any member of each group (all are equal).
        representative = group_members(child_group, groups.numel())
        parent_bits = lineage.parents.reshape(total, dim).index_select(0, representative)[:, sl]
        table = self._table(following.weight, parent_bits.shape[0])
        table[width : width + groups.numel()] = self._parent_pre(parent_bits, groups // n, h, following, table)

        # Every child: its parent's row plus its flipped columns, as one weighted sum of table rows
        # per child (an embedding bag: the parent's row in the table's tail, then the flipped
        # columns of the weight). The first masked layer's bits come first in a mask (columns <
        # width); a gain table of ``h`` padded with zeros past them drops, in one lookup, both the
        # other layers' flips and flips of units the activation zeroed (they change nothing).
        flips = lineage.flips
        rows = _floor_div(flips, dim, masks.numel())
        cols = flips.sub(rows, alpha=dim)
        gains = torch.nn.functional.pad(h, (0, dim - width)).reshape(-1)  # [B * dim]
        gain = gains.index_select(0, cols if h.shape[0] == 1 else _floor_div(rows, n, total) * dim + cols)
        # Via bool: on fresh data (branch mispredictions) a float tensor's nonzero is ~1.5x slower.
        live = (gain != 0).nonzero().squeeze(-1)
        rows, cols, gain = rows.index_select(0, live), cols.index_select(0, live), gain.index_select(0, live)
        turned_on = masks.reshape(-1).index_select(0, flips.index_select(0, live))
        values = torch.where(turned_on, gain, -gain)  # + where the flip turned the bit on
        pre = _bags(table, rows, cols, values, total, head=width + child_group)

        # Every later layer: per particle, the dense way, in place; 1 / keep_prob goes into the matmul.
        h = pre
        last = len(net.hidden) - 1
        flat_masks = masks.reshape(total, dim)
        for i in range(layer + 1, last + 1):
            h = h.relu_() if net.activation == "relu" else net.act(h)
            later = net.mask_slices[i]
            scale = 1.0
            if later is not None:
                # Cast into a kept buffer: a mixed-dtype in-place multiply would allocate a fresh one.
                bits = self._buffer(-1, tuple(h.shape), h).copy_(flat_masks[:, later].view(torch.uint8))
                h.mul_(bits)
                scale = inv_keep
            if i == last and readout is not None:
                return readout((h * scale).reshape(*batch, n, h.shape[-1]))
            linear = _linear(net, i + 1)
            out = None if i == last else self._buffer(i - layer, (total, linear.out_features), h)
            h = torch.addmm(linear.bias, h, linear.weight.t(), alpha=scale, out=out)
        return h.reshape(*batch, n, h.shape[-1])

    def _parent_pre(
        self, bits: Tensor, element: Tensor, h: Tensor, following: torch.nn.Linear, table: Tensor
    ) -> Tensor:
        """Pre-activations ``[U, fan_out]`` of the distinct parents ``bits [U, width]`` of batch elements ``element``.

        Each batch element's first parent (the reference) is summed over its kept live units only,
        the others as the reference's row plus their differing columns (parents descend from a few
        common ancestors and differ in few bits), unless they differ in so many bits that the
        dense matmul is cheaper.
        """
        width = bits.shape[1]
        first = torch.searchsorted(element, torch.arange(h.shape[0], device=element.device))  # groups are sorted
        reference = bits.index_select(0, first)  # [B, width]
        rows, cols = (bits ^ reference.index_select(0, element)).nonzero(as_tuple=True)
        if SPARSE_COST * rows.numel() + h.shape[0] * width >= bits.numel():
            return following(bits.view(torch.uint8) * h.index_select(0, element))
        live_rows, live_cols = (reference & (h != 0)).nonzero(as_tuple=True)
        weights = h[live_rows, live_cols]
        reference_pre = _bags(table, live_rows, live_cols, weights, h.shape[0]).add_(following.bias)
        gain = h[element[rows], cols]
        values = torch.where(bits[rows, cols], gain, -gain)
        return _bags(table, rows, cols, values, bits.shape[0]).add_(reference_pre.index_select(0, element))

    def _buffer(self, slot: int, shape: tuple[int, ...], like: Tensor) -> Tensor:
        """Workspace ``slot`` of ``shape``, reused while shape, dtype and device stay the same."""
        buffer = self._buffers.get(slot)
        if buffer is None or buffer.shape != shape or buffer.dtype != like.dtype or buffer.device != like.device:
            buffer = self._buffers[slot] = torch.empty(shape, dtype=like.dtype, device=like.device)
        return buffer

    def _table(self, weight: Tensor, parents: int) -> Tensor:
        """``weight.t()`` as contiguous rows, then room for ``parents`` rows; cached until the weight changes.

        Each bag reads weight columns: a contiguous transpose makes each one row. The room grows
        geometrically, so a growing number of parents rarely copies the weight again.
        """
        key = (weight.data_ptr(), weight._version)
        width = weight.shape[1]
        cached = self._table_cache
        if cached is None or cached[0] != key or cached[1].shape[0] < width + parents:
            room = max(parents, 64, 2 * (cached[1].shape[0] - width) if cached is not None else 0)
            table = torch.empty(width + room, weight.shape[0], dtype=weight.dtype, device=weight.device)
            table[:width] = weight.detach().t()
            self._table_cache = cached = (key, table)
        return cached[1]

    def _check(self, x: Tensor, masks: Tensor, lineage: Lineage) -> None:
        net = self.net
        net._check_input(x)
        if masks.shape[-1] != net.mask_dim or tuple(x.shape[:-1]) != tuple(masks.shape[:-2]):
            raise ValueError(
                f"need x [*B, {net.in_features}] and masks [*B, N, {net.mask_dim}] with the same B, "
                f"got {list(x.shape)} and {list(masks.shape)}"
            )
        if lineage.parents.shape != masks.shape or lineage.ancestors.shape != masks.shape[:-1]:
            raise ValueError(
                f"lineage parents {list(lineage.parents.shape)} and ancestors {list(lineage.ancestors.shape)} "
                f"do not match masks {list(masks.shape)}"
            )


def _linear(net: MaskedMLP, index: int) -> torch.nn.Linear:
    """``net.linears[index]``, typed: a ModuleList hands out plain Modules."""
    linear = net.linears[index]
    assert isinstance(linear, torch.nn.Linear)
    return linear


def _floor_div(index: Tensor, divisor: int, bound: int) -> Tensor:
    """``index // divisor`` for int64 ``0 <= index < bound``, twice as fast as integer division.

    A power-of-two divisor (a mask of 2 x 1024 bits) is one shift. Otherwise float: exact, since
    ``index + 0.5`` is at least ``0.5 / divisor`` from any multiple of ``divisor``, far more than the
    float64 rounding error while ``bound <= 2**40``.
    """
    if divisor & (divisor - 1) == 0:
        return index >> (divisor.bit_length() - 1)
    if bound > 2**40:
        return index // divisor
    return index.to(torch.float64).add_(0.5).mul_(1.0 / divisor).long()


def _bags(
    table: Tensor, rows: Tensor, cols: Tensor, values: Tensor, num_rows: int, head: Tensor | None = None
) -> Tensor:
    """``out[r] = table[head[r]] + sum over k with rows[k] == r of values[k] * table[cols[k]]``.

    ``rows`` must be sorted. One ``embedding_bag`` call: each output row is a bag of table rows,
    weighted, so nothing of size ``num_rows x fan_out`` is read before it is written.
    """
    bag = torch.arange(num_rows, device=rows.device)
    offsets = torch.searchsorted(rows, bag)
    if head is not None:  # put row r's head entry first in its bag
        starts = offsets.add_(bag)
        index = torch.empty(num_rows + cols.numel(), dtype=torch.long, device=cols.device)
        weight = torch.empty(index.shape, dtype=values.dtype, device=values.device)
        after = torch.arange(1, cols.numel() + 1, device=rows.device).add_(rows)
        index.index_copy_(0, starts, head).index_copy_(0, after, cols)
        weight.index_fill_(0, starts, 1.0).index_copy_(0, after, values)
        cols, values, offsets = index, weight, starts
    return torch.nn.functional.embedding_bag(cols, table, offsets, mode="sum", per_sample_weights=values)
