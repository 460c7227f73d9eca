"""The fair protocol as one call: every adaptation strategy tuned by one criterion, under one budget.

:func:`tune` takes a fitted model and held-out episodes of its *training* tasks (never the tasks
it will be scored on; :func:`smcd_rl.episodes` cuts them from collected transitions) and tunes
each requested strategy on them by the same criterion (:mod:`smcd_rl.criteria`): by default the
**one-step prediction error** (the error of predicting each step from the steps before it); with
``criterion="lookahead", horizon=H`` the error of the open-loop predictions ``H`` steps ahead (what
a planner's rollout or a look-ahead table scores); or a callable score of your own:

* gradient descent over a grid of learning rate x steps x window x loss (squared error and
  Huber, which bounds the pull of an outlier) that goes on past an edge of the learning rate,
  steps or window, along that dimension through the best point, while the best point lies there
  (the result says which edges it extended). The settings are raced: each runs first on a
  quarter of the episodes, and only those within 10 % of the best there run on the rest
  (:mod:`smcd_rl.tuning_search`); the others are listed as raced out;
* SMCD by :func:`smcd_rl.calibrate` (noise and flip probability; per-dimension noise, then a
  scalar noise at the flip probability chosen for it, the better kept);
* :class:`smcd_rl.BayesianLastLayer` over prior scale x drift x likelihood (Gaussian, or
  Student-t at two noise scales), raced, the prior scale extended past an edge
  (:data:`~smcd_rl.tuning_kinds.LAST_LAYER_GRID`);
* :class:`smcd_rl.SMCDLastLayer`: the tuned SMCD with the tuned last layer's readout at three
  prior scales around its best (it tunes both first);
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

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import torch
from tensordict import TensorDictBase

from smcd_rl.adaptation import SMCD, Adaptation
from smcd_rl.calibration import Calibration, _checked_flips
from smcd_rl.checks import check_count, check_real, check_seed
from smcd_rl.combination import Combination
from smcd_rl.criteria import Criterion, Score, checked_criterion
from smcd_rl.diagnostics import Trace
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.held_out import checked_model, pairs, stacked
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategy_specs import KINDS, build_strategy, describe_settings, on_device
from smcd_rl.tuning_advice import advice
from smcd_rl.tuning_kinds import (
    COMBINATION_GRID,
    EXTENSIBLE,
    GD_GRID,
    LAST_LAYER_GRID,
    MAX_EXTENSIONS,
    MIN_PARTICLES,
    checked_gd_grid,
    checked_gd_limits,
    tune_combination,
    tune_gd,
    tune_last_layer,
    tune_smcd,
    tune_smcd_last_layer,
)
from smcd_rl.tuning_search import Search, Timing, TuneCandidate, setting_key

__all__ = [
    "tune",
    "TuneResult",
    "TuneCandidate",
    "KINDS",
    "GD_GRID",
    "MAX_EXTENSIONS",
    "EXTENSIBLE",
    "COMBINATION_GRID",
    "LAST_LAYER_GRID",
    "MIN_PARTICLES",
    "build_strategy",
    "ms_per_observation",
    "describe_settings",
]


@dataclass
class TuneResult:
    """What :func:`tune` chose and every candidate it chose from (``print`` it for a table)."""

    #: ``"one-step"``, ``"evidence"`` (SMCD calibrated by its evidence; the kinds compared by one-step
    #: error), ``"lookahead"`` or ``"custom"`` (a score of your own, :attr:`score_label`).
    criterion: str
    #: The per-observation budget in milliseconds, or ``None``.
    budget_ms: float | None
    candidates: list[TuneCandidate]
    #: Kind -> its best candidate.
    best_of: dict[str, TuneCandidate]
    #: What the search did beyond its first grid (extended GD edges, halved particles).
    notes: list[str] = field(default_factory=list)
    episodes: int = 0
    steps: int = 0
    seconds: float = 0.0
    #: A digest of the model, the episodes and the seed: which results ``tune(..., reuse=...)`` may reuse.
    data: str = ""
    #: Every time per observation measured (ms), by setting: ``tune(..., reuse=...)`` takes them from here.
    timings: dict[str, float] = field(default_factory=dict)
    #: Every run on the episodes, step by step, by setting (this call's; not in :meth:`to_dict`).
    traces: dict[str, Trace] = field(default_factory=dict, repr=False, compare=False)
    #: Raced settings' runs on the first episodes, by setting (this call's; not in :meth:`to_dict`).
    heads: dict[str, tuple[Trace, Any]] = field(default_factory=dict, repr=False, compare=False)
    #: SMCD's calibrations by noise form, ``"per-dimension"`` and ``"scalar"`` (this call's; not in
    #: :meth:`to_dict`): ``calibrate(..., reuse=...)`` of the other criterion runs fewer filters from them.
    calibrations: dict[str, Calibration] = field(default_factory=dict, repr=False, compare=False)
    #: The steps ahead the criterion scores (1 for one-step and evidence).
    horizon: int = 1
    #: The name of the score the kinds are compared by (``"one-step RMSE"``, ``"10-step look-ahead RMSE"``...).
    score_label: str = "one-step RMSE"

    @property
    def best_kind(self) -> str:
        """The kind of lowest score (the first of :data:`KINDS` among equals)."""
        return min(self.best_of, key=lambda kind: (self.best_of[kind].score, KINDS.index(kind)))

    @property
    def best(self) -> Adaptation:
        """A fresh instance of the overall best strategy, ready for ``model.with_adaptation``."""
        return self.strategy(self.best_kind)

    @property
    def combination(self) -> Combination | None:
        """A fresh instance of the tuned combination, or ``None`` if none was tuned."""
        strategy = self.strategy("combination") if "combination" in self.best_of else None
        return strategy if isinstance(strategy, Combination) else None

    def trace(self, kind: str) -> Trace | None:
        """The run of the best strategy of ``kind`` on the tuning episodes, step by step (``None`` if not at hand).

        The same as :func:`smcd_rl.diagnostics.trace` of :meth:`strategy` on those episodes, for a
        strategy this call ran (a setting reused from an earlier call has none). A combination's
        holds its one-step errors only.
        """
        best = self.best_of.get(kind)
        return None if best is None else self.traces.get(setting_key(kind, best.settings))

    def strategy(self, kind: str, *, device: torch.device | str | None = None) -> Adaptation:
        """A fresh instance of the best strategy of ``kind``.

        ``device``: where SMCD's random generator lives (the model's device); default: where it
        was tuned. A tuning recorded on a GPU rebuilds on a CPU-only machine with ``device="cpu"``.
        """
        if kind not in self.best_of:
            raise KeyError(f"no {kind!r} was tuned; tuned: {sorted(self.best_of)}")
        settings = self.best_of[kind].settings
        return build_strategy(kind, settings if device is None else on_device(kind, settings, str(device)))

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> TuneResult:
        """Rebuild a result from its :meth:`to_dict` record, such as a loaded model's ``model.tuning``.

        Raises:
            ValueError: ``record`` is not a record of :meth:`to_dict` (another tuning procedure's).

        Example:
            >>> result = TuneResult("one-step", None, [TuneCandidate("none", {}, 0.5, 0.1)], {})
            >>> result.best_of["none"] = result.candidates[0]
            >>> TuneResult.from_dict(result.to_dict()).best_kind
            'none'
        """
        needed = ("criterion", "budget_ms", "best_of", "candidates")
        if not isinstance(record, Mapping) or any(key not in record for key in needed):
            raise ValueError(
                f"not a record of TuneResult.to_dict (it needs the entries {list(needed)}); a model's tuning holds "
                "one after smcd_rl.tune(model, ...)"
            )

        def candidate(entry: Mapping[str, Any]) -> TuneCandidate:
            # to_dict writes inf as None (JSON has no infinity).
            rmse, ms, score = entry["one_step_rmse"], entry["ms_per_step"], entry.get("score", math.nan)
            return TuneCandidate(
                entry["kind"],
                dict(entry["settings"]),
                math.inf if rmse is None else float(rmse),
                math.inf if ms is None else float(ms),
                entry.get("skipped", ""),
                math.inf if score is None else float(score),
            )

        return cls(
            criterion=record["criterion"],
            budget_ms=record["budget_ms"],
            candidates=[candidate(c) for c in record["candidates"]],
            best_of={kind: candidate(c) for kind, c in record["best_of"].items()},
            notes=list(record.get("notes", [])),
            episodes=int(record.get("episodes", 0)),
            steps=int(record.get("steps", 0)),
            seconds=float(record.get("seconds", 0.0)),
            data=str(record.get("data", "")),
            timings={k: math.inf if v is None else float(v) for k, v in record.get("timings", {}).items()},
            horizon=int(record.get("horizon", 1)),
            score_label=str(record.get("score_label", "one-step RMSE")),
        )

    def table(self) -> str:
        """The best of each kind: settings, score(s) and time per observation, then what to use."""
        ahead = self.criterion in ("lookahead", "custom")
        by = self.score_label if ahead else self.criterion
        lines = [
            f"tuned by {by} on {self.episodes} episodes x {self.steps} steps"
            + (f", budget {self.budget_ms:g} ms per observation" if self.budget_ms is not None else ""),
            "",
            "| strategy | settings | one-step RMSE |"
            + (f" {self.score_label} |" if ahead else "")
            + " ms / observation |",
            "|---|---|---|" + ("---|" if ahead else "") + "---|",
        ]
        for kind in KINDS:
            if kind in self.best_of:
                c = self.best_of[kind]
                mark = " (best)" if kind == self.best_kind else ""
                score = f" {c.score:.4g} |" if ahead else ""
                lines.append(
                    f"| {kind}{mark} | {describe_settings(c.settings)} | {c.one_step_rmse:.4g} |{score} {c.ms_per_step:.3g} |"
                )
        return "\n".join(lines + ["", *self.notes, *([""] if self.notes else []), *advice(self)])

    def __str__(self) -> str:
        return self.table()

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready record (what ``model.tuning`` holds; an infinite score or time is ``None``)."""
        return _json_numbers(
            {
                "criterion": self.criterion,
                "horizon": self.horizon,
                "score_label": self.score_label,
                "budget_ms": self.budget_ms,
                "best_kind": self.best_kind,
                "best_of": {kind: asdict(c) for kind, c in self.best_of.items()},
                "candidates": [asdict(c) for c in self.candidates],
                "notes": list(self.notes),
                "episodes": self.episodes,
                "steps": self.steps,
                "seconds": self.seconds,
                "data": self.data,
                "timings": dict(self.timings),
            }
        )


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
    flip_probs: Sequence[float] = (0.001, 0.003, 0.01, 0.03),
    seed: int = 0,
    progress: bool = True,
    reuse: TuneResult | None = None,
) -> TuneResult:
    """Tune each of ``strategies`` on held-out training-task ``episodes`` by one criterion (see the module doc).

    Args:
        model: a fitted model; its network is not changed.
        episodes: batch ``[E, T]`` in the model's keys (or a list of ``[T]``): held-out episodes
            of the *training* tasks, at least 2 of 2 steps.
        strategies: which of :data:`KINDS` to tune; ``"smcd_last_layer"`` starts from the tuned
            SMCD and last layer (tuned too); ``"combination"`` mixes the others tuned with no
            adaptation (tuned too, at no cost), so it needs another strategy that adapts.
        criterion: what every setting is scored by (:mod:`smcd_rl.criteria`): ``"one-step"``
            (default), ``"lookahead"`` (the RMSE ``horizon`` steps ahead, open loop: score what
            your planner or table scores), or a callable ``score(predicted, observed) -> float``
            of your own; ``"evidence"`` calibrates SMCD by its evidence and compares the kinds by
            one-step error.
        horizon: the steps ahead of ``"lookahead"`` or of your score (episodes must be longer).
        budget_ms: skip settings whose median time per observation exceeds this (``None``: no budget).
        num_particles: SMCD's particles (halved while over budget, down to 8).
        gd_grid: gradient descent's starting grid, ``{"lr": ..., "steps": ..., "window": ...,
            "loss": ...}``; a key left out takes its values from :data:`GD_GRID` (so a grid
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
        reuse: an earlier result of this function on the same model, episodes, seed, flip
            probabilities and criterion (e.g. the unbudgeted one, before a call with ``budget_ms``): each setting
            it scored takes its score from there, and each setting it timed its time, instead of running again.

    Returns:
        The :class:`TuneResult`, also stored as ``model.tuning`` (its :meth:`~TuneResult.to_dict`).
        Nothing else of the model changes: its calibration is :func:`smcd_rl.calibrate`'s alone, so
        ``tune`` and ``calibrate`` on one model from two threads each keep their own record (their
        runs only read the network).

    Raises:
        ValueError: an unknown strategy or criterion, a horizon the criterion does not take or
            episodes no longer than it, a budget that is not positive, no strategy
            within the budget, episodes :func:`smcd_rl.calibrate` refuses, or a ``reuse`` of
            another model, other episodes, another seed or another criterion.
    """
    started = time.perf_counter()
    model = checked_model(model)
    unknown = [s for s in strategies if s not in KINDS]
    if unknown or not strategies:
        raise ValueError(f"strategies: unknown {unknown}; choose one or more of {list(KINDS)}")
    chosen_by = checked_criterion(criterion, horizon)
    if "combination" in strategies and not set(_ADAPTING) & set(strategies):
        raise ValueError(
            "strategies: a 'combination' mixes the other strategies tuned (and no adaptation); add one or more "
            f"of {list(_ADAPTING)}, e.g. strategies=['gradient_descent', 'smcd', 'combination']"
        )
    if budget_ms is not None:
        budget_ms = check_real(budget_ms, "budget_ms", low=0.0, open_low=True)
    seed = check_seed(seed)
    num_particles = check_count(num_particles, "num_particles")
    grid = checked_gd_grid(gd_grid)
    limits = checked_gd_limits(gd_limits, grid)
    td = stacked(episodes)
    x, y = pairs(model, td)  # checks keys, shapes and values before any run
    flips = _checked_flips(flip_probs, model, SMCD(num_particles=num_particles))  # calibrate's own check
    data = content_digest({"model": model_digest(model), "episodes": content_digest(td), "seed": seed, "flips": flips})
    known = _reusable(reuse, data, chosen_by)
    timing = Timing(model, x[0], y[0], budget_ms, known=None if reuse is None else reuse.timings)
    search = Search(
        model, td, timing, progress, known, heads=None if reuse is None else reuse.heads, criterion=chosen_by
    )
    # A combination mixes no adaptation too, which costs nothing to tune; SMCD with a Bayesian
    # readout starts from the tuned SMCD and last layer.
    needed = {*strategies, *(("none",) if "combination" in strategies else ())}
    needed |= {"smcd", "last_layer"} if "smcd_last_layer" in strategies else set()
    kinds = [k for k in KINDS if k in needed]
    calibrations: dict[str, Calibration] = {}
    try:
        if "none" in kinds:
            search.score("none", {})
        if "gradient_descent" in kinds:
            tune_gd(search, grid, limits)
        if "smcd" in kinds:
            calibrations = tune_smcd(search, num_particles, chosen_by, tuple(flips), seed, progress)
        if "last_layer" in kinds:
            tune_last_layer(search)
        if "smcd_last_layer" in kinds:
            tune_smcd_last_layer(search)
        if "combination" in kinds:
            tune_combination(search, [k for k in ("none", *_ADAPTING) if k in search.best_of])
        for kind in kinds:
            search.time_best(kind)
    finally:
        search.bar.close()
    if not search.best_of:
        raise ValueError(f"no strategy fits a budget of {budget_ms:g} ms per observation; raise budget_ms")
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
    )
    model.tuning = result.to_dict()
    return result


#: The kinds that adapt: what a combination mixes (with no adaptation).
_ADAPTING = ("gradient_descent", "smcd", "last_layer", "smcd_last_layer")


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
    x, y = pairs(model, episode.unsqueeze(0))
    return Timing(model, x[0], y[0], None).ms_per_step(strategy)


def _json_numbers(value: Any) -> Any:
    """``value`` with every float that JSON cannot hold (inf, NaN) as ``None``."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_numbers(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_numbers(v) for v in value]
    return value
