"""Calibration of SMCD's likelihood noise and flip probability on held-out episodes.

The likelihood noise ``Σ`` of eq. (1) and the flip probability ``d`` of the mask transition are
parameters of the state-space model the filter assumes. :func:`calibrate` runs the filter over
held-out episodes of the *training* tasks for a few candidate settings and keeps the best by one
of these criteria (:mod:`smcd_rl.tuning.criteria`):

* ``"one-step"`` (the default): the lowest one-step prediction error, the RMSE of the filter's
  prediction of each step from the steps before it (:attr:`Candidate.one_step_rmse`), which is
  the point prediction planners and controllers use.
* ``"evidence"`` (empirical Bayes): the highest log evidence, the model's marginal likelihood
  ``log p(z_1:T) = Σ_t log p(z_t | z_<t)`` that the filter estimates as it runs
  (:attr:`smcd_rl.SMCDFilter.log_evidence`): too small a noise punishes every residual the
  network cannot explain, too large a one spreads the likelihood over masks that predict nothing.
* ``"lookahead"`` with ``horizon=H``: the lowest RMSE of the open-loop predictions ``H`` steps
  ahead (the score of a planner's rollout or a look-ahead table), or a callable score of your own.

The two can disagree. The evidence scores the filter's predictive *density*; where the network's
residuals are not the independent Gaussian noise the filter assumes (a misspecified network's are
systematic, or heavy-tailed), the setting of best evidence can predict worse than another.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> _ = torch.manual_seed(0)
    >>> q = torch.rand(40, 2)
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    >>> _ = smcd_rl.fit(model, TensorDict({"q": q, "ee": q.cos()}, [40]), epochs=2, lr=1e-2, progress=False)
    >>> episodes = TensorDict({"q": q.reshape(4, 10, 2), "ee": q.cos().reshape(4, 10, 2)}, [4, 10])
    >>> result = smcd_rl.calibrate(model, episodes, base=smcd_rl.SMCD(num_particles=20), progress=False)
    >>> result.criterion, len(result.candidates) >= 15, model.calibration["flip_prob"] == result.flip_prob
    ('one-step', True, True)
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from torch import Tensor
from tqdm.auto import tqdm

from smcd_rl.checks import check_count, check_real, check_seed
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.filter import SMCDFilter
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies import SMCD, NoAdaptation
from smcd_rl.tuning.criteria import Criterion as _Criterion
from smcd_rl.tuning.criteria import Score, checked_criterion
from smcd_rl.tuning.defaults import CALIBRATION_REFINE, FLIP_PROBS
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.held_out import checked_model, stacked
from smcd_rl.tuning.scoring import Scorer
from smcd_rl.tuning.search import usable

__all__ = ["calibrate", "evidence", "Calibration", "Candidate", "checked_flips", "NOISE_SHAPES", "NoiseShape"]

#: Factors of the residual scale tried first: 1/8 .. 8 in doublings.
_BRACKET = tuple(range(-3, 4))
#: At most this many doublings past either end of a bracket whose best value lies at that end.
_EXTEND = 6
_LOG2 = math.log(2.0)
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0

Stage = Literal["bracket", "flip", "shape", "rebracket", "refine"]
#: The noise's shape across output dimensions: ``"proportional"`` keeps the residual's proportions,
#: ``"scalar"`` is one noise for every dimension, ``"sqrt"`` lies between (each dimension's noise
#: proportional to the square root of its residual); ``"search"`` tries all three.
NoiseShape = Literal["search", "proportional", "sqrt", "scalar"]
#: The noise shapes by name, in the order a search tries them.
NOISE_SHAPES = ("proportional", "scalar", "sqrt")
#: What :func:`calibrate` optimises by name: the one-step error, the log evidence, or the look-ahead
#: error (:mod:`smcd_rl.tuning.criteria`; a callable score of your own is taken too).
Criterion = Literal["one-step", "evidence", "lookahead"]


@dataclass(frozen=True)
class Candidate:
    """One filter run of :func:`calibrate`: a setting and how well it explains the episodes."""

    #: Which part of the search proposed it: ``bracket``, ``flip``, ``shape``, ``rebracket`` or ``refine``.
    stage: Stage
    #: The noise as a multiple of the residual scale the search started from.
    factor: float
    #: The likelihood noise (a float, or one per output dimension), in the target's units.
    noise_std: float | tuple[float, ...]
    flip_prob: float
    #: Mean log evidence per episode, ``log p(z_1:T)`` (``-inf`` if the filter refused an observation).
    log_evidence: float
    #: RMSE (target units, all dimensions pooled) of the filter's prediction of each step from the
    #: steps before it (the MMSE mask before its update), over every episode's steps 2..T.
    one_step_rmse: float
    #: The run step by step (:func:`smcd_rl.tuning.diagnostics.trace` of this setting, which it equals).
    trace: Trace | None = field(default=None, compare=False, repr=False)
    #: The score of the calibration's criterion (lower is better): the one-step RMSE (also under
    #: the evidence criterion), the look-ahead RMSE or your own score (``inf`` if the filter refused).
    score: float = math.nan
    #: The noise's shape across output dimensions (:data:`NoiseShape`).
    shape: str = "proportional"

    def __post_init__(self) -> None:
        if math.isnan(self.score):  # scored by its one-step error
            object.__setattr__(self, "score", self.one_step_rmse)


@dataclass
class Calibration:
    """What :func:`calibrate` chose and every candidate it tried; ``print`` it for the table."""

    #: A fresh :class:`smcd_rl.SMCD` with the chosen settings (and the other settings of ``base``).
    strategy: SMCD = field(compare=False)
    noise_std: float | list[float]
    flip_prob: float
    #: What chose the setting: ``"one-step"`` (the lowest one-step RMSE), ``"evidence"`` (the
    #: highest log evidence), ``"lookahead"`` (the lowest look-ahead RMSE over :attr:`horizon`
    #: steps) or ``"custom"`` (the lowest score of your own, :attr:`score_label`).
    criterion: str
    #: Every filter run, in the order run.
    candidates: list[Candidate]
    #: The residual scale per output dimension the search started from.
    residual_scale: list[float]
    #: Where it came from: the model's fit (``"fit"``) or, without one, the episodes themselves.
    residual_source: Literal["fit", "episodes"]
    #: The chosen noise's shape (:data:`NoiseShape`): ``"proportional"`` (the residual's
    #: proportions), ``"sqrt"`` or ``"scalar"`` (the factor times the residual's RMS).
    noise_shape: str
    #: The flip probabilities tried, sorted.
    flip_probs: list[float]
    episodes: int
    steps: int
    num_particles: int
    #: Wall time of the search.
    seconds: float = field(compare=False)
    #: The steps ahead the criterion scores (1 for one-step and evidence).
    horizon: int = 1
    #: The name of the criterion's score in tables.
    score_label: str = "one-step RMSE"
    #: A digest of the model, the episodes, the seed and the base settings: what ``reuse`` checks.
    data: str = field(default="", compare=False)
    #: The shapes searched, in the order searched.
    shapes: list[str] = field(default_factory=lambda: ["proportional"])

    @property
    def per_dimension(self) -> bool:
        """Whether the chosen noise has one value per output dimension (any shape but ``"scalar"``)."""
        return self.noise_shape != "scalar"

    def ranked(self) -> list[Candidate]:
        """The candidates best first by :attr:`criterion`, one per setting (noise, flip)."""
        seen: set[tuple[Any, float]] = set()
        ranked = []
        for c in sorted(self.candidates, key=lambda c: -_objective(c, self.criterion)):  # stable: first of equals
            if (c.noise_std, c.flip_prob) not in seen:
                seen.add((c.noise_std, c.flip_prob))
                ranked.append(c)
        return ranked

    @property
    def best(self) -> Candidate:
        """The chosen candidate: the best by :attr:`criterion` (the first of equals)."""
        return _best(self.candidates, self.criterion)

    def table(self) -> str:
        """Every candidate's setting, log evidence and one-step error; the chosen one marked ``*``."""
        scale = "[" + ", ".join(f"{s:.4g}" for s in self.residual_scale) + "]"
        if self.shapes == ["scalar"]:
            scale = f"RMS of {scale}"
        shaped = len(self.shapes) > 1
        ahead = self.criterion in ("lookahead", "custom")
        lines = [
            f"calibrate: {self.episodes} episodes x {self.steps} steps, {self.num_particles} particles; "
            f"noise = factor x residual scale {scale} (from {self.residual_source})"
            + (
                f" in the shapes {self.shapes} (sqrt: each dimension's noise as the root of its residual's)"
                if shaped
                else ""
            ),
            f"{'':1} {'run':>3}  {'stage':<9}  "
            + (f"{'shape':<12}  " if shaped else "")
            + f"{'factor':>8}  {'noise(rms)':>10}  {'flip_prob':>9}  "
            f"{'log evidence/ep':>15}  {'1-step RMSE':>11}" + (f"  {self.score_label}" if ahead else ""),
        ]
        best = self.best
        for i, c in enumerate(self.candidates, 1):
            noise = (
                c.noise_std
                if isinstance(c.noise_std, float)
                else math.sqrt(sum(v * v for v in c.noise_std) / len(c.noise_std))
            )
            lines.append(
                f"{'*' if c is best else ' '} {i:>3}  {c.stage:<9}  "
                + (f"{c.shape:<12}  " if shaped else "")
                + f"{c.factor:>8.4g}  {noise:>10.4g}  "
                f"{c.flip_prob:>9.4g}  {c.log_evidence:>15.6g}  {c.one_step_rmse:>11.4g}"
                + (f"  {c.score:.4g}" if ahead else "")
            )
        noise_text = (
            f"{self.noise_std:.4g}"
            if isinstance(self.noise_std, float)
            else str([float(f"{v:.4g}") for v in self.noise_std])
        )
        by = {"evidence": "highest log evidence", "one-step": "lowest 1-step RMSE"}.get(
            self.criterion, f"lowest {self.score_label}"
        )
        lines.append(
            f"chosen ({by}): noise_std={noise_text}"
            + (f" ({self.noise_shape})" if shaped else "")
            + f", flip_prob={self.flip_prob:g} "
            f"({len(self.candidates)} filter runs, {self.seconds:.1f} s)"
        )
        if len(self.flip_probs) > 1 and self.flip_prob in (self.flip_probs[0], self.flip_probs[-1]):
            better = "explain the episodes" if self.criterion == "evidence" else "predict"
            lines.append(
                f"note: flip_prob {self.flip_prob:g} is at the end of the flip_probs tried {self.flip_probs}; "
                f"a wider range may {better} better"
            )
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


