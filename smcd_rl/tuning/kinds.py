"""How :func:`smcd_rl.tune` searches each kind of strategy: gradient descent's grid, SMCD's calibration,
the Bayesian last layer's grid, SMCD with a Bayesian readout, the combination.

Each function adds its kind's candidates to a :class:`~smcd_rl.tuning.search.Search`; the
module doc of :mod:`smcd_rl.tuning.protocol` says what each searches, and
:mod:`smcd_rl.tuning.defaults` holds the grids.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> _ = torch.manual_seed(0)
    >>> q = torch.rand(80, 2)
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    >>> _ = smcd_rl.fit(model, TensorDict({"q": q, "ee": q.cos()}, [80]), epochs=2, progress=False)
    >>> episodes = TensorDict({"q": q.reshape(8, 10, 2), "ee": q.cos().reshape(8, 10, 2) + 0.5}, [8, 10])
    >>> grid = {"lr": (1e-3, 1e-2), "steps": (1,), "window": (10,), "loss": ("mse",)}
    >>> result = smcd_rl.tune(model, episodes, strategies=["gradient_descent"], gd_grid=grid, progress=False)
    >>> any("on the grid's high edge; tried" in note for note in result.notes)  # the best lr was the largest
    True
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Mapping, Sequence
from itertools import product
from typing import Any

import torch
from torch import Tensor

from smcd_rl.checks import check_count, check_real
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies import SMCD, BayesianLastLayer, GradientDescent
from smcd_rl.strategies.combination import weight_path
from smcd_rl.tuning.calibration import NOISE_SHAPES, Calibration, search_noise
from smcd_rl.tuning.defaults import (
    CALIBRATION_REFINE,
    COMBINATION_GRID,
    EXTENSIBLE,
    FINALISTS,
    GD_GRID,
    LAST_LAYER_GRID,
    MAX_EXTENSIONS,
    MIN_PARTICLES,
    MIN_SEARCH_PARTICLES,
    PREDICTIONS,
    RACE_MARGIN,
    ROBUST_FORMS,
    ROBUST_SCALE_FACTOR,
    SEARCH_PARTICLE_SHARE,
    SMCD_LAST_LAYER_FINALISTS,
    SMCD_LAST_LAYER_QUIET_SHARE,
    SMCD_LAST_LAYER_SCALES,
    WEIGHINGS,
)
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.search import Search, TuneCandidate, setting_key, usable, within

__all__ = [
    "checked_gd_grid",
    "checked_gd_limits",
    "checked_predictions",
    "checked_weighings",
    "tune_gd",
    "tune_smcd",
    "tune_last_layer",
    "tune_smcd_last_layer",
    "smcd_last_layer_factors",
    "quiet_readout_scale",
    "tune_combination",
]


# ---------------------------------------------------------------------------- gradient descent
def checked_gd_grid(gd_grid: Mapping[str, Sequence[Any]] | None) -> dict[str, tuple[Any, ...]]:
    """``gd_grid`` filled in from :data:`GD_GRID`, or an error before any run."""
    if gd_grid is not None and not isinstance(gd_grid, Mapping):
        raise TypeError(f"gd_grid must be a dict such as {GD_GRID}, got {type(gd_grid).__name__}")
    given = dict(gd_grid or {})
    grid = {k: tuple(v) for k, v in {**GD_GRID, **given}.items()}
    # A bare string is iterable too: "mse" would become the losses "m", "s", "e".
    if set(grid) != set(GD_GRID) or not all(grid.values()) or any(isinstance(v, str) for v in given.values()):
        raise ValueError(
            f"gd_grid takes non-empty sequences of 'lr', 'steps', 'window' and 'loss' values, such as "
            f"{{'lr': (0.01, 0.1), 'loss': ('huber',)}} (a key left out keeps GD_GRID's values), got {gd_grid!r}"
        )
    unknown = [loss for loss in grid["loss"] if loss not in GradientDescent.LOSSES]
    if unknown:
        raise ValueError(f"gd_grid['loss'] takes losses from {list(GradientDescent.LOSSES)}, got {unknown}")
    # The values GradientDescent takes, checked here: steps=1.5 would otherwise run as int(1.5) = 1.
    grid["lr"] = tuple(
        check_real(v, f"gd_grid['lr'][{i}]", low=0.0, high=1e30, open_low=True) for i, v in enumerate(grid["lr"])
    )
    for name in ("steps", "window"):
        grid[name] = tuple(check_count(v, f"gd_grid[{name!r}][{i}]") for i, v in enumerate(grid[name]))
    return grid


def checked_gd_limits(
    gd_limits: Mapping[str, tuple[float | None, float | None]] | None, grid: dict[str, tuple[Any, ...]]
) -> dict[str, tuple[float, float]]:
    """``gd_limits`` as ``{dimension: (low, high)}`` for every extensible dimension, or an error before any run."""
    if gd_limits is not None and not isinstance(gd_limits, Mapping):
        raise TypeError(f"gd_limits must be a dict such as {{'lr': (None, 0.03)}}, got {type(gd_limits).__name__}")
    given = dict(gd_limits or {})
    unknown = sorted(set(given) - set(EXTENSIBLE))
    if unknown:
        raise ValueError(f"gd_limits: unknown {unknown}; the grid extends only along {list(EXTENSIBLE)}")
    limits = {}
    for name in EXTENSIBLE:
        bounds = given.get(name, (None, None))
        if not isinstance(bounds, (tuple, list)) or len(bounds) != 2:
            raise ValueError(f"gd_limits[{name!r}] must be a pair (low, high), None for no limit, got {bounds!r}")
        low, high = (-math.inf if bounds[0] is None else bounds[0], math.inf if bounds[1] is None else bounds[1])
        outside = [v for v in grid[name] if not low <= v <= high]
        if outside:
            raise ValueError(f"gd_grid[{name!r}] has {outside} outside gd_limits[{name!r}] = {tuple(bounds)}")
        limits[name] = (low, high)
    return limits


def tune_gd(search: Search, grid: dict[str, tuple[Any, ...]], limits: dict[str, tuple[float, float]]) -> None:
    """Score the grid; while the best point lies on an edge, go on past that edge along that dimension.

    The grid, and each extension's settings, are raced (:meth:`~smcd_rl.tuning.search.Search.race`).
    Past an edge only the line through the best point is scored (the new value with the other
    settings at their best), not the whole grid again: each extension costs one setting, and
    steps and window double the cost of a setting with each extension. The search extends only
    the learning rate, steps and window, never past ``limits``.

    The loss has no edge and is not crossed with the grid: the first loss (the squared error,
    where given) is searched, and every other loss runs at its best setting. The robust losses
    equal the squared one on residuals well within their scale, so on clean episodes they share
    its best setting up to the noise, which :meth:`~smcd_rl.tuning.search.Search.prefer_robust`
    then weighs; searching the grid once halves gradient descent's runs. Where every setting of a
    loss diverges, the next loss is searched on the whole grid instead.
    """
    # The losses keep GradientDescent.LOSSES' order, so that the squared one is searched.
    losses = [loss for loss in GradientDescent.LOSSES if loss in grid["loss"]]
    grid = {k: tuple(sorted(v)) for k, v in grid.items() if k != "loss"}
    scored: dict[tuple[Any, ...], float] = {}

    # The robust losses' scale is the unadapted network's residual: a reading far beyond what the
    # network gets wrong is a corrupted one. At the default scale (one standard deviation of the
    # targets) a reading tens of residuals off pulls with tens of residuals' force under the Huber
    # loss, and even where it is bounded, that pull adds up over steps x window gradient steps and
    # outweighs the other readings once they fit: Tukey's biweight, tuned by default, ignores it.
    delta = math.sqrt(statistics.fmean(r * r for r in _unadapted_residual(search))) * ROBUST_SCALE_FACTOR

    def race(points: list[tuple[Any, ...]]) -> None:
        points = [p for p in points if p not in scored]
        configs = [
            GradientDescent(lr=lr, steps=s, window=w, loss=loss, huber_delta=delta).config()
            for lr, s, w, loss in points
        ]
        scored.update(zip(points, search.race("gradient_descent", configs), strict=True))

    for i, loss in enumerate(losses):
        best = _search_grid(search, dict(grid), limits, loss, race, scored)
        if best is not None:
            race([(*best[:3], other) for other in losses[i + 1 :]])  # the other losses at its best setting
            break
    else:
        search.notes.append(
            f"gradient descent: every one of its {len(scored)} settings diverged or was over the budget, so none "
            "is kept; try smaller learning rates (gd_grid['lr'])"
        )
        return
    search.prefer_robust("gradient_descent", ROBUST_FORMS["gradient_descent"])
    search.time_best("gradient_descent")


def _search_grid(
    search: Search,
    grid: dict[str, tuple[Any, ...]],
    limits: dict[str, tuple[float, float]],
    loss: str,
    race: Callable[[list[tuple[Any, ...]]], None],
    scored: dict[tuple[Any, ...], float],
) -> tuple[Any, ...] | None:
    """:func:`tune_gd`'s search of one loss: the grid, then past its edges; the best point, or
    ``None`` where every setting diverged or was over the budget."""
    race(list(product(grid["lr"], grid["steps"], grid["window"], (loss,))))
    extensions = {("lr", "low"): 0, ("lr", "high"): 0, ("steps", "high"): 0, ("window", "high"): 0}
    while True:
        finite = {k: v for k, v in scored.items() if usable(v) and k[3] == loss}
        if not finite:
            return None
        point = min(finite.items(), key=lambda item: item[1])[0]
        best = dict(zip(("lr", "steps", "window", "loss"), point, strict=True))
        edge = _edge(grid, best, extensions, limits)
        if edge is None:
            search.notes.extend(
                f"gradient descent: best {name} {best[name]:g} on the grid's {side} edge, at gd_limits"
                for name, side in extensions
                if _on_edge(grid[name], best[name], side) and not _within(limits[name], _past(grid[name], name, side))
            )
            return point
        name, side = edge
        extensions[edge] += 1
        new = _past(grid[name], name, side)
        grid[name] = tuple(sorted({*grid[name], new}))
        race([tuple({**best, name: new}.values())])
        search.notes.append(f"gradient descent: best {name} {best[name]:g} on the grid's {side} edge; tried {new:g}")


def _past(values: tuple[Any, ...], name: str, side: str) -> Any:
    """The next value past an edge: the learning rate continues the grid's own ratio; steps and
    window double, since each multiplies the cost of an observation."""
    ratio = values[1] / values[0] if name == "lr" else 2.0
    new = values[0] / ratio if side == "low" else values[-1] * ratio
    return new if name == "lr" else int(round(new))


def _edge(
    grid: dict[str, tuple[Any, ...]],
    best: dict[str, Any],
    extensions: dict[tuple[str, str], int],
    limits: dict[str, tuple[float, float]],
) -> tuple[str, str] | None:
    """The first edge the best point lies on that may still extend, or ``None``."""
    for name, side in extensions:
        values = grid[name]
        if (
            _on_edge(values, best[name], side)
            and extensions[(name, side)] < MAX_EXTENSIONS
            and _within(limits[name], _past(values, name, side))
        ):
            return name, side
    return None


def _on_edge(values: tuple[Any, ...], value: Any, side: str) -> bool:
    """Whether ``value`` is the grid's ``side`` end (a dimension of one value has no edge)."""
    return len(values) > 1 and value == (values[0] if side == "low" else values[-1])


