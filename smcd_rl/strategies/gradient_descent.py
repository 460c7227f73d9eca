"""Online gradient descent on the most recent transitions: the M+G baseline (:class:`GradientDescent`)."""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

import smcd_rl.strategies.stream_weights as stream_weights
from smcd_rl.checks import check_count, check_real, checked_rows
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import Adaptation

__all__ = ["GradientDescent"]


class GradientDescent(Adaptation):
    """Online gradient descent on the most recent transitions (the M+G baseline).

    After each observation, ``steps`` SGD steps on the loss (normalised units) over the last
    ``window`` transitions update a private copy of the weights, one copy per batch element.
    :meth:`reset` restores the trained weights; the network itself never changes. An observation
    after which the weights, or their predictions for the window's inputs, are inf or NaN (an
    outlier target, a learning rate far too large) is refused with a ValueError and leaves the
    weights and the window as they were.

    The loss is the mean over the window of the mean over output dimensions of a per-residual
    loss ``rho(r)``, where ``r`` is the prediction error in normalised units (a unit is one
    standard deviation of that output in the training targets):

    * ``"mse"``: ``rho(r) = r**2``.
    * ``"huber"``: ``rho(r) = r**2`` while ``|r| <= huber_delta``, beyond it
      ``2 * huber_delta * |r| - huber_delta**2`` (twice
      :func:`torch.nn.functional.huber_loss`, so that it equals ``"mse"`` on residuals within
      ``huber_delta`` and a learning rate means the same for both losses). Its gradient is
      bounded: one corrupted observation, which stays in the window for ``window`` steps, pulls
      the weights with at most the force of a residual of ``huber_delta`` instead of a force
      that grows with its error.
    * ``"tukey"``: Tukey's biweight, ``rho(r) = (c**2 / 3) * (1 - (1 - (r / c)**2)**3)`` while
      ``|r| <= c`` and ``c**2 / 3`` beyond, with ``c = TUKEY_CUT * huber_delta`` (equal to ``"mse"``
      near zero, as the Huber loss). Its gradient redescends to zero: a reading more than ``c`` off
      the current prediction does not pull at all. The Huber loss's bounded pull still adds up
      over ``steps x window`` gradient steps and, once the other residuals have shrunk, outweighs
      them; the biweight ignores such a reading. Where every residual lies beyond ``c`` (a task
      far from the trained ones), it does not adapt: it falls back on the trained network.

    Args:
        lr: learning rate.
        steps: gradient steps per observation.
        window: how many recent transitions the loss uses.
        loss: ``"mse"`` (squared error), ``"huber"`` (squared, then linear beyond ``huber_delta``)
            or ``"tukey"`` (squared near zero, flat beyond ``TUKEY_CUT * huber_delta``).
        huber_delta: the robust losses' scale, in normalised units (``1.0`` is one standard
            deviation of the training targets, of each output): where the Huber loss turns
            linear; Tukey's is flat beyond :data:`smcd_rl.strategies.base.TUKEY_CUT` times it. Positive and finite; unused
            with ``loss="mse"``.

    Example:
        >>> import smcd_rl
        >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(8, 8))
        >>> model = smcd_rl.AdaptiveModel(
        ...     net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.GradientDescent(lr=0.01, steps=1, window=10))
        >>> smcd_rl.GradientDescent(lr=0.01, window=10, loss="huber", huber_delta=2.0)
        GradientDescent(lr=0.01, steps=1, window=10, loss='huber', huber_delta=2.0)
    """

    name = "gradient_descent"

    #: The losses ``loss`` takes.
    LOSSES: ClassVar[tuple[str, ...]] = ("mse", "huber", "tukey")

    # Always every argument, so that type(s)(**s.config()) is the same strategy; configs saved
    # before ``loss`` existed lack it and rebuild with its default, "mse", which they used.
    _CONFIG = ("lr", "steps", "window", "loss", "huber_delta")

    def __init__(
        self,
        lr: float = 1e-2,
        steps: int = 1,
        window: int = 10,
        loss: Literal["mse", "huber", "tukey"] = "mse",
        huber_delta: float = 1.0,
    ) -> None:
        super().__init__()
        self.lr = check_real(lr, "lr", low=0.0, open_low=True)
        self.steps = check_count(steps, "steps")
        self.window = check_count(window, "window")
        if not isinstance(loss, str) or loss not in self.LOSSES:
            raise ValueError(f"loss must be one of {list(self.LOSSES)}, got {loss!r}")
        self.loss: Literal["mse", "huber", "tukey"] = loss
        # Checked even with loss="mse": config() records it, and a bad value should fail here,
        # not when someone later switches the loss.
        try:
            # Finite too: inf - inf in the linear branch would make NaN gradients (loss="mse" is the squared loss).
            self.huber_delta = check_real(huber_delta, "huber_delta", low=0.0, high=sys.float_info.max, open_low=True)
        except ValueError:
            raise ValueError(
                f"huber_delta must be positive and finite (normalised units: 1.0 is one standard deviation "
                f"of the training targets), got {huber_delta}"
            ) from None
        self._params: dict[str, Tensor] = {}
        self._inputs: Tensor | None = None
        self._targets: Tensor | None = None
        self._count: Tensor | None = None  # transitions seen, per batch element
        self._output_scale = torch.tensor(1.0)

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        self._output_scale = output_scale.detach()  # to check predictions in the target's units

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self._batch_shape = batch_shape
        net = self.net
        flat = math.prod(batch_shape)
        self._params = stream_weights.stream_copies(net, flat)
        weight = net.readout_layer.weight  # the buffers take the network's device and dtype
        # The window holds what the stepped layers read: the input, or a frozen trunk's features.
        self._inputs = weight.new_zeros(flat, self.window, self._params["linears.0.weight"].shape[-1])
        self._targets = weight.new_zeros(flat, self.window, net.out_features)
        device = weight.device
        self._count = torch.zeros(flat, dtype=torch.long, device=device)

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        assert self._inputs is not None and self._targets is not None and self._count is not None, "call reset() first"
        self._check_transition(inputs, targets)
        rows = torch.arange(self._count.numel(), device=self._count.device)
        slot = self._count % self.window  # a ring buffer per batch element
        before = (self._count, self._inputs[rows, slot].clone(), self._targets[rows, slot].clone())
        self._inputs[rows, slot] = self.net.trunk(inputs.reshape(-1, inputs.shape[-1]))
        self._targets[rows, slot] = targets.reshape(-1, targets.shape[-1]).to(self._targets.dtype)
        self._count = self._count + 1
        # Slots filled so far count in the loss; the rest (after a reset) do not.
        filled = (torch.arange(self.window, device=rows.device) < self._count.unsqueeze(-1)).to(self._inputs.dtype)
        # The steps write into new tensors, so the weights before the observation stay for a refusal
        # to put back. A few streams at a time take every step, while their weights are in the cache.
        stepped = {k: torch.empty_like(v) for k, v in self._params.items()}
        finite = True
        for streams in stream_weights.stream_chunks(self._params):
            into = {k: v[streams] for k, v in stepped.items()}
            params = {k: v[streams] for k, v in self._params.items()}
            for _ in range(self.steps):
                params = stream_weights.sgd_step(
                    self.net,
                    params,
                    self._inputs[streams],
                    self._targets[streams],
                    filled[streams],
                    lr=self.lr,
                    loss=self.loss,
                    delta=self.huber_delta,
                    out=into,
                )
            finite = self._predicts_finite(into, self._inputs[streams], filled[streams])  # while in the cache
            if not finite:
                break
        if finite:
            self._params = stepped
        else:
            # Put everything back, so that one outlier does not leave NaN weights for good.
            self._count = before[0]
            self._inputs[rows, slot], self._targets[rows, slot] = before[1], before[2]
            raise ValueError(
                "gradient descent diverged on this observation (its weights, or its predictions for the "
                "observed inputs, became inf or NaN); the adaptation state is unchanged. Drop the outlier, "
                f"or lower the learning rate (lr={self.lr})"
            )

    def _predicts_finite(self, params: dict[str, Tensor], inputs: Tensor, filled: Tensor) -> bool:
        """Whether the weights ``params`` are finite and predict finite values, in the target's units, for the window.

        Finite weights are not enough: one step on a 1e18 target (or with a huge ``lr``) leaves
        weights of 1e20 that predict inf. Checked on the observed inputs, where the loss pulled the
        weights, and after the model's de-normalisation (``* output_scale``), where a float32 value
        of 1e37 becomes inf.
        """
        if not stream_weights.all_finite(params):
            return False
        prediction = stream_weights.forward(self.net, params, inputs)
        observed = prediction[filled.to(torch.bool)]  # the empty slots after a reset hold no input
        return bool(torch.isfinite(observed * self._output_scale).all())

    def state_dict(self) -> dict[str, Any]:
        inputs, targets, count = self._state()
        return {
            "params": {k: v.clone() for k, v in self._params.items()},
            "inputs": inputs.clone(),
            "targets": targets.clone(),
            "count": count.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._checked_state(state)
        self._params = {k: v.clone() for k, v in state["params"].items()}
        self._inputs, self._targets = state["inputs"].clone(), state["targets"].clone()
        self._count = state["count"].clone()

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        self._checked_state(state)
        inputs, targets, count = self._state()
        rows = checked_rows(torch.as_tensor(rows, device=count.device), self._batch_shape).reshape(-1)

        def pick(saved: Tensor, current: Tensor) -> Tensor:
            return torch.where(rows.reshape(-1, *([1] * (current.dim() - 1))), saved, current)

        self._params = {k: pick(state["params"][k], p) for k, p in self._params.items()}
        self._inputs, self._targets = pick(state["inputs"], inputs), pick(state["targets"], targets)
        self._count = pick(state["count"], count)

    def _state(self) -> tuple[Tensor, Tensor, Tensor]:
        if self._inputs is None or self._targets is None or self._count is None:
            raise RuntimeError("GradientDescent has no weights yet; call model.reset() first")
        return self._inputs, self._targets, self._count

    def _checked_state(self, state: Any) -> None:
        """Refuse ``state`` unless it is a :meth:`state_dict` of this strategy at its batch shape, finite."""
        inputs, targets, count = self._state()
        buffers = {"inputs": inputs, "targets": targets, "count": count}
        if (
            not isinstance(state, Mapping)
            or state.keys() != {"params", *buffers}
            or not isinstance(state["params"], Mapping)
        ):
            raise ValueError(
                f"a gradient descent state is a dict of {sorted(['params', *buffers])} (its state_dict()), got "
                f"{sorted(state) if isinstance(state, Mapping) else type(state).__name__}"
            )
        # Every tensor by one name: a weight "params.linears.0.weight", a buffer its own name.
        own = {**{f"params.{k}": v for k, v in self._params.items()}, **buffers}
        given = {**{f"params.{k}": v for k, v in state["params"].items()}, **{k: state[k] for k in buffers}}
        for name, value in own.items():
            got = given.get(name)
            if not isinstance(got, Tensor) or got.shape != value.shape or got.dtype != value.dtype:
                described = f"{got.dtype} {list(got.shape)}" if isinstance(got, Tensor) else type(got).__name__
                raise ValueError(
                    f"a gradient descent state whose {name} is {described}, this one's {value.dtype} "
                    f"{list(value.shape)} (another batch size or network?); reset the model to the batch shape it "
                    "was saved with"
                )
            if got.is_floating_point() and not bool(torch.isfinite(got).all()):
                raise ValueError(f"a gradient descent state with inf or NaN in its {name}; pass its state_dict()")
        if given.keys() != own.keys():
            raise ValueError(f"a gradient descent state with weights {sorted(given)}, this one's {sorted(own)}")

    def predict(self, inputs: Tensor) -> Tensor:
        self._extra_dims(inputs)
        flat = inputs.reshape(math.prod(self._batch_shape), -1, inputs.shape[-1])
        out = stream_weights.forward(self.net, self._params, self.net.trunk(flat))
        return out.reshape(*inputs.shape[:-1], out.shape[-1])
