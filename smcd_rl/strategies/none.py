"""No adaptation: the trained network as it is, the M+N baseline."""

from __future__ import annotations

from torch import Tensor

from smcd_rl.strategies.base import Adaptation

__all__ = ["NoAdaptation"]


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
        self._check_transition(inputs, targets)  # refused as the other strategies refuse it

    def predict(self, inputs: Tensor) -> Tensor:
        return self.net(inputs)