def _within(bounds: tuple[float, float], value: float) -> bool:
    return bounds[0] <= value <= bounds[1]


# ---------------------------------------------------------------------------- SMCD
def checked_predictions(predictions: Sequence[str]) -> tuple[str, ...]:
    """``tune``'s ``predictions`` as a tuple: ``("mask",)`` or :data:`~smcd_rl.tuning.defaults.PREDICTIONS`
    (the calibration runs with the MMSE mask's prediction, so it is always among them).

    Example:
        >>> checked_predictions(["mask"])
        ('mask',)
    """
    return _checked_choices("predictions", predictions, PREDICTIONS, "SMCD's calibration predicts with the MMSE mask")


def checked_weighings(weighings: Sequence[str]) -> tuple[str, ...]:
    """``tune``'s ``weighings`` as a tuple: ``("predictive",)`` or :data:`~smcd_rl.tuning.defaults.WEIGHINGS`
    (SMCD with a Bayesian readout's scales are searched with the readout's predictive, so it is always among them).

    Example:
        >>> checked_weighings(["predictive", "mean"])
        ('predictive', 'mean')
    """
    return _checked_choices("weighings", weighings, WEIGHINGS, "the readout's scales are searched with it")


def _checked_choices(name: str, given: Sequence[str], allowed: tuple[str, ...], why: str) -> tuple[str, ...]:
    """``given`` as a tuple: ``allowed[:1]`` or ``allowed`` (in any order), the first always among them."""
    if isinstance(given, str) or not isinstance(given, Sequence):
        raise TypeError(f"{name} must be a sequence such as {allowed}, got {given!r}")
    chosen = tuple(given)
    if allowed[0] not in chosen or not set(chosen) <= set(allowed):
        raise ValueError(f"{name} must be {allowed[:1]} or {allowed} ({why}), got {chosen}")
    return chosen


