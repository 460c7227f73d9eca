"""SMCD with a Bayesian readout: the mask filter infers the context, the readout adapts on the masked features.

:class:`SMCDLastLayer` composes an :class:`smcd_rl.SMCD` (the filter over dropout masks) and a
:class:`smcd_rl.BayesianLastLayer` (the posterior over the output layer), one of each per stream,
and updates them in two stages per observation, **the filter first**:

1. **the filter**: each particle's likelihood is that of the particle's own last hidden features
   read out by the readout as it stood *before* the observation (at first the trained one), so
   the filter sees the whole error, as SMCD alone does, and weighs the sub-networks by it;
2. **the readout**: its exact Bayesian update on the features of the filter's *new* MMSE mask, so
   it learns only what the best sub-network still gets wrong (a shift, a scale no mask expresses).

A refused observation leaves both as they were. It predicts with the readout's posterior mean on
the MMSE mask's features.

Why this order. The readout-first coupling (update the readout on the old mask's features, then
weigh the particles through the *updated* readout) let the readout absorb the error before the
filter saw it: every particle then explained the observation about equally well, the weights
stayed flat and the masks stopped identifying the task. On a network whose masks were trained to
identify the task, that threw the filter's answer away (two-link arms after 3 observations: 0.274
against SMCD's 0.079, barely below no adaptation's 0.285). With the filter first, the masks move
exactly as SMCD's do until the readout has learnt something, and the readout then fits the
residual of a mask that already explains what masks can; reading the particles out with the
readout's mean costs each particle the output layer's multiply-adds, where the readout's full
predictive density per particle (``phi^T P phi``) would cost ``width^2`` more per particle.
The filter's noise and flip probability and the readout's prior and noise are the settings of
the two parts.

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

from torch import Tensor

from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.last_layer import BayesianLastLayer
from smcd_rl.strategies.smcd import SMCD

__all__ = ["SMCDLastLayer"]


class SMCDLastLayer(Adaptation):
    """The SMCD mask filter and a Bayesian readout, updated in two stages (see the module doc).

    Args:
        smcd: the filter, or its ``settings()`` dict.
        last_layer: the readout, or its ``settings()`` dict.
    """

    name = "smcd_last_layer"

    def __init__(self, smcd: SMCD | Mapping[str, Any], last_layer: BayesianLastLayer | Mapping[str, Any]) -> None:
        super().__init__()
        for part, kind in ((smcd, SMCD), (last_layer, BayesianLastLayer)):
            if not isinstance(part, (kind, Mapping)):
                raise TypeError(
                    f"SMCDLastLayer takes an smcd_rl.SMCD and an smcd_rl.BayesianLastLayer (or their settings() dicts), "
                    f"got a {type(part).__name__} for the {kind.__name__}"
                )
        self.smcd = smcd if isinstance(smcd, SMCD) else SMCD.from_settings(smcd)
        self.last_layer = last_layer if isinstance(last_layer, BayesianLastLayer) else BayesianLastLayer(**last_layer)

    def config(self) -> dict[str, Any]:
        return {"smcd": self.smcd.settings(), "last_layer": self.last_layer.settings()}

    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        self.smcd.bind(net, output_scale, calibration=calibration)
        self.last_layer.bind(net, output_scale, calibration=calibration)
        self.smcd.readout = self.last_layer.readout  # the particles read out by the adapted readout

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self._batch_shape = batch_shape
        self.smcd.reset(batch_shape)
        self.last_layer.reset(batch_shape)

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        self._check_transition(inputs, targets)
        before = self.smcd.state_dict()
        self.smcd.observe(inputs, targets)  # through the readout as it stands; a refusal changes nothing
        mask = self.smcd.mask.reshape(-1, self.net.mask_dim)
        features = self.net.features(inputs.reshape(mask.shape[0], -1), mask=mask)
        try:
            self.last_layer.update(features, targets)  # on the new MMSE mask's features
        except ValueError:
            self.smcd.load_state_dict(before)  # the readout refused it: the filter forgets it too
            raise

    def predict(self, inputs: Tensor) -> Tensor:
        return self.smcd.predict(inputs)  # the readout's mean on the MMSE mask's features

    def predict_particles(self, inputs: Tensor) -> Tensor:
        return self.smcd.predict_particles(inputs)

    def predictive(self, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and variance of the predictive for ``inputs [*B, *extra, in]``, in normalised units.

        The mean is :meth:`predict`'s; the variance the readout's predictive variance on the MMSE
        mask's features (noise and readout uncertainty) plus the particles' weighted spread.
        """
        mask = self.smcd._mask_view(self.smcd.mask, inputs, trailing=1)
        mean, variance = self.last_layer.predictive_of(self.net.features(inputs, mask=mask))
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
        return {"smcd": self.smcd.state_dict(), "last_layer": self.last_layer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not isinstance(state, Mapping) or set(state) != {"smcd", "last_layer"}:
            raise ValueError("an SMCDLastLayer's state is a dict of 'smcd' and 'last_layer' states (its state_dict())")
        before = self.state_dict()
        try:
            self.last_layer.load_state_dict(state["last_layer"])  # checks its shapes against this batch
            self.smcd.load_state_dict(state["smcd"])
        except Exception:
            self.smcd.load_state_dict(before["smcd"])  # a refused state leaves both parts as they were
            self.last_layer.load_state_dict(before["last_layer"])
            raise

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        self.smcd.restore_rows(state["smcd"], rows)
        self.last_layer.restore_rows(state["last_layer"], rows)
