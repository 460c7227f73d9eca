"""The fair protocol: every adaptive method gets its settings from the same held-out training-task episodes.

Before any test task is seen, each experiment draws ``--tuning-episodes`` episodes from its
*training* distribution (fresh tasks, never the test tasks) and tunes on them:

- **SMCD (``S``)** by :func:`smcd_rl.calibrate`: the likelihood noise and flip probability of
  highest log evidence (about 17 filter runs);
- **gradient descent (``G``)** by the best one-step error over the grid ``--gd-lr`` x
  ``--gd-steps`` x ``--gd-window`` (16 runs by default);
- **SMCD with the paper's settings (``S(paper)``)**: ``--noise-std`` and ``--flip-prob`` as given,
  not tuned, so every table shows what calibration changed.

Both tuned methods see the same episodes and a similar number of runs over them. The chosen
settings, every candidate's score and a step-by-step diagnosis of each strategy on those episodes
(:func:`smcd_rl.diagnostics.trace`: one-step error, ESS, log evidence, kept share) go into the
run's report and ``tuning-<model>.png``, with the one-step error of the calibrated SMCD under each
of :data:`OPTIONS` (five times the particles; the posterior predictive mean instead of the MMSE
mask) and of SMCD with a Student-t likelihood calibrated by its own evidence, measured on the same
tuning episodes and never on the test tasks.

Example:
    >>> method_variant("M+S(paper)")
    ('M', 'S(paper)')
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from itertools import product
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.calibration import calibrate
from smcd_rl.diagnostics import Trace, trace
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.shared.adaptation_config import VARIANTS
from smcd_rl.experiments.shared.adaptations import StrategySettings
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table, save_figure

__all__ = ["Tuning", "tune", "VARIANTS", "method_variant", "strategy_for"]

#: Options of SMCD measured on the tuning episodes only (their one-step error goes into the tuning
#: table beside the calibrated S): option -> the settings it changes, from the calibrated SMCD's.
OPTIONS: dict[str, Callable[[smcd_rl.SMCD], dict[str, Any]]] = {
    "5x particles": lambda smcd: {"num_particles": 5 * smcd.num_particles},
    "predictive mean": lambda smcd: {"prediction": "predictive"},
}
#: The option of a Student-t likelihood (4 degrees of freedom), calibrated by its own evidence.
STUDENT = "Student-t likelihood"


@dataclass
class Tuning:
    """What :func:`tune` chose for one trained model, and the evidence it chose from."""

    #: The model's name in the experiment (``"M"``, ``"R"``...).
    name: str
    #: Calibrated SMCD and the best GD of the grid (variant ``S`` and ``G``).
    tuned: StrategySettings
    #: SMCD at the given (paper) settings, GD at the grid's first point (variant ``S(paper)``).
    paper: StrategySettings
    #: Every GD grid point with its one-step RMSE.
    gd_grid: list[dict[str, Any]]
    #: Every calibration candidate (noise, flip, log evidence, one-step RMSE).
    calibration: list[dict[str, Any]]
    #: Per variant: the :class:`~smcd_rl.diagnostics.Trace` on the tuning episodes, as a dict.
    traces: dict[str, dict[str, Any]]
    #: The calibrated SMCD with one option changed (see :data:`OPTIONS`): its trace, per option.
    options: dict[str, dict[str, Any]]
    #: Wall seconds of calibration, of the GD grid and of the diagnosis runs.
    seconds: dict[str, float]
    episodes: int
    steps: int

    def strategy(self, variant: str, *, seed: int, device: torch.device | str = "cpu") -> smcd_rl.Adaptation:
        """The strategy of a variant in :data:`VARIANTS`."""
        if variant == "S(paper)":
            return self.paper.strategy("S", seed=seed, device=device)
        if variant not in VARIANTS:
            raise ValueError(f"unknown strategy {variant!r}; choose from {list(VARIANTS)}")
        return self.tuned.strategy(variant, seed=seed, device=device)

    def table(self) -> str:
        """Each variant's settings and its one-step RMSE (and SMCD's evidence) on the tuning episodes."""
        rows = []
        for variant in VARIANTS:
            t = self.traces[variant]
            settings = {
                "N": "-",
                "G": f"lr {self.tuned.gd_lr:g}, {self.tuned.gd_steps} steps, window {self.tuned.gd_window}",
                "S": f"noise {_noise_text(self.tuned.noise_std)}, flip {self.tuned.flip_prob:g}",
                "S(paper)": f"noise {_noise_text(self.paper.noise_std)}, flip {self.paper.flip_prob:g}",
            }[variant]
            rows.append([f"{self.name}+{variant}", settings, *_scores(t)])
        for option, t in self.options.items():
            rows.append([f"{self.name}+S, {option}", t["settings"], *_scores(t)])
        return format_table(rows, ["method", "settings", "one-step RMSE", "log evidence / episode", "min ESS share"])

    def caption(self) -> str:
        s = self.seconds
        return (
            f"Tuning of {self.name} on {self.episodes} held-out training-task episodes x {self.steps} steps "
            f"(calibration {len(self.calibration)} filter runs, {s['calibrate']:.1f} s; GD grid {len(self.gd_grid)} "
            f"runs, {s['gd_grid']:.1f} s)"
        )

    def payload(self) -> dict[str, Any]:
        """The ``results.json`` entry: chosen settings, every candidate, traces and times."""
        return {
            "tuned": asdict(self.tuned),
            "paper": asdict(self.paper),
            "gd_grid": self.gd_grid,
            "calibration": self.calibration,
            "traces": self.traces,
            "options": self.options,
            "seconds": self.seconds,
            "episodes": self.episodes,
            "steps": self.steps,
        }

    def plot(self, path: Path) -> None:
        """``tuning-<name>.png``: one-step error, ESS share, log evidence and kept share over the steps."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 4, figsize=(15, 3.4))
        panels = [
            ("one_step_rmse", "one-step RMSE", 2),
            ("ess", "ESS / particles (before resampling)", 1),
            ("log_evidence", "log evidence so far / episode", 1),
            ("kept", "share of units the mask keeps", 1),
        ]
        for ax, (key, label, first) in zip(axes, panels, strict=True):
            for i, (variant, t) in enumerate(self.traces.items()):
                if t[key]:  # a colour per strategy in every panel, also where some have no values
                    steps = range(first, first + len(t[key]))
                    ax.plot(steps, t[key], marker=".", color=f"C{i}", label=f"{self.name}+{variant}")
            ax.set_xlabel("step")
            ax.set_title(label, fontsize=9)
            ax.grid(alpha=0.3)
        axes[0].set_yscale("log")
        axes[2].set_yscale("symlog")
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{self.name}: strategies on {self.episodes} held-out training-task episodes (diagnosis)")
        fig.tight_layout()
        save_figure(fig, path, dpi=110)
        plt.close(fig)