def calibrate(
    model: AdaptiveModel,
    episodes: TensorDictBase | Sequence[TensorDictBase],
    *,
    base: SMCD | None = None,
    flip_probs: Sequence[float] = FLIP_PROBS,
    noise_shape: NoiseShape = "search",
    per_dimension: bool | None = None,
    refine: int = CALIBRATION_REFINE,
    criterion: Criterion | Score = "one-step",
    horizon: int | None = None,
    seed: int = 0,
    progress: bool = True,
    reuse: Calibration | None = None,
    store: bool = True,
) -> Calibration:
    """Choose SMCD's ``noise_std`` and ``flip_prob`` on held-out episodes, by the error you are judged by.

    The episodes must come from the *training* tasks (held out from training, never the test
    tasks): calibration is part of fitting the model, and tuning it on the tasks it is then
    scored on would leak them into the score.

    The criterion is the one-step RMSE by default (lower is better): the error of the filter's
    prediction of each step from the steps before it. ``criterion="evidence"`` maximises the
    filter's log evidence instead (empirical Bayes). The evidence scores the filter's predictive
    density, while planners and controllers use its point prediction, so the setting of best
    evidence can predict worse: where the network's residuals are not the independent Gaussian
    noise the filter assumes, the evidence may choose a small noise that makes the filter
    over-confident (it then jumps between masks on every residual), or a large one that pays for
    rare outliers with a filter that barely adapts. ``criterion="lookahead", horizon=H`` scores
    the filter's open-loop predictions ``H`` steps ahead (:mod:`smcd_rl.tuning.criteria`), what a
    planner's rollout or a look-ahead table is scored by: a noise chosen for the next step can be
    too small (a filter that jumps between masks) or too large for ten. A callable
    ``criterion(predicted, observed) -> float`` scores them your way. The search is the same for
    every criterion; only the value it optimises differs.

    The noise is searched as ``factor x residual scale``, starting from the model's
    :attr:`~smcd_rl.AdaptiveModel.residual_scale` (recorded by :func:`smcd_rl.fit`; without one,
    the RMS residual of the network with dropout off on the episodes), in one of three shapes
    across output dimensions: the residual's proportions (``"proportional"``), one noise for every
    dimension (``"scalar"``, the residual's RMS) and between them (``"sqrt"``: each dimension's
    noise as the square root of its residual's, times the RMS's). Each shape has one parameter,
    the common factor, well posed even for few episodes. Which shape is right depends on the
    criterion: the one-step error weighs each dimension by its own residual (proportional), while
    a look-ahead may need the filter to listen to a dimension whose residual is large but where
    the task shows most (a pendulum's angular velocity). ``noise_shape="search"`` (the default)
    lets the criterion choose; ``"proportional"``, ``"sqrt"`` or ``"scalar"`` searches that
    shape alone. Search, in log factor:

    1. a bracket of factors 1/8 .. 8 in doublings at the middle of ``flip_probs`` (7 runs),
       extended past an end while the best value lies there (the proportional shape first, when
       searching shapes);
    2. the other ``flip_probs`` at the best factor (``len(flip_probs) - 1`` runs);
    3. when searching shapes, each other shape at the chosen flip probability: the factors half,
       once and twice the best one (3 runs, extended while the best lies at an end); the shape of
       the best run is kept;
    4. if the best flip probability changed, the factors half and twice the best one at it
       (2 runs, extended in the same way; done by step 3 for a shape it searched);
    5. a golden-section refinement between those neighbours (``refine`` runs), which narrows
       the bracket around the optimum to a factor ``4 ** (0.618 ** (refine - 1))`` (1.22 for
       the default 5).

    That is 17 filter runs for one shape (15 when the flip probability stays, one more per
    extension) and about 23 for the three, each over all episodes at once as one batch of independent filters, every one seeded alike from ``seed``
    (common random numbers, so candidates differ by their setting and not by their draws). The
    cost of a run is that of ``steps`` SMCD updates of batch ``episodes`` (memory: ``episodes x
    num_particles`` masks and activations at once). The chosen setting is the best candidate by
    ``criterion`` (the lowest one-step RMSE, or the highest log evidence; the first of equals);
    it is stored in ``model.calibration`` with the criterion that chose it (saved with the model,
    used by ``SMCD(noise_std="auto", flip_prob="auto")``); a call that raises leaves it as it was.

    Args:
        model: a fitted model; its network is not changed.
        episodes: a TensorDict of batch ``[E, T]`` (E episodes of T consecutive steps) in the
            model's keys, or a list of ``[T]`` ones; at least 2 episodes of 2 steps.
        base: the SMCD whose other settings (particles, resampling, transition...) the filter
            runs use and the result keeps (default ``SMCD()``); its noise and flip are ignored.
        flip_probs: the flip probabilities tried.
        noise_shape: ``"search"`` (the three shapes, the criterion chooses), ``"proportional"``,
            ``"sqrt"`` or ``"scalar"`` (that shape alone).
        per_dimension: the older spelling of one shape: ``True`` is ``noise_shape="proportional"``,
            ``False`` is ``"scalar"`` (``None``: use ``noise_shape``).
        refine: golden-section runs at the end (0 for none).
        criterion: what the search optimises and the choice is made by: ``"one-step"``, the
            one-step RMSE (:attr:`Candidate.one_step_rmse`, lowest wins), ``"evidence"``, the
            log evidence (:attr:`Candidate.log_evidence`, highest wins), ``"lookahead"``, the
            RMSE ``horizon`` steps ahead open loop, or a callable score of your own
            (:mod:`smcd_rl.tuning.criteria`; :attr:`Candidate.score`, lowest wins).
        horizon: the steps ahead of ``"lookahead"`` or of your score (episodes must be longer).
        seed: seed of every filter run: two calls with the same arguments give the same result.
        progress: show a progress bar over the filter runs.
        reuse: an earlier result on the same model, episodes, seed and ``base`` (the other
            criterion's, say): a setting it ran takes its run from there instead of running again.
            The two criteria's searches start from the same bracket, so the second runs fewer.
        store: write the choice into ``model.calibration`` (``False``: leave the model as it is,
            as :func:`smcd_rl.tune` does, which keeps its own record).

    Returns:
        The chosen strategy and settings and every candidate (``print`` it for a table).

    Raises:
        TypeError: ``model`` is not an AdaptiveModel, ``episodes`` not TensorDicts, a value not real.
        KeyError: a key the model needs is missing from ``episodes``.
        ValueError: shapes that do not fit the model, fewer than 2 episodes or steps, NaN or inf,
            episodes of different lengths, an unfitted model, a flip probability the transition
            cannot take, an unknown ``criterion`` or a ``horizon`` it does not take, episodes no
            longer than the horizon, or a filter that refused the episodes under every candidate
            (no finite evidence or score).
    """
    started = time.perf_counter()
    chosen_by = checked_criterion(criterion, horizon)
    model, base = checked_model(model, "calibrate"), _checked_base(base)
    if not isinstance(store, bool):
        raise TypeError(f"store must be True or False, got {store!r} ({type(store).__name__})")
    if per_dimension is not None and not isinstance(per_dimension, bool):  # "no" is truthy: it would mean True
        raise TypeError(f"per_dimension must be True or False, got {per_dimension!r} ({type(per_dimension).__name__})")
    if noise_shape not in NOISE_SHAPES and noise_shape != "search":
        raise ValueError(f"noise_shape must be 'search' or one of {list(NOISE_SHAPES)}, got {noise_shape!r}")
    shapes = (
        ["proportional" if per_dimension else "scalar"]
        if per_dimension is not None
        else list(NOISE_SHAPES)
        if noise_shape == "search"
        else [noise_shape]
    )
    grid = checked_flips(flip_probs, model, base)
    refine = check_count(refine, "refine", minimum=0)
    seed = check_seed(seed)
    scorer = Scorer(model, stacked(episodes, "calibrate"), chosen_by, "calibrate")  # checks keys, shapes and values
    result = search_noise(scorer, base, grid, shapes=shapes, refine=refine, seed=seed, progress=progress, reuse=reuse)
    result.seconds = time.perf_counter() - started
    if not store:
        return result
    best = result.best
    model.calibration = {
        "noise_std": result.noise_std,
        "flip_prob": result.flip_prob,
        "criterion": chosen_by.key,
        "log_evidence": best.log_evidence,
        "one_step_rmse": best.one_step_rmse,
        "episodes": result.episodes,
        "steps": result.steps,
        "num_particles": base.num_particles,
    }
    return result


