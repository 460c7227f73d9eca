"""Many private copies of one network's weights, one per stream: batched forward and SGD steps.

:class:`smcd_rl.GradientDescent` adapts a private copy of a :class:`~smcd_rl.MaskedMLP`'s
weights for every stream it serves (every episode of a batch, every sub-env of a vector env).
With ``B`` streams a linear layer's weight is a ``[B, out, in]`` tensor, and for the networks of
this package the hidden-to-hidden layers dominate: 512 x 512 floats are 1 MB per stream, so a
step over 200 streams reads and writes hundreds of MB and costs what its memory traffic costs,
not its arithmetic.

This module writes the forward pass, the backward pass and the update out as batched matrix
products instead of ``vmap(grad(...))`` over a functional call: the update of a weight is one
``baddbmm`` that adds ``-lr * delta^T h`` to the weight where it lies, with no gradient tensor
and no new copy of the weights after the first step of an observation. That is four passes over
each weight per step (forward, the backward product, read and write of the update) instead of
seven, and no large allocations. The gradients are those of the same loss, up to the order of
float summation.

Example:
    >>> import torch, smcd_rl
    >>> net = smcd_rl.MaskedMLP(2, 1, hidden=(8,)).eval()
    >>> params = stream_copies(net, streams=3)
    >>> x = torch.rand(3, 4, 2)
    >>> torch.allclose(forward(net, params, x), net(x), atol=1e-6)
    True
    >>> weight = torch.ones(3, 4)
    >>> stepped = sgd_step(net, params, x, torch.zeros(3, 4, 1), weight, lr=0.1, loss="mse", delta=1.0)
    >>> bool((forward(net, stepped, x).abs() < forward(net, params, x).abs()).all())
    True
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import TUKEY_CUT

__all__ = ["stream_copies", "stream_chunks", "forward", "sgd_step", "all_finite", "CACHE_BYTES"]

Params = dict[str, Tensor]


def stream_copies(net: MaskedMLP, streams: int) -> Params:
    """``streams`` private copies of the parameters of ``net.linears``, ``{name: [streams, *shape]}``.

    Only ``linears`` are stepped: a network's frozen :meth:`~smcd_rl.MaskedMLP.trunk` before them is
    shared by every stream.
    """
    return {f"linears.{k}": v.detach().expand(streams, *v.shape).clone() for k, v in net.linears.named_parameters()}


#: The bytes of weights a chunk of streams may hold: a few MB stay in a core's cache across the
#: passes of a step and across the steps of an observation (measured on a 2-core x86 CPU: 2 x 512
#: networks in chunks of 4 streams took 260 us per stream and step, in one batch of 32 or more 530 us).
CACHE_BYTES = 4 << 20


def stream_chunks(params: Params) -> list[slice]:
    """Consecutive ranges of streams whose weights together fit :data:`CACHE_BYTES` (at least one stream each).

    Example:
        >>> import torch, smcd_rl
        >>> params = stream_copies(smcd_rl.MaskedMLP(2, 2, hidden=(512, 512)), streams=10)
        >>> stream_chunks(params)
        [slice(0, 3, None), slice(3, 6, None), slice(6, 9, None), slice(9, 10, None)]
    """
    streams = next(iter(params.values())).shape[0]
    per_stream = sum(p[0].numel() * p.element_size() for p in params.values())
    size = max(1, CACHE_BYTES // max(per_stream, 1))
    return [slice(begin, min(begin + size, streams)) for begin in range(0, streams, size)]


def forward(net: MaskedMLP, params: Params, x: Tensor) -> Tensor:
    """Each stream's network on its own inputs: ``x [B, n, in]`` -> ``[B, n, out]`` (dropout off)."""
    return _forward(net, params, x)[0]


