"""The fair protocol: every method's settings from :func:`smcd_rl.tune` on held-out training-task episodes.

Before any test task is seen, each experiment draws ``--tuning-episodes`` episodes from its
*training* distribution (fresh tasks, never the test tasks) and tunes every method on them by
one criterion, the one-step prediction error:

- **gradient descent (``G``)** over the grid ``--gd-lr`` x ``--gd-steps`` x ``--gd-window`` x
  {squared error, Huber}, extended past an edge while the best point lies there;
- **SMCD (``S``)**: noise (scalar or per dimension) and flip probability (``--calibrate-flips``);
- **the combination (``C``)** of N, G and S, its ``eta`` and fixed share;
- **SMCD calibrated by its evidence (``S(evidence)``)** and **SMCD at the paper's settings
  (``S(paper)``)**, the two references: what the filter's own criterion and no tuning give.

A second call under ``--budget-ms`` per observation (reusing the first call's scores) gives the
budgeted view: what each kind would be within a 100 Hz control step. Each method's median time
per observation (one stream, the run's threads) is measured in the main process, while no worker
runs. The chosen settings, every kind's best with its time, and a step-by-step diagnosis of each
method on the tuning episodes (:func:`smcd_rl.diagnostics.trace`: one-step error, ESS, log
evidence, kept share) go into the run's report and ``tuning-<model>.png``. With ``options``,
the one-step error of the tuned SMCD under each of :data:`OPTIONS` (five times the particles;
the posterior predictive mean instead of the MMSE mask) and of SMCD with a Student-t likelihood
calibrated by its own evidence is measured on the same episodes, never on the test tasks.

Example:
    >>> TUNED["S"]
    'smcd'
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.calibration import calibrate
from smcd_rl.diagnostics import Trace, trace
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.shared.adaptation_config import VARIANTS
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table, ms_cell
from smcd_rl.experiments.shared.tuning_options import OPTIONS, STUDENT, trace_options
from smcd_rl.experiments.shared.tuning_plot import plot_traces
from smcd_rl.tuning import build_strategy, describe_settings, ms_per_observation

__all__ = [
    "Tuning",
    "tune",
    "tuned_specs",
    "VARIANTS",
    "TUNED",
    "OPTIONS",
    "STUDENT",
]

#: Variant -> the kind of :func:`smcd_rl.tune`'s result it takes.
TUNED = {"N": "none", "G": "gradient_descent", "S": "smcd", "C": "combination"}


@dataclass
class Tuning:
    """What :func:`tune` chose for one trained model, and the evidence it chose from."""

    #: The model's name in the experiment (``"M"``, ``"R"``...).
    name: str
    #: Variant (:data:`VARIANTS`) -> ``{"kind": ..., "settings": ...}`` for :func:`smcd_rl.tuning.build_strategy`.
    specs: dict[str, dict[str, Any]]
    #: Variant -> median wall milliseconds per observation (one stream, the run's threads).
    ms: dict[str, float]
    #: Caption -> Markdown: :func:`smcd_rl.tune`'s tables, unbudgeted and under ``--budget-ms``.
    tune_tables: dict[str, str]
    #: Per variant: the :class:`~smcd_rl.diagnostics.Trace` on the tuning episodes, as a dict.
    traces: dict[str, dict[str, Any]]
    #: The tuned SMCD with one option changed (see :data:`OPTIONS`): its trace, per option.
    options: dict[str, dict[str, Any]]
    #: Wall seconds of tuning, of the references and of the diagnosis runs.
    seconds: dict[str, float]
    episodes: int
    steps: int

    def strategy(self, variant: str, *, seed: int, device: torch.device | str = "cpu") -> smcd_rl.Adaptation:
        """A fresh strategy of a variant in :data:`VARIANTS`, SMCD's generator seeded with ``seed`` on ``device``."""
        if variant not in self.specs:
            raise ValueError(f"unknown strategy {variant!r}; choose from {list(self.specs)}")
        spec = self.specs[variant]
        return build_strategy(spec["kind"], _reseeded(spec["kind"], spec["settings"], seed, str(device)))

    def table(self) -> str:
        """Each variant's settings, its one-step RMSE (and SMCD's evidence) on the tuning episodes, its time."""
        rows = []
        for variant, spec in self.specs.items():
            settings = describe_settings(spec["settings"])
            rows.append([f"{self.name}+{variant}", settings, *_scores(self.traces[variant]), ms_cell(self.ms[variant])])
        for option, t in self.options.items():
            rows.append([f"{self.name}+S, {option}", t["settings"], *_scores(t), "-"])
        header = ["method", "settings", "one-step RMSE", "log evidence / episode", "min ESS share", "ms / observation"]
        return format_table(rows, header)

    def caption(self) -> str:
        s = self.seconds
        return (
            f"Tuning of {self.name} on {self.episodes} held-out training-task episodes x {self.steps} steps "
            f"(smcd_rl.tune {s['tune']:.1f} s, references {s['references']:.1f} s; diagnosis on the same episodes)"
        )

    def tables(self) -> dict[str, str]:
        """Every tuning table of this model for the report, caption -> Markdown."""
        return {self.caption(): self.table(), **self.tune_tables}

    def payload(self) -> dict[str, Any]:
        """The ``results.json`` entry: chosen settings, times, traces and the tuning tables."""
        return {
            "specs": self.specs,
            "ms_per_observation": self.ms,
            "tune_tables": self.tune_tables,
            "traces": self.traces,
            "options": self.options,
            "seconds": self.seconds,
            "episodes": self.episodes,
            "steps": self.steps,
        }

    def plot(self, path: Path) -> None:
        """``tuning-<name>.png``: one-step error, ESS share, log evidence and kept share over the steps."""
        plot_traces(self.name, self.traces, self.episodes, path)


