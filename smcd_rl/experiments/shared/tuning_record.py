"""What tuning chose for one trained model, and the evidence it chose from: :class:`Tuning`.

:func:`~smcd_rl.experiments.shared.tuning.tune` returns one per trained network; the experiments
build each method's strategy from it and put its tables and plot into their reports.

Example:
    >>> TUNED["S"]
    'smcd'
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

import smcd_rl
from smcd_rl.experiments.shared.outputs import format_table, ms_cell
from smcd_rl.experiments.shared.tuning_plot import plot_traces
from smcd_rl.strategies.registry import build, with_generators
from smcd_rl.tuning import describe_settings

__all__ = ["Tuning", "TUNED", "reseeded"]

#: Variant -> the kind of :func:`smcd_rl.tune`'s result it takes.
TUNED = {
    "N": "none",
    "G": "gradient_descent",
    "S": "smcd",
    "L": "last_layer",
    "SL": "smcd_last_layer",
    "C": "combination",
}


@dataclass
class Tuning:
    """What :func:`tune` chose for one trained model, and the evidence it chose from."""

    #: The model's name in the experiment (``"M"``, ``"R"``...).
    name: str
    #: Variant (:data:`VARIANTS`) -> ``{"name": ..., "settings": ...}`` (a strategy spec, :func:`smcd_rl.strategies.registry.spec`) for :func:`smcd_rl.strategies.registry.build`.
    specs: dict[str, dict[str, Any]]
    #: Variant -> median wall milliseconds per observation (one stream, the run's threads).
    ms: dict[str, float]
    #: Caption -> Markdown: :func:`smcd_rl.tune`'s tables, unbudgeted and under ``--budget-ms``.
    tune_tables: dict[str, str]
    #: Per variant: the :class:`~smcd_rl.tuning.diagnostics.Trace` on the tuning episodes, as a dict.
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
        return build(spec["name"], reseeded(spec["name"], spec["settings"], seed, str(device)))

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


def reseeded(kind: str, settings: dict[str, Any], seed: int, device: str) -> dict[str, Any]:
    """``settings`` with every SMCD's generator seeded by ``seed`` on ``device`` (a combination's members too)."""
    return with_generators(kind, settings, seed=seed, device=device)


def _scores(t: Mapping[str, Any]) -> list[Any]:
    """A trace's table cells: one-step RMSE, final log evidence and smallest ESS share (``-`` without SMCD)."""
    evidence = f"{t['log_evidence'][-1]:.1f}" if t["log_evidence"] else "-"
    ess = f"{min(t['ess']):.3f}" if t["ess"] else "-"
    return [t["rmse"], evidence, ess]
