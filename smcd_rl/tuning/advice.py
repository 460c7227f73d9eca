"""What to use on your data: the closing lines of :meth:`smcd_rl.TuneResult.table`.

The same questions as the decision table of the protocol page, answered from the tuning run
itself: which strategy scores best; which is best with few observations (the first quarter of
the steps) and with many (the last quarter), from each best strategy's one-step errors step by
step; whether a much cheaper strategy is nearly as good (a per-step budget); whether the
residuals called for a robust form (corrupted readings); and whether adapting helps at all.

Example:
    >>> from smcd_rl.tuning import TuneResult, TuneCandidate
    >>> result = TuneResult("one-step", None, [], {
    ...     "none": TuneCandidate("none", {}, 0.20, 0.02),
    ...     "gradient_descent": TuneCandidate("gradient_descent", {"loss": "mse"}, 0.100, 9.0),
    ...     "last_layer": TuneCandidate("last_layer", {"likelihood": "gaussian"}, 0.102, 0.3)})
    >>> print("\\n".join(advice(result)))
    what to use on these episodes (one-step RMSE):
    - best: gradient_descent (0.1 against 0.2 unadapted)
    - under a per-step budget: last_layer is within 5% of it (0.102) at 30x less time per observation (0.3 ms)
"""

from __future__ import annotations

import math
from typing import Any

from smcd_rl.tuning.defaults import ROBUST_FORMS
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.search import usable, within

__all__ = ["advice", "NEAR", "CHEAPER"]

#: A strategy within this share of the best's score counts as nearly as good.
NEAR = 0.05
#: ... and is worth naming under a per-step budget when it is at least this many times cheaper.
CHEAPER = 3.0


def advice(result: Any) -> list[str]:
    """The advice lines for ``result``, a :class:`smcd_rl.TuneResult` (empty if fewer than two kinds were scored)."""
    scored = {kind: c for kind, c in result.best_of.items() if usable(c.score)}
    if len(scored) < 2:
        return []
    best_kind = result.best_kind
    best = scored[best_kind]
    lines = [f"what to use on these episodes ({result.score_label}):"]
    plain = scored.get("none")
    against = f" against {plain.score:.4g} unadapted" if plain is not None and best_kind != "none" else ""
    lines.append(f"- best: {best_kind} ({best.score:.4g}{against})")
    if plain is not None and best_kind != "none" and _near(plain.score, best.score):
        lines.append(f"- adapting gains less than {NEAR:.0%} here: the episodes may not differ from the training tasks")
    lines += _few_and_many(result, scored)
    cheap = [
        (kind, c)
        for kind, c in scored.items()
        if kind not in (best_kind, "none")
        and _near(c.score, best.score)
        and math.isfinite(c.ms_per_step)
        and c.ms_per_step * CHEAPER <= best.ms_per_step
    ]
    if cheap:
        kind, c = min(cheap, key=lambda item: item[1].ms_per_step)
        lines.append(
            f"- under a per-step budget: {kind} is within {NEAR:.0%} of it ({c.score:.4g}) at "
            f"{best.ms_per_step / c.ms_per_step:.0f}x less time per observation ({c.ms_per_step:.3g} ms)"
        )
    robust = [
        f"{kind} ({form})" for kind, c in scored.items() for form, has in ROBUST_FORMS.get(kind, ()) if has(c.settings)
    ]
    if robust:
        lines.append(
            f"- robust forms: {', '.join(robust)}, which bound what one corrupted reading does; the plain "
            "forms break on one"
        )
    return lines


def _near(score: float, best: float) -> bool:
    """Whether ``score`` is within :data:`NEAR` of ``best`` (``best`` usable: finite or ``-inf``)."""
    return score <= within(best, NEAR)


def _few_and_many(result: Any, scored: dict[str, Any]) -> list[str]:
    """The best kind by one-step error over the first and the last quarter of the steps, where they differ."""
    runs: dict[str, Trace] = {}
    for kind in scored:
        run = result.trace(kind)
        if run is not None and math.isfinite(run.rmse) and len(run.one_step_rmse) >= 4:
            runs[kind] = run
    if len(runs) < 2:
        return []
    quarter = max(1, len(next(iter(runs.values())).one_step_rmse) // 4)

    def pooled(values: list[float]) -> float:
        return math.sqrt(sum(v * v for v in values) / len(values))

    early = {kind: pooled(run.one_step_rmse[:quarter]) for kind, run in runs.items()}
    late = {kind: pooled(run.one_step_rmse[-quarter:]) for kind, run in runs.items()}
    first, last = min(early, key=early.__getitem__), min(late, key=late.__getitem__)
    if first == last:
        return []
    return [
        f"- few observations (first {quarter} steps): {first} ({early[first]:.4g} one-step RMSE); "
        f"many (last {quarter}): {last} ({late[last]:.4g})"
    ]
