"""Per-feature standardisation stored as module buffers, so it travels with the model's checkpoint."""

from __future__ import annotations

import torch
from torch import Tensor, nn

__all__ = ["Normalizer"]


class Normalizer(nn.Module):
    """``(x - mean) / std`` per feature; the identity until :meth:`fit` is called.

    Example:
        >>> import torch
        >>> from smcd_rl.normalization import Normalizer
        >>> norm = Normalizer(2)
        >>> norm.fit(torch.tensor([[0.0, 10.0], [2.0, 30.0]]))
        >>> norm(torch.tensor([1.0, 20.0]))
        tensor([0., 0.])
    """

    mean: Tensor
    std: Tensor
    fitted: Tensor

    def __init__(self, size: int, *, eps: float = 1e-6) -> None:
        super().__init__()
        self.eps = eps
        self.register_buffer("mean", torch.zeros(size))
        self.register_buffer("std", torch.ones(size))
        self.register_buffer("fitted", torch.tensor(False))

    def fit(self, data: Tensor) -> None:
        """Set mean and std from ``data [..., size]``."""
        flat = data.reshape(-1, data.shape[-1]).to(self.mean)
        if flat.shape[0] == 0:
            raise ValueError("cannot fit a Normalizer on an empty dataset")
        self.mean.copy_(flat.mean(0))
        # A constant feature keeps std 1 instead of blowing up its (meaningless) deviations.
        std = flat.std(0, unbiased=False) if flat.shape[0] > 1 else torch.ones_like(self.std)
        self.std.copy_(torch.where(std > self.eps, std, torch.ones_like(std)))
        self.fitted.fill_(True)

    def forward(self, x: Tensor) -> Tensor:
        return (x - self.mean) / self.std

    def inverse(self, y: Tensor) -> Tensor:
        """Map normalised values back to the data's units."""
        return y * self.std + self.mean