def tune_smcd(
    search: Search,
    num_particles: int,
    flip_probs: tuple[float, ...],
    seed: int,
    progress: bool,
    shortcuts: bool = True,
    predictions: Sequence[str] = PREDICTIONS,
) -> dict[str, Calibration]:
    """Halve the particles until a step fits the budget, then calibrate by the search's criterion:
    the noise's factor, its shape (:data:`~smcd_rl.tuning.calibration.NOISE_SHAPES`) and the flip
    probability (:func:`~smcd_rl.tuning.calibration.search_noise`).

    With ``"predictive"`` in ``predictions``, the best setting also predicts with the posterior
    predictive mean (the weighted mean of every particle's prediction) instead of the MMSE mask's.
    The filter runs the same either way; the mean costs a forward pass per particle at every
    prediction, so it is kept only where it predicts better beyond the episodes' noise
    (:meth:`~smcd_rl.tuning.search.Search.prefer_cheaper`). Then the robust form.

    With ``shortcuts`` (not under the evidence criterion, whose choice is SMCD's own score) the
    search runs with :data:`~smcd_rl.tuning.defaults.SEARCH_PARTICLE_SHARE` of the particles, and
    its best settings (at most :data:`~smcd_rl.tuning.defaults.FINALISTS`, each within
    :data:`~smcd_rl.tuning.defaults.RACE_MARGIN` of the best) run again at full size, the best of
    those kept: a filter's error moves with its particle count, but the ranking of settings far
    apart hardly does, and the finalists settle the close ones.

    Returns the calibration run (``{"search": ...}``, empty where an earlier call's choice was
    reused); the model's own calibration is left as it is.
    """
    model = search.model
    particles, ms = num_particles, math.nan
    while search.timing.budget_ms is not None:
        ms = search.timing.ms("smcd", {"num_particles": particles, "noise_std": 1.0, "flip_prob": 0.01})
        if not search.timing.over(ms) or particles // 2 < MIN_PARTICLES:
            break
        particles //= 2
    if search.timing.over(ms):
        search.notes.append(
            f"SMCD: over the budget even with {particles} particles ({ms:.3g} ms per observation), so not tuned"
        )
        search.candidates.append(TuneCandidate("smcd", {"num_particles": particles}, math.inf, ms, "over budget"))
        return {}
    if particles != num_particles:
        search.notes.append(f"SMCD: {particles} particles instead of {num_particles}, to fit the budget")
    device = str(next(model.net.parameters()).device)
    known = [c for c in search.known.values() if c.kind == "smcd" and c.settings.get("num_particles") == particles]
    calibrations: dict[str, Calibration] = {}
    if known:  # an earlier call calibrated these particles on the same data: its choice stands
        for candidate in known:
            search.score("smcd", candidate.settings)
        chosen = search.chosen_before.get("smcd")
        again = [c for c in search.candidates if c.kind == "smcd" and c.settings == chosen and usable(c.score)]
        if again:
            search.best_of["smcd"] = again[-1]
    else:
        small = int(particles * SEARCH_PARTICLE_SHARE)
        reduced = shortcuts and search.scorer.criterion.name != "evidence" and small >= MIN_SEARCH_PARTICLES
        # calibrate's search, every noise shape, on the episodes tune checked, scored by tune's
        # scorer; tune's record is model.tuning, so the model's calibration stays as it was.
        result = search_noise(
            search.scorer,
            SMCD(num_particles=small if reduced else particles),
            list(flip_probs),
            shapes=NOISE_SHAPES,
            refine=CALIBRATION_REFINE,
            seed=seed,
            progress=progress,
        )
        calibrations["search"] = result
        measured = None if math.isnan(ms) else ms
        generator = {"seed": seed, "device": device}
        if not reduced:
            search.score("smcd", {**result.strategy.config(), **generator}, ms=measured, run=result.best.trace)
        else:
            ranked = result.ranked()
            near = within(ranked[0].score, RACE_MARGIN)  # a setting further behind is not a contender
            finalists = [c for c in ranked[:FINALISTS] if c.score <= near]
            for finalist in finalists:  # each run again at full size
                noise = list(finalist.noise_std) if isinstance(finalist.noise_std, tuple) else finalist.noise_std
                config = {**result.strategy.config(), "num_particles": particles, "noise_std": noise}
                search.score("smcd", {**config, "flip_prob": finalist.flip_prob, **generator}, ms=measured)
            search.notes.append(
                f"SMCD: searched with {small} particles ({len(result.candidates)} runs), its {len(finalists)} best "
                f"settings (at most {FINALISTS}, within {RACE_MARGIN:.0%} of the best) confirmed with {particles}"
            )
        best = search.best_of.get("smcd")
        if best is not None and "predictive" in predictions:
            search.score("smcd", {**best.settings, "prediction": "predictive"})
            search.prefer_cheaper("smcd", best.settings, "the MMSE mask's prediction", "the posterior predictive mean")
            best = search.best_of["smcd"]
        if best is not None and search.scorer.criterion.name != "evidence":
            # The robust form at the best setting: a Student-t likelihood of the same scale, whose
            # heavy tails keep one corrupted reading from collapsing the particles onto whichever
            # masks explain it. (Under the evidence criterion the likelihood is what is scored.)
            search.score("smcd", {**best.settings, "likelihood": "student-t"}, ms=measured)
    search.prefer_robust("smcd", ROBUST_FORMS["smcd"])
    search.time_best("smcd")
    return calibrations


