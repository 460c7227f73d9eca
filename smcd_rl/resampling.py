"""Resampling schemes for particle filters, as pure batched functions of the log-weights."""

from __future__ import annotations

from typing import Literal, get_args

import torch
from torch import Tensor

from smcd_rl.checks import check_count

__all__ = ["ResamplingScheme", "RESAMPLING_SCHEMES", "resample_indices", "check_scheme"]

ResamplingScheme = Literal["systematic", "multinomial", "stratified", "residual"]
RESAMPLING_SCHEMES: tuple[str, ...] = get_args(ResamplingScheme)


def check_scheme(scheme: str) -> ResamplingScheme:
    """Return ``scheme`` if it names a resampling scheme, else raise a ValueError listing them."""
    if scheme not in RESAMPLING_SCHEMES:
        raise ValueError(f"unknown resampling scheme {scheme!r}; choose one of {list(RESAMPLING_SCHEMES)}")
    return scheme  # type: ignore[return-value]


def resample_indices(
    log_weights: Tensor,
    scheme: ResamplingScheme = "systematic",
    *,
    num_samples: int | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ancestor indices so that particle ``i`` has ``num_samples * w_i`` offspring in expectation.

    All four schemes are unbiased; systematic, stratified and residual have lower variance than
    multinomial. Returned indices are sorted, so children of one parent are contiguous.

    Args:
        log_weights: ``[..., N]`` unnormalised log-weights; each row needs a finite entry.
        scheme: ``"systematic"`` (one uniform per row), ``"stratified"`` (one per stratum),
            ``"multinomial"`` (i.i.d. draws) or ``"residual"`` (floor(M w) copies, rest multinomial).
        num_samples: number of offspring ``M`` per row (default ``N``).
        generator: random source, for repeatable draws.

    Returns:
        ``[..., M]`` int64 ancestor indices in ``[0, N)``.

    Example:
        >>> import torch
        >>> from smcd_rl.resampling import resample_indices
        >>> resample_indices(torch.log(torch.tensor([0.0, 1.0, 0.0])))
        tensor([1, 1, 1])
    """
    check_scheme(scheme)
    n = log_weights.shape[-1]
    m = n if num_samples is None else check_count(num_samples, "num_samples")
    if n < 1 or m < 1:
        raise ValueError(f"need at least one particle and one sample, got N={n}, M={m}")
    batch = log_weights.shape[:-1]
    device = log_weights.device
    # float64 keeps the cumulative sum exact enough that no offspring are lost at N in the thousands.
    weights = torch.softmax(log_weights.to(torch.float64), dim=-1)
    if scheme == "residual":
        return _residual(weights, m, generator)
    steps = torch.arange(m, device=device, dtype=torch.float64)
    if scheme == "systematic":
        u = (torch.rand(*batch, 1, generator=generator, device=device, dtype=torch.float64) + steps) / m
    elif scheme == "stratified":
        u = (torch.rand(*batch, m, generator=generator, device=device, dtype=torch.float64) + steps) / m
    else:  # multinomial by inverting the CDF at sorted i.i.d. uniforms
        u = torch.rand(*batch, m, generator=generator, device=device, dtype=torch.float64).sort(dim=-1).values
    return _invert_cdf(weights, u)


def _invert_cdf(weights: Tensor, u: Tensor) -> Tensor:
    cdf = weights.cumsum(dim=-1)
    return torch.searchsorted(cdf, u.contiguous(), right=True).clamp_(max=weights.shape[-1] - 1)


def _residual(weights: Tensor, m: int, generator: torch.Generator | None) -> Tensor:
    scaled = weights * m
    counts = scaled.floor()
    remaining = m - counts.sum(dim=-1, keepdim=True)  # [..., 1], integer-valued
    residual = (scaled - counts).clamp_min(0.0)
    residual = residual / residual.sum(dim=-1, keepdim=True).clamp_min(1e-300)
    u = torch.rand(*weights.shape[:-1], m, generator=generator, device=weights.device, dtype=torch.float64)
    # The first `remaining` of i.i.d. (unsorted) uniforms: taking the smallest would bias low indices.
    picks = _invert_cdf(residual, u)
    used = (torch.arange(m, device=weights.device) < remaining).to(torch.float64)
    counts = counts.scatter_add(-1, picks, used)
    return counts_to_indices(counts.round().long(), m)


def counts_to_indices(counts: Tensor, m: int) -> Tensor:
    """Turn offspring counts ``[..., N]`` (summing to ``m``) into sorted ancestor indices ``[..., m]``."""
    ends = counts.cumsum(dim=-1)
    slots = torch.arange(m, device=counts.device).expand(*counts.shape[:-1], m).contiguous()
    return torch.searchsorted(ends, slots, right=True).clamp_(max=counts.shape[-1] - 1)