def method_variant(name: str) -> tuple[str, str]:
    """``"M+S(paper)"`` -> ``("M", "S(paper)")``."""
    model, _, variant = name.partition("+")
    return model, variant


def strategy_for(
    name: str, tunings: Mapping[str, Tuning], *, seed: int, device: torch.device | str = "cpu"
) -> smcd_rl.Adaptation:
    """The strategy of method ``name`` (``"M+G"``, ``"R+S(paper)"``...) from its network's tuning.

    ``N`` needs none (an experiment runs no tuning when only unadapted methods run).
    """
    network, variant = method_variant(name)
    if variant == "N":
        return smcd_rl.NoAdaptation()
    if network not in tunings:
        raise ValueError(f"{name} adapts with tuned settings, but {network} was not tuned")
    return tunings[network].strategy(variant, seed=seed, device=device)


def tune(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str = "M",
    paper_noise_std: float | Sequence[float] | None = None,
    options: bool = True,
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
        options: also trace the calibrated SMCD with each of :data:`OPTIONS` and with a Student-t
            likelihood of its own calibration (diagnosis only: no method uses them; about as long
            again as the calibration).
    """
    paper_noise = config.noise_std if paper_noise_std is None else paper_noise_std
    paper_noise = tuple(float(v) for v in paper_noise) if isinstance(paper_noise, Sequence) else float(paper_noise)
    key = {
        "model": model_digest(model),
        "episodes": content_digest(episodes),
        "paper_noise": paper_noise,
        "options": options,
        "settings": {
            k: getattr(config, k)
            for k in ("particles", "flip_prob", "seed", "gd_lr", "gd_steps", "gd_window", "calibrate_flips")
        },
    }
    with ex.stage(f"tune {name}"):
        found = ex.store.get(f"tuning-{name}", key)
        if found is None:
            found = _tune(ex, model, episodes, config, name=name, paper_noise=paper_noise, options=options)
            ex.store.put(f"tuning-{name}", key, found)
    tuning = Tuning(
        name=name,
        tuned=_settings(found["tuned"]),
        paper=_settings(found["paper"]),
        gd_grid=found["gd_grid"],
        calibration=found["calibration"],
        traces=found["traces"],
        options=found["options"],
        seconds=found["seconds"],
        episodes=found["episodes"],
        steps=found["steps"],
    )
    for stage, seconds in tuning.seconds.items():
        ex.timings[f"tune {name} {stage}"] = seconds
    return tuning


def _settings(values: Mapping[str, Any]) -> StrategySettings:
    return StrategySettings(**{**values, "noise_std": _as_tuple(values["noise_std"])})


def _tune(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    *,
    name: str,
    paper_noise: float | tuple[float, ...],
    options: bool,
) -> dict[str, Any]:
    num_episodes, steps = episodes.batch_size
    seed = config.seed + 23
    timer = _Timer()

    with timer("calibrate"):
        base = smcd_rl.SMCD(num_particles=config.particles)
        result = calibrate(
            model,
            episodes,
            base=base,
            flip_probs=config.calibrate_flips,
            criterion="evidence",
            seed=seed,
            progress=ex.progress,
        )
    calibration = [asdict(c) for c in result.candidates]

    with timer("gd_grid"):
        grid = list(product(config.gd_lr, config.gd_steps, config.gd_window))
        gd_grid = []
        for lr, gd_steps, window in ex.bar(grid, desc=f"tune {name}+G", unit="setting"):
            gd = smcd_rl.GradientDescent(lr=lr, steps=gd_steps, window=window)
            gd_grid.append({"lr": lr, "steps": gd_steps, "window": window, "one_step_rmse": _rmse(model, episodes, gd)})
    best = min(gd_grid, key=lambda row: row["one_step_rmse"])  # the first of equals: the grid's order

    tuned = StrategySettings(
        particles=config.particles,
        noise_std=_as_tuple(result.noise_std),
        flip_prob=result.flip_prob,
        gd_lr=best["lr"],
        gd_steps=best["steps"],
        gd_window=best["window"],
    )
    first = gd_grid[0]
    paper = StrategySettings(
        particles=config.particles,
        noise_std=paper_noise,
        flip_prob=config.flip_prob,
        gd_lr=first["lr"],
        gd_steps=first["steps"],
        gd_window=first["window"],
    )
    with timer("diagnose"):
        traces = {}
        for variant in VARIANTS:
            settings = paper if variant == "S(paper)" else tuned
            strategy = settings.strategy(variant[0], seed=seed, device=ex.device)
            traces[variant] = asdict(trace(model, episodes, strategy))
    traced = _trace_options(ex, model, episodes, config, tuned, seed=seed, timer=timer) if options else {}
    return {
        "tuned": asdict(tuned),
        "paper": asdict(paper),
        "gd_grid": gd_grid,
        "calibration": calibration,
        "traces": traces,
        "options": traced,
        "seconds": timer.seconds,
        "episodes": int(num_episodes),
        "steps": int(steps),
    }


def _trace_options(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    tuned: StrategySettings,
    *,
    seed: int,
    timer: _Timer,
) -> dict[str, dict[str, Any]]:
    """The calibrated SMCD's trace with each option changed, and with a Student-t likelihood of its own calibration."""
    options = {}
    with timer("options"):
        for option, changed in OPTIONS.items():
            smcd = tuned.strategy("S", seed=seed, device=ex.device)
            assert isinstance(smcd, smcd_rl.SMCD)
            generator = torch.Generator(device=ex.device).manual_seed(seed)
            other = smcd_rl.SMCD(**{**smcd.config(), **changed(smcd)}, generator=generator)
            options[option] = {**asdict(trace(model, episodes, other)), "settings": "as S"}
    with timer("student-t"):  # a likelihood of its own needs a noise of its own: calibrated by its evidence
        chosen = model.calibration
        student = calibrate(
            model,
            episodes,
            base=smcd_rl.SMCD(num_particles=config.particles, likelihood="student-t"),
            flip_probs=config.calibrate_flips,
            criterion="evidence",
            seed=seed,
            progress=ex.progress,
        )
        model.calibration = chosen  # the model keeps the Gaussian SMCD's calibration
        generator = torch.Generator(device=ex.device).manual_seed(seed)
        strategy = smcd_rl.SMCD(**student.strategy.config(), generator=generator)
        options[STUDENT] = {
            **asdict(trace(model, episodes, strategy)),
            "settings": f"noise {_noise_text(_as_tuple(student.noise_std))}, flip {student.flip_prob:g}",
        }
    return options


def _rmse(model: smcd_rl.AdaptiveModel, episodes: TensorDictBase, strategy: smcd_rl.Adaptation) -> float:
    result: Trace = trace(model, episodes, strategy)
    return result.rmse if math.isfinite(result.rmse) else math.inf


def _as_tuple(noise: float | Sequence[float]) -> float | tuple[float, ...]:
    """A noise as :class:`StrategySettings` holds it: a float, or a tuple of per-dimension ones."""
    return noise if isinstance(noise, (int, float)) else tuple(noise)


def _scores(t: Mapping[str, Any]) -> list[Any]:
    """A trace's table cells: one-step RMSE, final log evidence and smallest ESS share (``-`` without SMCD)."""
    evidence = f"{t['log_evidence'][-1]:.1f}" if t["log_evidence"] else "-"
    ess = f"{min(t['ess']):.3f}" if t["ess"] else "-"
    return [t["rmse"], evidence, ess]


def _noise_text(noise: float | tuple[float, ...]) -> str:
    if isinstance(noise, tuple):
        rms = math.sqrt(sum(v * v for v in noise) / len(noise))
        return f"rms {rms:.3g} ({len(noise)} dims)"
    return f"{noise:.3g}"


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
