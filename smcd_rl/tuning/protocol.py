"""The fair protocol as one call: every adaptation strategy tuned by one criterion, under one budget.

:func:`tune` takes a fitted model and held-out episodes of its *training* tasks (never the tasks
it will be scored on; :func:`smcd_rl.episodes` cuts them from collected transitions) and tunes
each requested strategy on them by the same criterion (:mod:`smcd_rl.tuning.criteria`): by default the
**one-step prediction error** (the error of predicting each step from the steps before it); with
``criterion="lookahead", horizon=H`` the error of the open-loop predictions ``H`` steps ahead (what
a planner's rollout or a look-ahead table scores); or a callable score of your own:

* gradient descent over a grid of learning rate x steps x window with the squared error, that
  goes on past an edge of the learning rate, steps or window, along that dimension through the
  best point, while the best point lies there (the result says which edges it extended); the
  Huber loss, which bounds the pull of an outlier, then runs at the best setting. The settings
  are raced: each runs first on a quarter of the episodes, and only those within 10 % of the
  best there run on the rest (:mod:`smcd_rl.tuning.search`); the others are listed as raced out;
* SMCD by :func:`smcd_rl.calibrate`: the noise's factor and shape across output dimensions and
  the flip probability, one search; then, at the best setting, the posterior predictive mean in
  place of the MMSE mask's prediction, kept only where it predicts better beyond the episodes'
  noise (``predictions``);
* :class:`smcd_rl.BayesianLastLayer` over prior scale x drift x likelihood (Gaussian, or
  Student-t at two noise scales), raced, the prior scale extended past an edge
  (:data:`~smcd_rl.tuning.defaults.LAST_LAYER_GRID`);
* :class:`smcd_rl.SMCDLastLayer`: the tuned SMCD with the tuned last layer's readout at four
  prior scales, from a tenth of its best to three times it (it tunes both first);
* :class:`smcd_rl.Combination` of the best members, its ``eta`` and ``share`` chosen on the same
  episodes.

With ``budget_ms`` each setting's median wall time per observation (one stream, observe and
predict) is measured first, and settings over the budget are skipped (SMCD halves its particles
until it fits); without one, the best of each kind is timed. The result lists every candidate with its score and time, the best of each kind,
``.best`` (ready for ``model.with_adaptation``) and ``.combination``; it is stored in
``model.tuning``, saved with the model.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> _ = torch.manual_seed(0)
    >>> q = torch.rand(60, 2)
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    >>> _ = smcd_rl.fit(model, TensorDict({"q": q, "ee": q.cos()}, [60]), epochs=2, lr=1e-2, progress=False)
    >>> episodes = TensorDict({"q": q.reshape(6, 10, 2), "ee": q.cos().reshape(6, 10, 2) + 0.1}, [6, 10])
    >>> result = smcd_rl.tune(model, episodes, num_particles=20, progress=False)
    >>> sorted(result.best_of), isinstance(result.best, smcd_rl.Adaptation)
    (['combination', 'gradient_descent', 'last_layer', 'none', 'smcd', 'smcd_last_layer'], True)
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

from tensordict import TensorDictBase

from smcd_rl.checks import check_count, check_real, check_seed
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies import SMCD, Adaptation
from smcd_rl.tuning.calibration import Calibration, checked_flips
from smcd_rl.tuning.criteria import Criterion, Score, checked_criterion
from smcd_rl.tuning.defaults import ADAPTING, FLIP_PROBS, KINDS, MASKED_KINDS, PREDICTIONS, WEIGHINGS, kinds_needed
from smcd_rl.tuning.held_out import checked_model, pairs, stacked
from smcd_rl.tuning.kinds import (
    checked_gd_grid,
    checked_gd_limits,
    checked_predictions,
    checked_weighings,
    tune_combination,
    tune_gd,
    tune_last_layer,
    tune_smcd,
    tune_smcd_last_layer,
)
from smcd_rl.tuning.result import TuneResult
from smcd_rl.tuning.scoring import Scorer
from smcd_rl.tuning.search import Search, Timing, TuneCandidate, setting_key

__all__ = ["tune", "ms_per_observation"]


def tune(
    model: AdaptiveModel,
    episodes: TensorDictBase | Sequence[TensorDictBase],
    *,
    strategies: Sequence[str] = KINDS,
    criterion: Literal["one-step", "evidence", "lookahead"] | Score = "one-step",
    horizon: int | None = None,
    budget_ms: float | None = None,
    num_particles: int = 1000,
    gd_grid: dict[str, Sequence[Any]] | None = None,
    gd_limits: Mapping[str, tuple[float | None, float | None]] | None = None,
    flip_probs: Sequence[float] = FLIP_PROBS,
    seed: int = 0,
    progress: bool = True,
    reuse: TuneResult | None = None,
    shortcuts: bool = True,
    predictions: Sequence[str] = PREDICTIONS,
    weighings: Sequence[str] = WEIGHINGS,
) -> TuneResult:
    """Tune each of ``strategies`` on held-out training-task ``episodes`` by one criterion (see the module doc).

    Args:
        model: a fitted model; its network is not changed.
        episodes: batch ``[E, T]`` in the model's keys (or a list of ``[T]``): held-out episodes
            of the *training* tasks, at least 2 of 2 steps.
        strategies: which of :data:`~smcd_rl.tuning.defaults.KINDS` to tune; each also tunes what it
            is built from (:data:`~smcd_rl.tuning.defaults.NEEDS`): ``"smcd_last_layer"`` starts from
            the tuned SMCD and last layer; ``"combination"`` mixes no adaptation, gradient descent,
            SMCD and every other kind tuned that adapts.
        criterion: what every setting is scored by (:mod:`smcd_rl.tuning.criteria`): ``"one-step"``
            (default), ``"lookahead"`` (the RMSE ``horizon`` steps ahead, open loop: score what
            your planner or table scores), or a callable ``score(predicted, observed) -> float``
            of your own; ``"evidence"`` calibrates SMCD by its evidence and compares the kinds by
            one-step error.
        horizon: the steps ahead of ``"lookahead"`` or of your score (episodes must be longer).
        budget_ms: skip settings whose median time per observation exceeds this (``None``: no budget).
        num_particles: SMCD's particles (halved while over budget, down to 8).
        gd_grid: gradient descent's starting grid, ``{"lr": ..., "steps": ..., "window": ...,
            "loss": ...}``; a key left out takes its values from
            :data:`~smcd_rl.tuning.defaults.GD_GRID` (so a grid
            without ``"loss"`` tries both losses; ``"loss": ("mse",)`` tries the squared error
            only).
        gd_limits: how far the grid may extend past its edges, ``{"lr": (low, high), ...}``
            (``None``: no limit on that side), e.g. ``{"lr": (None, 0.03)}`` where a larger
            learning rate makes a planner's rollouts overflow, or ``{"steps": (None, 20)}`` to
            cap the cost per observation. The starting grid must lie within them.
        flip_probs: the flip probabilities SMCD's calibration tries (:func:`smcd_rl.calibrate`'s).
        seed: seed of every SMCD run: two calls with the same arguments give the same choice. With
            ``budget_ms``, measured wall times decide which settings fit, and they vary from call to
            call and machine to machine; pass ``reuse`` to take an earlier call's times and repeat
            its choice.
        progress: show a progress bar.
        shortcuts: search SMCD's settings (and SMCD with a Bayesian readout's) with a quarter of
            the particles and confirm the best few at full size (:func:`~smcd_rl.tuning.kinds.tune_smcd`);
            ``False``: the full search, every run at full size. Both choices repeat bit for bit
            for one seed.
        predictions: how SMCD may predict (:data:`~smcd_rl.tuning.defaults.PREDICTIONS`): with
            its MMSE mask, and with ``"predictive"`` also the posterior predictive mean at its best
            setting, kept only where it predicts better beyond the episodes' noise (it costs a
            forward pass per particle at every prediction). Pass ``("mask",)`` where a planner
            scores many candidates per step.
        weighings: how SMCD with a Bayesian readout may weigh its particles
            (:data:`~smcd_rl.tuning.defaults.WEIGHINGS`): by the readout's predictive, and with
            ``"mean"`` also by each particle's readout mean, tried at the best scale and the next
            wider one; the lower score wins, as between the readout's scales.
        reuse: an earlier result of this function on the same model, episodes, seed, flip
            probabilities and criterion (e.g. the unbudgeted one, before a call with ``budget_ms``): each setting
            it scored takes its score from there, and each setting it timed its time, instead of running again.

    Returns:
        The :class:`TuneResult`, also stored as ``model.tuning`` (its :meth:`~TuneResult.to_dict`).
        Nothing else of the model changes: its calibration is :func:`smcd_rl.calibrate`'s alone, so
        ``tune`` and ``calibrate`` on one model from two threads each keep their own record (their
        runs only read the network).

    Raises:
        TypeError: ``predictions`` or ``weighings`` a string or not a sequence.
        ValueError: an unknown strategy, criterion, prediction or weighing, a horizon the criterion does not take or
            episodes no longer than it, a budget that is not positive, no strategy
            within the budget, episodes :func:`smcd_rl.calibrate` refuses, or a ``reuse`` of
            another model, other episodes, another seed or another criterion.
    """
    started = time.perf_counter()
    model = checked_model(model, "tune")
    if isinstance(strategies, str) or not isinstance(strategies, Sequence):
        hint = f"; for one, pass [{strategies!r}]" if isinstance(strategies, str) else ""
        raise TypeError(f"strategies must be a list of kinds such as {list(KINDS[:2])}, got {strategies!r}{hint}")
    unknown = [s for s in strategies if s not in KINDS]
    if unknown or not strategies:
        raise ValueError(f"strategies: unknown {unknown or strategies}; choose one or more of {list(KINDS)}")
    for name, flag in (("progress", progress), ("shortcuts", shortcuts)):
        if not isinstance(flag, bool):
            raise TypeError(f"{name} must be True or False, got {flag!r}")
    chosen_by = checked_criterion(criterion, horizon)
    if budget_ms is not None:
        budget_ms = check_real(budget_ms, "budget_ms", low=0.0, open_low=True)
    seed = check_seed(seed)
    num_particles = check_count(num_particles, "num_particles")
    choices = checked_predictions(predictions)
    weighs = checked_weighings(weighings)
    grid = checked_gd_grid(gd_grid)
    limits = checked_gd_limits(gd_limits, grid)
    td = stacked(episodes, "tune")
    # The one scorer of every run, calibrate's included: it checks keys, shapes and values before any run.
    scorer = Scorer(model, td, chosen_by, "tune")
    flips = checked_flips(flip_probs, model, SMCD(num_particles=num_particles))
    data = content_digest({"model": model_digest(model), "episodes": content_digest(td), "seed": seed, "flips": flips})
    known = _reusable(reuse, data, chosen_by)
    timing = Timing(model, scorer.x[0], scorer.y[0], budget_ms, known=None if reuse is None else reuse.timings)
    search = Search(
        scorer,
        timing,
        progress,
        known,
        heads=None if reuse is None else reuse.heads,
        chosen_before=None if reuse is None else {kind: c.settings for kind, c in reuse.best_of.items()},
    )
    kinds = kinds_needed(strategies)
    if model.net.dropout == 0.0:  # no masks to filter over: SMCD's kinds cannot run
        asked = [s for s in strategies if s in MASKED_KINDS]
        if asked and tuple(strategies) != KINDS:
            raise ValueError(
                f"strategies {asked} filter over dropout masks, and this network has no dropout; tune the others "
                f"({[k for k in KINDS if k not in MASKED_KINDS]})"
            )
        kinds = [k for k in kinds if k not in MASKED_KINDS]
        search.notes.append("SMCD and SMCD with a Bayesian readout: not tuned, the network has no dropout")
    calibrations: dict[str, Calibration] = {}
    kind_seconds: dict[str, float] = {}
    try:
        steps: dict[str, Callable[[], Any]] = {
            "none": lambda: search.score("none", {}),
            "gradient_descent": lambda: tune_gd(search, grid, limits),
            "smcd": lambda: calibrations.update(
                tune_smcd(search, num_particles, tuple(flips), seed, progress, shortcuts, choices)
            ),
            "last_layer": lambda: tune_last_layer(search),
            "smcd_last_layer": lambda: tune_smcd_last_layer(search, shortcuts, weighs),
            "combination": lambda: tune_combination(search, [k for k in ("none", *ADAPTING) if k in search.best_of]),
        }
        for kind in kinds:
            begun = time.perf_counter()
            steps[kind]()
            search.time_best(kind)
            kind_seconds[kind] = time.perf_counter() - begun
    finally:
        search.bar.close()
    if not search.best_of:
        if budget_ms is not None and all(c.skipped == "over budget" for c in search.candidates):
            raise ValueError(f"no strategy fits a budget of {budget_ms:g} ms per observation; raise budget_ms")
        raise ValueError(
            f"no setting of {kinds} has a usable score on these episodes: each refused an observation or "
            f"scored inf or NaN by {chosen_by.label}; check the episodes' units and outliers, or the score function"
        )
    result = TuneResult(
        criterion=chosen_by.name,
        budget_ms=budget_ms,
        candidates=search.candidates,
        best_of=search.best_of,
        notes=search.notes,
        episodes=int(td.batch_size[0]),
        steps=int(td.batch_size[1]),
        seconds=time.perf_counter() - started,
        data=data,
        timings=timing.times,
        traces=search.traces,
        heads=search.heads,
        calibrations=calibrations,
        horizon=chosen_by.horizon,
        score_label=chosen_by.label if chosen_by.name != "evidence" else "one-step RMSE",
        score_fn=chosen_by.fn,
        kind_seconds=kind_seconds,
    )
    model.tuning = result.to_dict()
    return result


def _reusable(reuse: TuneResult | None, data: str, criterion: Criterion) -> dict[str, TuneCandidate]:
    """The scored candidates of ``reuse`` by :func:`_key`, after checking it was tuned on the same data."""
    if reuse is None:
        return {}
    if not isinstance(reuse, TuneResult):
        raise TypeError(f"reuse must be a TuneResult of an earlier tune call, got {type(reuse).__name__}")
    same = (reuse.criterion, reuse.horizon) == (criterion.name, criterion.horizon)
    if reuse.data != data or not same or (criterion.name == "custom" and reuse.score_label != criterion.label):
        raise ValueError(
            "reuse holds a result for another model, other episodes, another seed or another criterion; "
            "pass the result of a tune call on the same ones, or none"
        )
    if criterion.name == "custom" and reuse.score_fn is not criterion.fn:
        # Two functions of one name (two lambdas, a def edited since) cannot be told apart by it.
        raise ValueError(
            f"reuse holds a result scored by another score function than this {criterion.label!r} (functions "
            "of the same name cannot be told apart by it); pass the result of a tune call with this very "
            "function object, or none"
        )
    return {setting_key(c.kind, c.settings): c for c in reuse.candidates if not c.skipped}


def ms_per_observation(model: AdaptiveModel, strategy: Adaptation, episode: TensorDictBase) -> float:
    """Median wall milliseconds of one observation (predict, then observe) of ``strategy`` on one stream.

    ``episode`` is one episode ``[T]`` in the model's keys; the strategy is reset for one stream
    and run over it with the current torch threads. A step the strategy refuses ends the
    measurement (``inf`` if none was timed). Wall times depend on the machine and its load:
    compare strategies measured side by side, on a quiet machine.

    Example:
        >>> import torch, smcd_rl, warnings
        >>> from tensordict import TensorDict
        >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
        >>> episode = TensorDict({"q": torch.rand(5, 2), "ee": torch.rand(5, 2)}, [5])
        >>> ms_per_observation(model, smcd_rl.SMCD(num_particles=10), episode) > 0
        True
    """
    if not isinstance(model, AdaptiveModel):  # timing needs no fitted weights, unlike tune's scores
        raise TypeError(f"model must be an smcd_rl.AdaptiveModel, got {type(model).__name__}")
    if not isinstance(strategy, Adaptation):
        raise TypeError(f"strategy must be an smcd_rl.Adaptation, got {type(strategy).__name__}")
    if not isinstance(episode, TensorDictBase) or episode.batch_dims != 1:
        raise ValueError("episode must be one episode: a TensorDict of batch [T] in the model's keys")
    x, y = pairs(model, episode.unsqueeze(0), "ms_per_observation")
    return Timing(model, x[0], y[0], None).ms_per_step(strategy)