# ---------------------------------------------------------------------------- Bayesian last layer
def tune_last_layer(search: Search) -> None:
    """Race :data:`LAST_LAYER_GRID`; while the best prior scale lies on an edge, go on past it (x3).

    The noise is in the model's normalised units, per output: the root-mean-square residual of
    the unadapted network on the episodes (what a readout that starts at the trained one has to
    explain), times each ``noise_factor`` for the Student-t form, whose down-weighting of an
    observation depends on it.
    """
    residual = _unadapted_residual(search)
    grid = LAST_LAYER_GRID
    forms: list[tuple[Any, list[float]]] = [
        (likelihood, [f * r for r in residual])
        for likelihood in grid["likelihood"]
        for f in ((1.0,) if likelihood == "gaussian" else grid["noise_factor"])
    ]
    scales = list(grid["prior_scale"])

    def race(points: list[tuple[Any, Any, tuple[Any, list[float]]]]) -> None:
        configs = [
            BayesianLastLayer(prior_scale=p, drift=d, likelihood=likelihood, noise_std=noise).config()
            for p, d, (likelihood, noise) in points
        ]
        search.race("last_layer", configs)

    race(list(product(scales, grid["drift"], forms)))
    extensions = {"low": 0, "high": 0}
    while True:
        best = search.best_of.get("last_layer")
        if best is None:
            search.notes.append("last layer: every setting refused an observation, so none is kept")
            return
        scale = best.settings["prior_scale"]
        side = "low" if scale == scales[0] else "high" if scale == scales[-1] else None
        if side is None or extensions[side] == MAX_EXTENSIONS:
            break
        extensions[side] += 1
        new = scales[0] / 3 if side == "low" else scales[-1] * 3
        scales = sorted({*scales, new})
        form = (best.settings["likelihood"], best.settings["noise_std"])
        race([(new, best.settings["drift"], form)])
        search.notes.append(f"last layer: best prior_scale {scale:g} on the grid's edge; tried {new:g}")
    search.prefer_robust("last_layer", ROBUST_FORMS["last_layer"])
    search.time_best("last_layer")


