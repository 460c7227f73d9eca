"""The bookkeeping of :func:`smcd_rl.tune`: each setting's score, run and time, and the race that spares work.

Every setting is scored on the tuning episodes by the tuning's criterion (:mod:`smcd_rl.tuning.criteria`:
the one-step RMSE, the look-ahead RMSE or a score of your own) from its run
(:func:`smcd_rl.tuning.diagnostics.trace`, with the open-loop predictions where the criterion looks ahead).
A :class:`Search` keeps each run (its trace and predictions), so that a setting is never run
twice and the combination and the experiments' diagnosis take the runs as they are.

**Racing.** Settings whose runs are independent per episode (no adaptation, gradient descent: no
random numbers) are raced: every setting of a batch runs first on :data:`~smcd_rl.tuning.defaults.RACE_SHARE` of the
episodes, and only those within :data:`~smcd_rl.tuning.defaults.RACE_MARGIN` of the best on those episodes run on the
rest. The others are dropped, by their error alone, and listed as raced out. A setting that runs
on would give the same run in one batch: each episode's run depends on that episode only.

**Times.** Under a budget every setting's time per observation is measured before it runs, and
one over the budget is skipped; without a budget only the best of each kind is timed, once its
kind is tuned. Times are kept per setting: a setting met again, or given by an earlier call,
keeps its time, so that the settings that fit a budget, and the choice among them, repeat.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> _ = torch.manual_seed(0)
    >>> q = torch.rand(80, 2)
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    >>> _ = smcd_rl.fit(model, TensorDict({"q": q, "ee": q.cos()}, [80]), epochs=2, progress=False)
    >>> episodes = TensorDict({"q": q.reshape(8, 10, 2), "ee": q.cos().reshape(8, 10, 2) + 0.1}, [8, 10])
    >>> result = smcd_rl.tune(model, episodes, strategies=["gradient_descent"], progress=False)
    >>> raced_out = [c for c in result.candidates if c.skipped.startswith("raced out")]
    >>> len(raced_out) > 0  # settings far behind on the first quarter of the episodes ran no further
    True
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.registry import build
from smcd_rl.tuning.defaults import RACE_MARGIN, RACE_SHARE, ROBUST_MARGIN
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.scoring import Scorer

__all__ = ["TuneCandidate", "Timing", "Search", "setting_key", "usable", "within", "race_threshold"]


@dataclass(frozen=True)
class TuneCandidate:
    """One setting :func:`smcd_rl.tune` tried: what it is, how well it predicted, how long a step took."""

    #: One of :data:`~smcd_rl.strategies.registry.KINDS`.
    kind: str
    #: The strategy's settings (its ``config()``; a combination's members by name).
    settings: dict[str, Any]
    #: The one-step RMSE (target units) on the episodes; ``inf`` if skipped, raced out or refused.
    one_step_rmse: float
    #: Median wall milliseconds of one observation (observe and predict, one stream); ``nan``
    #: where not measured (without a budget only the best of each kind is timed).
    ms_per_step: float
    #: Why it was not scored on every episode (``"over budget"``, ``"raced out: ..."``), or empty.
    skipped: str = ""
    #: The tuning criterion's score (lower is better; the one-step RMSE unless the criterion looks
    #: ahead or is your own): what the choice is made by.
    score: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.score):  # scored by its one-step error (or a record from before scores)
            object.__setattr__(self, "score", self.one_step_rmse)


def usable(score: float) -> bool:
    """Whether a score can be chosen: not NaN and not ``inf`` (``-inf``, the best possible, can).

    Example:
        >>> usable(-math.inf), usable(math.inf), usable(math.nan), usable(0.3)
        (True, False, False, True)
    """
    return not math.isnan(score) and score != math.inf


def within(best: float, margin: float) -> float:
    """The highest score within ``margin`` of ``best``, relative to its size (a score of your own may be
    negative; an infinite ``best`` is its own bound).

    Example:
        >>> within(2.0, 0.1), within(-2.0, 0.1), within(-math.inf, 0.1)
        (2.2, -1.8, -inf)
    """
    if math.isinf(best):
        return best
    return (1 + margin) * best if best >= 0 else (1 - margin) * best


def race_threshold(leader: float) -> float:
    """The highest score on the first episodes that still runs on: within :data:`RACE_MARGIN` of the leader's."""
    return within(leader, RACE_MARGIN)