def search_noise(
    scorer: Scorer,
    base: SMCD,
    grid: list[float],
    *,
    shapes: Sequence[str],
    refine: int,
    seed: int,
    progress: bool,
    reuse: Calibration | None = None,
) -> Calibration:
    """:func:`calibrate`'s search (its doc) on checked arguments: the episodes and the criterion
    are ``scorer``'s, ``grid`` the sorted flip probabilities, ``shapes`` the noise shapes searched
    (:data:`NOISE_SHAPES`' names, the first bracketed at every flip); the model is left as it is.

    :func:`smcd_rl.tune` calls it with the scorer of all its runs.
    """
    started = time.perf_counter()
    model, chosen_by, td = scorer.model, scorer.criterion, scorer.td
    num_episodes, steps = td.batch_size
    x, y = scorer.x, scorer.y

    recorded = model.residual_scale
    source: Literal["fit", "episodes"] = "fit" if recorded is not None else "episodes"
    scale = recorded if recorded is not None else _residual_scale(model, x, y)
    start = scale.to(torch.float64)
    rms = start.square().mean().sqrt()
    # Each shape's noise at factor 1: the residual's proportions, their root (times the RMS's, so
    # that every shape's factors mean about the same), or the RMS alone.
    unit = {
        "proportional": start,
        "sqrt": start.sqrt() * rms.sqrt(),
        "scalar": rms.reshape(1),
    }

    def noise_of(log_factor: float, shape: str) -> float | tuple[float, ...]:
        values = (math.exp(log_factor) * unit[shape]).tolist()
        return values[0] if shape == "scalar" else tuple(values)

    config = {k: v for k, v in base.config().items() if k not in ("noise_std", "flip_prob")}
    device = next(model.net.parameters()).device
    candidates: list[Candidate] = []
    scores: dict[tuple[float, float, str], float] = {}
    middle = grid[len(grid) // 2]
    planned = len(_BRACKET) + len(grid) - 1 + refine + 3 * (len(shapes) - 1)
    data = content_digest(
        {
            "model": model_digest(model),
            "episodes": content_digest(td),
            "seed": seed,
            "base": config,
            "scale": start.tolist(),
        }
    )
    ran_before = _reusable(reuse, data)
    bar = tqdm(total=planned, desc="calibrate", unit="run", disable=not progress)

    def score(log_factor: float, flip: float, stage: Stage, shape: str) -> float:
        key = (round(log_factor, 9), flip, shape)
        if key in scores:
            return scores[key]
        nonlocal planned
        if len(candidates) >= planned:  # an extended bracket: more runs than planned
            planned += 1
            bar.total = planned
            bar.refresh()
        noise = noise_of(log_factor, shape)
        earlier = ran_before.get((noise, flip))
        if earlier is not None and earlier.trace is not None and _reusable_run(earlier.trace, chosen_by):
            evidence, rmse, run = earlier.log_evidence, earlier.one_step_rmse, earlier.trace
        else:
            strategy = SMCD(
                **config,
                noise_std=list(noise) if isinstance(noise, tuple) else noise,
                flip_prob=flip,
                generator=torch.Generator(device=device).manual_seed(seed),
            )
            evidence, rmse, run = _run(scorer, strategy)
        candidate = Candidate(stage, math.exp(log_factor), noise, flip, evidence, rmse, run, scorer.score(run), shape)
        candidates.append(candidate)
        scores[key] = value = _objective(candidate, chosen_by.name)
        bar.update(1)
        bar.set_postfix(
            factor=f"{math.exp(log_factor):.3g}", flip=f"{flip:g}", evidence=f"{evidence:.4g}", rmse=f"{rmse:.4g}"
        )
        return value

    try:
        # 1. Bracket the noise at the middle flip probability; 2. the other flip probabilities there.
        first = shapes[0]
        log_factor = _climb([k * _LOG2 for k in _BRACKET], lambda u: score(u, middle, "bracket", first))
        flip = max(grid, key=lambda f: score(log_factor, f, "flip", first))
        # 3. The other shapes at that flip probability, each around the best factor; the best shape stays.
        best_of_shape = {first: log_factor}
        for other in shapes[1:]:
            best_of_shape[other] = _climb(
                [log_factor - _LOG2, log_factor, log_factor + _LOG2],
                lambda u, other=other: score(u, flip, "shape", other),  # type: ignore[misc]
            )
        shape = max(shapes, key=lambda one: scores[(round(best_of_shape[one], 9), flip, one)])
        log_factor = best_of_shape[shape]
        # 4. Bracket again if the flip probability moved (step 3 did for its shapes); 5. golden section.
        if flip != middle and shape == first:
            log_factor = _climb(
                [log_factor - _LOG2, log_factor, log_factor + _LOG2], lambda u: score(u, flip, "rebracket", shape)
            )
        _golden(log_factor - _LOG2, log_factor + _LOG2, refine, lambda u: score(u, flip, "refine", shape))
    finally:
        bar.close()

    best = _best(candidates, chosen_by.name)
    if _objective(best, chosen_by.name) == -math.inf:
        if chosen_by.name != "evidence" and any(math.isfinite(c.one_step_rmse) for c in candidates):
            raise ValueError(
                f"your score returned inf for every candidate setting ({chosen_by.label}), although the "
                "filter ran on the episodes; check the score function, or score with criterion='one-step'"
            )
        raise ValueError(
            "the filter refused the episodes under every candidate setting (an observation impossible under "
            "every particle); check that the episodes are in the model's units and free of outliers"
        )
    chosen: float | list[float] = list(best.noise_std) if isinstance(best.noise_std, tuple) else best.noise_std
    return Calibration(
        strategy=SMCD(**config, noise_std=chosen, flip_prob=best.flip_prob),
        noise_std=chosen,
        flip_prob=best.flip_prob,
        criterion=chosen_by.name,
        candidates=candidates,
        residual_scale=start.tolist(),
        residual_source=source,
        noise_shape=best.shape,
        flip_probs=grid,
        episodes=num_episodes,
        steps=steps,
        num_particles=base.num_particles,
        seconds=time.perf_counter() - started,
        data=data,
        horizon=chosen_by.horizon,
        score_label=chosen_by.label,
        shapes=list(shapes),
    )


def _reusable(reuse: Calibration | None, data: str) -> dict[tuple[Any, float], Candidate]:
    """The runs of ``reuse`` by (noise, flip), after checking that it searched the same model and episodes."""
    if reuse is None:
        return {}
    if not isinstance(reuse, Calibration):
        raise TypeError(f"reuse must be a Calibration of an earlier calibrate call, got {type(reuse).__name__}")
    if reuse.data != data:
        raise ValueError(
            "reuse holds a calibration of another model, other episodes, another seed or other base settings"
            "; pass one of the same, or none"
        )
    return {(c.noise_std, c.flip_prob): c for c in reuse.candidates}


def evidence(
    model: AdaptiveModel,
    episodes: TensorDictBase | Sequence[TensorDictBase],
    *,
    noise_std: float | Sequence[float],
    flip_prob: float,
    base: SMCD | None = None,
    seed: int = 0,
) -> tuple[float, float]:
    """One filter run of :func:`calibrate` for a setting of your choice: its evidence and one-step error.

    Takes ``episodes``, ``base`` and ``seed`` as :func:`calibrate` does and checks them the same
    way; stores nothing on the model.

    Returns:
        The mean log evidence per episode and the one-step RMSE (see :class:`Candidate`).

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
        >>> model.fitted = True  # a toy network: declare it trained
        >>> q = torch.rand(3, 5, 2)
        >>> episodes = TensorDict({"q": q, "ee": torch.zeros(3, 5, 2)}, [3, 5])
        >>> log_evidence, rmse = evidence(model, episodes, noise_std=0.1, flip_prob=0.01, base=smcd_rl.SMCD(num_particles=10))
        >>> log_evidence < 0 < rmse
        True
    """
    model, base, seed = checked_model(model, "evidence"), _checked_base(base), check_seed(seed)
    td = stacked(episodes, "evidence")
    scorer = Scorer(model, td, checked_criterion("one-step"), "evidence")
    config = {k: v for k, v in base.config().items() if k not in ("noise_std", "flip_prob")}
    device = next(model.net.parameters()).device
    generator = torch.Generator(device=device).manual_seed(seed)
    return _run(scorer, SMCD(**config, noise_std=noise_std, flip_prob=flip_prob, generator=generator))[:2]


def _checked_base(base: SMCD | None) -> SMCD:
    base = SMCD() if base is None else base
    if not isinstance(base, SMCD):
        raise TypeError(f"base must be a smcd_rl.SMCD whose other settings the runs use, got {type(base).__name__}")
    return base


def _objective(candidate: Candidate, criterion: str) -> float:
    """What the search maximises: the log evidence, or minus the score (``-inf`` if not finite)."""
    if criterion == "evidence":
        return candidate.log_evidence
    return -candidate.score if usable(candidate.score) else -math.inf


def _reusable_run(run: Trace, criterion: _Criterion) -> bool:
    """Whether an earlier run can be scored by ``criterion`` (a look-ahead needs its predictions that far)."""
    return not criterion.looks_ahead or run.ahead is not None and run.ahead.shape[2] == criterion.horizon


def _best(candidates: Sequence[Candidate], criterion: str) -> Candidate:
    """The candidate of highest :func:`_objective` (the first of equals)."""
    return max(candidates, key=lambda c: _objective(c, criterion))


def _climb(log_factors: list[float], score: Callable[[float], float]) -> float:
    """The best of ``log_factors`` after extending them by doublings while the best lies at an end."""
    points = sorted(log_factors)
    lowest, highest = points[0] - _EXTEND * _LOG2, points[-1] + _EXTEND * _LOG2
    values = [score(u) for u in points]
    for _ in range(2 * _EXTEND):
        best = max(range(len(points)), key=values.__getitem__)
        low, high = points[0] <= lowest + 1e-9, points[-1] >= highest - 1e-9
        if not math.isfinite(values[best]):
            break  # nothing explains the episodes here: no direction to climb
        if best == 0 and not low:
            points.insert(0, points[0] - _LOG2)
            values.insert(0, score(points[0]))
        elif best == len(points) - 1 and not high:
            points.append(points[-1] + _LOG2)
            values.append(score(points[-1]))
        else:
            break
    return points[max(range(len(points)), key=values.__getitem__)]


def _golden(low: float, high: float, runs: int, score: Callable[[float], float]) -> None:
    """Golden-section search for the maximum of ``score`` on ``[low, high]`` in ``runs`` evaluations."""
    if runs < 1:
        return
    c = high - _GOLDEN * (high - low)
    fc = score(c)
    if runs < 2:
        return
    d = low + _GOLDEN * (high - low)
    fd = score(d)
    for _ in range(runs - 2):
        if fc >= fd:  # the maximum is in [low, d]
            high, d, fd = d, c, fc
            c = high - _GOLDEN * (high - low)
            fc = score(c)
        else:  # in [c, high]
            low, c, fc = c, d, fd
            d = low + _GOLDEN * (high - low)
            fd = score(d)


def _run(scorer: Scorer, strategy: SMCD) -> tuple[float, float, Trace]:
    """One filter over every episode at once: mean log evidence per episode, the one-step RMSE and the trace.

    The RMSE is in the target's units. A filter that refused an observation has evidence ``-inf``
    and RMSE ``inf``: this setting cannot explain the episodes.
    """
    run = scorer.run(strategy)
    if not math.isfinite(run.rmse):
        return -math.inf, math.inf, run
    return run.log_evidence[-1], run.rmse, run


def _residual_scale(model: AdaptiveModel, x: Tensor, y: Tensor) -> Tensor:
    """RMS residual per output of the network with dropout off on normalised ``x``, ``y``, in target units."""
    plain = model.with_adaptation(NoAdaptation())
    plain.reset()
    with torch.no_grad():
        residual = plain.adaptation.predict(x.reshape(-1, x.shape[-1])) - y.reshape(-1, y.shape[-1])
    std = model.output_norm.std.to(torch.float64)
    rms = residual.to(torch.float64).square().mean(0).sqrt() * std
    return torch.maximum(rms, 1e-6 * std).to(torch.float32).cpu()  # a dimension fitted exactly keeps a scale


def checked_flips(flip_probs: Sequence[float], model: AdaptiveModel, base: SMCD) -> list[float]:
    """The flip probabilities, sorted and distinct, each one the model's transition can take."""
    if isinstance(flip_probs, (str, bytes)) or not isinstance(flip_probs, Sequence):
        raise TypeError(f"flip_probs must be a sequence of probabilities such as (0.003, 0.01), got {flip_probs!r}")
    if not flip_probs:
        raise ValueError("flip_probs must hold at least one flip probability")
    grid = sorted({check_real(f, f"flip_probs[{i}]", low=0.0, high=1.0) for i, f in enumerate(flip_probs)})
    for flip in grid:  # the transition's own check; a generator of its own, so no global random draw
        SMCDFilter(
            1,
            num_particles=1,
            flip_prob=flip,
            keep_prob=model.net.keep_prob,
            transition=base.transition,
            generator=torch.Generator(),
        )
    return grid
