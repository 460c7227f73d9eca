"""The oracle baseline (O+P): a particle filter over the true physical parameters of a known model."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from smcd_rl.checks import check_real, check_real_tensor, check_shape, check_tensordict
from smcd_rl.filter import ParticleFilter
from smcd_rl.resampling import ResamplingScheme

__all__ = ["ParameterFilter", "OracleModel"]

#: ``prior(shape, generator) -> [*shape, P]`` draws parameter vectors.
PriorFn = Callable[[tuple[int, ...], torch.Generator], Tensor]
#: ``predict(params [*B, *extra, N, P], inputs [*B, *extra, 1, in]) -> [*B, *extra, N, out]``.
PredictFn = Callable[[Tensor, Tensor], Tensor]


class ParameterFilter(ParticleFilter):
    """Particles over continuous parameters with a Gaussian random-walk transition.

    Args:
        prior: draws initial parameter vectors, ``prior(shape, generator) -> [*shape, P]``.
        num_particles: ``N``.
        jitter_std: standard deviation of the random walk per step (keeps the particle set
            diverse after resampling, and lets it follow slowly changing parameters).
        lower: parameters are clamped from below at this value (e.g. a minimum link length).
        resampling: see :class:`smcd_rl.ParticleFilter`.
        ess_threshold: see :class:`smcd_rl.ParticleFilter`.
        generator: see :class:`smcd_rl.ParticleFilter`.
        device: see :class:`smcd_rl.ParticleFilter`.

    Example:
        >>> import torch
        >>> from smcd_rl.baselines import ParameterFilter
        >>> filt = ParameterFilter(lambda shape, g: torch.randn(*shape, 2, generator=g), num_particles=64)
        >>> filt.reset()
        >>> filt.particles.shape
        torch.Size([64, 2])
    """

    def __init__(
        self,
        prior: PriorFn,
        num_particles: int = 1000,
        *,
        jitter_std: float | Sequence[float] = 0.01,
        lower: float | None = None,
        resampling: ResamplingScheme = "systematic",
        ess_threshold: float = 1.0,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(
            num_particles, resampling=resampling, ess_threshold=ess_threshold, generator=generator, device=device
        )
        self.prior = prior
        self.jitter_std = torch.as_tensor(jitter_std, dtype=torch.float32, device=self.device)
        self.lower = lower

    @property
    def mean(self) -> Tensor:
        """Weighted mean of the parameters, ``[*batch, P]``."""
        particles = self._state()[0]
        return (self.weights.unsqueeze(-2) @ particles).squeeze(-2)

    def _initial(self, batch_shape: tuple[int, ...], num_particles: int) -> Tensor:
        return self.prior((*batch_shape, num_particles), self.generator).to(self.device, torch.float32)

    def _transition(self, particles: Tensor) -> Tensor:
        noise = torch.randn(particles.shape, generator=self.generator, device=self.device)
        moved = particles + noise * self.jitter_std
        return moved if self.lower is None else moved.clamp_min(self.lower)


class OracleModel(TensorDictModuleBase):
    """Known physics with unknown parameters, inferred online by a :class:`ParameterFilter`.

    Has the interface of :class:`smcd_rl.AdaptiveModel` (``reset``, ``observe``, ``forward``)
    so experiments treat it like any other method. Predictions are the posterior predictive mean.

    Args:
        predict: the known model, ``predict(params, inputs)`` (see ``PredictFn``).
        prior: parameter prior (see :class:`ParameterFilter`).
        in_keys: keys concatenated into ``inputs``.
        out_key: where predictions are written; also the measurement key in :meth:`observe`.
        noise_std: measurement noise of the Gaussian likelihood.
        num_particles: see :class:`ParameterFilter`.
        jitter_std: see :class:`ParameterFilter`.
        lower: see :class:`ParameterFilter`.
        generator: see :class:`ParameterFilter`.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from smcd_rl.baselines import OracleModel
        >>> from smcd_rl.envs.two_link_arm import two_link_fk, sample_link_lengths
        >>> oracle = OracleModel(lambda p, q: two_link_fk(q, p), lambda s, g: sample_link_lengths(s, generator=g),
        ...                      in_keys=["q"], out_key="ee", num_particles=200)
        >>> oracle.reset()
        >>> oracle.observe(TensorDict({"q": torch.zeros(2), "ee": torch.tensor([2.0, 0.0])}, []))
        >>> oracle(TensorDict({"q": torch.zeros(2)}, []))["ee"].shape
        torch.Size([2])
    """

    def __init__(
        self,
        predict: PredictFn,
        prior: PriorFn,
        *,
        in_keys: Sequence[NestedKey],
        out_key: NestedKey,
        noise_std: float = 0.05,
        num_particles: int = 1000,
        jitter_std: float | Sequence[float] = 0.01,
        lower: float | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.noise_std = check_real(noise_std, "noise_std", low=0.0, open_low=True)
        if not in_keys or isinstance(in_keys, (str, tuple)):
            raise TypeError(f"in_keys must be a non-empty list of keys such as ['q'], got {in_keys!r}")
        self.in_keys = list(in_keys)
        self.out_keys = [out_key]
        self.predict_fn = predict
        self.filter = ParameterFilter(prior, num_particles, jitter_std=jitter_std, lower=lower, generator=generator)
        self._batch_shape: tuple[int, ...] = ()

    def reset(self, batch_shape: Sequence[int] = ()) -> None:
        self._batch_shape = check_shape(batch_shape, "batch_shape")
        self.filter.reset(self._batch_shape)

    def observe(self, td: TensorDictBase) -> None:
        check_tensordict(td, "observe")
        if tuple(td.batch_size) != self._batch_shape:
            raise ValueError(
                f"observe got a TensorDict of batch {list(td.batch_size)} but the oracle was reset with "
                f"batch_shape={list(self._batch_shape)}; pass one transition per batch element"
            )
        inputs = self._inputs(td)
        target = self._read(td, self.out_keys[0])
        for key, value in (("inputs", inputs), (self.out_keys[0], target)):
            if tuple(value.shape[:-1]) != tuple(td.batch_size):
                raise ValueError(
                    f"observe: {key!r} has shape {list(value.shape)} but the TensorDict's batch is "
                    f"{list(td.batch_size)}; pass one transition per batch element, [*batch, features]"
                )
        # Checked in float32, the dtype the physics runs in: a float64 1e39 would be inf there.
        if not (bool(torch.isfinite(inputs).all()) and bool(torch.isfinite(target).all())):
            raise ValueError("observe: NaN or inf in the transition; the filter state is unchanged")
        sigma = self.noise_std
        log_norm = -target.shape[-1] * (math.log(sigma) + 0.5 * math.log(2 * math.pi))

        def log_likelihood(params: Tensor) -> Tensor:
            residual = (target.unsqueeze(-2) - self.predict_fn(params, inputs.unsqueeze(-2))) / sigma
            return log_norm - 0.5 * residual.square().sum(-1)

        self.filter.update(log_likelihood)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        check_tensordict(td, "forward")
        inputs = self._inputs(td)
        extra = inputs.dim() - 1 - len(self._batch_shape)
        params = self.filter.particles
        weights = self.filter.weights
        assert params is not None
        view = (*self._batch_shape, *([1] * extra))
        predictions = self.predict_fn(params.reshape(*view, *params.shape[-2:]), inputs.unsqueeze(-2))
        mean = (weights.reshape(*view, -1, 1) * predictions).sum(-2)
        td.set(self.out_keys[0], mean)
        return td

    def _read(self, td: TensorDictBase, key: NestedKey) -> Tensor:
        value = td.get(key, None)
        if value is None:
            raise KeyError(f"the TensorDict has no key {key!r}; it has {sorted(map(str, td.keys(True, True)))}")
        value = check_real_tensor(value, repr(key))
        if value.dim() == 0:
            raise ValueError(f"{key!r} must have shape [..., features], got a scalar")
        return value.to(torch.float32)

    def _inputs(self, td: TensorDictBase) -> Tensor:
        parts = [self._read(td, k) for k in self.in_keys]
        try:
            return torch.cat(parts, -1) if len(parts) > 1 else parts[0]
        except RuntimeError as err:
            shapes = {str(k): list(p.shape) for k, p in zip(self.in_keys, parts, strict=True)}
            raise ValueError(f"cannot concatenate inputs {shapes} along the last dim") from err
