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

from smcd_rl.checks import check_count, check_real, check_real_tensor, check_shape, checked_rows
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
        missing = [
            name for name in ("_initial", "_transition") if getattr(type(self), name) is getattr(ParticleFilter, name)
        ]
        if missing:  # checked here, not at the first reset, so the class is fixed where it is written
            raise TypeError(
                f"{type(self).__name__} does not define {' and '.join(missing)} (how to draw the first particles and "
                "how they move): ParticleFilter is a base class; subclass it with both, or use smcd_rl.SMCDFilter "
                "for dropout masks"
            )
        num_particles = check_count(num_particles, "num_particles")
        self.ess_threshold = check_real(ess_threshold, "ess_threshold", low=0.0, high=1.0)
        self.resampling: ResamplingScheme = check_scheme(resampling)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        if device is None:
            device = generator.device if generator is not None else "cpu"
        self.device = _checked_device(device)
        if generator is None:
            generator = torch.Generator(device=self.device)
            generator.manual_seed(int(torch.randint(0, 2**62, (1,)).item()))
        elif generator.device.type != self.device.type:
            raise ValueError(f"generator is on {generator.device} but the filter is on {self.device}")
        self.generator = generator
        self._num_particles = num_particles
        self._particles: Tensor | None = None
        self._log_weights: Tensor | None = None
        #: Quantities computed from particles and weights (e.g. the MMSE mask), dropped when either changes.
        self._derived: dict[str, Any] = {}
        self.log_evidence: Tensor | None = None
        #: Ancestor index of every particle at the last resampling, ``[*batch, N]``: particles with
        #: the same ancestor are identical copies. ``None`` when unknown (no resampling since the
        #: last reset, transition or state load); an SMCD update uses it to skip repeated work.
        self.ancestors: Tensor | None = None
        #: ESS of the last reweighting, before any resampling (``ess`` is N right after one).
        self.last_ess: Tensor | None = None

    # ------------------------------------------------------------------ to implement
    def _initial(self, batch_shape: tuple[int, ...], num_particles: int) -> Tensor:
        """Return the first particles ``[*batch_shape, num_particles, D]`` (a subclass defines it)."""
        raise NotImplementedError  # unreachable: __init__ refuses a class without it

    def _transition(self, particles: Tensor) -> Tensor:
        """Return the next particles; must not modify ``particles`` in place (a subclass defines it)."""
        raise NotImplementedError  # unreachable: __init__ refuses a class without it

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
        # Clamped: float rounding of weights that sum to 1 can put the sum of squares a hair outside [1/N, 1].
        return torch.exp(-torch.logsumexp(2.0 * self._state()[1], dim=-1)).clamp_(1.0, float(self._num_particles))

    def reset(self, batch_shape: Sequence[int] = ()) -> None:
        """Draw fresh particles from the prior, with uniform weights and zero log evidence."""
        batch_shape = check_shape(batch_shape, "batch_shape")
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
            log_likelihood: ``[*batch, N]`` log p(z | particle), checked in the weights' dtype
                (float32 by default): NaN or ``+inf`` entries, a batch element whose entries are all
                ``-inf`` (or below that dtype's range, as a float64 -1e40 is in float32), or a log
                evidence that would overflow raise ValueError and change nothing.
        """
        self._commit(*self._reweighted(*self._checked_log_likelihood(log_likelihood)))

    def distinct(self) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """The particles with resampling's copies merged, over every batch element at once.

        Copies of one ancestor are equal, so a weighted sum over the particles' predictions needs
        each only once. Returns ``(particles [G, D], weights [G], streams [G], members [G])``: each
        distinct particle, its copies' summed weight, the flat index of its batch element and the
        index among that element's particles of one of its copies (state kept per particle, such as
        a readout, is read there); ``None`` where the copies are unknown (no resampling since the
        last transition). Computed once per filter state.

        Example:
            >>> import torch
            >>> filt = SMCDFilter(mask_dim=4, num_particles=8, generator=torch.Generator().manual_seed(0))
            >>> filt.reset(batch_shape=(2,))
            >>> _ = filt.update(lambda masks: 5.0 * masks[..., 0].float())  # first bit on: far likelier
            >>> particles, weights, streams, members = filt.distinct()
            >>> per_stream = torch.zeros(2).index_add_(0, streams, weights)  # each stream's weights sum to 1
            >>> particles.shape[0] <= 16, torch.allclose(per_stream, torch.ones(2))
            (True, True)
        """
        if "distinct" in self._derived:
            return self._derived["distinct"]
        if self.ancestors is None:
            return None
        particles, log_weights, _ = self._state()
        n, dim = particles.shape[-2], particles.shape[-1]
        groups, inverse = group_copies(flat_particle_index(self.ancestors, n))
        summed = torch.zeros(groups.numel(), dtype=log_weights.dtype, device=self.device)
        summed.index_add_(0, inverse, log_weights.exp().reshape(-1))
        member = group_members(inverse, groups.numel())  # the flat row of one copy of each
        found = (particles.reshape(-1, dim).index_select(0, member), summed, member // n, member % n)
        self._derived["distinct"] = found
        return found

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
            log_likelihood, finite = self._checked_log_likelihood(log_likelihood_fn(proposed))
            reweighted = self._reweighted(log_likelihood, finite)  # may still refuse: nothing changed before it
        except BaseException:
            self.generator.set_state(rng_state)
            raise
        self.particles = proposed
        self._commit(*reweighted)
        return log_likelihood

    def resize(self, num_particles: int) -> None:
        """Change ``N`` online by resampling ``num_particles`` from the current weighted set.

        The weighted distribution is kept (in expectation); weights become uniform.
        """
        num_particles = check_count(num_particles, "num_particles")
        particles, log_weights, _ = self._state()
        idx = resample_indices(log_weights, self.resampling, num_samples=num_particles, generator=self.generator)
        self.particles = _gather_particles(particles, idx)
        self._num_particles = num_particles
        self.log_weights = torch.full(idx.shape, -math.log(self._num_particles), device=self.device)
        self.ancestors = idx

    def state_dict(self) -> dict[str, Any]:
        """A copy of the full state, generator included; :meth:`load_state_dict` restores it."""
        particles, log_weights, log_evidence = self._state()
        return {
            "particles": particles.clone(),
            "log_weights": log_weights.clone(),
            "log_evidence": log_evidence.clone(),
            "last_ess": _clone(self.last_ess),
            # Which particles are copies decides how later updates and summaries are computed (and so
            # their float rounding): a restored state must compute them exactly as the saved one would.
            "ancestors": _clone(self.ancestors),
            "generator": self.generator.get_state(),
        }

    def snapshot(self) -> tuple[dict[str, Any], Tensor]:
        """The state as it is now, by reference, for :meth:`restore` to put back.

        For a step of several parts that must undo the filter's part when a later one fails:
        nothing is copied, since a step replaces the filter's tensors and never writes into them.
        A state to keep past the next change, to save or to edit is :meth:`state_dict`'s.

        Example:
            >>> import torch
            >>> filt = SMCDFilter(4, num_particles=8)
            >>> filt.reset()
            >>> before, particles = filt.snapshot(), filt.particles
            >>> _ = filt.update(lambda masks: masks.sum(-1).float())
            >>> filt.restore(before)
            >>> filt.particles is particles
            True
        """
        return {**vars(self), "_derived": dict(self._derived)}, self.generator.get_state()

    def restore(self, snapshot: tuple[dict[str, Any], Tensor]) -> None:
        """Put back a :meth:`snapshot` of this filter, generator included.

        Raises:
            ValueError: ``snapshot`` is not one of this filter's (another filter's would make the
                two share one random generator); the filter is left as it was.
        """
        if (
            not isinstance(snapshot, tuple)
            or len(snapshot) != 2
            or not isinstance(snapshot[0], dict)
            or snapshot[0].get("generator") is not self.generator  # only this filter's snapshot holds its own
        ):
            raise ValueError(
                "restore takes a snapshot() of this same filter; to copy another filter's state use "
                "load_state_dict(other.state_dict())"
            )
        attributes, generator = snapshot
        vars(self).update(attributes, _derived=dict(attributes["_derived"]))
        self.generator.set_state(generator)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` exactly: later updates give the same bits as from the saved state.

        Raises:
            ValueError: ``state`` is not a state of this filter: not a :meth:`state_dict`, of another
                batch shape, particle count or mask width, or with NaN weights, or a generator state
                that is not one; the filter is left as it was.
        """
        self._check_state(state)
        self.generator.set_state(state["generator"])  # checked: cannot fail after the parts below
        self.particles = state["particles"].clone().to(self.device)
        self.log_weights = state["log_weights"].clone().to(self.device)
        self.log_evidence = state["log_evidence"].clone().to(self.device)
        self._num_particles = self.particles.shape[-2]
        self.last_ess = _clone(state.get("last_ess"), self.device)
        self.ancestors = _clone(state.get("ancestors"), self.device)

    def _check_state(self, state: Any) -> None:
        """Raise ``ValueError`` unless ``state`` is a :meth:`state_dict` that fits this filter as it is."""
        names = ("particles", "log_weights", "log_evidence", "generator")
        if not isinstance(state, dict) or not all(isinstance(state.get(name), Tensor) for name in names):
            raise ValueError(f"a filter's state is a dict of the tensors {list(names)} (its state_dict())")
        particles, log_weights, log_evidence = (state[name] for name in names[:3])
        current = self.particles
        if (
            particles.dim() < 2
            or log_weights.shape != particles.shape[:-1]
            or log_evidence.shape != particles.shape[:-2]
            or (current is not None and particles.shape != current.shape)
        ):
            fits = f"this filter's {list(current.shape)}" if current is not None else "its weights and evidence"
            raise ValueError(
                f"a state with particles {list(particles.shape)} and weights {list(log_weights.shape)} does not fit "
                f"{fits} (another batch size, particle count or network?); reset the model to the batch shape "
                "it was saved with"
            )
        if current is not None and particles.dtype != current.dtype:
            raise ValueError(f"the state's particles are {particles.dtype}, this filter's {current.dtype}")
        if not log_weights.is_floating_point() or not log_evidence.is_floating_point():
            raise ValueError(
                f"the state's log weights and evidence must be float tensors, got {log_weights.dtype} and "
                f"{log_evidence.dtype}"
            )
        if bool(torch.isnan(log_weights).any()) or not bool(torch.isfinite(log_weights).any(-1).all()):
            raise ValueError("the state's log weights are NaN, or -inf for every particle of a batch element")
        # Normalised, as every update leaves them: unnormalised weights would skew the ESS and the evidence.
        total = torch.logsumexp(log_weights.to(torch.float64), dim=-1)
        if bool((total.abs() > NORMALISED_TOLERANCE).any()):
            raise ValueError(
                f"the state's weights sum to {total.exp().max().item():.6g}, not 1; pass a state_dict() of a filter"
            )
        if bool(torch.isnan(log_evidence).any()):
            raise ValueError("the state's log evidence is NaN")
        for name, shape in (("last_ess", log_evidence.shape), ("ancestors", log_weights.shape)):
            value = state.get(name)
            if value is not None and (not isinstance(value, Tensor) or value.shape != shape):
                got = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(f"the state's {name} is {got}, expected None or a tensor of shape {list(shape)}")
        ancestors = state.get("ancestors")
        if ancestors is not None:
            _check_ancestors(ancestors, particles)
        try:
            torch.Generator().set_state(state["generator"])
        except (RuntimeError, TypeError) as err:
            raise ValueError(f"the state's generator state is not a random generator's ({err})") from err

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
        rows = self._checked_rows(state, rows)
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

    def _checked_rows(self, state: dict[str, Any], rows: Tensor) -> Tensor:
        """``rows`` as bool ``[*batch]`` on the filter's device, after checking it and ``state`` fit the filter."""
        particles = self._state()[0]
        saved = state.get("particles") if isinstance(state, dict) else None
        if not isinstance(saved, Tensor) or saved.shape != particles.shape:
            got = list(saved.shape) if isinstance(saved, Tensor) else type(saved).__name__
            raise ValueError(
                f"restore_rows needs a state_dict() of this filter with particles {list(particles.shape)}, got {got}; "
                "save the state after the reset whose rows you restore"
            )
        self._check_state(state)  # NaN weights, weights of another shape: refused, not mixed in
        return checked_rows(torch.as_tensor(rows, device=self.device), self.batch_shape)

    def _checked_log_likelihood(self, log_likelihood: Tensor) -> tuple[Tensor, bool]:
        """``log_likelihood`` in the weights' dtype after checking it, and whether all of it is finite.

        Checked after the cast: a float64 log-likelihood of -1e40 (a float64 model, an outlier
        target) is finite, but -inf in float32 weights, and checked before the cast it reached
        the reweighting as finite and turned every weight into ``-inf - (-inf) = NaN``.
        """
        log_weights = self._state()[1]
        if not isinstance(log_likelihood, Tensor):
            raise TypeError(f"log_likelihood must be a Tensor, got {type(log_likelihood).__name__}")
        if log_likelihood.shape != log_weights.shape:
            raise ValueError(
                f"log_likelihood must have shape [*batch, N] = {list(log_weights.shape)}, "
                f"got {list(log_likelihood.shape)}"
            )
        check_real_tensor(log_likelihood, "log_likelihood")  # a complex one would lose its imaginary part
        # Detached: weights that kept the likelihood's autograd graph would chain every update's graph
        # to the next, and hold them all in memory.
        log_likelihood = log_likelihood.detach().to(log_weights.dtype)  # overflows to -inf here, if it does
        finite = bool(torch.isfinite(log_likelihood).all())
        if not finite:  # one pass above; the checks below name the problem
            if torch.isnan(log_likelihood).any():
                raise ValueError("log_likelihood contains NaN; check the observation and the model's prediction")
            if torch.isposinf(log_likelihood).any():
                raise ValueError("log_likelihood contains +inf; check the likelihood's noise scale (it must be > 0)")
            if (log_likelihood == -math.inf).all(dim=-1).any():
                raise ValueError(
                    "every particle of a batch element has zero likelihood (all -inf, or below the "
                    f"{log_weights.dtype} range): the observation is impossible under the model; drop the "
                    "outlier, or increase the likelihood's noise scale"
                )
        return log_likelihood, finite

    def _reweighted(self, log_likelihood: Tensor, finite: bool) -> tuple[Tensor, Tensor, Tensor]:
        """The log-weights, log evidence and ESS after ``log_likelihood``, computed without changing the filter.

        In float64 and relative to each batch element's largest joint log-weight. The plain
        ``joint - logsumexp(joint)`` loses the normaliser's small part when the joint values are
        large (a small likelihood noise makes them 1e8 and more): the weights then summed to 2 or
        even 200, the ESS fell below 1 and the MMSE mask left [0, 1]. Shifted, the largest entry is
        exactly 0, the normaliser ``log sum exp(shifted)`` is in ``[0, log N]`` and accurate, and
        the weights sum to 1 up to rounding for any finite likelihood.

        Args:
            log_likelihood: checked by :meth:`_checked_log_likelihood`.
            finite: whether all of ``log_likelihood`` is finite: then every batch element keeps a
                particle of nonzero weight (its largest weight is at least ``1 / N``), and the check
                for one that does not is skipped.

        Raises:
            ValueError: in a batch element, every particle of nonzero weight has zero likelihood, or
                the log evidence would overflow the filter's dtype: a filter state never holds NaN
                weights or an infinite evidence or ESS.
        """
        log_weights, log_evidence = self._state()[1:]
        joint = log_weights.to(torch.float64, copy=True).add_(log_likelihood)  # a fresh copy (float64 weights too)
        peak = joint.amax(dim=-1, keepdim=True)
        if not finite and not bool(torch.isfinite(peak).all()):
            raise ValueError(
                "every particle with a nonzero weight has zero likelihood (-inf) in some batch element: the "
                "observation is impossible under the current posterior; increase the likelihood's noise scale, "
                "or reset the filter"
            )
        shifted = joint.sub_(peak)  # <= 0, exactly 0 at the peak
        relative = shifted.exp()  # in [0, 1], with a 1 at the peak
        total = relative.sum(dim=-1, keepdim=True)  # in [1, N]
        log_total = total.log()
        # ESS = (sum w)^2 / sum w^2 of the unnormalised relative weights: no second logsumexp.
        ess = total.squeeze(-1).square_().div_(relative.mul_(relative).sum(dim=-1))
        dtype = log_weights.dtype
        new_log_weights = shifted.sub_(log_total).to(dtype)
        new_log_evidence = peak.add_(log_total).squeeze(-1).add_(log_evidence).to(log_evidence.dtype)
        new_ess = ess.clamp_(1.0, float(self._num_particles)).to(dtype)
        # With the likelihood checked in the weights' dtype, weights and ESS are finite here (weights
        # of -inf are zero weights); the evidence sums every step's and can still overflow.
        if not bool(torch.isfinite(new_log_evidence).all()):
            raise ValueError(
                f"the log evidence would overflow {log_evidence.dtype}: the observations are far outside "
                "what the model predicts; drop the outlier, increase the likelihood's noise scale, or reset "
                "the filter"
            )
        return new_log_weights, new_log_evidence, new_ess

    def _commit(self, log_weights: Tensor, log_evidence: Tensor, ess: Tensor) -> None:
        """Take the result of :meth:`_reweighted`, then resample where the ESS is low."""
        self.log_weights, self.log_evidence, self.last_ess = log_weights, log_evidence, ess
        self._resample_if_needed(ess)

    def _resample_if_needed(self, ess: Tensor) -> None:
        particles, log_weights, _ = self._state()
        n = self._num_particles
        need = ess < self.ess_threshold * n
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