def _unadapted_residual(search: Search) -> list[float]:
    """The unadapted network's root-mean-square one-step residual per output, normalised units."""
    with torch.no_grad():
        residual = search.model.net(search.x) - search.y
    return [max(float(v), 1e-6) for v in residual.square().mean(dim=(0, 1)).sqrt()]


def tune_smcd_last_layer(search: Search, shortcuts: bool = True, weighings: Sequence[str] = WEIGHINGS) -> None:
    """SMCD with a Bayesian readout: the tuned SMCD's filter with the tuned last layer's readout,
    its prior scale at :data:`~smcd_rl.tuning.defaults.SMCD_LAST_LAYER_SCALES` times the last layer's best.

    Each particle's readout takes over part of what the masks explained, so a readout alone at
    its best may be too free beside the filter (or too tight); the scales say which. The
    readout's form (Gaussian or Student-t) is the tuned last layer's, chosen by the robust-form rule. The filter's
    settings are the tuned SMCD's: calibrating them again would cost as many runs as SMCD's own.
    With ``shortcuts`` the scales run with SMCD's reduced particles first (as its calibration
    does), and only the best :data:`~smcd_rl.tuning.defaults.SMCD_LAST_LAYER_FINALISTS` of those
    within :data:`~smcd_rl.tuning.defaults.RACE_MARGIN` of the best there run at full size. With
    ``"mean"`` in ``weighings``, ``weighing="mean"`` runs last, at the best scale and the next wider
    one, and the lower score wins.
    """
    smcd, readout = search.best_of.get("smcd"), search.best_of.get("last_layer")
    if smcd is None or readout is None:
        search.notes.append("SMCD with a Bayesian readout: needs a tuned SMCD and last layer, so not tuned")
        return
    scale = readout.settings["prior_scale"]
    particles = smcd.settings.get("num_particles", SMCD().num_particles)
    small = int(particles * SEARCH_PARTICLE_SHARE)

    def setting(factor: float) -> dict[str, Any]:
        return {"smcd": smcd.settings, "last_layer": {**readout.settings, "prior_scale": scale * factor}}

    quiet = quiet_readout_scale(search.model, search.x, smcd.settings, readout.settings)
    factors = smcd_last_layer_factors(quiet / scale)
    if min(factors) < min(SMCD_LAST_LAYER_SCALES):
        search.notes.append(
            f"SMCD with a Bayesian readout: the quiet readout scale is the last layer's x {min(factors):.2g}; "
            "the scales reach down to it"
        )
    settings = [setting(factor) for factor in factors]
    known = all(setting_key("smcd_last_layer", one) in search.known for one in settings)
    if shortcuts and small >= MIN_SEARCH_PARTICLES and not known and search.scorer.criterion.name != "evidence":
        reduced = [
            search.scorer.score(search.run("smcd_last_layer", {**one, "smcd": {**one["smcd"], "num_particles": small}}))
            for one in settings
        ]
        # The readout's scales score close together: confirming every one within the margin at full
        # size cost more than the full search. The best few of them are confirmed.
        near = within(min(reduced), RACE_MARGIN)
        ranked = sorted((score, i) for i, score in enumerate(reduced) if score <= near)
        settings = [settings[i] for _, i in ranked[:SMCD_LAST_LAYER_FINALISTS]] or settings
    for one in settings:
        search.score("smcd_last_layer", one)
    # A best readout at the tightest scale: the filter wants the masks to explain more; go tighter.
    factor, tried = min(factors), list(factors)
    for _ in range(MAX_EXTENSIONS):
        best = search.best_of.get("smcd_last_layer")
        if best is None or best.settings["last_layer"]["prior_scale"] > scale * factor * (1 + 1e-9):
            break
        factor /= 3
        tried.append(factor)
        search.score("smcd_last_layer", setting(factor))
        search.notes.append(
            f"SMCD with a Bayesian readout: best prior_scale {scale * factor * 3:g} on the grid's low edge; tried "
            f"{scale * factor:g}"
        )
    if "mean" in weighings:
        _try_mean_weighing(search, setting, sorted(tried), scale)
    search.time_best("smcd_last_layer")


