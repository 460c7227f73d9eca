"""The latent-variable baseline (LV+N): a variational recurrent network (VRNN, Chung et al. 2015).

Task variability is captured by a low-dimensional recurrent state ``h`` (8 numbers in the
paper) that each observed (input, target) pair updates; a latent ``z`` with a prior ``p(z | h)``
and a posterior ``q(z | x, y, h)`` feeds a decoder ``p(y | x, z, h)``. The paper trains it on
windows of two consecutive transitions, the context a feed-forward model sees, so training data
are the same transitions as the multi-task model's: ``(x, y)`` then ``(("next", x), ("next", y))``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torch.nn import functional as F

from smcd_rl.checks import check_key, check_shape, check_tensordict, read_inputs, read_tensor
from smcd_rl.files import CheckpointMismatchError, load_file
from smcd_rl.normalization import Normalizer
from smcd_rl.training.fitting import _Loop, _normalised_pairs, _require_samples, _shuffled_epoch, _train

__all__ = ["LatentVariableModel", "fit_latent"]

_FORMAT = "smcd_rl.LatentVariableModel/1"
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)
_MIN_STD = 1e-3  # keeps the Gaussians' log-densities finite when a std collapses


def _mlp(sizes: Sequence[int], device: torch.device | str | None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:], strict=True):
        layers += [nn.Linear(a, b, device=device), nn.ReLU()]
    return nn.Sequential(*layers[:-1])  # no activation on the output


def _gaussian(params: Tensor) -> tuple[Tensor, Tensor]:
    mean, raw = params.chunk(2, dim=-1)
    return mean, F.softplus(raw) + _MIN_STD


def _next_key(key: NestedKey) -> NestedKey:
    return ("next", key) if isinstance(key, str) else ("next", *key)


class LatentVariableModel(TensorDictModuleBase):
    """A VRNN that adapts by updating its recurrent state ``h`` from observations.

    Same interface as :class:`smcd_rl.AdaptiveModel` for the experiments: :meth:`reset`,
    :meth:`observe` (updates ``h`` with the posterior mean of ``z``) and ``forward`` (predicts
    with the current ``h`` and the prior mean of ``z``, for any number of look-ahead inputs,
    without changing ``h``). Inputs and targets are standardised with statistics that
    :func:`fit_latent` computes from the training data.

    Architecture (Chung et al. 2015, with the input ``x`` as a condition): feature layers
    ``phi_x, phi_y, phi_z``; prior ``p(z | h)``; posterior ``q(z | phi_x, phi_y, h)``; decoder
    ``p(y | phi_x, phi_z, h)`` (a Gaussian with predicted std); recurrence
    ``h' = GRU([phi_x, phi_y, phi_z], h)`` starting from ``h = 0``.

    Args:
        in_features: size of the concatenated ``in_keys``.
        out_features: size of ``out_key``.
        in_keys: keys whose values, concatenated, are the input ``x``.
        out_key: the predicted (and, in :meth:`observe`, measured) key ``y``.
        state_dim: size of the recurrent state ``h`` (the paper's 8).
        latent_dim: size of ``z``.
        width: width of the feature, prior, posterior and decoder layers.
        device: where the parameters live.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from smcd_rl.baselines import LatentVariableModel
        >>> lv = LatentVariableModel(2, 2, in_keys=["q"], out_key="ee")
        >>> lv.reset(batch_shape=(3,))
        >>> lv.observe(TensorDict({"q": torch.zeros(3, 2), "ee": torch.ones(3, 2)}, [3]))
        >>> lv(TensorDict({"q": torch.zeros(3, 5, 2)}, [3, 5]))["ee"].shape  # 5 steps ahead
        torch.Size([3, 5, 2])
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        *,
        in_keys: Sequence[NestedKey],
        out_key: NestedKey,
        state_dim: int = 8,
        latent_dim: int = 8,
        width: int = 128,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        sizes = {
            "in_features": in_features,
            "out_features": out_features,
            "state_dim": state_dim,
            "latent_dim": latent_dim,
            "width": width,
        }
        bad = {k: v for k, v in sizes.items() if isinstance(v, bool) or not isinstance(v, int) or v < 1}
        if bad:
            raise ValueError(f"sizes must be positive ints, got {bad}")
        if isinstance(in_keys, (str, tuple)) or not isinstance(in_keys, Sequence):
            raise TypeError(f"in_keys must be a list of keys such as ['q'], got {in_keys!r}")
        if not in_keys:
            raise ValueError("in_keys must name at least one input key")
        for key in in_keys:
            check_key(key, "in_keys")
        check_key(out_key, "out_key")
        self.in_keys = list(in_keys)
        self.out_keys = [out_key]
        self.out_key = out_key
        self.in_features, self.out_features = in_features, out_features
        self.state_dim, self.latent_dim, self.width = state_dim, latent_dim, width
        self.phi_x = _mlp((in_features, width, width), device)
        self.phi_y = _mlp((out_features, width, width), device)
        self.phi_z = _mlp((latent_dim, width, width), device)
        self.prior = _mlp((state_dim, width, 2 * latent_dim), device)
        self.posterior = _mlp((2 * width + state_dim, width, 2 * latent_dim), device)
        self.decoder = _mlp((2 * width + state_dim, width, width, 2 * out_features), device)
        self.cell = nn.GRUCell(3 * width, state_dim, device=device)
        self.input_norm = Normalizer(in_features).to(device)
        self.output_norm = Normalizer(out_features).to(device)
        self._h: Tensor | None = None

    @property
    def config(self) -> dict[str, Any]:
        """The constructor's size arguments."""
        return {
            "in_features": self.in_features,
            "out_features": self.out_features,
            "state_dim": self.state_dim,
            "latent_dim": self.latent_dim,
            "width": self.width,
        }

    # ------------------------------------------------------------------ online use
    def reset(self, batch_shape: Sequence[int] = ()) -> None:
        """Forget all observations: ``h = 0`` for each element of ``batch_shape``."""
        batch_shape = check_shape(batch_shape, "batch_shape")
        self.eval()
        weight = self.cell.weight_hh
        self._h = weight.new_zeros(*batch_shape, self.state_dim)

    @torch.no_grad()
    def observe(self, td: TensorDictBase) -> None:
        """Update ``h`` from one (input, target) pair per batch element (``td`` has the reset batch)."""
        check_tensordict(td, "observe")
        h = self._require_reset()
        if tuple(td.batch_size) != tuple(h.shape[:-1]):
            raise ValueError(
                f"observe got a TensorDict of batch {list(td.batch_size)} but the model was reset with "
                f"batch_shape={list(h.shape[:-1])}; pass one pair per batch element or reset with that shape"
            )
        x = self.input_norm(self._inputs(td, "observe", check_finite=True, exact=True))
        y = self.output_norm(self._target(td, self.out_key, "observe", exact=True))
        fx, fy = self.phi_x(x), self.phi_y(y)
        z, _ = _gaussian(self.posterior(torch.cat([fx, fy, h], -1)))
        self._h = self._advance(fx, fy, self.phi_z(z), h)

    @torch.no_grad()
    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Write the prediction for ``td``'s inputs (batch dims beyond the reset batch broadcast)."""
        check_tensordict(td, "forward")
        h = self._require_reset()
        x = self.input_norm(self._inputs(td, "forward", check_finite=False))
        extra = x.dim() - h.dim()
        if extra < 0 or x.shape[: h.dim() - 1] != h.shape[:-1]:
            raise ValueError(
                f"forward: inputs {list(x.shape)} do not start with the reset batch shape {list(h.shape[:-1])}"
            )
        h = h.reshape(*h.shape[:-1], *([1] * extra), self.state_dim).expand(*x.shape[:-1], self.state_dim)
        z, _ = _gaussian(self.prior(h))
        mean, _ = _gaussian(self.decoder(torch.cat([self.phi_x(x), self.phi_z(z), h], -1)))
        td.set(self.out_key, self.output_norm.inverse(mean))
        return td

    # ------------------------------------------------------------------ training
    def training_pairs(self, td: TensorDictBase) -> tuple[Tensor, Tensor]:
        """Raw windows of two steps: inputs ``[*batch, 2, in]`` and targets ``[*batch, 2, out]``."""
        steps = [(key, _next_key(key)) for key in self.in_keys]
        x0 = self._inputs(td, "fit_latent", keys=[a for a, _ in steps])
        x1 = self._inputs(td, "fit_latent", keys=[b for _, b in steps])
        y0 = self._target(td, self.out_key, "fit_latent")
        y1 = self._target(td, _next_key(self.out_key), "fit_latent")
        return torch.stack([x0, x1], -2), torch.stack([y0, y1], -2)

    def negative_elbo(self, x: Tensor, y: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Negative ELBO (nats) of each normalised sequence ``x [N, T, in]``, ``y [N, T, out]``: ``[N]``.

        ``z`` is sampled with the reparameterisation trick from ``generator``.
        """
        h = x.new_zeros(x.shape[0], self.state_dim)
        total = x.new_zeros(x.shape[0])
        for t in range(x.shape[1]):
            fx, fy = self.phi_x(x[:, t]), self.phi_y(y[:, t])
            prior_mean, prior_std = _gaussian(self.prior(h))
            post_mean, post_std = _gaussian(self.posterior(torch.cat([fx, fy, h], -1)))
            noise = torch.randn(post_mean.shape, generator=generator, device=x.device, dtype=x.dtype)
            fz = self.phi_z(post_mean + post_std * noise)
            mean, std = _gaussian(self.decoder(torch.cat([fx, fz, h], -1)))
            nll = (0.5 * ((y[:, t] - mean) / std).square() + std.log() + _HALF_LOG_2PI).sum(-1)
            kl = (
                (prior_std / post_std).log()
                + (post_std.square() + (post_mean - prior_mean).square()) / (2 * prior_std.square())
                - 0.5
            ).sum(-1)
            total = total + nll + kl
            h = self._advance(fx, fy, fz, h)
        return total

    # ------------------------------------------------------------------ persistence
    def checkpoint(self) -> dict[str, Any]:
        """Architecture, keys and weights (what :meth:`load_checkpoint` needs)."""
        return {
            "format": _FORMAT,
            "config": self.config,
            "keys": self._key_config(),
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
        }

    def load_checkpoint(self, checkpoint: dict[str, Any] | str | os.PathLike[str]) -> None:
        """Load weights and normalisation saved by :meth:`checkpoint` (a dict or a file written by ``save_file``)."""
        if not isinstance(checkpoint, dict):
            checkpoint = load_file(
                checkpoint,
                what="LatentVariableModel checkpoint",
                expect_format=_FORMAT,
                expect_keys=("config", "keys", "state_dict"),
            )
        if not isinstance(checkpoint, dict) or checkpoint.get("format") != _FORMAT:
            raise CheckpointMismatchError(f"not a LatentVariableModel checkpoint (expected format {_FORMAT})")
        missing = [key for key in ("config", "keys", "state_dict") if key not in checkpoint]
        if missing:
            raise CheckpointMismatchError(f"the LatentVariableModel checkpoint has no {missing} entries")
        if checkpoint["config"] != self.config or checkpoint["keys"] != self._key_config():
            raise CheckpointMismatchError(
                f"checkpoint holds a model {checkpoint['config']} with keys {checkpoint['keys']} but this one is "
                f"{self.config} with keys {self._key_config()}; build the model with the checkpoint's architecture"
            )
        self.load_state_dict(checkpoint["state_dict"])

    # ------------------------------------------------------------------ internals
    def _advance(self, fx: Tensor, fy: Tensor, fz: Tensor, h: Tensor) -> Tensor:
        features = torch.cat([fx, fy, fz], -1)
        # GRUCell takes one batch dim: flatten any others and restore them.
        return self.cell(features.reshape(-1, features.shape[-1]), h.reshape(-1, self.state_dim)).reshape(h.shape)

    def _require_reset(self) -> Tensor:
        if self._h is None:
            raise RuntimeError("call reset() (or reset(batch_shape=(B,))) before observe or predict")
        return self._h

    def _key_config(self) -> dict[str, Any]:
        def plain(key: NestedKey) -> Any:
            return list(key) if isinstance(key, tuple) else key

        return {"in_keys": [plain(k) for k in self.in_keys], "out_key": plain(self.out_key)}

    def _inputs(
        self,
        td: TensorDictBase,
        what: str,
        *,
        keys: Sequence[NestedKey] | None = None,
        check_finite: bool = True,
        exact: bool = False,
    ) -> Tensor:
        keys = keys or self.in_keys
        like = self.input_norm.mean
        x = read_inputs(td, keys, what=what, like=like, check_finite=check_finite, exact=exact)
        if x.shape[-1] != self.in_features:
            raise ValueError(
                f"{what}: the inputs {keys} give {x.shape[-1]} features, the model takes {self.in_features}"
            )
        return x

    def _target(self, td: TensorDictBase, key: NestedKey, what: str, *, exact: bool = False) -> Tensor:
        """``td[key]``, ``out_features`` values, checked and in the model's dtype (see :func:`smcd_rl.checks.read_tensor`)."""
        return read_tensor(td, key, self.out_features, what=what, like=self.input_norm.mean, exact=exact)


def fit_latent(
    model: LatentVariableModel,
    data: TensorDictBase,
    *,
    epochs: int = 200,
    batch_size: int = 64,
    lr: float = 1e-3,
    seed: int = 0,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool = True,
    callback: Callable[[int, float], None] | None = None,
) -> list[float]:
    """Train a :class:`LatentVariableModel` by maximising the ELBO on two-step windows.

    Each transition of ``data`` (any batch shape) is one window: ``(in_keys, out_key)`` then
    ``(("next", in_keys), ("next", out_key))``. Normalisation (fitted on first use), seeding and
    checkpoint/resume behave as in :func:`smcd_rl.fit`; the optimiser is Adam.

    Args:
        model: the model to train.
        data: transitions with the model's keys and their ``("next", ...)`` versions.
        epochs: passes over the windows (the paper trains 200).
        batch_size: windows per gradient step.
        lr: Adam learning rate.
        seed: seed of shuffling and of the sampled latents.
        checkpoint: file to save to after each epoch and to resume from.
        progress: show a progress bar.
        callback: called as ``callback(epoch, mean_loss)`` after each epoch.

    Returns:
        Mean negative ELBO per window (nats, normalised units) of every epoch.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from smcd_rl.baselines import LatentVariableModel, fit_latent
        >>> q = torch.rand(64, 2)
        >>> data = TensorDict({"q": q, "ee": q.cos(), ("next", "q"): q + 0.1, ("next", "ee"): (q + 0.1).cos()}, [64])
        >>> lv = LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=16)
        >>> len(fit_latent(lv, data, epochs=2, batch_size=16, progress=False))
        2
    """
    if not isinstance(model, LatentVariableModel):
        raise TypeError(f"fit_latent trains a LatentVariableModel, got {type(model).__name__}")
    if epochs < 0 or batch_size < 1 or lr <= 0:
        raise ValueError(f"need epochs >= 0, batch_size >= 1 and lr > 0, got {epochs}, {batch_size}, {lr}")
    loop = _Loop("fit_latent", epochs, seed, checkpoint, progress, callback)
    _require_samples(data, "fit_latent")
    device = model.cell.weight_hh.device
    x, y = _normalised_pairs(model, data.reshape(-1), device)  # [windows, 2, features]
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    settings = {"trainer": "latent", "batch_size": batch_size, "lr": lr, "seed": seed}
    n = x.shape[0]

    def one_epoch(generator: torch.Generator) -> float:
        return _shuffled_epoch(
            n, batch_size, optimizer, generator, lambda idx: model.negative_elbo(x[idx], y[idx], generator).mean()
        )

    return _train(model, one_epoch, data, loop, trained=model, settings=settings, optimizer=optimizer)
