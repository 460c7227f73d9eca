"""Adaptation strategies: how a trained masked network changes in response to real observations.

A strategy works in the network's normalised units; :class:`smcd_rl.AdaptiveModel` does the
conversion and the TensorDict plumbing. All three share one interface, so experiments swap them
by name (:func:`make_adaptation`).
"""

from __future__ import annotations

import importlib
import math
import sys
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from smcd_rl import stream_weights
from smcd_rl.checks import check_count, check_real
from smcd_rl.filter import SMCDFilter, Transition, check_transition
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.particle_forward import Lineage, ParticleForward, ParticlePath, check_path
from smcd_rl.resampling import ResamplingScheme, check_scheme

__all__ = ["Adaptation", "SMCD", "GradientDescent", "NoAdaptation", "make_adaptation", "ADAPTATIONS"]


class Adaptation(ABC):
    """Base class of the strategies. A strategy instance serves one model at a time."""

    name: ClassVar[str]

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

    @abstractmethod
    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        """Adapt to one transition per batch element: ``inputs [*B, in]``, ``targets [*B, out]``."""

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
        return {}

    # -------------------------------------------------------------- helpers
    @property
    def net(self) -> MaskedMLP:
        if self._net is None:
            raise RuntimeError(f"{type(self).__name__} is not attached to a model; pass it to AdaptiveModel(...)")
        return self._net

    def _extra_dims(self, inputs: Tensor) -> int:
        """How many batch dims ``inputs`` has beyond the model's batch shape (they broadcast)."""
        extra = inputs.dim() - 1 - len(self._batch_shape)
        if extra < 0 or tuple(inputs.shape[: len(self._batch_shape)]) != self._batch_shape:
            raise ValueError(
                f"inputs of shape {list(inputs.shape)} do not start with the model's batch shape "
                f"{list(self._batch_shape)}; call model.reset(batch_shape=...) to match"
            )
        return extra

    def _mask_view(self, value: Tensor, inputs: Tensor, trailing: int) -> Tensor:
        """View ``value [*B, *rest]`` with singleton dims for ``inputs``' extra batch dims."""
        extra = self._extra_dims(inputs)
        rest = value.shape[value.dim() - trailing :]
        return value.reshape(*self._batch_shape, *([1] * extra), *rest)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.config().items())
        return f"{type(self).__name__}({args})"


class NoAdaptation(Adaptation):
    """Predict with the trained network as it is (dropout off): the M+N baseline.

    Example:
        >>> import smcd_rl
        >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(8,))
        >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.NoAdaptation())
    """

    name = "none"

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self._batch_shape = batch_shape

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        pass

    def predict(self, inputs: Tensor) -> Tensor:
        return self.net(inputs)


