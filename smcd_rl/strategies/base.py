"""The contract every adaptation strategy keeps: :class:`Adaptation`.

A strategy works in the network's normalised units; :class:`smcd_rl.AdaptiveModel` does the
conversion and the TensorDict plumbing. Every strategy (:mod:`smcd_rl.strategies`) keeps this
one interface, so experiments and :func:`smcd_rl.tune` swap them by name through the registry
(:mod:`smcd_rl.strategies.registry`).

Example:
    >>> import torch, smcd_rl
    >>> class Shift(smcd_rl.Adaptation):  # predicts the trained network plus the last residual
    ...     name = "shift"
    ...     def reset(self, batch_shape):
    ...         self._batch_shape, self.offset = batch_shape, torch.zeros(*batch_shape, self.net.out_features)
    ...     def observe(self, inputs, targets):
    ...         self.offset = targets - self.net(inputs)
    ...     def predict(self, inputs):
    ...         return self.net(inputs) + self.offset
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee", adaptation=Shift())
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from smcd_rl.checks import check_real, check_real_tensor
from smcd_rl.masked_mlp import MaskedMLP

__all__ = ["Adaptation", "is_auto", "checked_noise", "checked_likelihood", "Likelihood", "TUKEY_CUT"]

#: Tukey's biweight (gradient descent's ``loss="tukey"``, the Bayesian last layer's
#: ``likelihood="tukey"``) ignores a residual beyond this many units of its scale: the classic
#: constant, at which the biweight keeps 95 % of least squares' efficiency on Gaussian residuals.
TUKEY_CUT = 4.685

#: The observation likelihoods of the strategies that weigh residuals (SMCD, the Bayesian last layer).
Likelihood = Literal["gaussian", "student-t"]


class Adaptation(ABC):
    """Base class of the strategies. A strategy instance serves one model at a time."""

    name: ClassVar[str]

    #: The constructor arguments :meth:`config` reports, each kept in the attribute of its name.
    _CONFIG: ClassVar[tuple[str, ...]] = ()

    def __init__(self) -> None:
        self._net: MaskedMLP | None = None
        self._batch_shape: tuple[int, ...] = ()

    # -------------------------------------------------------------- called by the model
    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        """Attach to ``net``; ``output_scale`` converts the target's units to normalised ones.

        ``calibration`` is the model's :attr:`smcd_rl.AdaptiveModel.calibration` (``None`` if it has
        none), for strategies whose settings come from it.
        """
        self._net = net

    @abstractmethod
    def reset(self, batch_shape: tuple[int, ...]) -> None:
        """Forget everything adapted so far; keep one independent state per batch element."""

    def check_batch(self, batch_shape: tuple[int, ...]) -> None:  # noqa: B027 - a hook with a default
        """Raise ``ValueError`` if this strategy cannot keep a state for ``batch_shape``.

        :meth:`smcd_rl.AdaptiveModel.reset` asks before it changes anything, so a refused batch
        shape leaves the model and its state as they were. Every batch shape is fine by default.
        """

    @abstractmethod
    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        """Adapt to one transition per batch element: ``inputs [*B, in]``, ``targets [*B, out]``.

        ``inputs`` in the network's dtype, ``targets`` real floats of any precision, both on the
        network's device. The built-in strategies refuse anything else with a ``ValueError`` or
        ``TypeError`` (``_check_transition``, which a strategy of your own can call too), and an
        observation a strategy refuses leaves its state as it was.
        """

    @abstractmethod
    def predict(self, inputs: Tensor) -> Tensor:
        """Adapted prediction for ``inputs [*B, *extra, in]`` -> ``[*B, *extra, out]``."""

    def predict_particles(self, inputs: Tensor) -> Tensor:
        """One prediction per posterior sample, ``[*B, *extra, N, out]`` (``N = 1`` without particles)."""
        return self.predict(inputs).unsqueeze(-2)

    @property
    def mask(self) -> Tensor | None:
        """Current mask estimate ``[*B, mask_dim]``, or ``None`` if the strategy has no mask."""
        return None

    def summary(self) -> dict[str, Tensor]:
        """Diagnostics per batch element (for example ESS and log evidence)."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """A copy of the adaptation state; :meth:`load_state_dict` restores it, :meth:`restore_rows` rows of it."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:  # noqa: B027 - stateless default
        """Restore a :meth:`state_dict` exactly (random generator included), as if nothing happened since."""

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:  # noqa: B027 - stateless default
        """Put back ``state``'s batch elements where ``rows [*B]`` is True, leave the others.

        With :meth:`state_dict` this resets or updates part of a batch: save the state, act on
        the whole batch, restore the rows that should not have changed.
        """

    def config(self) -> dict[str, Any]:
        """Constructor arguments; ``type(s)(**s.config())`` is an unadapted copy."""
        return {name: getattr(self, name) for name in self._CONFIG}

    def settings(self) -> dict[str, Any]:
        """What stores this strategy (JSON types only): :meth:`config`, plus for a strategy that draws
        random numbers what repeats its draws (SMCD's seed). :meth:`from_settings` rebuilds it."""
        return self.config()

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> Adaptation:
        """A fresh strategy from :meth:`settings` (see :mod:`smcd_rl.strategies.registry`)."""
        return cls(**settings)

    # -------------------------------------------------------------- helpers
    @property
    def net(self) -> MaskedMLP:
        if self._net is None:
            raise RuntimeError(f"{type(self).__name__} is not attached to a model; pass it to AdaptiveModel(...)")
        return self._net

    def _extra_dims(self, inputs: Tensor) -> int:
        """How many batch dims ``inputs`` has beyond the model's batch shape (they broadcast).

        Inputs that are not ``[*B, *extra, in]`` real floats of the network's dtype on its device
        are refused first, with the fix (gradient descent's own weights, which bypass the
        network's checks, would read meta-device inputs and return numbers).
        """
        name = f"{type(self).__name__}.predict: inputs"
        self._check_tensor(inputs, name, same_dtype=True)
        if inputs.dim() < 1 or inputs.shape[-1] != self.net.in_features:
            raise ValueError(f"{name} of shape {list(inputs.shape)}, expected [..., {self.net.in_features}]")
        extra = inputs.dim() - 1 - len(self._batch_shape)
        if extra < 0 or tuple(inputs.shape[: len(self._batch_shape)]) != self._batch_shape:
            raise ValueError(
                f"inputs of shape {list(inputs.shape)} do not start with the model's batch shape "
                f"{list(self._batch_shape)}; call model.reset(batch_shape=...) to match"
            )
        return extra

    def _check_transition(self, inputs: Tensor, targets: Tensor) -> None:
        """Refuse an :meth:`observe` whose ``inputs`` are not ``[*B, in]`` or ``targets`` not ``[*B, out]``
        (a transposed or wrong-width tensor would otherwise be reshaped into nonsense), whose
        inputs are not of the network's dtype or targets not real floats (a complex target would
        lose its imaginary part), or either is not on the network's device (the meta device holds
        no values at all)."""
        net = self.net
        for name, value, width in (("inputs", inputs, net.in_features), ("targets", targets, net.out_features)):
            expected = (*self._batch_shape, width)
            if not isinstance(value, Tensor) or tuple(value.shape) != expected:
                shape = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(
                    f"{type(self).__name__}.observe: {name} of shape {shape}, expected {list(expected)} (the model's "
                    f"batch shape, then {width} values); call model.reset(batch_shape=...) to change the batch shape"
                )
            self._check_tensor(value, f"{type(self).__name__}.observe: {name}", same_dtype=name == "inputs")

    def _check_tensor(self, value: Any, name: str, *, same_dtype: bool) -> None:
        """Refuse ``value`` unless it is a real float tensor (of the network's dtype if ``same_dtype``) on its device."""
        check_real_tensor(value, name)
        weight = self.net.readout_layer.weight
        if not value.is_floating_point() or (same_dtype and value.dtype != weight.dtype):
            raise TypeError(
                f"{name} of dtype {value.dtype}, expected the network's {weight.dtype}; convert them with "
                f".to({weight.dtype}) (or the model with model.to(...))"
            )
        if value.device != weight.device:
            raise ValueError(
                f"{name} on {value.device}, the network on {weight.device}; move them with "
                f".to({str(weight.device)!r}) (or the model with model.to(...))"
            )

    def _mask_view(self, value: Tensor, inputs: Tensor, trailing: int) -> Tensor:
        """View ``value [*B, *rest]`` with singleton dims for ``inputs``' extra batch dims."""
        extra = self._extra_dims(inputs)
        rest = value.shape[value.dim() - trailing :]
        return value.reshape(*self._batch_shape, *([1] * extra), *rest)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.config().items())
        return f"{type(self).__name__}({args})"