#: How the notes name :class:`smcd_rl.SMCDLastLayer`'s weighings.
WEIGHING_NAMES = {"predictive": "the readout's predictive", "mean": "each particle's readout mean"}


def _try_mean_weighing(
    search: Search, setting: Callable[[float], dict[str, Any]], factors: Sequence[float], scale: float
) -> None:
    """Score ``weighing="mean"`` at the best readout scale and the next wider one tried; the lower
    score wins, as between the scales (the two weighings cost the same), and a note says which.

    Without the readout's uncertainty in the particles' likelihood a freer readout no longer blurs
    the masks' weights, so the next wider scale is the other contender.
    """
    best = search.best_of.get("smcd_last_layer")
    if best is None:
        return
    chosen = best.settings["last_layer"]["prior_scale"] / scale
    wider = [f for f in factors if f > chosen * (1 + 1e-9)]
    scores = [search.score("smcd_last_layer", {**setting(f), "weighing": "mean"}) for f in (chosen, *wider[:1])]
    kept = search.best_of["smcd_last_layer"].settings.get("weighing", "predictive")
    search.notes.append(
        f"SMCD with a Bayesian readout: weighs its particles by {WEIGHING_NAMES[kept]} ({best.score:.4g} by the "
        f"readout's predictive; {min(scores):.4g} by each particle's readout mean)"
    )