def sgd_step(
    net: MaskedMLP,
    params: Params,
    x: Tensor,
    targets: Tensor,
    weight: Tensor,
    *,
    lr: float,
    loss: str,
    delta: float,
    in_place: bool = False,
    out: Params | None = None,
) -> Params:
    """One SGD step of every stream on its weighted mean loss; returns the stepped parameters.

    Each stream's loss is ``sum_n weight[b, n] * mean_o rho(r[b, n, o]) / sum_n weight[b, n]``,
    the residual ``r = net(x) - targets`` and ``rho`` the squared error (``loss="mse"``) or
    twice the Huber loss of ``delta`` (``"huber"``) or Tukey's biweight of ``TUKEY_CUT * delta`` (``"tukey"``), as :class:`smcd_rl.GradientDescent` defines
    them.

    Args:
        net: the network whose architecture (and activation) the parameters follow.
        params: ``{name: [B, *shape]}``; left unchanged unless ``in_place``.
        x: inputs ``[B, n, in]``.
        targets: ``[B, n, out]``.
        weight: ``[B, n]``, each stream's weights of its ``n`` samples (a stream's sum must be > 0).
        lr: learning rate.
        loss: ``"mse"``, ``"huber"`` or ``"tukey"``.
        delta: the robust losses' scale (unused with ``"mse"``).
        in_place: update ``params``' tensors where they lie (their owner no longer needs the
            values before the step); otherwise the result holds new tensors.
        out: tensors of ``params``' shapes to write the result into (``params`` itself, or views of
            a larger buffer), instead of new ones.
    """
    if in_place:
        out = params
    prediction, pre, post = _forward(net, params, x)
    residual = prediction - targets
    if loss == "huber":
        slope = torch.where(residual.abs() <= delta, 2 * residual, 2 * delta * residual.sign())
    elif loss == "tukey":
        inside = (1 - (residual / (TUKEY_CUT * delta)).square()).clamp(min=0.0)
        slope = 2 * residual * inside.square()
    else:
        slope = 2 * residual
    # d loss / d output, per stream: the weight of each sample over the stream's total, per output.
    scale = weight / weight.sum(-1, keepdim=True) / prediction.shape[-1]
    grad_out = slope * scale.unsqueeze(-1)
    derivative = _DERIVATIVES[net.activation]
    stepped = dict(params)
    for i in reversed(range(len(net.linears))):
        w_name, b_name = f"linears.{i}.weight", f"linears.{i}.bias"
        w, b = params[w_name], params[b_name]
        # The gradient that flows on is taken through the weight before its update.
        below = derivative(torch.bmm(grad_out, w), pre[i - 1], post[i]) if i > 0 else None
        if out is not None:
            stepped[w_name] = torch.baddbmm(w, grad_out.transpose(1, 2), post[i], alpha=-lr, out=out[w_name])
            stepped[b_name] = torch.sub(b, grad_out.sum(1), alpha=lr, out=out[b_name])
        else:
            stepped[w_name] = torch.baddbmm(w, grad_out.transpose(1, 2), post[i], alpha=-lr)
            stepped[b_name] = b - lr * grad_out.sum(1)
        if below is not None:
            grad_out = below
    return stepped


def all_finite(params: Params) -> bool:
    """Whether every parameter is finite.

    A sum is finite only if every term is, so one read of each tensor settles the common case;
    only a non-finite sum (of which overflow of finite values is a cause) needs the exact check.
    """
    return all(bool(torch.isfinite(p.sum())) or bool(torch.isfinite(p).all()) for p in params.values())


def _forward(net: MaskedMLP, params: Params, x: Tensor) -> tuple[Tensor, list[Tensor], list[Tensor]]:
    """Output, each hidden layer's pre-activation and each layer's input (``post[0] = x``)."""
    pre: list[Tensor] = []
    post = [x]
    last = len(net.linears) - 1
    for i in range(last + 1):
        w, b = params[f"linears.{i}.weight"], params[f"linears.{i}.bias"]
        z = torch.baddbmm(b.unsqueeze(1), post[-1], w.transpose(1, 2))
        if i == last:
            return z, pre, post
        pre.append(z)
        post.append(net.act(z))
    raise AssertionError("unreachable: a MaskedMLP has at least one linear layer")


def _relu(grad: Tensor, z: Tensor, h: Tensor) -> Tensor:
    return grad * (z > 0)


def _tanh(grad: Tensor, z: Tensor, h: Tensor) -> Tensor:
    return grad * (1 - h.square())


def _elu(grad: Tensor, z: Tensor, h: Tensor) -> Tensor:  # alpha 1: the derivative is h + 1 below 0
    return grad * torch.where(z > 0, 1.0, h + 1)


def _silu(grad: Tensor, z: Tensor, h: Tensor) -> Tensor:
    s = torch.sigmoid(z)
    return grad * (s * (1 + z * (1 - s)))


#: The activations' derivatives, from the pre-activation ``z`` and the activation ``h`` (by
#: :class:`~smcd_rl.MaskedMLP`'s ``activation`` names).
_DERIVATIVES: dict[str, Callable[[Tensor, Tensor, Tensor], Tensor]] = {
    "relu": _relu,
    "tanh": _tanh,
    "elu": _elu,
    "silu": _silu,
}
