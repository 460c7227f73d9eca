"""Confidence intervals and paired comparisons of methods evaluated on the same trials.

Every experiment scores each method on the same trials (the same arms, tasks or episodes), so
methods are compared *paired*: the bootstrap resamples trials, and one resample of trials is
applied to every method at once. A difference whose 95 % interval excludes zero gets the verdict
``better`` or ``worse``; otherwise ``no significant difference``.

Example:
    >>> import torch
    >>> scores = {"none": torch.tensor([1.0, 1.2, 0.9, 1.1] * 10), "smcd": torch.tensor([0.5, 0.7, 0.4, 0.6] * 10)}
    >>> [c.verdict for c in paired_comparisons(scores, baseline="none", adaptive=["smcd"])]
    ['better']
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

__all__ = [
    "Estimate",
    "Comparison",
    "Verdict",
    "mean_ci",
    "paired_comparisons",
    "bootstrap_indices",
    "cell_statistics",
    "oriented",
    "verdict_table",
]

Verdict = Literal["better", "worse", "no significant difference"]

#: Bootstrap resamples: the Monte Carlo error of a 95 % percentile bound is then ~0.01 standard errors.
RESAMPLES = 4000


@dataclass(frozen=True)
class Estimate:
    """A mean over trials with its bootstrap confidence interval.

    Example:
        >>> str(Estimate(mean=0.1234, low=0.1, high=0.15, trials=50))
        '0.123 [0.100, 0.150]'
    """

    mean: float
    low: float
    high: float
    trials: int

    def __str__(self) -> str:
        return f"{_number(self.mean)} [{_number(self.low)}, {_number(self.high)}]"


@dataclass(frozen=True)
class Comparison:
    """``method`` minus ``against``, paired over the same trials, with its interval and verdict."""

    method: str
    against: str
    difference: float
    low: float
    high: float
    verdict: Verdict


def bootstrap_indices(trials: int, *, resamples: int = RESAMPLES, seed: int = 0) -> Tensor:
    """``[resamples, trials]`` indices of trials drawn with replacement, the same for a given seed.

    Example:
        >>> bootstrap_indices(3, resamples=2).shape
        torch.Size([2, 3])
    """
    if trials < 1:
        raise ValueError(f"need at least one trial to bootstrap, got {trials}")
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(trials, (resamples, trials), generator=generator)


def mean_ci(values: Tensor, *, level: float = 0.95, indices: Tensor | None = None) -> Estimate:
    """The mean of per-trial ``values [trials]`` and its percentile bootstrap interval.

    Example:
        >>> import torch
        >>> e = mean_ci(torch.arange(100.0))
        >>> e.low < e.mean < e.high
        True
    """
    values = _trials(values)
    indices = bootstrap_indices(len(values)) if indices is None else indices
    means = values[indices].mean(-1)
    low, high = _bounds(means, level)
    return Estimate(mean=float(values.mean()), low=low, high=high, trials=len(values))


def paired_comparisons(
    scores: Mapping[str, Tensor],
    *,
    baseline: str,
    adaptive: Sequence[str],
    lower_is_better: bool = True,
    level: float = 0.95,
    seed: int = 0,
) -> list[Comparison]:
    """Each adaptive method against ``baseline`` and against every other adaptive method.

    Args:
        scores: method -> per-trial scores ``[trials]``, row ``k`` the same trial for every method.
        baseline: the method without adaptation (compared with every adaptive one).
        adaptive: the adaptive methods, compared with the baseline and pairwise with each other.
        lower_is_better: ``True`` for errors, ``False`` for success rates or returns.
        level: the confidence level of the intervals.
        seed: seed of the bootstrap resamples (one set shared by all comparisons).

    Returns:
        One :class:`Comparison` per pair, ``method - against``.
    """
    names = [baseline, *adaptive]
    missing = [name for name in names if name not in scores]
    if missing:
        raise ValueError(f"no scores for {missing}; have {sorted(scores)}")
    sizes = {name: len(_trials(scores[name])) for name in names}
    if len(set(sizes.values())) != 1:
        raise ValueError(f"paired comparisons need the same trials for every method, got trial counts {sizes}")
    indices = bootstrap_indices(sizes[baseline], seed=seed)
    pairs = [(a, baseline) for a in adaptive] + [
        (a, b) for i, a in enumerate(adaptive) for b in adaptive[i + 1 :] if a != b
    ]
    comparisons = []
    for a, b in pairs:
        difference = _trials(scores[a]) - _trials(scores[b])
        low, high = _bounds(difference[indices].mean(-1), level)
        verdict: Verdict = "no significant difference"
        if low > 0 or high < 0:  # the interval excludes zero: a is above b (low > 0) or below it
            verdict = "better" if (high < 0) == lower_is_better else "worse"
        comparisons.append(Comparison(a, b, float(difference.mean()), low, high, verdict))
    return comparisons


def _trials(values: Tensor) -> Tensor:
    values = torch.as_tensor(values, dtype=torch.float64).detach().cpu()
    if values.dim() != 1 or len(values) == 0:
        raise ValueError(f"scores must be one value per trial, a non-empty [trials] tensor; got {list(values.shape)}")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("scores contain NaN or inf: a method diverged on some trial; inspect trials.csv")
    return values


def _bounds(samples: Tensor, level: float) -> tuple[float, float]:
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    tail = (1 - level) / 2
    low, high = torch.quantile(samples, torch.tensor([tail, 1 - tail], dtype=samples.dtype))
    return float(low), float(high)


def _number(value: float) -> str:
    # Three decimals keep a column of differences aligned and comparable; only huge values need 'g'.
    return f"{value:.3f}" if math.isfinite(value) and abs(value) < 1e4 else f"{value:.4g}"


def cell_statistics(
    scores: Mapping[tuple[Any, ...], Mapping[str, Tensor]],
    *,
    cell: Sequence[str],
    baseline: str | None,
    adaptive: Sequence[str],
    metric: str,
    lower_is_better: bool = True,
    seed: int = 0,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Table rows with 95 % CIs and paired comparison rows, for every cell of an experiment's table.

    Args:
        scores: cell (a tuple of the ``cell`` fields' values) -> method -> per-trial scores.
        cell: the names of the cell's fields (e.g. ``("burn_in", "horizon")``).
        baseline: the method without adaptation, or ``None`` to compare only adaptive methods
            with each other; methods absent from a cell are skipped there.
        adaptive: the adaptive methods.
        metric: the name of the score (e.g. ``"rmse"``), which prefixes the row fields.
        lower_is_better: ``True`` for errors.
        seed: the bootstrap seed.

    Returns:
        ``(rows, comparisons)``: one row per cell and method (``{metric}_mean``, ``{metric}_low``,
        ``{metric}_high``, ``{metric}_std``, ``trials``) and one per cell and compared pair.

    Example:
        >>> import torch
        >>> scores = {(1,): {"M+N": torch.ones(20), "M+S": torch.linspace(0.1, 0.3, 20)}}
        >>> rows, comparisons = cell_statistics(scores, cell=["T"], baseline="M+N", adaptive=["M+S"], metric="rmse")
        >>> comparisons[0]["verdict"]
        'better'
    """
    rows: list[dict[str, Any]] = []
    comparisons: list[dict[str, Any]] = []
    for key, by_method in scores.items():
        where = dict(zip(cell, key, strict=True))
        indices = bootstrap_indices(len(_trials(next(iter(by_method.values())))), seed=seed)
        for method, values in by_method.items():
            estimate = mean_ci(values, indices=indices) if len(values) == indices.shape[1] else mean_ci(values)
            rows.append(
                {
                    **where,
                    "method": method,
                    f"{metric}_mean": estimate.mean,
                    f"{metric}_low": estimate.low,
                    f"{metric}_high": estimate.high,
                    f"{metric}_std": float(_trials(values).std()) if len(values) > 1 else 0.0,
                    "trials": estimate.trials,
                }
            )
        present = [m for m in adaptive if m in by_method]
        if baseline is not None and baseline in by_method:
            pairs = paired_comparisons(
                by_method, baseline=baseline, adaptive=present, lower_is_better=lower_is_better, seed=seed
            )
        elif len(present) > 1:
            pairs = paired_comparisons(
                by_method, baseline=present[0], adaptive=present[1:], lower_is_better=lower_is_better, seed=seed
            )
        else:
            pairs = []
        comparisons += [{**where, **dataclasses.asdict(c)} for c in pairs]
    return rows, comparisons