#: How far from 0 a loaded state's ``logsumexp(log_weights)`` may be: the updates leave the weights
#: normalised up to float32 rounding, far inside it.
NORMALISED_TOLERANCE = 1e-3


def _check_ancestors(ancestors: Tensor, particles: Tensor) -> None:
    """Refuse ``ancestors`` unless they are particle indices under which every copy equals its ancestor's row.

    The MMSE mask and the SMCD update read one row per ancestor: fake ancestors would silently
    stand one particle in for others.
    """
    n = particles.shape[-2]
    if ancestors.is_floating_point() or ancestors.dtype == torch.bool or ancestors.is_complex():
        raise ValueError(f"the state's ancestors must be integer particle indices, got {ancestors.dtype}")
    if bool(((ancestors < 0) | (ancestors >= n)).any()):
        raise ValueError(f"the state's ancestors must be particle indices in [0, {n}); pass a filter's state_dict()")
    # One particle per ancestor stands for its copies: any one, since they must all be equal.
    index = ancestors.long()
    representative = torch.zeros_like(index).scatter_(-1, index, torch.arange(n, device=index.device).expand_as(index))
    chosen = representative.gather(-1, index)
    rows = particles.gather(-2, chosen.unsqueeze(-1).expand_as(particles))
    if not torch.equal(rows, particles):
        raise ValueError(
            "the state's ancestors call particles copies that differ; pass a filter's state_dict() as it was saved"
        )


