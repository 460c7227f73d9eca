"""Sequential Monte Carlo Dropout: a particle filter over the network's dropout masks (:class:`SMCD`)."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from smcd_rl.checks import check_count, check_real, check_seed
from smcd_rl.feature_readout import NO_MASKS, FeatureReadout
from smcd_rl.filter import SMCDFilter, Transition, check_transition
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.resampling import ResamplingScheme, check_scheme
from smcd_rl.strategies.base import Adaptation, checked_likelihood, checked_noise, is_auto
from smcd_rl.strategies.particle_forward import Lineage, ParticleForward, ParticlePath, check_path

__all__ = ["SMCD"]

#: The posterior predictive mean of many inputs per stream (a look-ahead's, a planner's) runs the
#: particles over them in pieces of at most this many particle rows (or one input per stream, if
#: the particles of the streams alone are more): its memory stays that of an observation, not that
#: many inputs' times it.
PREDICTIVE_ROWS = 1 << 16


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
            columns, :mod:`smcd_rl.strategies.particle_forward`) when it is cheaper, and for a grouped
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
    _CONFIG = (
        "num_particles",
        "flip_prob",
        "noise_std",
        "resampling",
        "ess_threshold",
        "transition",
        "forward_path",
        "prediction",
        "likelihood",
        "dof",
    )

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
        self.likelihood, self.dof = checked_likelihood(likelihood, dof)
        self.num_particles = check_count(num_particles, "num_particles")
        self.flip_prob: float | Literal["auto"] = (
            "auto" if is_auto(flip_prob) else check_real(flip_prob, "flip_prob", low=0.0, high=1.0)
        )
        self.ess_threshold = check_real(ess_threshold, "ess_threshold", low=0.0, high=1.0)
        noise = torch.tensor(1.0) if is_auto(noise_std) else checked_noise(noise_std)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        self.noise_std = noise_std
        self.resampling: ResamplingScheme = resampling
        # Checked here too, so a bad name fails at construction and not at the first reset.
        self.forward_path = check_path(forward_path, "forward_path")
        self.transition = check_transition(transition)
        self._generator = generator
        #: The seed and device the generator was made from (by :meth:`from_settings`), else empty.
        self._seeded: dict[str, Any] = {}
        self.filter: SMCDFilter | None = None
        #: Runs the proposed particles through the network (the path of ``forward_path``).
        self.particle_forward: ParticleForward | None = None
        #: What turns last hidden activations ``[*B, ..., width]`` into outputs instead of the
        #: network's output layer: an adapted readout per stream (:class:`smcd_rl.SMCDLastLayer`),
        #: called as ``readout(features)``, or ``readout(features, members=(streams, members))`` for
        #: features ``[..., G, width]`` of the particles those pick (:meth:`SMCDFilter.distinct`).
        self.readout: Callable[..., Tensor] | None = None
        #: With :attr:`readout`: each proposed particle's noise variance factor, ``[*B, N]`` or per
        #: output ``[*B, N, out]`` (at least 1), for the predictions the readout just made: the
        #: readout's own uncertainty at the particle's features (:class:`smcd_rl.SMCDLastLayer`);
        #: ``None``: the noise alone.
        self.noise_scale: Callable[[], Tensor] | None = None
        self._sigma = noise
        self._log_norm = torch.tensor(0.0)
        #: Why the strategy cannot run (an ``"auto"`` setting on a model without calibration), else None.
        self._unresolved: str | None = None

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> SMCD:
        """An SMCD from its settings; ``seed`` and ``device`` (where one is given, the other defaults to
        ``0`` or ``"cpu"``) seed its generator, so the strategy repeats the run it was stored from.

        Example:
            >>> SMCD.from_settings({"num_particles": 50, "seed": 3}).settings()["seed"]
            3
        """
        settings = dict(settings)
        if "seed" not in settings and "device" not in settings:
            return cls(**settings)  # stored without a generator: one seeded from torch's global generator
        seed, device = check_seed(settings.pop("seed", 0)), str(settings.pop("device", "cpu"))
        kind = torch.device(device).type
        if kind != "cpu" and not getattr(torch, kind).is_available():
            raise ValueError(
                f"this SMCD was stored on {device}, which this machine does not have; rebuild it for the model's "
                f"device, e.g. result.strategy('smcd', device='cpu')"
            )
        smcd = cls(**settings, generator=torch.Generator(device=device).manual_seed(seed))
        smcd._seeded = {"seed": seed, "device": device}
        return smcd

    def settings(self) -> dict[str, Any]:
        return {**self.config(), **self._seeded}

    def config(self) -> dict[str, Any]:
        config = super().config()
        if not isinstance(self.noise_std, (int, float, str)):
            config["noise_std"] = list(self.noise_std)  # a tensor or tuple as given: stored as a list
        return config

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        if isinstance(net, FeatureReadout):
            raise ValueError(NO_MASKS)
        if net.dropout == 0.0:
            raise ValueError(
                "SMCD filters over dropout masks, and this network was trained without dropout (a wrapped module "
                "with no nn.Dropout); it needs an nn.Dropout after the activation of each hidden layer it should "
                f"mask (hidden widths {list(net.hidden)}), trained with it. The last layer and gradient descent run "
                "without one"
            )
        super().bind(net, output_scale, calibration=calibration)
        noise_std, flip_prob = self.noise_std, self.flip_prob
        auto = [name for name, value in (("noise_std", noise_std), ("flip_prob", flip_prob)) if is_auto(value)]
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
        noise_value = calibrated["noise_std"] if is_auto(noise_std) else noise_std
        flip = float(calibrated["flip_prob"] if is_auto(flip_prob) else flip_prob)
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
        self._check_transition(inputs, targets)
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
            norm: Tensor | float = log_norm
            if self.noise_scale is not None:  # the noise's std times sqrt(scale), per particle (and output)
                scale = self.noise_scale()
                scale = scale.unsqueeze(-1).expand_as(residual) if scale.dim() < residual.dim() else scale
                residual = residual / scale.sqrt()
                norm = log_norm - 0.5 * scale.log().sum(-1)
            if student:
                return norm - (dof + 1) / 2 * torch.log1p(residual.square() / dof).sum(-1)
            return norm - 0.5 * residual.square().sum(-1)

        self._filter.update(log_likelihood)

    def predict(self, inputs: Tensor) -> Tensor:
        if self.prediction == "predictive":
            return self._predictive_mean(inputs)
        mask = self._mask_view(self._filter.mean_mask, inputs, trailing=1)
        if self.readout is not None:
            return self.readout(self.net.features(inputs, mask=mask))
        return self.net(inputs, mask=mask)

    def _predictive_mean(self, inputs: Tensor) -> Tensor:
        """The weighted mean of the particles' predictions for ``inputs [*B, *extra, in]``; many
        inputs per stream run each distinct particle once (:meth:`SMCDFilter.distinct`), in pieces
        of :data:`PREDICTIVE_ROWS` particle rows."""
        self._extra_dims(inputs)  # inputs that do not start with the batch shape would mix the streams
        extra = inputs.shape[len(self._batch_shape) : -1]
        if not extra:
            weights = self._mask_view(self._filter.weights, inputs, trailing=1).unsqueeze(-1)  # [*B, N, 1]
            return (weights * self.predict_particles(inputs)).sum(-2)
        streams = math.prod(self._batch_shape)
        flat = inputs.reshape(streams, -1, inputs.shape[-1])  # [S, K, in]
        found = self._filter.distinct()
        if found is None:  # copies unknown: every particle of every stream
            assert self._filter.particles is not None
            particles = self._filter.particles.reshape(streams * self.num_particles, -1)
            weights = self._filter.weights.reshape(-1)
            rows = torch.arange(streams * self.num_particles, device=particles.device)
            stream, member = rows // self.num_particles, rows % self.num_particles
        else:  # copies of one particle predict alike (a readout per particle is copied with it)
            particles, weights, stream, member = found
        readout = None if self.readout is None else functools.partial(self.readout, members=(stream, member))
        mean = torch.zeros(streams, flat.shape[1], self.net.out_features, dtype=inputs.dtype, device=inputs.device)
        piece = max(1, PREDICTIVE_ROWS // particles.shape[0])
        for start in range(0, flat.shape[1], piece):
            rows = flat[stream, start : start + piece].transpose(0, 1)  # [k, G, in]: each particle's stream's inputs
            predicted = self.net.forward_particles(rows, particles, readout)  # [k, G, out]
            weighted = (weights.unsqueeze(-1) * predicted).transpose(0, 1)  # [G, k, out]
            mean[:, start : start + piece].index_add_(0, stream, weighted.to(mean.dtype))
        return mean.reshape(*self._batch_shape, *extra, mean.shape[-1])

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


def _log_gamma_ratio(x: float) -> float:
    """``lgamma(x + 1/2) - lgamma(x)``, accurate also where the two lgammas are huge (large ``x``)."""
    if x < 1e4:
        return math.lgamma(x + 0.5) - math.lgamma(x)
    # The asymptotic series: its next term is below 1e-19 here, where the difference of lgammas
    # would have lost every digit.
    return 0.5 * math.log(x) - 1 / (8 * x) + 1 / (192 * x**3)