def tuned_specs(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str,
    paper_noise: float | tuple[float, ...] | list[float],
    budgeted: Sequence[str] = (),
    variants: Sequence[str] = VARIANTS,
) -> dict[str, Any]:
    """Every variant's spec and time per observation from :func:`smcd_rl.tune` and the two references.

    Args:
        ex: the running experiment (its device and progress setting).
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

    Returns:
        ``{"specs", "ms", "runs", "tables", "seconds", "candidates"}``, ``runs`` the variants'
        traces on ``episodes`` that tuning ran already; the unbudgeted result becomes ``model.tuning``.
    """
    seed = config.seed + 23
    device = str(ex.device)
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
        "seed": seed,
        "progress": ex.progress,
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
            specs[variant] = {"kind": kind, "settings": free.best_of[kind].settings}
            ms[variant] = free.best_of[kind].ms_per_step
            if (run := free.trace(kind)) is not None:
                runs[variant] = run
        if variant in budgeted and kind in budget.best_of:
            specs[label] = {"kind": kind, "settings": budget.best_of[kind].settings}
            # The same strategy: one time, not two noisy ones.
            same = variant in specs and specs[label] == specs[variant]
            ms[label] = ms[variant] if same else budget.best_of[kind].ms_per_step
    if "S(evidence)" in variants:
        evidence = calibrate(
            model,
            episodes,
            base=smcd_rl.SMCD(num_particles=config.particles),
            flip_probs=config.calibrate_flips,
            criterion="evidence",
            seed=seed,
            progress=ex.progress,
        )
        settings = {**evidence.strategy.config(), "seed": seed, "device": device}
        specs["S(evidence)"] = {"kind": "smcd", "settings": settings}
        if evidence.best.trace is not None:
            runs["S(evidence)"] = evidence.best.trace
    if "S(paper)" in variants:
        noise = list(paper_noise) if isinstance(paper_noise, (tuple, list)) else float(paper_noise)
        paper = {"num_particles": config.particles, "noise_std": noise, "flip_prob": config.flip_prob}
        specs["S(paper)"] = {"kind": "smcd", "settings": {**paper, "seed": seed, "device": device}}
    for variant in ("S(evidence)", "S(paper)"):
        if variant not in specs:
            continue
        spec = specs[variant]
        ms[variant] = ms_per_observation(model, build_strategy(spec["kind"], spec["settings"]), episodes[0])
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
    """The kinds of :func:`smcd_rl.tune` that ``variants`` need, ``"none"`` always (the table's reference row).

    Example:
        >>> _kinds(["G"]), _kinds(["C"]), _kinds(["S(paper)"])
        (['none', 'gradient_descent'], ['none', 'gradient_descent', 'smcd', 'combination'], ['none'])
    """
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    needed = {"N", *variants, *(("G", "S") if "C" in variants else ())}
    return [kind for variant, kind in TUNED.items() if variant in needed]


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
    paper_noise = config.noise_std if paper_noise_std is None else paper_noise_std
    paper_noise = tuple(float(v) for v in paper_noise) if isinstance(paper_noise, Sequence) else float(paper_noise)
    key = {
        "model": model_digest(model),
        "episodes": content_digest(episodes),
        "paper_noise": paper_noise,
        "options": options,
        "variants": sorted(variants),
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
    }
    with ex.stage(f"tune {name}"):
        found = ex.store.get(f"tuning-{name}", key)
        if found is None:
            found = _tune(
                ex, model, episodes, config, name=name, paper_noise=paper_noise, options=options, variants=variants
            )
            ex.store.put(f"tuning-{name}", key, found)
    tuning = Tuning(
        name=name,
        specs=found["specs"],
        ms=found["ms"],
        tune_tables=found["tables"],
        traces=found["traces"],
        options=found["options"],
        seconds=found["seconds"],
        episodes=found["episodes"],
        steps=found["steps"],
    )
    for stage, seconds in tuning.seconds.items():
        ex.timings[f"tune {name} {stage}"] = seconds
    return tuning