def smcd_last_layer_factors(quiet: float) -> tuple[float, ...]:
    """The readout scales SL tries, as factors of the last layer's best: :data:`SMCD_LAST_LAYER_SCALES`,
    or, where the ``quiet`` factor lies below their smallest, as many geometric steps from it up to the
    last layer's scale, and three times that.

    Example:
        >>> smcd_last_layer_factors(0.5) == SMCD_LAST_LAYER_SCALES  # quiet within the grid: the grid
        True
        >>> [f"{f:.0e}" for f in smcd_last_layer_factors(1e-4)]
        ['1e-04', '6e-04', '4e-03', '3e-02', '2e-01', '1e+00', '3e+00']
    """
    low = min(SMCD_LAST_LAYER_SCALES)
    if not quiet < low:
        return SMCD_LAST_LAYER_SCALES
    steps = len(SMCD_LAST_LAYER_SCALES) - 1  # below the last layer's own scale
    return (*(quiet ** (1 - i / steps) for i in range(steps)), 1.0, max(SMCD_LAST_LAYER_SCALES))


def quiet_readout_scale(model: AdaptiveModel, x: Tensor, smcd: Mapping[str, Any], readout: Mapping[str, Any]) -> float:
    """The readout prior scale at which SL's likelihood is SMCD's: the readout's predictive variance
    ``s_L^2 scale^2 |phi|^2`` at the unadapted network's mean ``|phi|^2`` over the normalised inputs
    ``x`` is :data:`SMCD_LAST_LAYER_QUIET_SHARE` of the filter's noise variance ``s_S^2``, on the
    output where that comes first. ``phi`` carries the readout's bias input; both noises are in
    normalised units (``smcd``'s and ``readout``'s settings give them).

    Example:
        >>> import torch, smcd_rl
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 1, hidden=(8,)), in_keys=["q"], out_key="y")
        >>> x = torch.rand(5, 2)
        >>> scale = quiet_readout_scale(model, x, {"noise_std": 0.1}, {"noise_std": 1.0})
        >>> squares = model.net.features(x).square().sum(-1).mean() + 1.0
        >>> round(float(1.0**2 * scale**2 * squares / 0.1**2), 6)  # readout's predictive / filter's noise variance
        0.1
    """
    net = model.net
    with torch.no_grad():
        features = net.features(x)
        squares = features.square().sum(-1).mean() + 1.0  # the bias input's 1
        filter_noise = torch.as_tensor(smcd["noise_std"], dtype=features.dtype) / model.output_norm.std.to(features)
        readout_noise = torch.as_tensor(readout["noise_std"], dtype=features.dtype)
        ratio = (filter_noise.expand(net.out_features) / readout_noise.expand(net.out_features)).min()
    return float((SMCD_LAST_LAYER_QUIET_SHARE * ratio.square() / squares).sqrt())


# ---------------------------------------------------------------------------- combination
def tune_combination(search: Search, kinds: list[str]) -> None:
    """Score the combination grid of the best members, from one run of each member.

    The members run on the same stream whatever the weights, so their one-step predictions are
    recorded once and every ``(eta, share)`` is scored from them (:func:`_combination_trace`), the
    same error :func:`smcd_rl.tuning.diagnostics.trace` gives a :class:`~smcd_rl.strategies.combination.Combination`,
    at the cost of one combination run instead of one per grid point.
    """
    if len(kinds) < 2:
        return
    for kind in kinds:
        search.time_best(kind)
    members: list[dict[str, Any]] = [{"name": kind, "settings": search.best_of[kind].settings} for kind in kinds]
    ms = sum(search.best_of[kind].ms_per_step for kind in kinds)
    grid = list(product(COMBINATION_GRID["eta"], COMBINATION_GRID["share"]))
    settings = [{"members": members, "eta": eta, "share": share} for eta, share in grid]
    if all(setting_key("combination", s) in search.known for s in settings) or search.timing.over(ms):
        for one in settings:  # reused from an earlier call, or over the budget: nothing to run
            search.score("combination", one, ms=ms)
        return
    if search.scorer.lookahead is not None and search.scorer.lookahead.dynamics:
        # A rollout feeds the mixed prediction back: the members' own rollouts do not give it.
        for one in settings:
            search.score("combination", one, ms=ms)
        return
    recorded = _member_predictions(search, members)
    for (eta, share), one in zip(grid, settings, strict=True):
        if recorded is None:
            search.score("combination", one, ms=ms, rmse=math.inf)
            continue
        run = _combination_trace(search.model, recorded, search.y, eta, share)
        if search.scorer.lookahead is not None:
            run.ahead = _combination_ahead(search, members, recorded, eta, share)
        search.score("combination", one, ms=ms, run=run)