def oriented(comparisons: Sequence[Mapping[str, Any]], pairs: Sequence[tuple[str, str]]) -> list[dict[str, Any]]:
    """The comparisons of ``pairs`` ``(method, against)``, each read as ``method`` minus ``against``.

    A pair stored the other way round is flipped: its difference and interval negated, ``better``
    and ``worse`` swapped. Pairs not compared are left out.

    Example:
        >>> rows = [{"T": 1, "method": "M+S", "against": "M+L", "difference": 0.1, "low": 0.05, "high": 0.2,
        ...          "verdict": "worse"}]
        >>> [(c["method"], c["difference"], c["low"], c["verdict"]) for c in oriented(rows, [("M+L", "M+S")])]
        [('M+L', -0.1, -0.2, 'better')]
    """
    flip = {"better": "worse", "worse": "better"}
    wanted = set(pairs)
    found = []
    for c in comparisons:
        if (c["method"], c["against"]) in wanted:
            found.append(dict(c))
        elif (c["against"], c["method"]) in wanted:
            found.append(
                {
                    **c,
                    "method": c["against"],
                    "against": c["method"],
                    "difference": -c["difference"],
                    "low": -c["high"],
                    "high": -c["low"],
                    "verdict": flip.get(c["verdict"], c["verdict"]),
                }
            )
    order = {pair: i for i, pair in enumerate(pairs)}
    return sorted(found, key=lambda c: order[(c["method"], c["against"])])


def verdict_table(comparisons: Sequence[Mapping[str, Any]], *, cell: Sequence[str]) -> str:
    """A Markdown table of the paired comparisons: difference [95 % CI] and verdict per cell and pair ("" if none).

    Example:
        >>> print(verdict_table([{"T": 1, "method": "M+S", "against": "M+N", "difference": -0.1,
        ...                       "low": -0.2, "high": -0.05, "verdict": "better"}], cell=["T"]))
        | T | method | against | difference [95% CI]     | verdict |
        |---|--------|---------|-------------------------|---------|
        | 1 | M+S    | M+N     | -0.100 [-0.200, -0.050] | better  |
    """
    from smcd_rl.experiments.shared.outputs import format_table

    if not comparisons:  # nothing was compared (e.g. the baseline did not run): no table, not an empty one
        return ""
    body = [
        [
            *(c[name] for name in cell),
            c["method"],
            c["against"],
            f"{Estimate(c['difference'], c['low'], c['high'], 0)}",
            c["verdict"],
        ]
        for c in comparisons
    ]
    return format_table(body, [*cell, "method", "against", "difference [95% CI]", "verdict"])