class SMCD(Adaptation):
    """Sequential Monte Carlo Dropout: a particle filter over the network's dropout masks.

    Predictions use the MMSE (weighted mean) mask, or with ``prediction="predictive"`` the mean of
    the posterior predictive (the weighted mean of every particle's prediction: N forward passes
    instead of one); :meth:`predict_particles` gives the posterior predictive of eq. (5), one
    prediction per particle, and :meth:`predictive` its mean and variance. ``keep_prob`` comes
    from the network.

    Args:
        num_particles: masks in the particle set.
        flip_prob: per-bit flip probability of the transition, or ``"auto"``: the one
            :func:`smcd_rl.calibrate` stored with the model this strategy is attached to.
        noise_std: measurement noise of the Gaussian likelihood, in the target's own units;
            a scalar or one value per output dimension, or ``"auto"``: the noise
            :func:`smcd_rl.calibrate` stored with the model. Calibration chooses noise and
            flip probability together, so pass both as ``"auto"`` unless you fixed the flip
            probability when calibrating. :meth:`reset` raises ``ValueError`` if the model has
            no calibration.
        resampling: resampling scheme (see :class:`smcd_rl.SMCDFilter`).
        ess_threshold: resample when ESS < ``ess_threshold * N``.
        generator: random source of the filter (default: seeded from torch's global generator).
        transition: how masks move between steps: ``"keep_rate"`` keeps them distributed as in
            training (the paper's xor flips at dropout 0.5), ``"symmetric"`` flips every bit
            with ``flip_prob`` (see :class:`smcd_rl.SMCDFilter`).
        forward_path: how an update runs the particles through the network: ``"auto"`` takes the
            exact incremental path (pre-activations once per distinct parent plus the flipped
            columns, :mod:`smcd_rl.particle_forward`) when it is cheaper, and for a grouped
            network (``mask_groups``) the next layer from each group's contribution; ``"dense"``
            always runs every particle in full, ``"incremental"`` forces the incremental path.
        prediction: ``"mask"`` (the network under the MMSE mask, the paper's choice) or
            ``"predictive"`` (the posterior predictive mean).
        likelihood: ``"gaussian"`` (eq. 1) or ``"student-t"``: independent Student-t errors of
            scale ``noise_std`` and ``dof`` degrees of freedom per output, whose heavy tails let
            a misspecified network's rare large residuals cost less than a Gaussian's.
        dof: degrees of freedom of the Student-t likelihood (> 0).

    Example:
        >>> import smcd_rl
        >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(8, 8))
        >>> smcd = smcd_rl.SMCD(num_particles=100, flip_prob=0.01, noise_std=0.05)
        >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd)
        >>> model.calibration = {"noise_std": [0.02, 0.03], "flip_prob": 0.003}  # as smcd_rl.calibrate stores it
        >>> model.fitted = True  # a toy network: declare it trained
        >>> auto = model.with_adaptation(smcd_rl.SMCD(num_particles=100, noise_std="auto", flip_prob="auto"))
        >>> auto.reset()
        >>> auto.adaptation.filter.flip_prob
        0.003
    """

    name = "smcd"

    def __init__(
        self,
        num_particles: int = 1000,
        flip_prob: float | Literal["auto"] = 0.01,
        noise_std: float | Sequence[float] | Literal["auto"] = 0.05,
        resampling: ResamplingScheme = "systematic",
        ess_threshold: float = 1.0,
        generator: torch.Generator | None = None,
        transition: Transition = "keep_rate",
        forward_path: ParticlePath = "auto",
        prediction: Literal["mask", "predictive"] = "mask",
        likelihood: Literal["gaussian", "student-t"] = "gaussian",
        dof: float = 4.0,
    ) -> None:
        super().__init__()
        check_scheme(resampling)
        if prediction not in ("mask", "predictive"):
            raise ValueError(
                f"prediction must be 'mask' (the MMSE mask) or 'predictive' (its mean), got {prediction!r}"
            )
        self.prediction: Literal["mask", "predictive"] = prediction
        if likelihood not in ("gaussian", "student-t"):
            raise ValueError(f"likelihood must be 'gaussian' or 'student-t', got {likelihood!r}")
        self.likelihood: Literal["gaussian", "student-t"] = likelihood
        self.dof = check_real(dof, "dof", low=0.0, high=1e12, open_low=True)  # beyond, use likelihood="gaussian"
        self.num_particles = check_count(num_particles, "num_particles")
        self.flip_prob: float | Literal["auto"] = (
            "auto" if _is_auto(flip_prob) else check_real(flip_prob, "flip_prob", low=0.0, high=1.0)
        )
        self.ess_threshold = check_real(ess_threshold, "ess_threshold", low=0.0, high=1.0)
        noise = torch.tensor(1.0) if _is_auto(noise_std) else _checked_noise(noise_std)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        self.noise_std = noise_std
        self.resampling: ResamplingScheme = resampling
        # Checked here too, so a bad name fails at construction and not at the first reset.
        self.forward_path = check_path(forward_path, "forward_path")
        self.transition = check_transition(transition)
        self._generator = generator
        self.filter: SMCDFilter | None = None
        #: Runs the proposed particles through the network (the path of ``forward_path``).
        self.particle_forward: ParticleForward | None = None
        #: What turns last hidden activations ``[*B, ..., width]`` into outputs instead of the
        #: network's output layer: an adapted readout per stream (:class:`smcd_rl.SMCDLastLayer`).
        self.readout: Callable[[Tensor], Tensor] | None = None
        self._sigma = noise
        self._log_norm = torch.tensor(0.0)
        #: Why the strategy cannot run (an ``"auto"`` setting on a model without calibration), else None.
        self._unresolved: str | None = None

    def config(self) -> dict[str, Any]:
        noise = self.noise_std if isinstance(self.noise_std, (int, float, str)) else list(self.noise_std)
        return {
            "num_particles": self.num_particles,
            "flip_prob": self.flip_prob,
            "noise_std": noise,
            "resampling": self.resampling,
            "ess_threshold": self.ess_threshold,
            "transition": self.transition,
            "forward_path": self.forward_path,
            "prediction": self.prediction,
            "likelihood": self.likelihood,
            "dof": self.dof,
        }

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        noise_std, flip_prob = self.noise_std, self.flip_prob
        auto = [name for name, value in (("noise_std", noise_std), ("flip_prob", flip_prob)) if _is_auto(value)]
        if auto and calibration is None:
            # Not raised here: a model is built (and smcd_rl.load rebuilds one) before its
            # calibration is known; reset() raises it.
            self._unresolved = (
                f"SMCD({', '.join(f'{name}=' + repr('auto') for name in auto)}) takes its settings from the "
                "model's calibration, but this model has none; run smcd_rl.calibrate(model, episodes) first "
                "(or pass numbers)"
            )
            return
        self._unresolved = None
        calibrated = calibration or {}
        noise_value = calibrated["noise_std"] if _is_auto(noise_std) else noise_std
        flip = float(calibrated["flip_prob"] if _is_auto(flip_prob) else flip_prob)
        noise = torch.as_tensor(noise_value, dtype=output_scale.dtype, device=output_scale.device)
        if noise.dim() == 1 and noise.shape[0] not in (1, net.out_features):
            raise ValueError(f"noise_std has {noise.shape[0]} values but the model predicts {net.out_features} outputs")
        noise = noise.expand(net.out_features)
        self._sigma = noise / output_scale  # the same noise, in normalised units
        # Normalising constant in the target's own units, so log evidence is a true log density.
        if self.likelihood == "gaussian":
            self._log_norm = -noise.log().sum() - 0.5 * net.out_features * math.log(2 * math.pi)
        else:  # the Student-t density's constant: lgamma((v+1)/2) - lgamma(v/2) - log(sqrt(v pi) sigma)
            v = self.dof
            per_output = _log_gamma_ratio(v / 2) - 0.5 * math.log(v * math.pi)
            self._log_norm = -noise.log().sum() + net.out_features * per_output
        self.particle_forward = ParticleForward(net, self.forward_path)
        device = next(net.parameters()).device
        generator = self._generator
        if generator is not None and generator.device.type != device.type:
            raise ValueError(f"the SMCD generator is on {generator.device} but the network is on {device}")
        old = self.filter
        if old is not None and old.device == device and old.mask_dim == net.mask_dim:
            # Keep the filter object (and its generator) across resets: references stay valid and
            # a seeded run is one random stream, not a reseed per episode.
            old.keep_prob = net.keep_prob
            old.flip_prob = flip  # a calibrated ("auto") one may have changed since
            old.flip_rates()  # the new keep_prob may not admit flip_prob
            old._num_particles = self.num_particles  # a reset undoes any online resize()
            return
        self.filter = SMCDFilter(
            net.mask_dim,
            num_particles=self.num_particles,
            flip_prob=flip,
            keep_prob=net.keep_prob,
            resampling=self.resampling,
            ess_threshold=self.ess_threshold,
            generator=generator,
            device=device,
            transition=self.transition,
        )

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self._batch_shape = batch_shape
        self._filter.reset(batch_shape)

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        sigma, log_norm, filt, forward = self._sigma, self._log_norm, self._filter, self.particle_forward
        student, dof = self.likelihood == "student-t", self.dof
        assert forward is not None
        parents = filt.particles
        assert parents is not None
        ancestors = filt.ancestors
        if ancestors is None:  # unknown copies: each particle is its own parent, always true
            ancestors = torch.arange(parents.shape[-2], device=parents.device).expand(parents.shape[:-1])

        def log_likelihood(masks: Tensor) -> Tensor:
            assert filt.last_flips is not None  # the transition that proposed ``masks`` set them
            lineage = Lineage(parents, ancestors, filt.last_flips)
            predictions = forward(inputs, masks, lineage, readout=self.readout)
            residual = (targets.unsqueeze(-2) - predictions) / sigma
            if student:
                return log_norm - (dof + 1) / 2 * torch.log1p(residual.square() / dof).sum(-1)
            return log_norm - 0.5 * residual.square().sum(-1)

        self._filter.update(log_likelihood)

    def predict(self, inputs: Tensor) -> Tensor:
        if self.prediction == "predictive":
            weights = self._mask_view(self._filter.weights, inputs, trailing=1).unsqueeze(-1)  # [*B, *1, N, 1]
            return (weights * self.predict_particles(inputs)).sum(-2)
        mask = self._mask_view(self._filter.mean_mask, inputs, trailing=1)
        if self.readout is not None:
            return self.readout(self.net.features(inputs, mask=mask))
        return self.net(inputs, mask=mask)

    def predict_particles(self, inputs: Tensor) -> Tensor:
        masks = self._mask_view(self._filter.particles, inputs, trailing=2)  # type: ignore[arg-type]
        return self.net.forward_particles(inputs, masks, self.readout)

    def predictive(self, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and variance of the posterior predictive for ``inputs [*B, *extra, in]``, in normalised units.

        The mean is the weighted mean of the particles' predictions (what ``prediction="predictive"``
        predicts, whatever this strategy's ``prediction``). The variance, per output, is the particles'
        weighted spread around that mean, ``sum_i w_i (f_i - mean)^2``, plus the variance of the
        likelihood's noise: ``noise_std**2``, or for the Student-t ``noise_std**2 * dof / (dof - 2)``
        (``inf`` for ``dof <= 2``, where the Student-t has no variance).
        :meth:`smcd_rl.AdaptiveModel.predictive` gives both in the target's units.

        Returns:
            ``(mean, variance)``, each ``[*B, *extra, out]``.

        Example:
            >>> import torch, smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> smcd = smcd_rl.SMCD(num_particles=20, noise_std=0.1)
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee",
            ...                               adaptation=smcd)
            >>> model.reset()
            >>> mean, variance = smcd.predictive(torch.zeros(5, 2))  # 5 inputs (planning candidates, say)
            >>> mean.shape, bool((variance >= 0.1**2 - 1e-6).all())  # never below the noise
            (torch.Size([5, 2]), True)
        """
        predictions = self.predict_particles(inputs)  # [*B, *extra, N, out]
        weights = self._mask_view(self._filter.weights, inputs, trailing=1).unsqueeze(-1)  # [*B, *1, N, 1]
        mean = (weights * predictions).sum(-2)  # as predict() computes it, so the two agree exactly
        spread = (weights * (predictions - mean.unsqueeze(-2)).square()).sum(-2)
        return mean, spread + self._noise_variance().to(spread)

    def _noise_variance(self) -> Tensor:
        """The likelihood's noise variance per output, in normalised units."""
        variance = self._sigma.square()
        if self.likelihood == "gaussian":
            return variance
        if self.dof <= 2:
            return torch.full_like(variance, math.inf)
        return variance * (self.dof / (self.dof - 2))

    @property
    def mask(self) -> Tensor:
        return self._filter.mean_mask

    @property
    def particles(self) -> Tensor:
        """Current mask particles ``[*B, N, mask_dim]`` (bool)."""
        return self._filter.particles  # type: ignore[return-value]

    def summary(self) -> dict[str, Tensor]:
        # The ESS of the last update before resampling: after resampling it is always N.
        return {"ess": self._filter.last_ess, "log_evidence": self._filter.log_evidence}  # type: ignore[dict-item]

    def state_dict(self) -> dict[str, Any]:
        return self._filter.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._filter.load_state_dict(state)

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        self._filter.restore_rows(state, rows)

    @property
    def _filter(self) -> SMCDFilter:
        if self._unresolved is not None:
            raise ValueError(self._unresolved)
        if self.filter is None:
            raise RuntimeError("SMCD is not attached to a model; pass it to AdaptiveModel(...)")
        return self.filter


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

    Args:
        lr: learning rate.
        steps: gradient steps per observation.
        window: how many recent transitions the loss uses.
        loss: ``"mse"`` (squared error) or ``"huber"`` (squared, then linear beyond ``huber_delta``).
        huber_delta: where the Huber loss turns linear, in normalised units: ``1.0`` is one
            standard deviation of the training targets (of each output). Positive and finite;
            unused with ``loss="mse"``.

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
    LOSSES: ClassVar[tuple[str, ...]] = ("mse", "huber")

    def __init__(
        self,
        lr: float = 1e-2,
        steps: int = 1,
        window: int = 10,
        loss: Literal["mse", "huber"] = "mse",
        huber_delta: float = 1.0,
    ) -> None:
        super().__init__()
        self.lr = check_real(lr, "lr", low=0.0, open_low=True)
        self.steps = check_count(steps, "steps")
        self.window = check_count(window, "window")
        if not isinstance(loss, str) or loss not in self.LOSSES:
            raise ValueError(f"loss must be one of {list(self.LOSSES)}, got {loss!r}")
        self.loss: Literal["mse", "huber"] = loss
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

    def config(self) -> dict[str, Any]:
        # Always every argument, so that type(s)(**s.config()) is the same strategy; configs saved
        # before ``loss`` existed lack it and rebuild with its default, "mse", which they used.
        return {
            "lr": self.lr,
            "steps": self.steps,
            "window": self.window,
            "loss": self.loss,
            "huber_delta": self.huber_delta,
        }

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        self._output_scale = output_scale.detach()  # to check predictions in the target's units

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self._batch_shape = batch_shape
        net = self.net
        flat = math.prod(batch_shape)
        self._params = stream_weights.stream_copies(net, flat)
        weight = next(net.parameters())  # the buffers take the network's device and dtype
        self._inputs = weight.new_zeros(flat, self.window, net.in_features)
        self._targets = weight.new_zeros(flat, self.window, net.out_features)
        device = weight.device
        self._count = torch.zeros(flat, dtype=torch.long, device=device)

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        assert self._inputs is not None and self._targets is not None and self._count is not None, "call reset() first"
        rows = torch.arange(self._count.numel(), device=self._count.device)
        slot = self._count % self.window  # a ring buffer per batch element
        before = (self._count, self._inputs[rows, slot].clone(), self._targets[rows, slot].clone())
        self._inputs[rows, slot] = inputs.reshape(-1, inputs.shape[-1])
        self._targets[rows, slot] = targets.reshape(-1, targets.shape[-1])
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
        assert self._inputs is not None and self._targets is not None and self._count is not None, "call reset() first"
        return {
            "params": {k: v.clone() for k, v in self._params.items()},
            "inputs": self._inputs.clone(),
            "targets": self._targets.clone(),
            "count": self._count.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._params = {k: v.clone() for k, v in state["params"].items()}
        self._inputs, self._targets = state["inputs"].clone(), state["targets"].clone()
        self._count = state["count"].clone()

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        assert self._inputs is not None and self._targets is not None and self._count is not None, "call reset() first"
        rows = rows.to(self._count.device).reshape(-1)

        def pick(saved: Tensor, current: Tensor) -> Tensor:
            return torch.where(rows.reshape(-1, *([1] * (current.dim() - 1))), saved, current)

        self._params = {k: pick(state["params"][k], p) for k, p in self._params.items()}
        self._inputs, self._targets = pick(state["inputs"], self._inputs), pick(state["targets"], self._targets)
        self._count = pick(state["count"], self._count)

    def predict(self, inputs: Tensor) -> Tensor:
        self._extra_dims(inputs)
        flat = inputs.reshape(math.prod(self._batch_shape), -1, inputs.shape[-1])
        out = stream_weights.forward(self.net, self._params, flat)
        return out.reshape(*inputs.shape[:-1], out.shape[-1])


def _is_auto(value: Any) -> bool:
    return isinstance(value, str) and value == "auto"


def _checked_noise(noise_std: Any, *, auto: bool = True) -> Tensor:
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


#: Strategy classes by name, for configuration files and the CLI.
ADAPTATIONS: dict[str, type[Adaptation]] = {
    "none": NoAdaptation,
    "gradient_descent": GradientDescent,
    "smcd": SMCD,
}


def make_adaptation(name: Literal["none", "gradient_descent", "smcd"] | str, **kwargs: Any) -> Adaptation:
    """Build a strategy by name: ``"none"``, ``"gradient_descent"`` (alias ``"gd"``), ``"smcd"``,
    ``"last_layer"``, ``"smcd_last_layer"`` or ``"combination"``.

    Example:
        >>> import smcd_rl
        >>> smcd_rl.make_adaptation("smcd", num_particles=10)
        SMCD(num_particles=10, flip_prob=0.01, noise_std=0.05, resampling='systematic', ess_threshold=1.0, transition='keep_rate', forward_path='auto', prediction='mask', likelihood='gaussian', dof=4.0)
    """
    return adaptation_class({"gd": "gradient_descent"}.get(name, name))(**kwargs)


#: Strategies defined in modules that build on this one: each registers its name when imported.
_REGISTERED_BY = {
    "combination": "smcd_rl.combination",
    "last_layer": "smcd_rl.last_layer",
    "smcd_last_layer": "smcd_rl.smcd_last_layer",
}


def adaptation_class(name: str) -> type[Adaptation]:
    """The strategy class registered as ``name`` (importing the module that defines it).

    Raises:
        ValueError: no strategy has that name.
    """
    if name in _REGISTERED_BY:
        importlib.import_module(_REGISTERED_BY[name])
    if name not in ADAPTATIONS:
        known = sorted({*ADAPTATIONS, *_REGISTERED_BY})
        raise ValueError(f"unknown adaptation {name!r}; choose one of {known} (or 'gd')")
    return ADAPTATIONS[name]


def _log_gamma_ratio(x: float) -> float:
    """``lgamma(x + 1/2) - lgamma(x)``, accurate also where the two lgammas are huge (large ``x``)."""
    if x < 1e4:
        return math.lgamma(x + 0.5) - math.lgamma(x)
    # The asymptotic series: its next term is below 1e-19 here, where the difference of lgammas
    # would have lost every digit.
    return 0.5 * math.log(x) - 1 / (8 * x) + 1 / (192 * x**3)