def _checked_device(device: Any) -> torch.device:
    """``device`` as a torch device this machine has (the meta device holds no values to filter)."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device must name a torch device such as 'cpu' or 'cuda', got {device!r} ({err})") from None
    kind = parsed.type
    if kind == "meta" or (kind != "cpu" and not getattr(getattr(torch, kind, None), "is_available", lambda: False)()):
        raise ValueError(f"device {str(parsed)!r} is not one this machine can filter on; pass device='cpu'")
    return parsed


def _clone(value: Tensor | None, device: torch.device | None = None) -> Tensor | None:
    """A copy of an optional tensor (on ``device`` if given)."""
    if value is None:
        return None
    value = value.clone()
    return value if device is None else value.to(device)


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
        self.mask_dim = check_count(mask_dim, "mask_dim")
        self.flip_prob = check_real(flip_prob, "flip_prob", low=0.0, high=1.0)
        self.keep_prob = check_real(keep_prob, "keep_prob", low=0.0, high=1.0, open_low=True)
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
            # Clamped: weights that sum to 1 up to float rounding can put a mean of bits a hair above 1.
            cached = self._derived["mean_mask"] = self._weighted_mean().clamp_(0.0, 1.0)
        return cached

    def update(self, log_likelihood_fn: Callable[[Tensor], Tensor]) -> Tensor:
        """See :meth:`ParticleFilter.update`; a refused update also leaves :attr:`last_flips` as it was."""
        flips = self.last_flips
        try:
            return super().update(log_likelihood_fn)
        except BaseException:
            self.last_flips = flips  # set by the refused transition: part of what a refused update undoes
            raise

    def state_dict(self) -> dict[str, Any]:
        """A copy of the full state, generator and MMSE mask included; :meth:`load_state_dict` restores it."""
        state = super().state_dict()
        # The mask as it is, not recomputed later: computed again after a restore (of some rows,
        # see restore_rows) it could take another summation path and differ in the last bits.
        state["mean_mask"] = self.mean_mask.clone()
        state["last_flips"] = _clone(self.last_flips)
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.last_flips = _clone(state.get("last_flips"), self.device)
        if state.get("mean_mask") is not None:
            self._derived["mean_mask"] = state["mean_mask"].clone().to(self.device)

    def _check_state(self, state: Any) -> None:
        super()._check_state(state)
        particles = state["particles"]
        if particles.dtype != torch.bool or particles.shape[-1] != self.mask_dim:
            raise ValueError(
                f"the state's particles are {particles.dtype} masks of {particles.shape[-1]} bits, this filter's "
                f"bool masks of {self.mask_dim}; pass a state_dict() of a filter of the same network"
            )
        mask = state.get("mean_mask")
        if mask is not None and (
            not isinstance(mask, Tensor)
            or mask.shape != particles.shape[:-2] + (particles.shape[-1],)
            or not mask.is_floating_point()
            or not bool(((mask >= 0) & (mask <= 1)).all())
        ):
            raise ValueError(
                "the state's MMSE mask does not fit its particles (its shape, or values outside [0, 1]); pass this "
                "filter's state_dict()"
            )
        flips = state.get("last_flips")
        if flips is not None and (
            not isinstance(flips, Tensor)
            or flips.dim() != 1
            or flips.is_floating_point()
            or bool(((flips < 0) | (flips >= particles.numel())).any())
        ):
            raise ValueError(
                "the state's last_flips are not positions in its particles; pass this filter's state_dict()"
            )

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        """As :meth:`ParticleFilter.restore_rows`; the restored rows' MMSE mask is restored bit for bit too.

        Their mask is not computed again: with other rows' particles changed, the copies of the batch
        change and the mean would take another summation path (float rounding in the last bits), so a
        sub-env's mask would move when another one resets.
        """
        saved_mask = state.get("mean_mask")
        super().restore_rows(state, rows)
        if saved_mask is not None:
            rows = torch.as_tensor(rows, device=self.device)
            self._derived["mean_mask"] = torch.where(rows.unsqueeze(-1), saved_mask.to(self.device), self.mean_mask)

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
