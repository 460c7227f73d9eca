"""SMCD with a Bayesian readout: the mask filter infers the context, the readout adapts on the masked features.

:class:`SMCDLastLayer` composes an :class:`smcd_rl.SMCD` (the filter over dropout masks) and a
:class:`smcd_rl.BayesianLastLayer` (the posterior over the output layer) as a Rao-Blackwellised
particle filter: each mask particle carries its own readout mean, learnt from the features of
its own masks, and every particle shares one readout covariance per stream. Per observation:

1. **each particle's likelihood is the readout's predictive**: ``N(m_i^T phi_i, s_S^2 + s_L^2
   phi_i^T P phi_i)`` with ``phi_i`` the particle's last hidden features, ``m_i`` its readout mean,
   ``P`` the shared covariance (in units of the readout's noise variance ``s_L^2``) and ``s_S`` the
   filter's noise. The readout's uncertainty, not a point estimate of it, meets the
   masks: while ``P`` is wide an error any readout could explain (a shift) costs a particle
   little, and as ``P`` settles the masks are weighed by what the readout cannot absorb;
2. **each particle's readout mean** takes its exact Kalman step on its own features and
   residual, and follows its particle through resampling;
3. **the shared covariance** takes the last layer's update (drift and Student-t included) on the
   particles' weighted mean features.

Two weighings of step 1. ``weighing="predictive"`` (the default) is the marginal above.
``weighing="mean"`` weighs each particle by its readout mean under the filter's noise alone,
``N(m_i^T phi_i, s_S^2)``, as SMCD weighs its masks: each readout still corrects its particle,
but the readout's uncertainty no longer flattens the masks' likelihoods while ``P`` is wide.
Neither wins everywhere, so :func:`smcd_rl.tune` tries both. Measured: on the toy family of the
tests (40 tasks, RMSE after 10 observations) the predictive is better, 0.049 against 0.058
where the task has a mask and a shift, 0.0112 against 0.0130 where it has a mask alone; on the
two-link arm's task-mask network of ``smcd-rl regimes`` (50 tasks, after one observation) the
predictive trailed SMCD, 0.117 against 0.105, where the mean ties it, and tuning chose the mean
weighing there.

It predicts with the particles' weighted mean readout on the MMSE mask's features (or, with
``SMCD(prediction="predictive")``, with each particle's own readout). A refused observation
leaves everything as it was.

Why this coupling. Two cheaper ones failed on measured tasks. Updating the readout first, on the
old MMSE mask, and weighing the particles through the updated readout let the readout absorb the
error before the filter saw it: every particle explained the observation equally well and, on
masks trained to identify the task, the filter's answer was lost. Updating the filter first,
through the readout as it stood, then the readout on the new MMSE mask, kept the filter's answer
but let the masks chase an error only a readout can express (a shift), and lost to the last
layer alone there. On a toy family built in the tests (a random network's masked sub-network
plus an output shift, 40 tasks, RMSE after 10 observations), this coupling is better than both
parts where the task has both (0.049 against the last layer's 0.070 and SMCD's 0.172), and ties
SMCD where it has masks alone (0.0112 against 0.0103; the readout-first coupling 0.035, the last
layer 0.154). An exact per-particle covariance would
cost ``N`` times the memory of ``P``; the shared one costs each particle ``width^2``
multiply-adds per observation (``phi_i^T P phi_i``), about what one hidden layer of the
particle's forward pass costs. The filter's noise and flip probability and the readout's prior
and noise are the settings of the two parts.

Example:
    >>> import torch, smcd_rl
    >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(16, 16))
    >>> both = SMCDLastLayer(smcd_rl.SMCD(num_particles=50, noise_std=0.1), smcd_rl.BayesianLastLayer(noise_std=0.1))
    >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=both)
    >>> model.fitted = True  # a toy network: declare it trained
    >>> model.reset(batch_shape=(3,))
    >>> both.observe(torch.rand(3, 2), torch.rand(3, 2))
    >>> both.predict(torch.rand(3, 2)).shape, both.mask.shape
    (torch.Size([3, 2]), torch.Size([3, 32]))
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from smcd_rl.checks import checked_rows
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.last_layer import BayesianLastLayer
from smcd_rl.strategies.smcd import SMCD

__all__ = ["SMCDLastLayer", "WEIGHINGS"]

#: How :class:`SMCDLastLayer`'s filter weighs a particle: by the readout's predictive, or by its readout mean.
WEIGHINGS = ("predictive", "mean")
#: Above this prior variance (in noise units, ``prior_scale**2`` plus the drift so far) each
#: particle's ``(P + q I) phi`` is computed in float64 whatever the network's precision: it is the
#: prior's ``s^2 phi`` less the observations' downdates, which cancel to a small remainder, and in
#: float32 the remainder is lost. Measured (a random network of 16 x 16, 2,000 observations):
#: float32 matches float64 at ``prior_scale`` 100 and drifts at 300; at 1e5 it predicts 1e12
#: and then refuses observations. Below it, float32 is as exact and cheaper.
FLOAT32_SPREAD_LIMIT = 1e4


class SMCDLastLayer(Adaptation):
    """The SMCD mask filter and a Bayesian readout, updated in two stages (see the module doc).

    Args:
        smcd: the filter, or its ``settings()`` dict.
        last_layer: the readout, or its ``settings()`` dict.
        weighing: how the filter weighs each particle: ``"predictive"``, by the readout's predictive
            ``N(m_i^T phi_i, s_S^2 + s_L^2 phi_i^T P phi_i)``; ``"mean"``, by its readout mean under
            the filter's noise alone, ``N(m_i^T phi_i, s_S^2)``, as SMCD weighs its masks (see the
            module doc for when each wins).
    """

    name = "smcd_last_layer"

    def __init__(
        self,
        smcd: SMCD | Mapping[str, Any],
        last_layer: BayesianLastLayer | Mapping[str, Any],
        weighing: str = "predictive",
    ) -> None:
        super().__init__()
        if weighing not in WEIGHINGS:
            raise ValueError(f"weighing must be one of {WEIGHINGS}, got {weighing!r}")
        self.weighing = weighing
        for part, kind in ((smcd, SMCD), (last_layer, BayesianLastLayer)):
            if not isinstance(part, (kind, Mapping)):
                raise TypeError(
                    f"SMCDLastLayer takes an smcd_rl.SMCD and an smcd_rl.BayesianLastLayer (or their settings() dicts), "
                    f"got a {type(part).__name__} for the {kind.__name__}"
                )
        self.smcd = smcd if isinstance(smcd, SMCD) else SMCD.from_settings(smcd)
        self.last_layer = last_layer if isinstance(last_layer, BayesianLastLayer) else BayesianLastLayer(**last_layer)

    def config(self) -> dict[str, Any]:
        return {"smcd": self.smcd.settings(), "last_layer": self.last_layer.settings(), "weighing": self.weighing}

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        self.smcd.bind(net, output_scale, calibration=calibration)
        self.last_layer.bind(net, output_scale, calibration=calibration)
        self.smcd.readout = self._particle_readout  # each particle read out by its own readout mean
        self.smcd.noise_scale = self._particle_noise_scale
        # [B, N, out, D]: each particle's readout mean, transposed so that a particle's readout and
        # its update run along contiguous features (measured: 3-4x faster than [B, N, D, out]).
        self._means: Tensor | None = None
        self._spare: Tensor | None = None  # the last means' storage, written by the next observation
        self._wide: Tensor | None = None  # the particles' features in float64 (see _float64)
        # The last particle readout's phi and predictions, then (P + q I) phi and the scale of each particle.
        self._seen: tuple[Tensor, ...] | None = None
        # The shared covariance as the prior's diagonal less the updates' downdates: P_t = (s^2 + q t) I
        # - U U^T exactly (float64), U [B, D, t]; None once t passes D, where the dense P is cheaper.
        self._downdates: Tensor | None = None
        self._steps: Tensor | None = None  # [B]: t, the observations each stream's P has taken
        self._downdate_buffer: Tensor | None = None  # U's storage, with room for the next columns

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self.check_batch(batch_shape)  # before either part changes
        self._batch_shape = batch_shape
        self.smcd.reset(batch_shape)
        self.last_layer.reset(batch_shape)
        prior = self.last_layer.state_dict()["mean"]  # [B, D, out], the trained readout
        dtype = self.net.readout_layer.weight.dtype
        particles = self.smcd.particles.shape[-2]
        self._means = prior.to(dtype).transpose(-1, -2).unsqueeze(1).expand(-1, particles, -1, -1).clone()
        self._spare = None
        self._seen = None
        self._downdates = prior.new_zeros(prior.shape[0], prior.shape[1], 0)
        self._steps = prior.new_zeros(prior.shape[0])

    def check_batch(self, batch_shape: tuple[int, ...]) -> None:
        self.smcd.check_batch(batch_shape)
        self.last_layer.check_batch(batch_shape)

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        self._check_transition(inputs, targets)
        means = self._state()
        before = self.smcd._filter.snapshot()
        self.smcd.observe(inputs, targets)  # weighs the proposed particles through _particle_readout
        try:
            assert self._seen is not None and len(self._seen) == 4
            phi, predicted, spread, scale = self._seen  # [B, N, D], [B, N, out], (P + q I) phi, [B, N]
            streams, means = phi.shape[0], means.to(phi.dtype)  # the network's precision (moved by model.to)
            residual = targets.reshape(streams, 1, -1).to(phi.dtype) - predicted
            gain = self.last_layer.gain(residual, scale)  # [B, N]: Kalman's 1 / (1 + phi^T P phi), weighted
            step = (gain.unsqueeze(-1) * residual).unsqueeze(-1)  # [B, N, out, 1]
            if not bool(torch.isfinite(step).all()):
                raise ValueError(
                    "a particle's readout became inf or NaN on this observation (a target of inf or of a far larger "
                    "scale than the model's); the adaptation state is unchanged"
                )
            particles = phi.shape[1]
            weights = self.smcd._filter.weights.reshape(streams, particles).to(phi.dtype)
            ancestors = self.smcd._filter.ancestors
            flat = None
            if ancestors is not None:  # each readout mean follows its particle through resampling
                rows = particles * torch.arange(streams, device=phi.device).unsqueeze(1)
                flat = (ancestors.reshape(streams, particles) + rows).reshape(-1)
                # the weights of each proposed particle's copies: its share of the weighted mean features
                weights = torch.zeros_like(weights).reshape(-1).index_add_(0, flat, weights.reshape(-1))
                weights = weights.reshape(streams, particles)
            mean_features = torch.bmm(weights.unsqueeze(1), phi)[:, 0, :-1]  # the shared covariance's update
            _, cov, downdate = self.last_layer.updated(mean_features, targets)
            # The new means go into a buffer kept across observations, not into a fresh [B, N, out, D]
            # tensor nor over the current means: a refused observation leaves those as they were.
            if flat is None:
                updated = torch.addcmul(means, step, spread.unsqueeze(-2), out=self._scratch(means))
            else:  # each mean, step and spread follows its particle, then the step is taken in place
                updated = self._scratch(means, contiguous=True)  # as index_select's own result was
                torch.index_select(
                    means.reshape(streams * particles, -1), 0, flat, out=updated.view(streams * particles, -1)
                )
                step = step.reshape(streams * particles, -1).index_select(0, flat).reshape(step.shape)
                spread = spread.reshape(streams * particles, -1).index_select(0, flat).reshape(spread.shape)
                updated.addcmul_(step, spread.unsqueeze(-2))
            # The readout the last layer holds: the particles' means weighted by the filter's weights now.
            current = self.smcd._filter.weights.reshape(streams, 1, -1).to(updated.dtype)
            mean = torch.bmm(current, updated.reshape(streams, particles, -1)).reshape(streams, *updated.shape[2:])
            # Finite exactly when every particle's mean is: one of weight 0 that overflowed makes it NaN (0 * inf).
            if not bool(torch.isfinite(mean).all()):
                raise ValueError(
                    "a particle's readout overflowed on this observation (a target of a far larger scale than the "
                    "model's); the adaptation state is unchanged"
                )
        except BaseException:
            self.smcd._filter.restore(before)  # the readout refused it: the filter forgets it too
            raise
        finally:
            self._seen = None
        self._spare = means  # the old means (or their copy in the network's precision), free now
        self._means = updated
        self._steps = self._steps + 1 if self._steps is not None else None
        self._grow_downdates(downdate)
        self.last_layer._take_update(mean.transpose(-1, -2), cov)  # [B, D, out], the last layer's layout

    def _grow_downdates(self, downdate: Tensor) -> None:
        """Append this observation's downdate ``[B, D]`` to ``U``, in a buffer that doubles as it
        fills (a ``cat`` each observation copied all of ``U``); past ``D`` columns, the dense ``P``."""
        if self._downdates is None:
            return
        streams, width, taken = self._downdates.shape
        if taken + 1 >= width:
            self._downdates = None
            return
        buffer = self._downdate_buffer
        if buffer is None or buffer.shape[-1] <= taken or buffer.data_ptr() != self._downdates.data_ptr():
            buffer = self._downdates.new_empty(streams, width, min(max(2 * (taken + 1), 8), width))
            buffer[..., :taken] = self._downdates
            self._downdate_buffer = buffer
        buffer[..., taken] = downdate
        self._downdates = buffer[..., : taken + 1]

    def _particle_readout(self, features: Tensor, members: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Each particle's readout of its last hidden ``features [*B, *extra, N, width]`` by its own
        mean; with ``members = (streams, indices)``, of features ``[..., G, width]`` of the
        particles they pick."""
        means = self._state()
        if members is not None:
            picked = means[members[0], members[1]].to(features.dtype)  # [G, out, width + 1]
            self._seen = None
            return torch.einsum("...gd,god->...go", BayesianLastLayer._augmented(features), picked)
        streams, particles = means.shape[:2]
        phi = BayesianLastLayer._augmented(features.reshape(streams, -1, particles, features.shape[-1]))
        extra = phi.shape[1]
        flat = phi.transpose(1, 2).reshape(streams * particles, extra, phi.shape[-1])  # [B N, e, D]
        readouts = means.to(phi.dtype).reshape(streams * particles, *means.shape[2:]).transpose(1, 2)  # a view
        out = torch.bmm(flat, readouts).reshape(streams, particles, extra, -1).transpose(1, 2)  # [B, e, N, out]
        self._seen = (phi[:, 0], out[:, 0]) if extra == 1 else None
        return out.reshape(*features.shape[:-1], out.shape[-1])

    def _particle_noise_scale(self) -> Tensor:
        """Each particle's predictive variance over the filter's noise variance, per output ``[B, N, out]``:
        ``1 + (s_L / s_S)^2 phi_i^T P phi_i`` for the particles :meth:`_particle_readout` just read
        (``1`` with ``weighing="mean"``; the readout's gains are computed either way).

        ``P`` is in units of the readout's noise variance ``s_L^2`` (its prior is ``s_L^2
        prior_scale^2 I``), so the readout's uncertainty at ``phi_i`` is ``s_L^2 phi_i^T P phi_i``,
        added to the filter's own noise ``s_S^2``.
        """
        if self._seen is None:
            raise RuntimeError("SMCDLastLayer: a particle's noise scale was asked for before its readout")
        phi = self._seen[0]
        spread, quadratic = self._spread(phi)  # (P + q I) phi [B, N, D] and phi^T (P + q I) phi [B, N]
        quadratic = quadratic.clamp_min(0.0)  # P is positive semi-definite: never below 0
        self._seen = (phi, self._seen[1], spread, 1.0 + quadratic)  # the gains: in the readout's noise units
        if self.weighing == "mean":
            return torch.ones_like(quadratic).reshape(*self._batch_shape, quadratic.shape[-1])
        ratio = (self.last_layer._sigma / self.smcd._sigma.to(self.last_layer._sigma)).square().to(phi.dtype)
        scale = 1.0 + quadratic.unsqueeze(-1) * ratio  # [B, N, out], the model's batch dims flattened
        return scale.reshape(*self._batch_shape, *scale.shape[1:])

    def _spread(self, phi: Tensor) -> tuple[Tensor, Tensor]:
        """``(P + q I) phi [B, N, D]`` for each particle's features ``phi [B, N, D]``, in ``phi``'s
        precision, and ``phi^T (P + q I) phi [B, N]``.

        While a stream has taken fewer observations than ``D``, from ``P = (s^2 + q t) I - U U^T``:
        ``N D t`` multiply-adds instead of the dense ``N D^2``. The quadratic form is taken in
        float64, where its two terms cancel when the posterior is sure of a direction, and so is
        the spread where the prior's variance passes :data:`FLOAT32_SPREAD_LIMIT`.
        """
        readout = self.last_layer
        q = readout.drift * readout.prior_scale**2
        if self._downdates is None or self._steps is None:
            # The dense P: its diagonal bounds the variance of every direction (see FLOAT32_SPREAD_LIMIT).
            exact = bool(readout._state()[1].diagonal(dim1=-2, dim2=-1).amax() + q > FLOAT32_SPREAD_LIMIT)
            spread = readout.spread(phi.to(torch.float64) if exact else phi)
            return spread.to(phi.dtype), (phi.to(spread.dtype) * spread).sum(-1).to(phi.dtype)
        diagonal = (readout.prior_scale**2 + q * (self._steps + 1)).reshape(-1, 1, 1)  # the drift of this step
        wide = self._float64(phi)
        if bool((diagonal > FLOAT32_SPREAD_LIMIT).any()):  # the cancellation needs float64 (see the constant)
            spread = diagonal * wide - torch.bmm(torch.bmm(wide, self._downdates), self._downdates.transpose(-1, -2))
            return spread.to(phi.dtype), (wide * spread).sum(-1).to(phi.dtype)
        projected = torch.bmm(wide, self._downdates)  # [B, N, t]
        streams, particles, width = wide.shape
        # |phi|^2 as a batched dot product: one pass, where square() and sum() make two.
        squares = torch.bmm(wide.reshape(-1, 1, width), wide.reshape(-1, width, 1)).reshape(streams, particles)
        quadratic = diagonal[..., 0] * squares - projected.square().sum(-1)
        downdates = self._downdates.to(phi.dtype).transpose(-1, -2)
        if bool((diagonal == diagonal.reshape(-1)[0]).all()):  # every stream has taken as many steps: one scalar
            scaled, beta = phi, float(diagonal.reshape(-1)[0])
        else:
            scaled, beta = diagonal.to(phi.dtype) * phi, 1.0
        spread = torch.baddbmm(
            scaled, projected.to(phi.dtype), downdates, beta=beta, alpha=-1.0
        )  # (s^2 + q t) phi - U U^T phi
        return spread, quadratic.to(phi.dtype)

    def _scratch(self, like: Tensor, contiguous: bool = False) -> Tensor:
        """A tensor to write new means into, of ``like``'s shape, dtype and layout (or contiguous):
        the storage the last observation's means left, where it fits, else a new one."""
        spare, self._spare = self._spare, None
        if (
            spare is not None
            and (spare.shape, spare.dtype, spare.device) == (like.shape, like.dtype, like.device)
            and (spare.is_contiguous() if contiguous else spare.stride() == like.stride())
            and spare.data_ptr() != self._state().data_ptr()  # never the current means
        ):
            return spare
        return like.new_empty(like.shape) if contiguous else torch.empty_like(like)

    def _float64(self, phi: Tensor) -> Tensor:
        """``phi`` in float64, in a buffer kept across observations (as the readout means are)."""
        if self._wide is None or self._wide.shape != phi.shape or self._wide.device != phi.device:
            self._wide = torch.empty(phi.shape, dtype=torch.float64, device=phi.device)
        return self._wide.copy_(phi)

    def predict(self, inputs: Tensor) -> Tensor:
        if self.smcd.prediction == "predictive":
            self._extra_dims(inputs)  # refused here, in SMCDLastLayer's name
            return self.smcd.predict(inputs)  # each particle's own readout, weighted
        mask = self._mask_view(self.smcd.mask, inputs, trailing=1)  # checks the inputs, in SMCDLastLayer's name
        return self.last_layer.readout(self.net.features(inputs, mask=mask))

    def predict_particles(self, inputs: Tensor) -> Tensor:
        self._extra_dims(inputs)
        return self.smcd.predict_particles(inputs)

    def predictive(self, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and variance of the predictive for ``inputs [*B, *extra, in]``, in normalised units.

        The mean is :meth:`predict`'s; the variance the readout's predictive variance on the MMSE
        mask's features (noise and readout uncertainty) plus the particles' weighted spread.
        """
        mask = self.smcd._mask_view(self.smcd.mask, inputs, trailing=1)
        _, variance = self.last_layer.predictive_of(self.net.features(inputs, mask=mask))
        mean = self.predict(inputs)
        weights = self.smcd._mask_view(self.smcd._filter.weights, inputs, trailing=1).unsqueeze(-1)
        spread = (weights * (self.predict_particles(inputs) - mean.unsqueeze(-2)).square()).sum(-2)
        return mean, variance + spread

    @property
    def mask(self) -> Tensor:
        return self.smcd.mask

    @property
    def particles(self) -> Tensor:
        """The filter's mask particles ``[*B, N, mask_dim]``."""
        return self.smcd.particles

    def summary(self) -> dict[str, Tensor]:
        return self.smcd.summary()

    def state_dict(self) -> dict[str, Any]:
        return {
            "smcd": self.smcd.state_dict(),
            "last_layer": self.last_layer.state_dict(),
            "means": self._state().clone(),
            "downdates": None if self._downdates is None else self._downdates.clone(),
            "steps": None if self._steps is None else self._steps.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        means = self._checked_means(state)
        before = self.state_dict()
        try:
            self.last_layer.load_state_dict(state["last_layer"])  # checks its shapes against this batch
            self.smcd.load_state_dict(state["smcd"])
        except Exception:
            self.smcd.load_state_dict(before["smcd"])  # a refused state leaves every part as it was
            self.last_layer.load_state_dict(before["last_layer"])
            raise
        self._means = state["means"].to(device=means.device, dtype=means.dtype).clone()
        downdates, steps = state.get("downdates"), state.get("steps")
        # Without its downdates (or with another's) the shared covariance is read dense: always exact.
        self._downdates = self._steps = None
        if (
            isinstance(downdates, Tensor)
            and isinstance(steps, Tensor)
            and downdates.shape[:2] == (means.shape[0], means.shape[-1])
            and steps.shape == (means.shape[0],)
        ):
            self._downdates = downdates.to(device=means.device, dtype=torch.float64).clone()
            self._steps = steps.to(device=means.device, dtype=torch.float64).clone()

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        # Every part checked before any is restored: a refused call leaves all of them as they were.
        means = self._checked_means(state)
        rows = checked_rows(rows, self._batch_shape)
        self.smcd._filter._checked_rows(state["smcd"], rows)
        self.last_layer._checked_state(state["last_layer"])
        self.smcd.restore_rows(state["smcd"], rows)
        self.last_layer.restore_rows(state["last_layer"], rows)
        keep = rows.to(means.device).reshape(-1, 1, 1, 1)
        self._means = torch.where(keep, state["means"].to(means), means)
        saved, steps = state.get("downdates"), state.get("steps")
        if self._downdates is None or self._steps is None or saved is None or steps is None:
            self._downdates = self._steps = None  # the dense covariance, restored by the last layer, is exact
            return
        width = max(saved.shape[-1], self._downdates.shape[-1])  # zero columns downdate nothing
        pad = [torch.nn.functional.pad(u, (0, width - u.shape[-1])) for u in (saved, self._downdates)]
        self._downdates = torch.where(keep[..., 0], pad[0], pad[1])
        self._steps = torch.where(keep.reshape(-1), steps, self._steps)

    def _checked_means(self, state: Any) -> Tensor:
        """This one's readout means, after checking ``state`` (a :meth:`state_dict`) has means that fit them."""
        if not isinstance(state, Mapping) or not {"smcd", "last_layer", "means"} <= set(state):
            raise ValueError(
                "an SMCDLastLayer's state is a dict of 'smcd', 'last_layer' and 'means' states (its state_dict())"
            )
        means = self._state()
        given = state["means"]
        if not isinstance(given, Tensor) or given.shape != means.shape:
            shape = list(given.shape) if isinstance(given, Tensor) else type(given).__name__
            raise ValueError(
                f"the particles' readout means of shape {shape} do not fit this one's {list(means.shape)} (another "
                "batch size, particle count or network?); reset the model to the batch shape it was saved with"
            )
        if not bool(torch.isfinite(given).all()):
            raise ValueError("the particles' readout means hold inf or NaN; pass an SMCDLastLayer's state_dict()")
        return means

    def _state(self) -> Tensor:
        if self._means is None:
            raise RuntimeError("SMCDLastLayer has no posterior yet; call model.reset() first")
        return self._means
