"""Particle filters: the SMCD filter over dropout masks and the weighted-particle machinery it uses.

The filters know particles, log-likelihoods and resampling only; they never see a network, an
environment or a TensorDict key. A caller turns an observation into per-particle
log-likelihoods and hands them to :meth:`ParticleFilter.reweight` (or to :meth:`ParticleFilter.update`,
which also proposes the next particles and rolls everything back if the likelihoods are invalid).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from smcd_rl.resampling import ResamplingScheme, check_scheme, resample_indices

__all__ = ["ParticleFilter", "SMCDFilter", "sample_flip_positions", "flat_particle_index", "Transition"]

#: How :class:`SMCDFilter` moves its masks, see its docstring.
Transition = Literal["keep_rate", "symmetric"]


def check_transition(transition: str) -> Transition:
    """Return ``transition`` if it names a :data:`Transition`, else raise a ValueError that lists them."""
    if transition not in ("keep_rate", "symmetric"):
        raise ValueError(f"transition must be 'keep_rate' or 'symmetric', got {transition!r}")
    return transition  # type: ignore[return-value]


#: Above this flip probability drawing one uniform per bit is as cheap as the sparse sampler.
_DENSE_FLIP_PROB = 0.05


class ParticleFilter:
    """Weighted particles ``[*batch, N, D]``: reweighting, resampling, ESS and log evidence.

    Subclasses define the prior (:meth:`_initial`) and the transition (:meth:`_transition`).
    Each element of ``batch_shape`` is an independent filter (one per environment of a vector env).

    Args:
        num_particles: ``N``.
        resampling: ``"systematic"``, ``"multinomial"``, ``"stratified"`` or ``"residual"``.
        ess_threshold: resample a batch element when its ESS drops below ``ess_threshold * N``;
            ``1.0`` resamples after every informative update (Algorithm 1), ``0.0`` never.
        generator: random source. Without one the filter seeds its own from torch's global
            generator, so ``torch.manual_seed`` makes runs repeatable.
        device: where particles live (default: the generator's device, else CPU).
    """

    def __init__(
        self,
        num_particles: int,
        *,
        resampling: ResamplingScheme = "systematic",
        ess_threshold: float = 1.0,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        if int(num_particles) < 1:
            raise ValueError(f"num_particles must be >= 1, got {num_particles}")
        if not 0.0 <= ess_threshold <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {ess_threshold}")
        self.resampling: ResamplingScheme = check_scheme(resampling)
        self.ess_threshold = float(ess_threshold)
        if device is None:
            device = generator.device if generator is not None else "cpu"
        self.device = torch.device(device)
        if generator is None:
            generator = torch.Generator(device=self.device)
            generator.manual_seed(int(torch.randint(0, 2**62, (1,)).item()))
        elif generator.device.type != self.device.type:
            raise ValueError(f"generator is on {generator.device} but the filter is on {self.device}")
        self.generator = generator
        self._num_particles = int(num_particles)
        self._particles: Tensor | None = None
        self._log_weights: Tensor | None = None
        #: Quantities computed from particles and weights (e.g. the MMSE mask), dropped when either changes.
        self._derived: dict[str, Tensor] = {}
        self.log_evidence: Tensor | None = None
        #: Ancestor index of every particle at the last resampling, ``[*batch, N]``: particles with
        #: the same ancestor are identical copies. ``None`` when unknown (no resampling since the
        #: last reset, transition or state load); an SMCD update uses it to skip repeated work.
        self.ancestors: Tensor | None = None
        #: ESS of the last reweighting, before any resampling (``ess`` is N right after one).
        self.last_ess: Tensor | None = None

    # ------------------------------------------------------------------ to implement
    def _initial(self, batch_shape: tuple[int, ...], num_particles: int) -> Tensor:
        raise NotImplementedError

    def _transition(self, particles: Tensor) -> Tensor:
        """Return the next particles; must not modify ``particles`` in place."""
        raise NotImplementedError

    # ------------------------------------------------------------------ state
    @property
    def particles(self) -> Tensor | None:
        """Particles ``[*batch, N, D]`` (``None`` before :meth:`reset`)."""
        return self._particles

    @particles.setter
    def particles(self, value: Tensor | None) -> None:
        # New particles: cached summaries are stale and copies are no longer known.
        self._particles, self._derived, self.ancestors = value, {}, None

    @property
    def log_weights(self) -> Tensor | None:
        """Normalised log-weights ``[*batch, N]`` (``None`` before :meth:`reset`)."""
        return self._log_weights

    @log_weights.setter
    def log_weights(self, value: Tensor | None) -> None:
        self._log_weights, self._derived = value, {}

    @property
    def num_particles(self) -> int:
        return self._num_particles

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self._state()[0].shape[:-2])

    @property
    def weights(self) -> Tensor:
        """Normalised weights ``[*batch, N]``."""
        return self._state()[1].exp()

    @property
    def ess(self) -> Tensor:
        """Effective sample size ``1 / sum w_i^2``, in ``[1, N]``, shape ``[*batch]``."""
        return torch.exp(-torch.logsumexp(2.0 * self._state()[1], dim=-1))

    def reset(self, batch_shape: Sequence[int] = ()) -> None:
        """Draw fresh particles from the prior, with uniform weights and zero log evidence."""
        batch_shape = tuple(int(b) for b in batch_shape)
        n = self._num_particles
        self.particles = self._initial(batch_shape, n)
        self.log_weights = torch.full((*batch_shape, n), -math.log(n), device=self.device)
        self.log_evidence = torch.zeros(batch_shape, device=self.device)
        self.last_ess = torch.full(batch_shape, float(n), device=self.device)

    def propagate(self) -> None:
        """Move every particle one step through the transition model."""
        self.particles = self._transition(self._state()[0])  # forgets the ancestors: copies now differ

    def reweight(self, log_likelihood: Tensor) -> None:
        """Multiply the weights by the likelihoods, accumulate the evidence, resample if the ESS is low.

        Args:
            log_likelihood: ``[*batch, N]`` log p(z | particle). NaN or ``+inf`` entries, or a
                batch element whose entries are all ``-inf``, raise ValueError and change nothing.
        """
        log_likelihood = self._checked_log_likelihood(log_likelihood)
        self._apply(log_likelihood)

    def update(self, log_likelihood_fn: Callable[[Tensor], Tensor]) -> Tensor:
        """One filter step: propagate, score the proposed particles, reweight and resample.

        The step is atomic: if ``log_likelihood_fn`` raises or returns invalid values, the
        particles, weights, evidence and random generator are left exactly as they were.

        Args:
            log_likelihood_fn: maps the proposed particles ``[*batch, N, D]`` to ``[*batch, N]``.

        Returns:
            The log-likelihoods of the proposed particles.
        """
        particles = self._state()[0]
        rng_state = self.generator.get_state()
        try:
            proposed = self._transition(particles)
            log_likelihood = self._checked_log_likelihood(log_likelihood_fn(proposed))
        except BaseException:
            self.generator.set_state(rng_state)
            raise
        self.particles = proposed
        self._apply(log_likelihood)
        return log_likelihood

    def resize(self, num_particles: int) -> None:
        """Change ``N`` online by resampling ``num_particles`` from the current weighted set.

        The weighted distribution is kept (in expectation); weights become uniform.
        """
        if int(num_particles) < 1:
            raise ValueError(f"num_particles must be >= 1, got {num_particles}")
        particles, log_weights, _ = self._state()
        idx = resample_indices(log_weights, self.resampling, num_samples=int(num_particles), generator=self.generator)
        self.particles = _gather_particles(particles, idx)
        self._num_particles = int(num_particles)
        self.log_weights = torch.full(idx.shape, -math.log(self._num_particles), device=self.device)
        self.ancestors = idx

    def state_dict(self) -> dict[str, Any]:
        """A copy of the full state, generator included; :meth:`load_state_dict` restores it."""
        particles, log_weights, log_evidence = self._state()
        return {
            "particles": particles.clone(),
            "log_weights": log_weights.clone(),
            "log_evidence": log_evidence.clone(),
            "last_ess": None if self.last_ess is None else self.last_ess.clone(),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.particles = state["particles"].clone().to(self.device)
        self.log_weights = state["log_weights"].clone().to(self.device)
        self.log_evidence = state["log_evidence"].clone().to(self.device)
        self._num_particles = self.particles.shape[-2]
        self.last_ess = None if state.get("last_ess") is None else state["last_ess"].clone().to(self.device)
        self.generator.set_state(state["generator"])

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        """Put back ``state``'s particles, weights and evidence in the batch elements where ``rows`` is True.

        The way to reset or update only some environments of a batch: save :meth:`state_dict`,
        act on the whole batch, then restore the rows that should not have changed. The
        generator is left as it is.

        Args:
            state: a :meth:`state_dict` of this filter with the same batch shape and ``N``.
            rows: bool ``[*batch]``.
        """
        particles, log_weights, log_evidence = self._state()
        ancestors = self.ancestors
        rows = rows.to(self.device).reshape(log_evidence.shape)
        self.particles = torch.where(rows[..., None, None], state["particles"], particles)
        self.log_weights = torch.where(rows[..., None], state["log_weights"], log_weights)
        self.log_evidence = torch.where(rows, state["log_evidence"], log_evidence)
        if state.get("last_ess") is not None and self.last_ess is not None:
            self.last_ess = torch.where(rows, state["last_ess"], self.last_ess)
        if ancestors is not None:
            # Restored rows' copies are unknown: give each particle its own ancestor, always true.
            own = torch.arange(self._num_particles, device=self.device).expand_as(ancestors)
            self.ancestors = torch.where(rows[..., None], own, ancestors)

    # ------------------------------------------------------------------ internals
    def _state(self) -> tuple[Tensor, Tensor, Tensor]:
        if self.particles is None or self.log_weights is None or self.log_evidence is None:
            raise RuntimeError(f"{type(self).__name__} has no particles yet: call reset(batch_shape) first")
        return self.particles, self.log_weights, self.log_evidence

    def _checked_log_likelihood(self, log_likelihood: Tensor) -> Tensor:
        log_weights = self._state()[1]
        if not isinstance(log_likelihood, Tensor):
            raise TypeError(f"log_likelihood must be a Tensor, got {type(log_likelihood).__name__}")
        if log_likelihood.shape != log_weights.shape:
            raise ValueError(
                f"log_likelihood must have shape [*batch, N] = {list(log_weights.shape)}, "
                f"got {list(log_likelihood.shape)}"
            )
        if not bool(torch.isfinite(log_likelihood).all()):  # one pass; the checks below name the problem
            if torch.isnan(log_likelihood).any():
                raise ValueError("log_likelihood contains NaN; check the observation and the model's prediction")
            if torch.isposinf(log_likelihood).any():
                raise ValueError("log_likelihood contains +inf; check the likelihood's noise scale (it must be > 0)")
            if (log_likelihood == -math.inf).all(dim=-1).any():
                raise ValueError(
                    "every particle of a batch element has zero likelihood (all -inf): "
                    "the observation is impossible under the model; increase the likelihood's noise scale"
                )
        return log_likelihood.to(log_weights.dtype)

    def _apply(self, log_likelihood: Tensor) -> None:
        particles, log_weights, log_evidence = self._state()
        joint = log_weights + log_likelihood
        log_norm = torch.logsumexp(joint, dim=-1)
        self.log_evidence = log_evidence + log_norm
        self.log_weights = joint - log_norm.unsqueeze(-1)
        self.last_ess = self.ess
        self._resample_if_needed()

    def _resample_if_needed(self) -> None:
        particles, log_weights, _ = self._state()
        n = self._num_particles
        need = self.last_ess < self.ess_threshold * n  # set by _apply for these weights
        if not bool(need.any()):
            return
        idx = resample_indices(log_weights, self.resampling, generator=self.generator)
        new_log_weights = torch.full_like(log_weights, -math.log(n))  # uniform after resampling
        if not bool(need.all()):  # only some batch elements resample
            idx = torch.where(need.unsqueeze(-1), idx, torch.arange(n, device=self.device))
            new_log_weights = torch.where(need.unsqueeze(-1), new_log_weights, log_weights)
        self.particles = _gather_particles(particles, idx)
        self.log_weights = new_log_weights
        self.ancestors = idx


def flat_particle_index(idx: Tensor, num_particles: int) -> Tensor:
    """Flatten per-batch-element particle indices ``idx [*batch, M]`` into rows of ``[prod(batch) * N]``.

    Example:
        >>> import torch
        >>> flat_particle_index(torch.tensor([[0, 2], [1, 1]]), num_particles=3)
        tensor([0, 2, 4, 4])
    """
    batch = idx.shape[:-1]
    if math.prod(batch) == 1:
        return idx.reshape(-1)
    offsets = (torch.arange(math.prod(batch), device=idx.device) * num_particles).reshape(*batch, 1)
    return (idx + offsets).reshape(-1)


def group_copies(index: Tensor) -> tuple[Tensor, Tensor]:
    """The sorted distinct values of ``index`` and each entry's group; cheaper when ``index`` is sorted.

    Every resampling scheme returns sorted ancestors, so the sort is almost never needed.

    Example:
        >>> import torch
        >>> group_copies(torch.tensor([0, 0, 3, 3, 3]))
        (tensor([0, 3]), tensor([0, 0, 1, 1, 1]))
    """
    if index.numel() < 2 or bool((index[1:] >= index[:-1]).all()):
        groups, inverse = torch.unique_consecutive(index, return_inverse=True)
    else:
        groups, inverse = torch.unique(index, return_inverse=True)
    return groups, inverse


def group_members(inverse: Tensor, num_groups: int) -> Tensor:
    """One member of each group, by its position in ``inverse`` (any will do: they are equal copies).

    Example:
        >>> import torch
        >>> inverse = torch.tensor([0, 0, 1, 1, 1])
        >>> inverse[group_members(inverse, 2)]  # each member belongs to its group
        tensor([0, 1])
    """
    member = torch.empty(num_groups, dtype=torch.long, device=inverse.device)
    return member.scatter_(0, inverse, torch.arange(inverse.numel(), device=inverse.device))


def _gather_particles(particles: Tensor, idx: Tensor) -> Tensor:
    """``particles[..., idx, :]`` per batch element, as one row copy (``gather`` is ~50x slower here)."""
    n, dim = particles.shape[-2], particles.shape[-1]
    rows = particles.reshape(-1, dim).index_select(0, flat_particle_index(idx, n))
    return rows.reshape(*idx.shape, dim)


def sample_flip_positions(
    numel: int, flip_prob: float, *, generator: torch.Generator | None = None, device: torch.device | str = "cpu"
) -> Tensor:
    """Positions of the flipped bits among ``numel`` independent Bernoulli(``flip_prob``) bits.

    Instead of one uniform per bit this draws the gaps between successive flips, which are
    i.i.d. geometric: ``P(gap >= g) = (1 - p)^g``, sampled exactly as ``floor(log U / log(1 - p))``.
    The result has exactly the distribution of ``(torch.rand(numel) < p).nonzero()`` but costs
    about ``numel * p`` uniforms instead of ``numel``.

    Returns:
        Sorted, distinct int64 positions in ``[0, numel)``.

    Example:
        >>> import torch
        >>> from smcd_rl.filter import sample_flip_positions
        >>> pos = sample_flip_positions(10_000, 0.01, generator=torch.Generator().manual_seed(0))
        >>> bool((pos[1:] > pos[:-1]).all())
        True
    """
    device = torch.device(device)
    if not 0.0 <= flip_prob <= 1.0:
        raise ValueError(f"flip_prob must be in [0, 1], got {flip_prob}")
    if numel == 0 or flip_prob == 0.0:
        return torch.empty(0, dtype=torch.long, device=device)
    if flip_prob >= _DENSE_FLIP_PROB:
        flips = torch.rand(numel, generator=generator, device=device) < flip_prob
        return flips.nonzero().squeeze(-1)
    log_stay = math.log1p(-flip_prob)
    mean = numel * flip_prob
    # Enough gaps to pass the end with overwhelming probability; otherwise draw another chunk.
    chunk = int(mean + 6.0 * math.sqrt(mean) + 16)
    pieces: list[Tensor] = []
    start = 0
    while True:
        # floor(log(1 - u) / log(1 - p)), op for op: 1 - u is in (0, 1], so the quotient is
        # >= 0 (or +inf, clamped) and the truncating cast to int64 is the floor.
        u = torch.rand(chunk, generator=generator, device=device, dtype=torch.float64)
        gaps = (1.0 - u).log_().div_(log_stay).clamp_(max=numel).long()
        positions = gaps.add_(1).cumsum_(0).add_(start - 1)
        inside = int(torch.searchsorted(positions, numel))  # positions are increasing
        if inside < chunk:
            pieces.append(positions[:inside])
            break
        pieces.append(positions)
        start = int(positions[-1]) + 1
    return pieces[0] if len(pieces) == 1 else torch.cat(pieces)


class SMCDFilter(ParticleFilter):
    """Sequential Monte Carlo Dropout: a bootstrap particle filter over binary dropout masks.

    Algorithm 1 of the paper: masks start as Bernoulli(``keep_prob``) draws (the training
    distribution), move by xor with random bit flips, are weighted by the likelihood of the real
    observation and resampled; the MMSE mask is the weighted mean.

    The transition (``transition``):

    * ``"keep_rate"`` (default): a kept bit (1) flips with probability ``2 d (1 - k)``, a dropped
      bit (0) with ``2 d k``, for ``d = flip_prob`` and ``k = keep_prob``. Masks then stay
      distributed as in training, Bernoulli(``k``), and forget their start at the rate ``1 - 2d``
      of symmetric flips. At ``k = 0.5`` (the paper's dropout) this *is* the paper's xor with
      Bernoulli(``d``) flips, random stream included.
    * ``"symmetric"``: every bit flips with probability ``d``, the paper's rule taken literally.
      With ``k != 0.5`` it drifts the masks towards half the units kept, a network the training
      never ran (with dropout 0.1 the share of kept units falls from 0.9 to 0.65 in 50 steps),
      which biases every prediction.

    Args:
        mask_dim: bits per mask.
        num_particles: ``N``.
        flip_prob: ``d``, the flip probability per bit and :meth:`propagate` at ``keep_prob = 0.5``.
        keep_prob: probability that a bit is 1 in the initial masks (``1 - dropout``).
        transition: ``"keep_rate"`` or ``"symmetric"``, see above.
        resampling: see :class:`ParticleFilter`.
        ess_threshold: see :class:`ParticleFilter`.
        generator: see :class:`ParticleFilter`.
        device: see :class:`ParticleFilter`.

    Example:
        >>> import torch, smcd_rl
        >>> filt = smcd_rl.SMCDFilter(8, num_particles=100, generator=torch.Generator().manual_seed(0))
        >>> filt.reset()
        >>> filt.propagate()
        >>> filt.reweight(-(filt.particles.float().sum(-1) - 8) ** 2)  # favour all-ones masks
        >>> filt.particles.shape, filt.mean_mask.shape
        (torch.Size([100, 8]), torch.Size([8]))
    """

    def __init__(
        self,
        mask_dim: int,
        num_particles: int = 1000,
        flip_prob: float = 0.01,
        keep_prob: float = 0.5,
        resampling: ResamplingScheme = "systematic",
        ess_threshold: float = 1.0,
        generator: torch.Generator | None = None,
        device: torch.device | str | None = None,
        transition: Transition = "keep_rate",
    ) -> None:
        super().__init__(
            num_particles, resampling=resampling, ess_threshold=ess_threshold, generator=generator, device=device
        )
        if int(mask_dim) < 1:
            raise ValueError(f"mask_dim must be >= 1, got {mask_dim}")
        if not 0.0 <= flip_prob <= 1.0:
            raise ValueError(f"flip_prob must be in [0, 1], got {flip_prob}")
        if not 0.0 < keep_prob <= 1.0:
            raise ValueError(f"keep_prob must be in (0, 1], got {keep_prob}")
        self.mask_dim = int(mask_dim)
        self.flip_prob = float(flip_prob)
        self.keep_prob = float(keep_prob)
        self.transition = check_transition(transition)
        self.flip_rates()  # fail now, not at the first propagate
        #: Flat positions (into ``particles.reshape(-1)``) flipped by the last transition.
        self.last_flips: Tensor | None = None

    @property
    def mean_mask(self) -> Tensor:
        """The MMSE mask: weighted mean of the particles, float ``[*batch, mask_dim]``.

        Computed once per filter state. After resampling, copies of one ancestor are summed
        first, so the cost scales with the number of distinct particles rather than ``N``.
        """
        cached = self._derived.get("mean_mask")
        if cached is None:
            cached = self._derived["mean_mask"] = self._weighted_mean()
        return cached

    def _weighted_mean(self) -> Tensor:
        particles, log_weights, _ = self._state()
        weights, dtype = log_weights.exp(), log_weights.dtype
        n, dim = particles.shape[-2], particles.shape[-1]
        if self.ancestors is not None:
            total = weights.numel()
            groups, inverse = group_copies(flat_particle_index(self.ancestors, n))
            if 2 * groups.numel() <= total:
                group_weight = torch.zeros(groups.numel(), dtype=dtype, device=self.device)
                group_weight.index_add_(0, inverse, weights.reshape(-1))
                member = group_members(inverse, groups.numel())
                rows = particles.reshape(total, dim).index_select(0, member).view(torch.uint8).to(dtype)
                mean = torch.zeros(total // n, dim, dtype=dtype, device=self.device)
                mean.index_add_(0, groups // n, rows.mul_(group_weight.unsqueeze(-1)))
                return mean.reshape(*weights.shape[:-1], dim)
        # Via uint8: converting bool to float directly is several times slower.
        bits = particles.view(torch.uint8).to(dtype)
        return (weights.unsqueeze(-2) @ bits).squeeze(-2)

    def flip_rates(self) -> tuple[float, float]:
        """``(P(1 -> 0), P(0 -> 1))`` per bit and step, under :attr:`transition`."""
        d, k = self.flip_prob, self.keep_prob
        if self.transition == "symmetric":
            return d, d
        off, on = 2.0 * d * (1.0 - k), 2.0 * d * k
        if max(off, on) > 1.0:
            raise ValueError(
                f"flip_prob={d} is too large for the keep_rate transition at keep_prob={k}: a bit would flip "
                f"with probability {max(off, on):.3g} > 1; use flip_prob <= {1 / (2 * max(k, 1 - k)):.3g}"
            )
        return off, on

    def _initial(self, batch_shape: tuple[int, ...], num_particles: int) -> Tensor:
        shape = (*batch_shape, num_particles, self.mask_dim)
        return torch.rand(shape, generator=self.generator, device=self.device) < self.keep_prob

    def _transition(self, particles: Tensor) -> Tensor:
        off, on = self.flip_rates()
        top = max(off, on)
        flips = sample_flip_positions(particles.numel(), top, generator=self.generator, device=self.device)
        if off != on:
            # Thinning: a candidate flips with (its bit's rate) / top, so each bit flips with
            # exactly its own rate, independently.
            bits = particles.reshape(-1)[flips]
            rate = torch.where(bits, off / top, on / top)
            flips = flips[torch.rand(flips.shape, generator=self.generator, device=self.device) < rate]
        self.last_flips = flips
        flat = particles.reshape(-1).clone()
        flat[flips] = ~flat[flips]
        return flat.view(particles.shape)
