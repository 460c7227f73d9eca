"""The fair protocol as one call: every adaptation strategy tuned by one criterion, under one budget.

:func:`tune` takes a fitted model and held-out episodes of its *training* tasks (never the tasks
it will be scored on; :func:`smcd_rl.episodes` cuts them from collected transitions) and tunes
each requested strategy on them by the same criterion, the **one-step prediction error** (the
error of predicting each step from the steps before it, what a planner or controller uses):

* gradient descent over a grid of learning rate x steps x window x loss (squared error and
  Huber, which bounds the pull of an outlier) that goes on past an edge of the learning rate,
  steps or window, along that dimension through the best point, while the best point lies there
  (the result says which edges it extended);
* SMCD by :func:`smcd_rl.calibrate` (noise and flip probability; scalar and per-dimension noise,
  the better kept);
* :class:`smcd_rl.Combination` of the best members, its ``eta`` and ``share`` chosen on the same
  episodes.

With ``budget_ms`` each setting's median wall time per observation (one stream, observe and
predict) is measured first, and settings over the budget are skipped (SMCD halves its particles
until it fits). The result lists every candidate with its score and time, the best of each kind,
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
    (['combination', 'gradient_descent', 'none', 'smcd'], True)
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from itertools import product
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from torch import Tensor
from tqdm.auto import tqdm

from smcd_rl.adaptation import SMCD, Adaptation, GradientDescent, NoAdaptation
from smcd_rl.calibration import _checked_flips, calibrate
from smcd_rl.checks import check_count, check_real, check_seed
from smcd_rl.combination import Combination, mixed_log_weights
from smcd_rl.diagnostics import Trace, trace_pairs
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.held_out import checked_model, pairs, stacked
from smcd_rl.model import AdaptiveModel

__all__ = ["tune", "TuneResult", "TuneCandidate", "KINDS", "build_strategy", "ms_per_observation", "describe_settings"]

#: The strategies :func:`tune` knows, in the order it tunes them (a combination needs the others).
KINDS = ("none", "gradient_descent", "smcd", "combination")
#: Gradient descent's starting grid: learning rate x steps per observation x window x loss
#: (:class:`smcd_rl.GradientDescent`'s ``loss``; this dimension is never extended).
GD_GRID: dict[str, tuple[Any, ...]] = {
    "lr": (1e-3, 1e-2, 1e-1),
    "steps": (1, 5),
    "window": (1, 10),
    "loss": ("mse", "huber"),
}
#: At most this many extensions past each edge of the GD grid.
MAX_EXTENSIONS = 3
#: The dimensions of the GD grid that extend past their edges.
EXTENSIBLE = ("lr", "steps", "window")
#: The combination's grid: the weights' learning rate and the fixed share.
COMBINATION_GRID = {"eta": (0.1, 1.0, 10.0, 100.0), "share": (0.0, 0.02)}
#: SMCD never halves its particles below this to meet a budget.
MIN_PARTICLES = 8


@dataclass(frozen=True)
class TuneCandidate:
    """One setting :func:`tune` tried: what it is, how well it predicted, how long a step took."""

    #: One of :data:`KINDS`.
    kind: str
    #: The strategy's settings (its ``config()``; a combination's members by name).
    settings: dict[str, Any]
    #: The one-step RMSE (target units) on the episodes; ``inf`` if skipped or refused.
    one_step_rmse: float
    #: Median wall milliseconds of one observation (observe and predict, one stream).
    ms_per_step: float
    #: Why it was not scored (``"over budget"``), or empty.
    skipped: str = ""


@dataclass
class TuneResult:
    """What :func:`tune` chose and every candidate it chose from (``print`` it for a table)."""

    #: ``"one-step"`` or ``"evidence"`` (SMCD's calibration; kinds are always compared by one-step error).
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

    @property
    def best_kind(self) -> str:
        """The kind of lowest one-step error (the first of :data:`KINDS` among equals)."""
        return min(self.best_of, key=lambda kind: (self.best_of[kind].one_step_rmse, KINDS.index(kind)))

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
        return None if best is None else self.traces.get(_key(kind, best.settings))

    def strategy(self, kind: str, *, device: torch.device | str | None = None) -> Adaptation:
        """A fresh instance of the best strategy of ``kind``.

        ``device``: where SMCD's random generator lives (the model's device); default: where it
        was tuned. A tuning recorded on a GPU rebuilds on a CPU-only machine with ``device="cpu"``.
        """
        if kind not in self.best_of:
            raise KeyError(f"no {kind!r} was tuned; tuned: {sorted(self.best_of)}")
        settings = self.best_of[kind].settings
        return build_strategy(kind, settings if device is None else _on_device(kind, settings, str(device)))

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
            rmse, ms = entry["one_step_rmse"], entry["ms_per_step"]
            return TuneCandidate(
                entry["kind"],
                dict(entry["settings"]),
                math.inf if rmse is None else float(rmse),
                math.inf if ms is None else float(ms),
                entry.get("skipped", ""),
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
        )

    def table(self) -> str:
        """The best of each kind: settings, one-step RMSE and time per observation."""
        lines = [
            f"tuned by {self.criterion} on {self.episodes} episodes x {self.steps} steps"
            + (f", budget {self.budget_ms:g} ms per observation" if self.budget_ms is not None else ""),
            "",
            "| strategy | settings | one-step RMSE | ms / observation |",
            "|---|---|---|---|",
        ]
        for kind in KINDS:
            if kind in self.best_of:
                c = self.best_of[kind]
                mark = " (best)" if kind == self.best_kind else ""
                lines.append(
                    f"| {kind}{mark} | {describe_settings(c.settings)} | {c.one_step_rmse:.4g} | {c.ms_per_step:.3g} |"
                )
        return "\n".join(lines + ["", *self.notes])

    def __str__(self) -> str:
        return self.table()

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready record (what ``model.tuning`` holds; an infinite score or time is ``None``)."""
        return _json_numbers(
            {
                "criterion": self.criterion,
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
    criterion: Literal["one-step", "evidence"] = "one-step",
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
        strategies: which of :data:`KINDS` to tune; ``"combination"`` mixes the others tuned
            with no adaptation (tuned too, at no cost), so it needs ``"gradient_descent"`` or ``"smcd"``.
        criterion: how SMCD's noise and flip are chosen: ``"one-step"`` (default) or the
            filter's ``"evidence"``. The kinds are compared by one-step error either way.
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

    Raises:
        ValueError: an unknown strategy or criterion, a budget that is not positive, no strategy
            within the budget, episodes :func:`smcd_rl.calibrate` refuses, or a ``reuse`` of
            another model, other episodes, another seed or another criterion.
    """
    started = time.perf_counter()
    model = checked_model(model)
    unknown = [s for s in strategies if s not in KINDS]
    if unknown or not strategies:
        raise ValueError(f"strategies: unknown {unknown}; choose one or more of {list(KINDS)}")
    if criterion not in ("one-step", "evidence"):
        raise ValueError(f"criterion must be 'one-step' or 'evidence', got {criterion!r}")
    if "combination" in strategies and not {"gradient_descent", "smcd"} & set(strategies):
        raise ValueError(
            "strategies: a 'combination' mixes the other strategies tuned (and no adaptation); add "
            "'gradient_descent' and/or 'smcd', e.g. strategies=['gradient_descent', 'smcd', 'combination']"
        )
    if budget_ms is not None:
        budget_ms = check_real(budget_ms, "budget_ms", low=0.0, open_low=True)
    seed = check_seed(seed)
    num_particles = check_count(num_particles, "num_particles")
    grid = _checked_gd_grid(gd_grid)
    limits = _checked_gd_limits(gd_limits, grid)
    td = stacked(episodes)
    x, y = pairs(model, td)  # checks keys, shapes and values before any run
    flips = _checked_flips(flip_probs, model, SMCD(num_particles=num_particles))  # calibrate's own check
    data = content_digest({"model": model_digest(model), "episodes": content_digest(td), "seed": seed, "flips": flips})
    known = _reusable(reuse, data, criterion)
    timing = _Timing(model, x[0], y[0], budget_ms, known=None if reuse is None else reuse.timings)
    search = _Search(model, td, timing, progress, known)
    # A combination mixes no adaptation too, which costs nothing to tune.
    kinds = [k for k in KINDS if k in strategies or (k == "none" and "combination" in strategies)]
    try:
        if "none" in kinds:
            search.score("none", {})
        if "gradient_descent" in kinds:
            _tune_gd(search, grid, limits)
        if "smcd" in kinds:
            _tune_smcd(search, model, td, num_particles, criterion, tuple(flips), seed, progress)
        if "combination" in kinds:
            _tune_combination(search, [k for k in ("none", "gradient_descent", "smcd") if k in search.best_of])
    finally:
        search.bar.close()
    if not search.best_of:
        raise ValueError(f"no strategy fits a budget of {budget_ms:g} ms per observation; raise budget_ms")
    result = TuneResult(
        criterion=criterion,
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
    )
    model.tuning = result.to_dict()
    return result


def _reusable(reuse: TuneResult | None, data: str, criterion: str) -> dict[str, TuneCandidate]:
    """The scored candidates of ``reuse`` by :func:`_key`, after checking it was tuned on the same data."""
    if reuse is None:
        return {}
    if not isinstance(reuse, TuneResult):
        raise TypeError(f"reuse must be a TuneResult of an earlier tune call, got {type(reuse).__name__}")
    if reuse.data != data or reuse.criterion != criterion:
        raise ValueError(
            "reuse holds a result for another model, other episodes, another seed or another criterion; "
            "pass the result of a tune call on the same ones, or none"
        )
    return {_key(c.kind, c.settings): c for c in reuse.candidates if not c.skipped}


def _key(kind: str, settings: dict[str, Any]) -> str:
    return json.dumps([kind, settings], sort_keys=True, default=str)


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
    return _Timing(model, x[0], y[0], None).ms_per_step(strategy)


class _Timing:
    """Median wall milliseconds per observation of a strategy on one stream (one held-out episode).

    Every time measured is kept in :attr:`times`, by setting, and measured once: a setting met
    again, or given by an earlier call (``known``), takes its time from there, so that the
    settings that fit a budget, and the choice among them, repeat.
    """

    def __init__(
        self,
        model: AdaptiveModel,
        x: torch.Tensor,
        y: torch.Tensor,
        budget_ms: float | None,
        known: Mapping[str, float] | None = None,
    ) -> None:
        self.model, self.x, self.y, self.budget_ms = model, x, y, budget_ms
        self.times: dict[str, float] = dict(known or {})

    def ms(self, kind: str, settings: dict[str, Any]) -> float:
        """The time per observation of ``kind`` with ``settings``, measured the first time it is asked for."""
        key = _key(kind, settings)
        if key not in self.times:
            self.times[key] = self.ms_per_step(build_strategy(kind, settings))
        return self.times[key]

    def ms_per_step(self, strategy: Adaptation) -> float:
        self.model.with_adaptation(strategy).reset(batch_shape=(1,))
        times = []
        with torch.no_grad():
            for t in range(self.x.shape[0]):
                started = time.perf_counter()
                strategy.predict(self.x[t : t + 1])
                try:
                    strategy.observe(self.x[t : t + 1], self.y[t : t + 1])
                except ValueError:
                    break
                times.append(time.perf_counter() - started)
        return 1000 * statistics.median(times) if times else math.inf

    def over(self, ms: float) -> bool:
        return self.budget_ms is not None and ms > self.budget_ms


class _Search:
    """The candidates so far and the best of each kind."""

    def __init__(
        self,
        model: AdaptiveModel,
        td: TensorDictBase,
        timing: _Timing,
        progress: bool,
        known: dict[str, TuneCandidate] | None = None,
    ) -> None:
        self.model, self.td, self.timing = model, td, timing
        self.x, self.y = pairs(model, td)
        self.known = known or {}  # scored by an earlier call on the same data: not run again
        self.candidates: list[TuneCandidate] = []
        self.best_of: dict[str, TuneCandidate] = {}
        self.notes: list[str] = []
        #: Every run on the episodes, by setting, and its normalised predictions ``[E, T, out]``
        #: where it ran to the end: what the combination and the diagnosis take instead of running again.
        self.traces: dict[str, Trace] = {}
        self.predictions: dict[str, Tensor] = {}
        self.bar = tqdm(desc="tune", unit="setting", disable=not progress)

    def run(self, kind: str, settings: dict[str, Any]) -> Trace:
        """The trace of ``kind`` with ``settings`` on the episodes, run the first time it is asked for."""
        key = _key(kind, settings)
        if key not in self.traces:
            self._record(kind, settings)
        return self.traces[key]

    def recorded(self, kind: str, settings: dict[str, Any]) -> Tensor | None:
        """The setting's normalised predictions ``[E, T, out]``, run again only if no run recorded them
        (``None``: it refused an observation)."""
        key = _key(kind, settings)
        if key not in self.predictions and math.isfinite(self.run(kind, settings).rmse):
            self._record(kind, settings)  # a run given from elsewhere (a calibration's) kept no predictions
        return self.predictions.get(key)

    def _record(self, kind: str, settings: dict[str, Any]) -> None:
        key = _key(kind, settings)
        predictions: list[Tensor] = []
        run = trace_pairs(self.model, self.x, self.y, build_strategy(kind, settings), predictions=predictions)
        self.traces.setdefault(key, run)
        if math.isfinite(run.rmse):
            self.predictions[key] = torch.stack(predictions, dim=1)

    def score(
        self,
        kind: str,
        settings: dict[str, Any],
        *,
        ms: float | None = None,
        rmse: float | None = None,
        run: Trace | None = None,
    ) -> float:
        """Measure one setting: time first, then one-step error unless over budget.

        ``run``: the setting's trace if it ran already (a calibration's); ``rmse``: its error where it
        is known without a trace of its own.
        """
        earlier = self.known.get(_key(kind, settings))
        if ms is not None:  # a time measured for it otherwise (SMCD's particle probe, a combination's members)
            self.timing.times.setdefault(_key(kind, settings), ms)
        ms = self.timing.ms(kind, settings)
        if self.timing.over(ms):
            self.candidates.append(TuneCandidate(kind, settings, math.inf, ms, "over budget"))
            return math.inf
        if earlier is not None:
            rmse = earlier.one_step_rmse
        elif rmse is None:
            if run is not None:
                self.traces.setdefault(_key(kind, settings), run)
            rmse = self.run(kind, settings).rmse
        candidate = TuneCandidate(kind, settings, rmse, ms)
        self.candidates.append(candidate)
        if math.isfinite(rmse) and (kind not in self.best_of or rmse < self.best_of[kind].one_step_rmse):
            self.best_of[kind] = candidate
        self.bar.update(1)
        self.bar.set_postfix(kind=kind, rmse=f"{rmse:.4g}")
        return rmse


def _checked_gd_grid(gd_grid: Mapping[str, Sequence[Any]] | None) -> dict[str, tuple[Any, ...]]:
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


def _checked_gd_limits(
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


def _tune_gd(search: _Search, grid: dict[str, tuple[Any, ...]], limits: dict[str, tuple[float, float]]) -> None:
    """Score the grid; while the best point lies on an edge, go on past that edge along that dimension.

    Past an edge only the line through the best point is scored (the new value with the other
    settings at their best), not the whole grid again: each extension costs one setting per loss
    at most, and steps and window double the cost of a setting with each extension. The loss is
    a dimension of the grid but has no edge: the search tries each loss given and extends only the
    learning rate, steps and window, never past ``limits``.
    """
    # The losses keep GradientDescent.LOSSES' order, so that among equal errors the squared one wins.
    grid = {k: tuple(sorted(v)) for k, v in grid.items() if k != "loss"} | {
        "loss": tuple(loss for loss in GradientDescent.LOSSES if loss in grid["loss"])
    }
    scored: dict[tuple[Any, ...], float] = {}

    def score(lr: float, steps: int, window: int, loss: Any) -> None:  # loss: one of GradientDescent.LOSSES
        if (lr, steps, window, loss) not in scored:
            strategy = GradientDescent(lr=lr, steps=steps, window=window, loss=loss)
            scored[(lr, steps, window, loss)] = search.score("gradient_descent", strategy.config())

    for point in product(grid["lr"], grid["steps"], grid["window"], grid["loss"]):
        score(*point)
    extensions = {("lr", "low"): 0, ("lr", "high"): 0, ("steps", "high"): 0, ("window", "high"): 0}
    while True:
        finite = {k: v for k, v in scored.items() if math.isfinite(v)}
        if not finite:
            search.notes.append(
                f"gradient descent: every one of its {len(scored)} settings diverged or was over the budget, so none "
                "is kept; try smaller learning rates (gd_grid['lr'])"
            )
            return
        point = min(finite.items(), key=lambda item: item[1])[0]
        best = dict(zip(("lr", "steps", "window", "loss"), point, strict=True))
        edge = _edge(grid, best, extensions, limits)
        if edge is None:
            search.notes.extend(
                f"gradient descent: best {name} {best[name]:g} on the grid's {side} edge, at gd_limits"
                for name, side in extensions
                if _on_edge(grid[name], best[name], side) and not _within(limits[name], _past(grid[name], name, side))
            )
            return
        name, side = edge
        extensions[edge] += 1
        new = _past(grid[name], name, side)
        grid[name] = tuple(sorted({*grid[name], new}))
        for loss in grid["loss"]:
            score(**{**best, name: new, "loss": loss})
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


def _tune_smcd(
    search: _Search,
    model: AdaptiveModel,
    td: TensorDictBase,
    num_particles: int,
    criterion: Literal["one-step", "evidence"],
    flip_probs: tuple[float, ...],
    seed: int,
    progress: bool,
) -> None:
    """Halve the particles until a step fits the budget, then calibrate (both noise forms) by ``criterion``."""
    particles = num_particles
    while True:
        ms = search.timing.ms("smcd", {"num_particles": particles, "noise_std": 1.0, "flip_prob": 0.01})
        if not search.timing.over(ms) or particles // 2 < MIN_PARTICLES:
            break
        particles //= 2
    if search.timing.over(ms):
        search.notes.append(
            f"SMCD: over the budget even with {particles} particles ({ms:.3g} ms per observation), so not tuned"
        )
        search.candidates.append(TuneCandidate("smcd", {"num_particles": particles}, math.inf, ms, "over budget"))
        return
    if particles != num_particles:
        search.notes.append(f"SMCD: {particles} particles instead of {num_particles}, to fit the budget")
    known = [c for c in search.known.values() if c.kind == "smcd" and c.settings.get("num_particles") == particles]
    if known:  # an earlier call calibrated these particles on the same data: its two choices stand
        for candidate in known:
            search.score("smcd", candidate.settings)
        return
    saved = model.calibration
    try:
        for per_dimension in (True, False):
            result = calibrate(
                model,
                td,
                base=SMCD(num_particles=particles),
                flip_probs=flip_probs,
                per_dimension=per_dimension,
                criterion=criterion,
                seed=seed,
                progress=progress,
            )
            settings = {**result.strategy.config(), "seed": seed, "device": str(_device(model))}
            search.score("smcd", settings, ms=ms, run=result.best.trace)
    finally:
        model.calibration = saved  # tune's record is model.tuning; calibrate's own stays as it was


def _tune_combination(search: _Search, kinds: list[str]) -> None:
    """Score the combination grid of the best members, from one run of each member.

    The members run on the same stream whatever the weights, so their one-step predictions are
    recorded once and every ``(eta, share)`` is scored from them (``_combination_rmse``), the
    same error :func:`smcd_rl.diagnostics.trace` gives a :class:`~smcd_rl.combination.Combination`,
    at the cost of one combination run instead of one per grid point.
    """
    if len(kinds) < 2:
        return
    members: list[dict[str, Any]] = [{"name": kind, "settings": search.best_of[kind].settings} for kind in kinds]
    ms = sum(search.best_of[kind].ms_per_step for kind in kinds)
    grid = list(product(COMBINATION_GRID["eta"], COMBINATION_GRID["share"]))
    settings = [{"members": members, "eta": eta, "share": share} for eta, share in grid]
    if all(_key("combination", s) in search.known for s in settings) or search.timing.over(ms):
        for one in settings:  # reused from an earlier call, or over the budget: nothing to run
            search.score("combination", one, ms=ms)
        return
    recorded = _member_predictions(search, members)
    for (eta, share), one in zip(grid, settings, strict=True):
        if recorded is None:
            search.score("combination", one, ms=ms, rmse=math.inf)
            continue
        search.score("combination", one, ms=ms, run=_combination_trace(search.model, recorded, search.y, eta, share))


def _member_predictions(search: _Search, members: list[dict[str, Any]]) -> Tensor | None:
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


def _combination_trace(model: AdaptiveModel, predictions: Tensor, targets: Tensor, eta: float, share: float) -> Trace:
    """The trace (one-step errors only) of a combination, from its members' recorded predictions.

    ``predictions [E, T, out, K]`` are the members' normalised one-step predictions, each made
    before its step was observed, ``targets [E, T, out]`` the normalised observations. The weights
    follow :class:`~smcd_rl.combination.Combination` operation for operation, and the errors are
    accumulated as :func:`smcd_rl.diagnostics.trace` accumulates them.
    """
    num_episodes, steps, outputs, count = predictions.shape
    log_weights = predictions.new_full((num_episodes, count), -math.log(count), dtype=torch.float64)
    output_std = model.output_norm.std.to(torch.float64)
    result = Trace([], math.inf, [], [], [], [], [[] for _ in range(num_episodes)])
    squared = 0.0
    episode_squared = torch.zeros(num_episodes, dtype=torch.float64)
    for t in range(steps):
        members = predictions[:, t]
        if t > 0:
            combined = (members * log_weights.exp().to(members.dtype).reshape(num_episodes, 1, count)).sum(-1)
            error = (combined - targets[:, t]).to(torch.float64) * output_std
            step_squared = float(error.square().sum())
            squared += step_squared
            result.one_step_rmse.append(math.sqrt(step_squared / (num_episodes * outputs)))
            per_episode = error.square().sum(-1).cpu()
            episode_squared += per_episode
            for errors, value in zip(result.one_step_errors, per_episode.tolist(), strict=True):
                errors.append(math.sqrt(value / outputs))
        step = (members - targets[:, t].unsqueeze(-1)).square().sum(-2)
        log_weights = mixed_log_weights(log_weights - eta * step.to(torch.float64), share)
    result.rmse = math.sqrt(squared / (num_episodes * (steps - 1) * outputs))
    result.per_episode_rmse = [math.sqrt(v / ((steps - 1) * outputs)) for v in episode_squared.tolist()]
    return result


def build_strategy(kind: str, settings: dict[str, Any]) -> Adaptation:
    """A fresh strategy of ``kind`` (one of :data:`KINDS`) with a candidate's ``settings``.

    SMCD's ``seed`` becomes its generator, so the strategy repeats the tuned run's filter.

    Example:
        >>> build_strategy("gradient_descent", {"lr": 0.1, "steps": 2, "window": 5}).config()["lr"]
        0.1
    """
    if kind not in KINDS:
        raise ValueError(f"unknown strategy kind {kind!r}; choose one of {list(KINDS)}")
    builders: dict[str, Callable[..., Adaptation]] = {
        "none": NoAdaptation,
        "gradient_descent": GradientDescent,
        "smcd": _smcd,
        "combination": _combination,
    }
    return builders[kind](**settings)


def _smcd(seed: int = 0, device: str = "cpu", **settings: Any) -> SMCD:
    kind = torch.device(device).type
    if kind != "cpu" and not getattr(torch, kind).is_available():
        raise ValueError(
            f"this SMCD was tuned on {device}, which this machine does not have; rebuild it for the model's "
            f"device, e.g. result.strategy('smcd', device='cpu')"
        )
    return SMCD(**settings, generator=torch.Generator(device=device).manual_seed(seed))


def _on_device(kind: str, settings: dict[str, Any], device: str) -> dict[str, Any]:
    """``settings`` with every SMCD's generator on ``device`` (a combination's members too)."""
    if kind == "smcd":
        return {**settings, "device": device}
    if kind == "combination":
        members = [{**m, "settings": _on_device(m["name"], m["settings"], device)} for m in settings["members"]]
        return {**settings, "members": members}
    return settings


def _json_numbers(value: Any) -> Any:
    """``value`` with every float that JSON cannot hold (inf, NaN) as ``None``."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_numbers(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_numbers(v) for v in value]
    return value


