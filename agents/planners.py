"""Sampling-based trajectory optimisers for model-predictive control.

The planners never see a model: they optimise an *objective*, a pure batched function that maps
action sequences of shape ``[*batch, P, H, A]`` (``P`` candidates, horizon ``H``, action size
``A``) to one score per candidate, ``[*batch, P]``, higher being better. Rolling a (learned or
true) model forward and summing the rewards over the horizon is the caller's job, so the same
optimiser serves the oracle baseline, a frozen network and an adapted one. (mbrl-lib style.)

Each planner keeps its last solution and, on the next :meth:`Planner.plan` call with the same
``batch_shape``, starts from it shifted left by one step, the freed last step set to the centre
of the action bounds. :meth:`Planner.reset` forgets it; call it at the start of an episode.

Every returned sequence lies inside ``[action_low, action_high]``: candidates are clipped (or
drawn) inside the bounds before the objective sees them.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

__all__ = ["CEM", "MPPI", "Objective", "Planner", "RandomShooting"]

Objective = Callable[[Tensor], Tensor]
"""Maps action sequences ``[*batch, P, H, A]`` to scores ``[*batch, P]`` (higher is better)."""

_Bound = Tensor | Sequence[float] | float


def _as_vector(value: _Bound, name: str, *, device: torch.device | str | None) -> Tensor:
    """Converts a float, sequence or tensor to a floating 1-D tensor (a scalar becomes [1])."""
    tensor = torch.as_tensor(value, device=device)
    if not tensor.is_floating_point():
        tensor = tensor.to(torch.get_default_dtype())
    if tensor.dim() > 1:
        raise ValueError(f"{name} must be a float or a 1-D sequence of shape [A], got shape {tuple(tensor.shape)}")
    return tensor.reshape(-1)


def _check_int(value: int, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return value


class Planner(abc.ABC):
    """Base class: bounds, warm start by shifting, objective checks and the ``plan`` entry point.

    Subclasses implement :meth:`_optimise`; :meth:`plan` wraps it in ``torch.no_grad()`` (so the
    objective runs without autograd while the returned tensor stays an ordinary tensor), clips the
    result to the bounds and stores the shifted warm start.

    Args:
        action_low: Lower action bound, a float or a sequence/tensor of shape ``[A]``.
        action_high: Upper action bound, same shape as ``action_low`` (a float broadcasts);
            must be strictly greater than ``action_low`` in every dimension.
        horizon: Number of steps ``H`` in a planned sequence, at least 1.
        warm_start: Whether to start each call from the previous solution, shifted by one step.
        device: Device of the bounds, the samples and the returned plan.
        generator: Source of all randomness (on ``device``); ``None`` uses torch's global RNG.
            A generator seeded the same way gives identical plans.

    Example:
        >>> import torch
        >>> from smcd_rl.agents.planners import Planner
        >>> class Centre(Planner):  # the smallest planner: always the middle of the bounds
        ...     def _optimise(self, objective, init, batch_shape):
        ...         return self.centre.expand(*batch_shape, self.horizon, self.action_dim)
        >>> planner = Centre(action_low=[0.0, -1.0], action_high=[2.0, 1.0], horizon=3)
        >>> planner.plan(lambda actions: actions.sum(dim=(-2, -1)), batch_shape=(4,)).shape
        torch.Size([4, 3, 2])
    """

    def __init__(
        self,
        *,
        action_low: _Bound,
        action_high: _Bound,
        horizon: int,
        warm_start: bool = True,
        device: torch.device | str | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        low = _as_vector(action_low, "action_low", device=device)
        high = _as_vector(action_high, "action_high", device=device)
        dtype = torch.promote_types(low.dtype, high.dtype)
        low, high = low.to(dtype), high.to(dtype)
        if low.numel() == 1 and high.numel() > 1:
            low = low.expand_as(high).clone()
        elif high.numel() == 1 and low.numel() > 1:
            high = high.expand_as(low).clone()
        if low.shape != high.shape:
            raise ValueError(
                f"action_low has shape {tuple(low.shape)} but action_high has shape {tuple(high.shape)}; "
                "pass both bounds with the same shape [A]"
            )
        if low.numel() == 0:
            raise ValueError("action bounds are empty; pass bounds of shape [A] with A >= 1")
        if not bool(torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError("action bounds must be finite; sampling needs a bounded box")
        if not bool((low < high).all()):
            bad = (low >= high).nonzero().flatten().tolist()
            raise ValueError(
                f"action_low must be < action_high in every dimension, violated at dims {bad}: "
                f"low={low.tolist()}, high={high.tolist()}"
            )
        self.action_low: Tensor = low
        self.action_high: Tensor = high
        self.horizon: int = _check_int(horizon, "horizon", minimum=1)
        self.warm_start: bool = bool(warm_start)
        self.generator: torch.Generator | None = generator
        self._warm: Tensor | None = None

    @property
    def action_dim(self) -> int:
        """Action size ``A``, inferred from the bounds."""
        return self.action_low.numel()

    @property
    def device(self) -> torch.device:
        return self.action_low.device

    @property
    def dtype(self) -> torch.dtype:
        return self.action_low.dtype

    @property
    def centre(self) -> Tensor:
        """Middle of the action bounds, shape ``[A]``."""
        return (self.action_low + self.action_high) / 2

    @property
    def mean(self) -> Tensor | None:
        """Warm start for the next :meth:`plan` call, ``[*batch, H, A]``, or ``None`` after a reset.

        It is the last returned plan shifted left by one step, its last step at :attr:`centre`.
        """
        return None if self._warm is None else self._warm.clone()

    def reset(self) -> None:
        """Forgets the warm start: the next call starts from the centre of the bounds."""
        self._warm = None

    def plan(self, objective: Objective, *, batch_shape: int | Sequence[int] = ()) -> Tensor:
        """Optimises ``objective`` and returns the best action sequence, ``[*batch_shape, H, A]``.

        Args:
            objective: Maps ``[*batch_shape, P, H, A]`` actions to ``[*batch_shape, P]`` scores,
                higher being better; NaN scores count as the worst.
            batch_shape: Independent problems solved at once (e.g. one per environment).
                Changing it between calls drops the warm start.

        Returns:
            The plan, inside the action bounds; execute its first step, then plan again.
        """
        shape = torch.Size((batch_shape,) if isinstance(batch_shape, int) else tuple(batch_shape))
        if any(isinstance(d, bool) or not isinstance(d, int) or d < 1 for d in shape):
            raise ValueError(f"batch_shape must hold positive ints, got {tuple(shape)}")
        if self._warm is not None and self._warm.shape[:-2] != shape:
            self.reset()
        with torch.no_grad():
            solution = self._optimise(objective, self._warm, shape)
            solution = solution.clamp(self.action_low, self.action_high)
            if self.warm_start:
                tail = self.centre.expand(*shape, 1, self.action_dim)
                self._warm = torch.cat([solution[..., 1:, :], tail], dim=-2)
        return solution

    @abc.abstractmethod
    def _optimise(self, objective: Objective, init: Tensor | None, batch_shape: torch.Size) -> Tensor:
        """Returns a ``[*batch_shape, H, A]`` solution; ``init`` is the warm start or ``None``."""

    # Helpers shared by the subclasses.

    def _initial_mean(self, init: Tensor | None, batch_shape: torch.Size) -> Tensor:
        if init is not None:
            return init
        return self.centre.expand(*batch_shape, self.horizon, self.action_dim)

    def _randn(self, batch_shape: torch.Size, num: int) -> Tensor:
        size = (*batch_shape, num, self.horizon, self.action_dim)
        return torch.randn(size, generator=self.generator, device=self.device, dtype=self.dtype)

    def _clip(self, actions: Tensor) -> Tensor:
        return actions.clamp(self.action_low, self.action_high)

    def _evaluate(self, objective: Objective, candidates: Tensor) -> Tensor:
        """Calls the objective and checks it; NaN becomes -inf and +inf the largest float."""
        scores = objective(candidates)
        expected = tuple(candidates.shape[:-2])
        if not isinstance(scores, Tensor):
            raise TypeError(f"objective must return a torch.Tensor of shape {expected}, got {type(scores).__name__}")
        if tuple(scores.shape) != expected:
            raise ValueError(
                f"objective returned shape {tuple(scores.shape)} for actions of shape "
                f"{tuple(candidates.shape)}, expected [*batch, P] = {expected}; sum rewards over the "
                "horizon and drop any trailing reward dimension so each candidate gets one score"
            )
        scores = scores.to(self.dtype)
        scores = torch.nan_to_num(scores, nan=-torch.inf, posinf=torch.finfo(scores.dtype).max, neginf=-torch.inf)
        usable = (scores > -torch.inf).any(dim=-1)
        if not bool(usable.all()):
            bad = int((~usable).sum())
            raise ValueError(
                f"objective returned NaN or -inf for all {candidates.shape[-3]} candidates in {bad} of "
                f"{usable.numel()} batch element(s); check the model rollout for NaN"
            )
        return scores


class CEM(Planner):
    """Cross-entropy method with smoothed updates and a shifted warm start.

    Each iteration draws ``num_candidates`` Gaussian sequences around the mean, clipped to the
    bounds, keeps the ``num_elites`` best and moves the mean and standard deviation towards the
    elites' statistics: ``new = alpha * old + (1 - alpha) * elite``. The standard deviation
    restarts at ``init_std`` on every call; only the mean is warm-started.

    The returned plan is the best candidate seen over all iterations (``return_mean=False``),
    which cannot be worse than any evaluated candidate; with a noisy objective (e.g. a stochastic
    model) ``return_mean=True`` returns the final mean instead, which averages the noise out.

    Args:
        action_low: Lower action bound, shape ``[A]`` or a float.
        action_high: Upper action bound, shape ``[A]`` or a float.
        horizon: Planning horizon ``H``.
        num_candidates: Sequences sampled per iteration.
        num_elites: Best sequences used to refit the mean and std, ``1 <= num_elites <= num_candidates``.
        iterations: Refits per call.
        alpha: Weight of the old mean/std in the smoothed update, in ``[0, 1)``.
        init_std: Initial standard deviation, a float or ``[A]``; default half the action range.
        min_std: Floor on the standard deviation, which keeps the search from collapsing.
        return_mean: Return the final mean instead of the best candidate seen.
        warm_start: Start each call from the previous plan shifted by one step.
        device: Device of all tensors.
        generator: Random source (on ``device``); ``None`` uses torch's global RNG.

    Example:
        >>> import torch
        >>> from smcd_rl.agents.planners import CEM
        >>> target = torch.tensor([0.5, -0.25])
        >>> def objective(actions):  # [*batch, P, H, A] -> [*batch, P]
        ...     return -((actions - target) ** 2).sum(dim=(-2, -1))
        >>> planner = CEM(action_low=[-1.0, -1.0], action_high=[1.0, 1.0], horizon=4, iterations=10,
        ...               generator=torch.Generator().manual_seed(0))
        >>> plan = planner.plan(objective)
        >>> plan.shape
        torch.Size([4, 2])
        >>> bool(torch.allclose(plan, target.expand(4, 2), atol=0.05))
        True
        >>> planner.mean.shape  # warm start for the next call
        torch.Size([4, 2])
    """

    def __init__(
        self,
        *,
        action_low: _Bound,
        action_high: _Bound,
        horizon: int,
        num_candidates: int = 500,
        num_elites: int = 50,
        iterations: int = 5,
        alpha: float = 0.1,
        init_std: _Bound | None = None,
        min_std: float = 1e-3,
        return_mean: bool = False,
        warm_start: bool = True,
        device: torch.device | str | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(
            action_low=action_low,
            action_high=action_high,
            horizon=horizon,
            warm_start=warm_start,
            device=device,
            generator=generator,
        )
        self.num_candidates = _check_int(num_candidates, "num_candidates", minimum=1)
        self.num_elites = _check_int(num_elites, "num_elites", minimum=1)
        if num_elites > num_candidates:
            raise ValueError(
                f"num_elites ({num_elites}) must be <= num_candidates ({num_candidates}); "
                "lower num_elites or sample more candidates"
            )
        self.iterations = _check_int(iterations, "iterations", minimum=1)
        if not 0.0 <= alpha < 1.0:
            raise ValueError(f"alpha must be in [0, 1) (weight of the old mean), got {alpha}")
        self.alpha = float(alpha)
        self.init_std = _positive_std(init_std, self, "init_std")
        if not min_std >= 0.0:
            raise ValueError(f"min_std must be >= 0, got {min_std}")
        self.min_std = float(min_std)
        self.return_mean = bool(return_mean)

    def _optimise(self, objective: Objective, init: Tensor | None, batch_shape: torch.Size) -> Tensor:
        mean = self._initial_mean(init, batch_shape)
        std = self.init_std.expand_as(mean)
        best = mean
        best_score = torch.full(batch_shape, -torch.inf, device=self.device, dtype=self.dtype)
        gather_shape = (*batch_shape, self.num_elites, self.horizon, self.action_dim)
        for _ in range(self.iterations):
            noise = self._randn(batch_shape, self.num_candidates)
            candidates = self._clip(mean.unsqueeze(-3) + std.unsqueeze(-3) * noise)
            # The mean itself is one candidate (as in iCEM): the best seen is never worse than it.
            candidates[..., 0, :, :] = self._clip(mean)
            scores = self._evaluate(objective, candidates)
            top, idx = scores.topk(self.num_elites, dim=-1)
            elites = candidates.gather(-3, idx[..., None, None].expand(gather_shape))
            better = top[..., 0] > best_score
            best = torch.where(better[..., None, None], elites[..., 0, :, :], best)
            best_score = torch.where(better, top[..., 0], best_score)
            mean = self.alpha * mean + (1 - self.alpha) * elites.mean(dim=-3)
            elite_std = elites.std(dim=-3, correction=0)
            std = (self.alpha * std + (1 - self.alpha) * elite_std).clamp_min(self.min_std)
        return mean if self.return_mean else best


class MPPI(Planner):
    """Model-predictive path integral control on summed returns (no value function needed).

    Each iteration perturbs the mean with Gaussian noise of fixed ``noise_std``, clips the
    candidates to the bounds and sets the mean to their softmax-weighted average,
    ``weights = softmax(returns / temperature)`` (max-subtracted, so large returns do not
    overflow). The final mean is returned. A low temperature approaches picking the best
    candidate; a high one approaches the plain average.

    Args:
        action_low: Lower action bound, shape ``[A]`` or a float.
        action_high: Upper action bound, shape ``[A]`` or a float.
        horizon: Planning horizon ``H``.
        num_candidates: Sequences sampled per iteration.
        iterations: Mean updates per call.
        temperature: ``lambda`` in the weights, in units of the objective; must be > 0.
        noise_std: Perturbation standard deviation, a float or ``[A]``; default half the action range.
        warm_start: Start each call from the previous plan shifted by one step.
        device: Device of all tensors.
        generator: Random source (on ``device``); ``None`` uses torch's global RNG.

    Example:
        >>> import torch
        >>> from smcd_rl.agents.planners import MPPI
        >>> target = torch.tensor([0.5, -0.25])
        >>> def objective(actions):  # [*batch, P, H, A] -> [*batch, P]
        ...     return -((actions - target) ** 2).sum(dim=(-2, -1))
        >>> planner = MPPI(action_low=[-1.0, -1.0], action_high=[1.0, 1.0], horizon=4,
        ...                temperature=0.05, noise_std=0.3,
        ...                generator=torch.Generator().manual_seed(0))
        >>> plan = planner.plan(objective)
        >>> plan.shape
        torch.Size([4, 2])
        >>> bool(torch.allclose(plan, target.expand(4, 2), atol=0.1))
        True
    """

    def __init__(
        self,
        *,
        action_low: _Bound,
        action_high: _Bound,
        horizon: int,
        num_candidates: int = 500,
        iterations: int = 3,
        temperature: float = 1.0,
        noise_std: _Bound | None = None,
        warm_start: bool = True,
        device: torch.device | str | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(
            action_low=action_low,
            action_high=action_high,
            horizon=horizon,
            warm_start=warm_start,
            device=device,
            generator=generator,
        )
        self.num_candidates = _check_int(num_candidates, "num_candidates", minimum=1)
        self.iterations = _check_int(iterations, "iterations", minimum=1)
        if not temperature > 0.0:
            raise ValueError(f"temperature must be > 0, got {temperature}")
        self.temperature = float(temperature)
        self.noise_std = _positive_std(noise_std, self, "noise_std")

    def _optimise(self, objective: Objective, init: Tensor | None, batch_shape: torch.Size) -> Tensor:
        mean = self._initial_mean(init, batch_shape)
        for _ in range(self.iterations):
            noise = self._randn(batch_shape, self.num_candidates)
            candidates = self._clip(mean.unsqueeze(-3) + self.noise_std * noise)
            scores = self._evaluate(objective, candidates)
            # A huge score over a small temperature must not overflow to inf (softmax would give NaN).
            largest = torch.finfo(scores.dtype).max
            logits = torch.nan_to_num(scores / self.temperature, posinf=largest, neginf=-torch.inf)
            weights = torch.softmax(logits, dim=-1)
            mean = (weights[..., None, None] * candidates).sum(dim=-3)
        return mean


class RandomShooting(Planner):
    """Random shooting: uniform sequences inside the bounds, the best one wins.

    With ``warm_start=True`` the previous best, shifted by one step, replaces the first
    candidate, so a plan that is still good is never lost to sampling noise.

    Args:
        action_low: Lower action bound, shape ``[A]`` or a float.
        action_high: Upper action bound, shape ``[A]`` or a float.
        horizon: Planning horizon ``H``.
        num_candidates: Sequences sampled per call.
        warm_start: Keep the shifted previous best as one candidate.
        device: Device of all tensors.
        generator: Random source (on ``device``); ``None`` uses torch's global RNG.

    Example:
        >>> import torch
        >>> from smcd_rl.agents.planners import RandomShooting
        >>> def objective(actions):  # [*batch, P, H, A] -> [*batch, P]
        ...     return -((actions - 0.3) ** 2).sum(dim=(-2, -1))
        >>> planner = RandomShooting(action_low=-1.0, action_high=1.0, horizon=1,
        ...                          generator=torch.Generator().manual_seed(0))
        >>> plan = planner.plan(objective)
        >>> plan.shape
        torch.Size([1, 1])
        >>> abs(plan.item() - 0.3) < 0.01
        True
    """

    def __init__(
        self,
        *,
        action_low: _Bound,
        action_high: _Bound,
        horizon: int,
        num_candidates: int = 1000,
        warm_start: bool = True,
        device: torch.device | str | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__(
            action_low=action_low,
            action_high=action_high,
            horizon=horizon,
            warm_start=warm_start,
            device=device,
            generator=generator,
        )
        self.num_candidates = _check_int(num_candidates, "num_candidates", minimum=1)

    def _optimise(self, objective: Objective, init: Tensor | None, batch_shape: torch.Size) -> Tensor:
        size = (*batch_shape, self.num_candidates, self.horizon, self.action_dim)
        unit = torch.rand(size, generator=self.generator, device=self.device, dtype=self.dtype)
        candidates = self.action_low + (self.action_high - self.action_low) * unit
        if init is not None:
            candidates[..., 0, :, :] = init
        scores = self._evaluate(objective, candidates)
        idx = scores.argmax(dim=-1)
        return candidates.gather(-3, idx[..., None, None, None].expand(*batch_shape, 1, *size[-2:])).squeeze(-3)


def _positive_std(value: _Bound | None, planner: Planner, name: str) -> Tensor:
    """Standard deviation of shape [A]; ``None`` means half the action range."""
    if value is None:
        return (planner.action_high - planner.action_low) / 2
    std = _as_vector(value, name, device=planner.device).to(planner.dtype)
    if std.numel() not in (1, planner.action_dim):
        raise ValueError(f"{name} must be a float or have shape [A] = [{planner.action_dim}], got {tuple(std.shape)}")
    if not bool((std > 0).all() and torch.isfinite(std).all()):
        raise ValueError(f"{name} must be finite and > 0, got {std.tolist()}")
    return std.expand(planner.action_dim).clone()