def _tune(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str,
    paper_noise: float | tuple[float, ...],
    options: bool,
    variants: Sequence[str],
) -> dict[str, Any]:
    num_episodes, steps = episodes.batch_size
    seed = config.seed + 23
    timer = _Timer()
    with timer("tune"):
        found = tuned_specs(ex, model, episodes, config, name=name, paper_noise=paper_noise, variants=variants)
    timer.seconds["references"] = timer.seconds["tune"] - found["seconds"]
    timer.seconds["tune"] = found["seconds"]
    specs = {variant: found["specs"][variant] for variant in VARIANTS if variant in found["specs"]}
    with timer("diagnose"):
        traces = {}
        for variant, spec in specs.items():
            run = found["runs"].get(variant)  # the same strategy, seed and episodes: tuning's own run
            if run is None:
                strategy = build_strategy(spec["kind"], _reseeded(spec["kind"], spec["settings"], seed, str(ex.device)))
                run = trace(model, episodes, strategy)
            traces[variant] = asdict(run)
    traced: dict[str, dict[str, Any]] = {}
    if options and "S" in specs:
        traced, seconds = trace_options(ex, model, episodes, config, specs["S"]["settings"], seed=seed)
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


def _reseeded(kind: str, settings: dict[str, Any], seed: int, device: str) -> dict[str, Any]:
    """``settings`` with every SMCD's generator seeded by ``seed`` on ``device`` (a combination's members too)."""
    if kind == "smcd":
        return {**settings, "seed": seed, "device": device}
    if kind == "combination":
        members = [{**m, "settings": _reseeded(m["name"], m["settings"], seed, device)} for m in settings["members"]]
        return {**settings, "members": members}
    return settings


def _scores(t: Mapping[str, Any]) -> list[Any]:
    """A trace's table cells: one-step RMSE, final log evidence and smallest ESS share (``-`` without SMCD)."""
    evidence = f"{t['log_evidence'][-1]:.1f}" if t["log_evidence"] else "-"
    ess = f"{min(t['ess']):.3f}" if t["ess"] else "-"
    return [t["rmse"], evidence, ess]


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
