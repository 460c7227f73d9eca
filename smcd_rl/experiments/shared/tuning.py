"""The fair protocol: every method's settings from :func:`smcd_rl.tune` on held-out training-task episodes.

Before any test task is seen, each experiment draws ``--tuning-episodes`` episodes from its
*training* distribution (fresh tasks, never the test tasks) and tunes every method on them by
one criterion: the error its table reports where that is a look-ahead (``--tuning-horizon``:
``smcd-rl two-link`` tunes by the 10-step look-ahead error), else the one-step prediction error:

- **gradient descent (``G``)** over the grid ``--gd-lr`` x ``--gd-steps`` x ``--gd-window`` with
  the squared error, extended past an edge while the best point lies there, and its robust losses
  (Huber, Tukey's biweight) at the best point;
- **SMCD (``S``)**: the noise (its factor and shape), flip probability (``--calibrate-flips``) and
  prediction (the MMSE mask's, or the predictive mean where ``SMCD_PREDICTIONS`` allow it);
- **the Bayesian last layer (``L``)** over prior scale x drift x likelihood, and **SMCD with a
  Bayesian readout (``SL``)**: the tuned S with L's readout (:class:`smcd_rl.SMCDLastLayer`), its
  scale and (where ``SL_WEIGHINGS`` allow it) how its filter weighs the particles;
- **the combination (``C``)** of N and the other tuned methods (G, S, and L and SL where they
  run), its ``eta`` and fixed share;
- **SMCD calibrated by its evidence (``S(evidence)``)** and **SMCD at the paper's settings
  (``S(paper)``)**, the two references: what the filter's own criterion and no tuning give.
  ``S(evidence)`` takes the likelihood's form (Gaussian or Student-t) that ``tune`` kept for S by
  its robust-form rule on the same episodes, at the noise its evidence chose.

A second call under ``--budget-ms`` per observation (reusing the first call's scores) gives the
budgeted view: what each kind would be within a 100 Hz control step. Each method's median time
per observation is measured on one stream with the run's threads, where the network is tuned
(:func:`tune_all`: a worker beside another with ``--workers``). The chosen settings, every kind's best with its time, and a step-by-step diagnosis of each
method on the tuning episodes (:func:`smcd_rl.tuning.diagnostics.trace`: one-step error, ESS, log
evidence, kept share) go into the run's report and ``tuning-<model>.png``. With ``options``,
the one-step error of the tuned SMCD under each of :data:`OPTIONS` (five times the particles;
the posterior predictive mean instead of the MMSE mask) and of SMCD with a Student-t likelihood
calibrated by its own evidence is measured on the same episodes, never on the test tasks.

Example:
    >>> TUNED["S"]
    'smcd'
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.shared.adaptation_config import VARIANTS
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.references import reference_specs
from smcd_rl.experiments.shared.tuning_options import OPTIONS, STUDENT, trace_options
from smcd_rl.experiments.shared.tuning_record import TUNED, Tuning, reseeded
from smcd_rl.experiments.shared.workers import computed, map_jobs
from smcd_rl.strategies.registry import build
from smcd_rl.tuning import ms_per_observation
from smcd_rl.tuning.defaults import PREDICTIONS, WEIGHINGS, kinds_needed
from smcd_rl.tuning.diagnostics import Trace, trace

__all__ = ["Tuning", "TuneJob", "tune", "tune_all", "tuned_specs", "VARIANTS", "TUNED", "OPTIONS", "STUDENT"]


def tuned_specs(
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str,
    paper_noise: float | tuple[float, ...] | list[float],
    budgeted: Sequence[str] = (),
    variants: Sequence[str] = VARIANTS,
    device: str = "cpu",
    progress: bool = False,
) -> dict[str, Any]:
    """Every variant's spec and time per observation from :func:`smcd_rl.tune` and the two references.

    Args:
        model: the trained model.
        episodes: held-out training-task episodes ``[E, T]`` in the model's keys.
        config: a :class:`~smcd_rl.experiments.shared.adaptation_config.TuningConfig` with
            ``particles`` and ``flip_prob``.
        name: the model's name in the tables' captions.
        paper_noise: the fixed likelihood noise of ``S(paper)``.
        budgeted: variants of :data:`TUNED` that also get a spec tuned under ``config.budget_ms``,
            labelled ``"G@10ms"`` and so on.
        variants: the variants (:data:`VARIANTS`) to tune: only the kinds they need are tuned
            (``C`` needs ``G`` and ``S``), and a reference only when asked for; ``N`` always is.
        device: the model's device (where SMCD's generators live).
        progress: show the progress bars.

    Returns:
        ``{"specs", "ms", "runs", "tables", "seconds", "candidates"}``, ``runs`` the variants'
        traces on ``episodes`` that tuning ran already; the unbudgeted result becomes ``model.tuning``.
    """
    seed = config.seed + 23
    grid = {"lr": config.gd_lr, "steps": config.gd_steps, "window": config.gd_window}
    common: dict[str, Any] = {
        "num_particles": config.particles,
        "gd_grid": grid,
        # An experiment may bound the grid's extension: fetch its learning rate (larger ones overflow
        # MPC's rollouts), panda its steps (more do not fit the control period).
        "gd_limits": {
            "lr": (None, getattr(config, "gd_max_lr", None)),
            "steps": (None, getattr(config, "gd_max_steps", None)),
        },
        "flip_probs": config.calibrate_flips,
        **_choices(config),
        "seed": seed,
        "progress": progress,
        # An experiment whose table scores a look-ahead tunes by it (tuning_horizon > 1), else by one-step error.
        **({"criterion": "lookahead", "horizon": h} if (h := getattr(config, "tuning_horizon", 1)) > 1 else {}),
    }
    common["strategies"] = _kinds(variants)
    free = smcd_rl.tune(model, episodes, **common)
    budget = smcd_rl.tune(model, episodes, budget_ms=config.budget_ms, reuse=free, **common)
    specs: dict[str, dict[str, Any]] = {}
    ms: dict[str, float] = {}
    runs: dict[str, Trace] = {}  # the runs on the episodes that tuning made already: the diagnosis reuses them
    for variant, kind in TUNED.items():
        label = f"{variant}@{config.budget_ms:g}ms"
        if kind in free.best_of:
            specs[variant] = {"name": kind, "settings": free.best_of[kind].settings}
            ms[variant] = free.best_of[kind].ms_per_step
            if (run := free.trace(kind)) is not None:
                runs[variant] = run
        if variant in budgeted and kind in budget.best_of:
            specs[label] = {"name": kind, "settings": budget.best_of[kind].settings}
            # The same strategy: one time, not two noisy ones.
            same = variant in specs and specs[label] == specs[variant]
            ms[label] = ms[variant] if same else budget.best_of[kind].ms_per_step
    references, reference_runs = reference_specs(
        model,
        episodes,
        config,
        free,
        variants=variants,
        paper_noise=paper_noise,
        seed=seed,
        device=device,
        progress=progress,
    )
    specs.update(references)
    runs.update(reference_runs)
    for variant in ("S(evidence)", "S(paper)"):
        if variant not in specs:
            continue
        spec = specs[variant]
        ms[variant] = ms_per_observation(model, build(spec["name"], spec["settings"]), episodes[0])
    model.tuning = free.to_dict()  # the unbudgeted choice is the model's own
    return {
        "specs": specs,
        "ms": ms,
        "runs": runs,
        "tables": {
            f"{name}: tuned on {free.episodes} held-out training-task episodes x {free.steps} steps": free.table(),
            f"{name}: tuned under {config.budget_ms:g} ms per observation": budget.table(),
        },
        "seconds": free.seconds + budget.seconds,
        "candidates": len(free.candidates) + len(budget.candidates),
    }


def _kinds(variants: Sequence[str]) -> list[str]:
    """The kinds of :func:`smcd_rl.tune` that ``variants`` need (``"none"`` always: the table's reference row).

    Example:
        >>> _kinds(["G"]), _kinds(["C"]), _kinds(["S(paper)"])
        (['none', 'gradient_descent'], ['none', 'gradient_descent', 'smcd', 'combination'], ['none'])
        >>> _kinds(["SL"])
        ['none', 'smcd', 'last_layer', 'smcd_last_layer']
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    return kinds_needed(["none", *(TUNED[v] for v in variants if v in TUNED)])


@dataclass(frozen=True)
class TuneJob:
    """One trained network to tune: what :func:`tune_all` takes per network (see :func:`tune` for the fields)."""

    model: smcd_rl.AdaptiveModel
    episodes: TensorDictBase
    paper_noise_std: float | Sequence[float] | None = None
    options: bool = True
    variants: Sequence[str] = VARIANTS


def tune(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str = "M",
    paper_noise_std: float | Sequence[float] | None = None,
    options: bool = True,
    variants: Sequence[str] = VARIANTS,
) -> Tuning:
    """Tune ``model``'s strategies on ``episodes`` (held-out training-task episodes), or reuse a rerun's result.

    Args:
        ex: the running experiment (its store caches the result, keyed by the model, the episodes and
            the settings).
        model: the trained model.
        episodes: batch ``[E, T]`` in the model's keys, from tasks drawn as the training tasks were.
        config: an experiment config with :class:`~smcd_rl.experiments.shared.adaptations.AdaptationConfig`'s fields.
        name: the model's name in the method labels.
        paper_noise_std: the fixed likelihood noise of ``S(paper)`` (default ``config.noise_std``).
        options: also trace the tuned SMCD with each of :data:`OPTIONS` and with a Student-t
            likelihood of its own calibration (diagnosis only: no method uses them), where ``S`` is tuned.
        variants: the variants to tune (default all of :data:`VARIANTS`); an experiment passes
            those its methods use, so a network that only runs ``G`` is not calibrated for SMCD.
    """
    return tune_all(ex, {name: TuneJob(model, episodes, paper_noise_std, options, variants)}, config)[name]


def tune_all(ex: Experiment, jobs: Mapping[str, TuneJob], config: Any) -> dict[str, Tuning]:
    """:func:`tune` every network of ``jobs`` (name -> :class:`TuneJob`); those still to tune side by side.

    With ``--workers``, worker processes tune the networks a rerun has not stored yet, each on
    one core; each network's times per observation are then measured beside the other worker's
    tuning (measured on the two-link networks: within 10 % of a quiet machine's, since one
    stream's weights fit in a core's cache). The results are the same for any number of workers.
    """
    keys = {name: _key(job, config) for name, job in jobs.items()}
    found = {name: ex.store.get(f"tuning-{name}", keys[name]) for name in jobs}
    pending = [name for name in jobs if found[name] is None]
    stages = {name: f"tune {name}" for name in jobs}
    workers = ex.workers_for([stages[name] for name in pending]) if len(pending) > 1 else 1

    def compute(name: str, progress: bool) -> functools.partial[dict[str, Any]]:
        job = jobs[name]
        return functools.partial(
            _tune,
            job.model,
            job.episodes,
            config,
            name=name,
            paper_noise=_paper_noise(job, config),
            options=job.options,
            variants=tuple(job.variants),
            device=str(ex.device),
            progress=progress,
        )

    def store(name: str, result: dict[str, Any]) -> None:  # as each finishes: Ctrl-C keeps it
        ex.store.put(f"tuning-{name}", keys[name], result)
        found[name] = result

    if workers > 1:
        with ex.stage(f"tune {', '.join(pending)} in {workers} workers", members=[stages[n] for n in pending]):
            map_jobs(
                {name: compute(name, False) for name in pending},
                computed,
                workers=workers,
                threads=ex.config.threads,
                on_result=store,
                progress=ex.progress,
                costs={name: ex.stages.costs.get(stages[name], 0.0) for name in pending},
            )
    for name in jobs:
        if workers > 1 and name in pending:
            continue
        with ex.stage(stages[name]):  # a stored result too: the progress line counts every stage
            if found[name] is None:
                store(name, compute(name, ex.progress)())
    tunings = {}
    for name in jobs:
        result = found[name]
        assert result is not None
        tunings[name] = Tuning(
            name=name,
            specs=result["specs"],
            ms=result["ms"],
            tune_tables=result["tables"],
            traces=result["traces"],
            options=result["options"],
            seconds=result["seconds"],
            episodes=result["episodes"],
            steps=result["steps"],
        )
        for stage, seconds in result["seconds"].items():
            ex.timings[f"tune {name} {stage}"] = seconds
    return tunings


def _paper_noise(job: TuneJob, config: Any) -> float | tuple[float, ...]:
    """``S(paper)``'s noise: the job's, else the config's ``noise_std``, as floats."""
    value = config.noise_std if job.paper_noise_std is None else job.paper_noise_std
    return tuple(float(v) for v in value) if isinstance(value, Sequence) else float(value)


def _key(job: TuneJob, config: Any) -> dict[str, Any]:
    """Everything a network's tuning depends on: what its stored result is keyed by."""
    return {
        "model": model_digest(job.model),
        "episodes": content_digest(job.episodes),
        "paper_noise": _paper_noise(job, config),
        "options": job.options,
        "variants": sorted(job.variants),
        "settings": {
            k: getattr(config, k)
            for k in (
                "particles",
                "flip_prob",
                "seed",
                "gd_lr",
                "gd_steps",
                "gd_window",
                "calibrate_flips",
                "budget_ms",
            )
        },
        # What else the tuning reads of the config: a change to any of them is another tuning.
        "read_too": [getattr(config, k, None) for k in ("tuning_horizon", "gd_max_lr", "gd_max_steps")],
        **{name: list(allowed) for name, allowed in _choices(config).items()},
    }


def _choices(config: Any) -> dict[str, tuple[str, ...]]:
    """``smcd_rl.tune``'s ``predictions`` and ``weighings`` as the config allows them."""
    return {
        "predictions": tuple(getattr(config, "SMCD_PREDICTIONS", PREDICTIONS)),
        "weighings": tuple(getattr(config, "SL_WEIGHINGS", WEIGHINGS)),
    }


def _tune(
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str,
    paper_noise: float | tuple[float, ...],
    options: bool,
    variants: Sequence[str],
    device: str,
    progress: bool,
) -> dict[str, Any]:
    """One network's tuning, diagnosis and options: what :func:`tune_all` stores (run in a worker or here)."""
    num_episodes, steps = episodes.batch_size
    seed = config.seed + 23
    timer = _Timer()
    with timer("tune"):
        found = tuned_specs(
            model,
            episodes,
            config,
            name=name,
            paper_noise=paper_noise,
            variants=variants,
            device=device,
            progress=progress,
        )
    timer.seconds["references"] = timer.seconds["tune"] - found["seconds"]
    timer.seconds["tune"] = found["seconds"]
    specs = {variant: found["specs"][variant] for variant in VARIANTS if variant in found["specs"]}
    with timer("diagnose"):
        traces = {}
        for variant, spec in specs.items():
            run = found["runs"].get(variant)  # the same strategy, seed and episodes: tuning's own run
            if run is None:
                strategy = build(spec["name"], reseeded(spec["name"], spec["settings"], seed, device))
                run = trace(model, episodes, strategy)
            traces[variant] = run.to_dict()
    traced: dict[str, dict[str, Any]] = {}
    if options and "S" in specs:
        traced, seconds = trace_options(
            model, episodes, config, specs["S"]["settings"], seed=seed, device=device, progress=progress
        )
        timer.seconds |= seconds
    return {
        "specs": specs,
        "ms": {variant: found["ms"][variant] for variant in specs},
        "tables": found["tables"],
        "traces": traces,
        "options": traced,
        "seconds": timer.seconds,
        "episodes": int(num_episodes),
        "steps": int(steps),
    }


class _Timer:
    """``with timer("stage"):`` adds the block's wall seconds to ``timer.seconds["stage"]``."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def __call__(self, stage: str) -> _Timer:
        self._stage = stage
        return self

    def __enter__(self) -> None:
        self._started = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.seconds[self._stage] = self.seconds.get(self._stage, 0.0) + time.perf_counter() - self._started