def is_auto(value: Any) -> bool:
    return isinstance(value, str) and value == "auto"


def checked_noise(noise_std: Any, *, auto: bool = True) -> Tensor:
    """``noise_std`` as a float tensor if it is a positive finite scalar or 1-d sequence, else a clear error
    (which names ``'auto'`` among the choices where the caller takes it)."""
    try:
        noise = torch.as_tensor(noise_std)
    except (TypeError, ValueError, RuntimeError) as err:
        choices = (
            "a positive number, a sequence of them or 'auto'" if auto else "a positive number or a sequence of them"
        )
        raise TypeError(f"noise_std must be {choices}, got {noise_std!r}") from err
    if noise.dtype == torch.bool or noise.is_complex() or not (noise.is_floating_point() or noise.dtype.is_signed):
        raise TypeError(f"noise_std must be a positive number or a sequence of them, got {noise_std!r}")
    noise = noise.to(torch.float32)
    if noise.dim() > 1 or noise.numel() == 0 or not bool((noise > 0).all()) or not bool(torch.isfinite(noise).all()):
        raise ValueError(f"noise_std must be a positive finite scalar or 1-d sequence, got {noise_std}")
    return noise


def checked_likelihood(likelihood: Any, dof: Any, *, also: tuple[str, ...] = ()) -> tuple[str, float]:
    """``likelihood`` and the Student-t's degrees of freedom ``dof``, checked (``dof`` is checked with any
    likelihood, so that a bad value fails now and not when the likelihood is switched). ``also``: the
    caller's further likelihoods (the Bayesian last layer's ``"tukey"``)."""
    choices = ("gaussian", "student-t", *also)
    if not isinstance(likelihood, str) or likelihood not in choices:
        raise ValueError(f"likelihood must be {' or '.join(repr(c) for c in choices)}, got {likelihood!r}")
    return likelihood, check_real(dof, "dof", low=0.0, high=1e12, open_low=True)  # beyond, use likelihood="gaussian"