def setting_key(kind: str, settings: dict[str, Any]) -> str:
    """The key of a setting in a search's records (and a tuning result's times)."""
    return json.dumps([kind, settings], sort_keys=True, default=str)


class Timing:
    """Median wall milliseconds per observation of a strategy on one stream (one held-out episode).

    Every time measured is kept in :attr:`times`, by setting, and measured once; ``known`` are
    the times of an earlier call.
    """

    def __init__(
        self,
        model: AdaptiveModel,
        x: Tensor,
        y: Tensor,
        budget_ms: float | None,
        known: Mapping[str, float] | None = None,
    ) -> None:
        self.model, self.x, self.y, self.budget_ms = model, x, y, budget_ms
        self.times: dict[str, float] = dict(known or {})

    def ms(self, kind: str, settings: dict[str, Any]) -> float:
        """The time per observation of ``kind`` with ``settings``, measured the first time it is asked for."""
        key = setting_key(kind, settings)
        if key not in self.times:
            self.times[key] = self.ms_per_step(build(kind, settings))
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


class Search:
    """The candidates so far, the best of each kind, and every run on the episodes."""

    def __init__(
        self,
        scorer: Scorer,
        timing: Timing,
        progress: bool,
        known: dict[str, TuneCandidate] | None = None,
        heads: Mapping[str, tuple[Trace, Tensor | None]] | None = None,
        chosen_before: Mapping[str, dict[str, Any]] | None = None,
    ) -> None:
        self.scorer, self.timing = scorer, timing
        self.model, self.td, self.x, self.y = scorer.model, scorer.td, scorer.x, scorer.y
        self.known = known or {}  # scored by an earlier call on the same data: not run again
        #: The settings that earlier call chose, by kind: a choice its runs decided stands.
        self.chosen_before: dict[str, dict[str, Any]] = dict(chosen_before or {})
        #: Raced settings' runs on the first episodes (an earlier call's too): a race is decided
        #: again against the leader of the day, from the same runs.
        self.heads: dict[str, tuple[Trace, Tensor | None]] = dict(heads or {})
        self.candidates: list[TuneCandidate] = []
        self.best_of: dict[str, TuneCandidate] = {}
        self.notes: list[str] = []
        #: Every run on the episodes, by setting, and its normalised predictions ``[E, T, out]``
        #: where it ran to the end: what the combination and the diagnosis take instead of running again.
        self.traces: dict[str, Trace] = {}
        self.predictions: dict[str, Tensor] = {}
        self.bar = tqdm(desc="tune", unit="setting", disable=not progress)

    # ------------------------------------------------------------------ runs
    def run(self, kind: str, settings: dict[str, Any]) -> Trace:
        """The trace of ``kind`` with ``settings`` on the episodes, run the first time it is asked for."""
        key = setting_key(kind, settings)
        if key not in self.traces:
            self._record(kind, settings, slice(None))
        return self.traces[key]

    def recorded(self, kind: str, settings: dict[str, Any]) -> Tensor | None:
        """The setting's normalised predictions ``[E, T, out]``, run again only if no run recorded them
        (``None``: it refused an observation)."""
        key = setting_key(kind, settings)
        if key not in self.predictions and math.isfinite(self.run(kind, settings).rmse):
            del self.traces[key]  # a run given from elsewhere (a calibration's) kept no predictions
            self._record(kind, settings, slice(None))
        return self.predictions.get(key)

    def _record(self, kind: str, settings: dict[str, Any], episodes: slice) -> tuple[Trace, Tensor | None]:
        """Run the setting on ``episodes``; a run on all of them is kept, a part is returned."""
        predictions: list[Tensor] = []
        run = self.scorer.run(build(kind, settings), episodes, predictions=predictions)
        recorded = torch.stack(predictions, dim=1) if math.isfinite(run.rmse) else None
        if episodes == slice(None):
            key = setting_key(kind, settings)
            self.traces[key] = run
            if recorded is not None:
                self.predictions[key] = recorded
        return run, recorded

    # ------------------------------------------------------------------ scores
    def score(
        self,
        kind: str,
        settings: dict[str, Any],
        *,
        ms: float | None = None,
        rmse: float | None = None,
        run: Trace | None = None,
    ) -> float:
        """Score one setting on every episode (unless over budget); its score.

        ``ms``: its time if measured otherwise (SMCD's particle probe, a combination's members);
        ``run``: its trace if it ran already (a calibration's); ``rmse``: its error where it is
        known without a trace of its own.
        """
        key = setting_key(kind, settings)
        if ms is not None:
            self.timing.times.setdefault(key, ms)
        if self._over_budget(kind, settings):
            return math.inf
        earlier = self.known.get(key)
        score = rmse
        if earlier is not None:
            rmse, score = earlier.one_step_rmse, earlier.score
        elif rmse is None:
            if run is not None:
                self.traces.setdefault(key, run)
            found = self.run(kind, settings)
            rmse, score = found.rmse, self.scorer.score(found)
        return self._add(kind, settings, rmse, score)

    def race(self, kind: str, batch: Sequence[dict[str, Any]]) -> list[float]:
        """Score ``batch``'s settings of ``kind`` by racing (module doc); each one's score, ``inf`` if dropped.

        Only for kinds whose runs are independent per episode (no random numbers). The best
        setting scored so far competes on the first episodes too, from its own run. The candidates
        are listed in the batch's order.
        """
        count = self.x.shape[0]
        first = max(2, math.ceil(RACE_SHARE * count))
        keys = [setting_key(kind, settings) for settings in batch]
        over = [self._over_budget(kind, settings, record=False) for settings in batch]
        heads: dict[int, tuple[Trace, Tensor | None]] = {}
        for i, settings in enumerate(batch):
            if over[i] or keys[i] in self.known or keys[i] in self.traces or first >= count:
                continue
            if keys[i] not in self.heads:
                self.heads[keys[i]] = self._record(kind, settings, slice(0, first))
            heads[i] = self.heads[keys[i]]
        # The best so far and every setting of the batch with a run on the first episodes compete (a
        # reused one too: its run there was kept).
        best = self.best_of.get(kind)
        head_score = {key: self.scorer.score(self.heads[key][0], slice(0, first)) for key in keys if key in self.heads}
        leader = self._head_score(setting_key(kind, best.settings), first) if best else math.inf
        raced = [head_score[key] for key, out in zip(keys, over, strict=True) if not out and key in head_score]
        leader = min([leader, *raced])
        scores = []
        for i, settings in enumerate(batch):
            if over[i]:
                self._over_budget(kind, settings)  # listed now, in the batch's order
                scores.append(math.inf)
            elif i not in heads:
                scores.append(self.score(kind, settings))
            elif not math.isfinite(heads[i][0].rmse):  # refused on the first episodes: on all of them too
                scores.append(self._add(kind, settings, math.inf))
            elif head_score[keys[i]] > race_threshold(leader):
                why = f"raced out: {head_score[keys[i]]:.4g} on the first {first} episodes, the best {leader:.4g}"
                ms = self.timing.times.get(keys[i], math.nan)
                self.candidates.append(TuneCandidate(kind, settings, math.inf, ms, why))
                self.bar.update(1)
                scores.append(math.inf)
            else:
                (head, head_predictions), (rest, rest_predictions) = (
                    heads[i],
                    self._record(kind, settings, slice(first, count)),
                )
                self.traces[keys[i]] = joined = _joined(head, rest)
                if head_predictions is not None and rest_predictions is not None:
                    self.predictions[keys[i]] = torch.cat([head_predictions, rest_predictions])
                scores.append(self._add(kind, settings, joined.rmse, self.scorer.score(joined)))
        return scores

    def prefer_robust(self, kind: str, forms: Sequence[tuple[str, Callable[[dict[str, Any]], bool]]]) -> None:
        """Where a stronger robust form of ``kind`` than its best's is not worse beyond the episodes'
        noise, keep it, and say so in :attr:`notes`.

        Clean tuning episodes cannot show what a robust form (Tukey's biweight, a Huber loss, a
        Student-t likelihood) is for: a corrupted reading. Where they cannot tell it from the best,
        it costs little there and bounds the damage of the reading they lack. ``forms`` are
        ``(name, has_form)`` pairs, the strongest protection first; the first form stronger than the
        best's whose best setting passes is kept. A form passes where its score is within
        :data:`~smcd_rl.tuning.defaults.ROBUST_MARGIN` of the best's, or where its mean excess over
        the best's, paired per episode, is at most twice its standard error.
        """
        best = self.best_of.get(kind)
        if best is None:
            return
        rank = next((i for i, (_, has) in enumerate(forms) if has(best.settings)), len(forms))
        for form, has in forms[:rank]:
            rivals = [c for c in self.candidates if c.kind == kind and has(c.settings) and usable(c.score)]
            if not rivals:
                continue
            rival = min(rivals, key=lambda c: c.score)
            if any(setting_key(kind, c.settings) not in self.traces for c in (best, rival)):
                # Scores reused from an earlier call, without their runs: its choice stands.
                if self.chosen_before.get(kind) == rival.settings:
                    self.best_of[kind] = rival
                    return
                continue
            paired = self._paired_excess(kind, rival, best)
            if paired is None:
                continue
            mean, noise = paired
            close = rival.score <= within(best.score, ROBUST_MARGIN)
            if mean > noise and not close:
                continue
            self.best_of[kind] = rival
            why = (
                f"its excess per episode, {mean:.3g}, is within the episodes' noise ({noise:.3g})"
                if mean <= noise
                else f"within {ROBUST_MARGIN:.0%} of it"
            )
            self.notes.append(
                f"{kind.replace('_', ' ')}: kept the robust form ({form}), {rival.score:.4g} against the best "
                f"form's {best.score:.4g}: {why}, and it bounds what one corrupted reading does"
            )
            return

    def prefer_cheaper(self, kind: str, cheaper: dict[str, Any], cheap: str, dear: str) -> None:
        """Keep ``cheaper``, a scored setting of ``kind`` that costs less per observation than the
        best, unless the best beats it beyond the episodes' noise; say which in :attr:`notes`.

        A setting that costs more must earn it: the best is kept only where its mean gain per
        episode over ``cheaper``, paired, is more than twice its standard error. ``cheap`` and
        ``dear`` name the two in the note.
        """
        best = self.best_of.get(kind)
        rival = next((c for c in self.candidates if c.kind == kind and c.settings == cheaper and usable(c.score)), None)
        if best is None or rival is None or best.settings == cheaper:
            return
        paired = self._paired_excess(kind, rival, best)
        if paired is None:
            return
        mean, noise = paired
        name = kind.replace("_", " ")
        if mean > noise:
            self.notes.append(
                f"{name}: kept {dear} ({best.score:.4g}; {cheap}: {rival.score:.4g}): its gain per episode, "
                f"{mean:.3g}, is beyond the episodes' noise ({noise:.3g})"
            )
            return
        self.best_of[kind] = rival
        self.notes.append(
            f"{name}: kept {cheap} ({rival.score:.4g}; {dear}: {best.score:.4g}): the gain per episode of "
            f"{dear}, which costs more, is {mean:.3g}, within the episodes' noise ({noise:.3g})"
        )

    def _paired_excess(self, kind: str, worse: TuneCandidate, better: TuneCandidate) -> tuple[float, float] | None:
        """The mean excess per episode of ``worse``'s score over ``better``'s, paired, and twice its
        standard error; ``None`` without both runs or with a refused episode."""
        if any(setting_key(kind, c.settings) not in self.traces for c in (worse, better)):
            return None
        first, second = (
            self.scorer.episode_scores(self.traces[setting_key(kind, c.settings)]) for c in (worse, better)
        )
        excess = [a - b for a, b in zip(first, second, strict=True)]
        if len(excess) < 2 or not all(math.isfinite(e) for e in excess):
            return None
        return statistics.fmean(excess), 2 * statistics.stdev(excess) / math.sqrt(len(excess))

    def time_best(self, kind: str) -> None:
        """Measure the time of ``kind``'s best setting, where it has none yet (no budget measured it)."""
        best = self.best_of.get(kind)
        if best is None or math.isfinite(best.ms_per_step):
            return
        timed = replace(best, ms_per_step=self.timing.ms(kind, best.settings))
        self.candidates = [timed if c is best else c for c in self.candidates]
        self.best_of[kind] = timed

    def _head_score(self, key: str, episodes: int) -> float:
        """A setting's score over the first ``episodes`` episodes: from its run there, or its run on all of them."""
        if key in self.heads:
            return self.scorer.score(self.heads[key][0], slice(0, episodes))
        run = self.traces.get(key)
        return math.inf if run is None else self.scorer.head_score(run, episodes)

    def _over_budget(self, kind: str, settings: dict[str, Any], *, record: bool = True) -> bool:
        """Under a budget, time the setting first: one over it is listed as skipped (with ``record``)."""
        if self.timing.budget_ms is None:
            return False
        ms = self.timing.ms(kind, settings)
        if not self.timing.over(ms):
            return False
        if record:
            self.candidates.append(TuneCandidate(kind, settings, math.inf, ms, "over budget"))
        return True

    def _add(self, kind: str, settings: dict[str, Any], rmse: float, score: float | None = None) -> float:
        score = rmse if score is None else score
        ms = self.timing.times.get(setting_key(kind, settings), math.nan)
        candidate = TuneCandidate(kind, settings, rmse, ms, "", score)
        self.candidates.append(candidate)
        if usable(score) and (kind not in self.best_of or score < self.best_of[kind].score):
            self.best_of[kind] = candidate
        self.bar.update(1)
        self.bar.set_postfix(kind=kind, score=f"{score:.4g}")
        return score


def _joined(head: Trace, rest: Trace) -> Trace:
    """The trace of one run on the episodes of ``head`` followed by those of ``rest`` (no SMCD entries).

    Each episode's errors and open-loop predictions are its own; the per-step and overall RMSEs
    pool the episodes of both, as one run over all of them computes them (equal lengths and dimensions).
    """
    if not math.isfinite(rest.rmse):
        return Trace(head.one_step_rmse, math.inf, [], [], [], [], head.one_step_errors + rest.one_step_errors)
    errors = head.one_step_errors + rest.one_step_errors
    steps = [math.sqrt(sum(e[t] ** 2 for e in errors) / len(errors)) for t in range(len(errors[0]))]
    per_episode = head.per_episode_rmse + rest.per_episode_rmse
    rmse = math.sqrt(sum(v * v for v in per_episode) / len(per_episode))
    ahead = None if head.ahead is None or rest.ahead is None else torch.cat([head.ahead, rest.ahead])
    return Trace(steps, rmse, [], [], [], per_episode, errors, ahead)
