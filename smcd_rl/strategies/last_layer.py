"""The Bayesian last layer: a Gaussian posterior over the network's readout, updated in closed form.

The network's last hidden layer, with dropout off, gives features ``phi(x)``; the output layer
reads them, ``y = K^T [phi(x), 1]`` (weights and bias, ``D = width + 1`` rows, one column per
output). :class:`BayesianLastLayer` keeps a Gaussian posterior over ``K`` for every stream,
centred at first on the trained readout, and updates it after every observation (Bayesian linear
regression; ALPaCA, Harrison, Sharma and Pavone 2018; Neural-Fly's Kalman-style adaptation,
O'Connell et al. 2022). The prior is ALPaCA's matrix-normal one: output ``o``'s weights have prior
covariance ``noise_o^2 * prior_scale^2 * I``, so one ``D x D`` matrix ``P`` (the posterior
covariance in units of each output's noise variance) serves every output:

* after an observation ``(phi, y)``: ``k = P phi / (1 + phi^T P phi)``, ``K += k (y - K^T phi)^T``,
  ``P -= u u^T`` with ``u = P phi / sqrt(1 + phi^T P phi)`` (a rank-one downdate: one pass over
  ``P``, exactly symmetric; float32 follows float64 over 10^4 observations), the exact posterior
  of all observations so far;
* ``drift`` adds ``drift * prior_scale^2 * I`` to ``P`` before each observation: the readout
  follows a random walk, so old observations lose weight and the posterior follows a task that
  drifts or switches (Kalman's process noise);
* ``likelihood="student-t"`` weighs each observation by ``(dof + m) / (dof + r^2)``, ``r^2`` its
  squared residual over its predictive variance summed over the ``m`` outputs (one EM step of a
  Student-t likelihood), so that one gross outlier barely moves the readout;
* ``likelihood="tukey"`` weighs it by Tukey's biweight ``(1 - u^2 / c^2)^2``, zero beyond
  ``c = TUKEY_CUT``, ``u^2`` its squared residual over the *noise* variance, averaged over the
  outputs. The Student-t judges a residual against the predictive variance, which a wide prior
  makes huge: at ``prior_scale = 9`` a reading 20 noise units off still counts nearly in full, and
  with few observations the readout bends to it. The biweight judges it against what the noise
  allows and leaves the posterior exactly as it was beyond ``c``. Where every residual lies beyond
  ``c`` (a task far from the trained ones; ``noise_std`` too small), it does not adapt and
  predicts as the trained network.

It predicts with the posterior mean; :meth:`BayesianLastLayer.predictive` gives the predictive mean
and variance. Everything is in the model's normalised units.

The posterior is kept and updated in float64 whatever the network's precision, and predictions
are cast to the network's dtype. In float32 the downdate ``P - u u^T`` cancels digits: with a
wide prior (``prior_scale`` of 3e3 and more) or a large drift, ``P`` lost its positive
definiteness within a few observations and the predictive variance went negative. In float64 the
update holds over 5,000 observations at every setting allowed; the one combination that breaks
it, a drift variance ``drift * prior_scale**2`` above :data:`MAX_DRIFT_VARIANCE`, is refused.

Example:
    >>> import torch, smcd_rl
    >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(16,))
    >>> readout = BayesianLastLayer(prior_scale=0.5, noise_std=0.1)
    >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=readout)
    >>> model.fitted = True  # a toy network: declare it trained
    >>> model.reset(batch_shape=(3,))
    >>> readout.observe(torch.rand(3, 2), torch.rand(3, 2))
    >>> mean, variance = readout.predictive(torch.rand(3, 2))
    >>> mean.shape, bool((variance > 0.1**2).all())
    (torch.Size([3, 2]), True)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from smcd_rl.checks import check_real, checked_rows
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import TUKEY_CUT, Adaptation, checked_likelihood, checked_noise

__all__ = ["BayesianLastLayer", "MAX_DRIFT_VARIANCE"]

#: The largest drift variance per observation, ``drift * prior_scale**2`` (in units of the noise
#: variance), the float64 posterior follows: beyond it, one observation's information is below
#: float64's resolution of the covariance, and 5,000 observations at ``1e18`` drove it indefinite.
MAX_DRIFT_VARIANCE = 1e12
#: The dtype of the posterior, whatever the network's.
STATE_DTYPE = torch.float64


class BayesianLastLayer(Adaptation):
    """Adapt the network's readout by exact Bayesian linear regression on its last hidden features.

    Args:
        prior_scale: the prior standard deviation of each readout weight, in units of its output's
            noise: how far the readout may move from the trained one before the data say more.
        noise_std: the observation noise, in the model's normalised units (one per output, or a
            scalar): what one observation's residual is worth.
        drift: the random walk of the readout per observation, as a share of the prior variance
            (``0``: a task that stays put; ``0.01`` forgets an observation's information over about a
            hundred).
        likelihood: ``"gaussian"``, ``"student-t"`` (robust: an outlier is down-weighted) or
            ``"tukey"`` (robust: a reading beyond :data:`~smcd_rl.strategies.base.TUKEY_CUT` noise units is ignored).
        dof: the Student-t's degrees of freedom.

    Example:
        >>> BayesianLastLayer(prior_scale=0.3, noise_std=[0.1, 0.2], likelihood="student-t").config()["dof"]
        4.0
    """

    name = "last_layer"
    _CONFIG = ("prior_scale", "noise_std", "drift", "likelihood", "dof")

    def __init__(
        self,
        prior_scale: float = 1.0,
        noise_std: float | Sequence[float] = 0.1,
        drift: float = 0.0,
        likelihood: Literal["gaussian", "student-t", "tukey"] = "gaussian",
        dof: float = 4.0,
    ) -> None:
        super().__init__()
        self.prior_scale = check_real(prior_scale, "prior_scale", low=0.0, high=1e6, open_low=True)
        self._noise = checked_noise(noise_std, auto=False)
        self.noise_std = noise_std if isinstance(noise_std, (int, float)) else [float(v) for v in noise_std]
        self.drift = check_real(drift, "drift", low=0.0, high=1e6)
        if self.drift * self.prior_scale**2 > MAX_DRIFT_VARIANCE:
            raise ValueError(
                f"drift * prior_scale**2 = {self.drift * self.prior_scale**2:.3g} is beyond {MAX_DRIFT_VARIANCE:g}, "
                "where the posterior's covariance loses its precision; use a smaller drift or prior_scale"
            )
        self.likelihood, self.dof = checked_likelihood(likelihood, dof, also=("tukey",))
        self._mean: Tensor | None = None  # [B, D, out]: the posterior mean of the readout per stream
        self._cov: Tensor | None = None  # [B, D, D]: its covariance, in units of each output's noise variance
        self._sigma = torch.ones(1)

    # -------------------------------------------------------------- called by the model
    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        if self._noise.dim() == 1 and self._noise.shape[0] not in (1, net.out_features):
            raise ValueError(f"noise_std has {self._noise.shape[0]} values but the model predicts {net.out_features}")
        weight = net.readout_layer.weight
        self._sigma = self._noise.to(device=weight.device, dtype=STATE_DTYPE).expand(net.out_features)

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self.check_batch(batch_shape)
        self._batch_shape = batch_shape
        streams = math.prod(batch_shape)
        output = self.net.readout_layer
        prior = torch.cat([output.weight.detach().t(), output.bias.detach().unsqueeze(0)]).to(STATE_DTYPE)  # [D, out]
        self._sigma = self._sigma.to(prior.device)
        self._mean = prior.expand(streams, *prior.shape).clone()
        eye = torch.eye(prior.shape[0], dtype=prior.dtype, device=prior.device)
        self._cov = (self.prior_scale**2 * eye).expand(streams, *eye.shape).clone()

    def check_batch(self, batch_shape: tuple[int, ...]) -> None:
        """Refuse a batch without streams (a dimension of 0): a readout posterior needs one stream at least."""
        if math.prod(batch_shape) == 0:
            raise ValueError(f"batch_shape {list(batch_shape)} has no streams; a Bayesian readout needs one at least")

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        mean, _ = self._state()
        self._check_transition(inputs, targets)
        self.update(self.net.features(inputs.reshape(mean.shape[0], -1)), targets)

    def update(self, features: Tensor, targets: Tensor) -> None:
        """The posterior after one observation per stream of last hidden ``features [*B, width]`` and ``targets``.

        What :meth:`observe` does with the features of the network with dropout off; a strategy that
        reads other features (a mask's: :class:`smcd_rl.SMCDLastLayer`) passes them here.

        Raises:
            ValueError: the posterior would become inf or NaN; it is left as it was.
        """
        self._mean, self._cov, _ = self.updated(features, targets)

    def _take_update(self, mean: Tensor, cov: Tensor) -> None:
        """Set the posterior to ``mean [B, width + 1, out]`` and ``cov [B, width + 1, width + 1]``
        from this posterior's own :meth:`updated`, without :meth:`load_state_dict`'s copies and
        checks: ``updated`` checked the covariance and the caller the mean, and checking a
        257 x 257 covariance again cost about 0.2 ms an observation."""
        self._mean, self._cov = mean.to(STATE_DTYPE), cov

    def updated(self, features: Tensor, targets: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The posterior mean and covariance :meth:`update` would set, without setting them, and the
        update's downdate ``u [B, width + 1]``: the new covariance is ``P + q I - u u^T``."""
        mean, cov = self._state()
        phi = self._augmented(features.reshape(mean.shape[0], -1).to(STATE_DTYPE))  # [B, D]
        if targets.numel() != mean.shape[0] * mean.shape[2]:
            raise ValueError(
                f"targets of shape {list(targets.shape)} for {mean.shape[0]} streams of {mean.shape[2]} outputs; "
                "pass one target per stream"
            )
        dtype = self.net.readout_layer.weight.dtype  # the precision its predictions are cast to
        targets = targets.reshape(mean.shape[0], -1).to(STATE_DTYPE)
        spread = self.spread(phi.unsqueeze(1)).squeeze(1)  # (P + q I) phi
        variance = 1.0 + (phi * spread).sum(-1)  # the predictive variance, in units of each output's noise variance
        residual = targets - torch.einsum("bdo,bd->bo", mean, phi)
        c = self.gain(residual, variance)
        q = self.drift * self.prior_scale**2
        new_mean = mean + (spread * c.unsqueeze(-1)).unsqueeze(-1) * residual.unsqueeze(-2)
        # P - c (P phi)(P phi)^T as the rank-one downdate P - u u^T, u = sqrt(c) P phi: one pass over P,
        # and u_i u_j = u_j u_i, so P stays exactly symmetric in any precision.
        u = spread * c.sqrt().unsqueeze(-1)
        # P is finite, so P - u u^T is too where every |u_i u_j| is: checked on u, not on the D x D result.
        largest = math.sqrt(torch.finfo(u.dtype).max) / 2
        # The mean must also hold in the network's precision, which its predictions are cast to.
        representable = torch.finfo(dtype).max / 2 if dtype.is_floating_point else largest
        if not (
            bool(torch.isfinite(targets).all())
            and bool((new_mean.abs() < representable).all())
            and bool((u.abs() < largest).all())
        ):
            raise ValueError(
                "the last layer's posterior became inf or NaN on this observation (a target of inf or of a far "
                "larger scale than the model's); the adaptation state is unchanged"
            )
        new_cov = torch.baddbmm(cov, u.unsqueeze(-1), u.unsqueeze(-2), alpha=-1.0)
        if q > 0:
            new_cov.diagonal(dim1=-2, dim2=-1).add_(q)
        return new_mean, new_cov, u

    def spread(self, phi: Tensor) -> Tensor:
        """``(P + q I) phi`` for augmented features ``phi [B, n, width + 1]``, in ``phi``'s precision:
        the covariance this observation meets (with drift ``q = drift * prior_scale**2``), times each."""
        _, cov = self._state()
        # With drift the prior of this step is P + q I: its product with phi, without forming it.
        q = self.drift * self.prior_scale**2
        return torch.bmm(phi, cov.to(phi.dtype)) + q * phi  # P is symmetric: phi P = (P phi)^T

    def gain(self, residual: Tensor, variance: Tensor) -> Tensor:
        """The scalar ``c`` of the update's gain ``k = c (P + q I) phi`` for ``residual [..., out]`` and the
        predictive variance ``variance [...]`` (``1 + phi^T (P + q I) phi``, in units of the noise's).

        An observation of weight ``w`` is one with noise variance ``1 / w``: its gain grows with ``w``,
        and an outlier the Student-t weighs at ``w = 0`` leaves the posterior exactly as it was.
        """
        weight = torch.ones_like(variance)
        if self.likelihood == "student-t":
            squared = (residual / self._sigma.to(residual.dtype)).square().sum(-1) / variance
            weight = (self.dof + residual.shape[-1]) / (self.dof + squared)
        elif self.likelihood == "tukey":
            squared = (residual / self._sigma.to(residual.dtype)).square().mean(-1)
            weight = (1 - squared / TUKEY_CUT**2).clamp(min=0.0).square()
        return weight / (1.0 + weight * (variance - 1.0))

    def predict(self, inputs: Tensor) -> Tensor:
        self._state()  # "call model.reset()" before any shape error
        self._extra_dims(inputs)
        return self.readout(self.net.features(inputs))

    def readout(self, features: Tensor) -> Tensor:
        """Each stream's posterior-mean readout of last hidden ``features [*B, ..., width]`` -> ``[*B, ..., out]``."""
        return self.readout_with(self._state()[0], features)

    @staticmethod
    def readout_with(mean: Tensor, features: Tensor) -> Tensor:
        """:meth:`readout` with the readout ``mean [B, width + 1, out]`` given (one per stream)."""
        flat = features.reshape(mean.shape[0], -1, features.shape[-1])
        mean = mean.to(flat.dtype)  # the posterior's float64 in the network's precision
        out = torch.baddbmm(mean[:, -1:, :], flat, mean[:, :-1, :])
        return out.reshape(*features.shape[:-1], out.shape[-1])

    def predictive(self, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and variance of the posterior predictive for ``inputs [*B, *extra, in]``, in normalised units.

        The variance is the noise's plus the readout's uncertainty at the input:
        ``noise^2 * (1 + phi^T P phi)`` per output.
        """
        self._extra_dims(inputs)
        return self.predictive_of(self.net.features(inputs))

    def predictive_of(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`predictive` for last hidden ``features [*B, ..., width]`` given."""
        mean, cov = self._state()
        phi = self._augmented(features.reshape(mean.shape[0], -1, features.shape[-1]).to(STATE_DTYPE))  # [B, n, D]
        spread = (torch.bmm(phi, cov) * phi).sum(-1)  # [B, n]
        variance = (1.0 + spread).unsqueeze(-1) * self._sigma.square()
        return self.readout(features), variance.reshape(*features.shape[:-1], -1).to(features.dtype)

    def state_dict(self) -> dict[str, Any]:
        mean, cov = self._state()
        return {"mean": mean.clone(), "cov": cov.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        given, given_cov = self._checked_state(state)
        mean, cov = self._state()
        self._mean = given.to(device=mean.device, dtype=STATE_DTYPE).clone()
        self._cov = given_cov.to(device=cov.device, dtype=STATE_DTYPE).clone()

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        given, given_cov = self._checked_state(state)
        mean, cov = self._state()
        keep = checked_rows(rows, self._batch_shape).to(mean.device).reshape(-1, 1, 1)
        self._mean = torch.where(keep, given.to(mean), mean)
        self._cov = torch.where(keep, given_cov.to(cov), cov)

    def _checked_state(self, state: Any) -> tuple[Tensor, Tensor]:
        """``state``'s mean and covariance after checking they fit this posterior, finite."""
        mean, cov = self._state()
        given = state.get("mean") if isinstance(state, Mapping) else None
        given_cov = state.get("cov") if isinstance(state, Mapping) else None
        if not (isinstance(given, Tensor) and isinstance(given_cov, Tensor)) or (
            given.shape != mean.shape or given_cov.shape != cov.shape
        ):
            shapes = (
                [list(v.shape) for v in (given, given_cov)]
                if isinstance(given, Tensor) and isinstance(given_cov, Tensor)
                else "not a {'mean', 'cov'} dict"
            )
            raise ValueError(
                f"a last layer's state of shapes {shapes} does not fit this one's {[list(mean.shape), list(cov.shape)]} "
                "(another batch size or network?); reset the model to the batch shape it was saved with"
            )
        if not (bool(torch.isfinite(given).all()) and bool(torch.isfinite(given_cov).all())):
            raise ValueError("a last layer's state with inf or NaN in its mean or covariance; pass its state_dict()")
        return given, given_cov

    # -------------------------------------------------------------- helpers
    @staticmethod
    def _augmented(features: Tensor) -> Tensor:
        """``[features, 1]``: the bias is the readout's last row."""
        return torch.cat([features, features.new_ones(*features.shape[:-1], 1)], dim=-1)

    def _state(self) -> tuple[Tensor, Tensor]:
        if self._mean is None or self._cov is None:
            raise RuntimeError("BayesianLastLayer has no posterior yet; call model.reset() first")
        return self._mean, self._cov