def _member_predictions(search: Search, members: list[dict[str, Any]]) -> Tensor | None:
    """Each member's normalised prediction of every step before it observes it, ``[E, T, out, K]``.

    A member scored on the episodes already gives them from that run; the others run now. ``None``
    if a member refuses an observation or predicts a non-finite value: a combination of them
    stops there too.
    """
    predictions = []
    for member in members:
        found = search.recorded(member["name"], member["settings"])
        if found is None:
            return None
        predictions.append(found)
    stacked = torch.stack(predictions, dim=-1)
    return stacked if bool(torch.isfinite(stacked).all()) else None


def _combination_ahead(
    search: Search, members: list[dict[str, Any]], predictions: Tensor, eta: float, share: float
) -> Tensor:
    """A combination's open-loop predictions ``[E, S, H, out]`` from its members' (inputs recorded, not rolled).

    From each start ``t`` the combination predicts with the weights it holds after the steps
    before ``t``, frozen over the horizon: each member's prediction mixed by them (an affine map
    of the normalised output, so mixing target units is the same).
    """
    weights = weight_path(predictions, search.y, eta=eta, share=share).exp()  # [E, T + 1, K]
    runs = [search.run(m["name"], m["settings"]).ahead for m in members]
    ahead = torch.stack([run for run in runs if run is not None], dim=-1)  # [E, S, H, out, K]: all ran to the end
    mixed = weights[:, 1 : ahead.shape[1] + 1].to(ahead.dtype).reshape(*ahead.shape[:2], 1, 1, ahead.shape[-1])
    return (ahead * mixed).sum(-1)


def _combination_trace(model: AdaptiveModel, predictions: Tensor, targets: Tensor, eta: float, share: float) -> Trace:
    """The trace (one-step errors only) of a combination, from its members' recorded predictions.

    ``predictions [E, T, out, K]`` are the members' normalised one-step predictions, each made
    before its step was observed, ``targets [E, T, out]`` the normalised observations. The weights
    follow :class:`~smcd_rl.strategies.combination.Combination` operation for operation, and the errors are
    accumulated as :func:`smcd_rl.tuning.diagnostics.trace` accumulates them.
    """
    num_episodes, steps, outputs, count = predictions.shape
    weights = weight_path(predictions, targets, eta=eta, share=share).exp().to(predictions.dtype)  # [E, T + 1, K]
    output_std = model.output_norm.std.to(torch.float64)
    result = Trace([], math.inf, [], [], [], [], [[] for _ in range(num_episodes)])
    squared = 0.0
    episode_squared = torch.zeros(num_episodes, dtype=torch.float64)
    for t in range(1, steps):
        combined = (predictions[:, t] * weights[:, t].reshape(num_episodes, 1, count)).sum(-1)
        error = (combined - targets[:, t]).to(torch.float64) * output_std
        step_squared = float(error.square().sum())
        squared += step_squared
        result.one_step_rmse.append(math.sqrt(step_squared / (num_episodes * outputs)))
        per_episode = error.square().sum(-1).cpu()
        episode_squared += per_episode
        for errors, value in zip(result.one_step_errors, per_episode.tolist(), strict=True):
            errors.append(math.sqrt(value / outputs))
    result.rmse = math.sqrt(squared / (num_episodes * (steps - 1) * outputs))
    result.per_episode_rmse = [math.sqrt(v / ((steps - 1) * outputs)) for v in episode_squared.tolist()]
    return result