def _device(model: AdaptiveModel) -> torch.device:
    return next(model.net.parameters()).device


def _combination(members: list[dict[str, Any]], eta: float, share: float) -> Combination:
    return Combination([build_strategy(m["name"], m["settings"]) for m in members], eta=eta, share=share)


def describe_settings(settings: dict[str, Any]) -> str:
    """A candidate's settings in a few words, as :meth:`TuneResult.table` shows them.

    What :func:`tune` searches is always shown (SMCD's particles, flip probability and noise;
    gradient descent's learning rate, steps and window); any other setting only where it differs
    from its default, so a row says what was chosen, not the strategy's whole config.

    Example:
        >>> describe_settings({"lr": 0.1, "steps": 5, "window": 10, "loss": "mse", "huber_delta": 1.0})
        'lr 0.1, steps 5, window 10'
        >>> describe_settings({**SMCD(num_particles=500, noise_std=[0.0134, 0.01325]).config(), "seed": 3})
        'num_particles 500, flip_prob 0.01, noise_std [0.0134, 0.0132]'
    """
    if "members" in settings:
        return f"{' + '.join(m['name'] for m in settings['members'])}, eta {settings['eta']:g}, share {settings['share']:g}"
    searched = ("num_particles", "flip_prob", "noise_std", "lr", "steps", "window")
    defaults = _DEFAULTS["smcd" if "num_particles" in settings else "gradient_descent"]
    shown = {
        k: v
        for k, v in settings.items()
        if k not in ("seed", "device") and (k in searched or defaults.get(k, _UNSET) != v)
    }
    if shown.get("loss", "mse") == "mse":  # the squared error's Huber delta is unused
        shown.pop("huber_delta", None)
    parts = []
    for k, v in shown.items():
        if isinstance(v, (list, tuple)) and len(v) > 3:
            v = f"rms {math.sqrt(sum(float(u) ** 2 for u in v) / len(v)):.3g} ({len(v)} dims)"
        elif isinstance(v, (list, tuple)):
            v = "[" + ", ".join(f"{float(u):.3g}" for u in v) + "]"
        parts.append(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}")
    return ", ".join(parts) or "-"


#: Each kind's default settings: :func:`describe_settings` leaves out what equals them.
_DEFAULTS: dict[str, dict[str, Any]] = {"smcd": SMCD().config(), "gradient_descent": GradientDescent().config()}
_UNSET = object()
