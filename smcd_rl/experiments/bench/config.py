"""The config every ``smcd-rl bench`` command derives from (see :mod:`smcd_rl.experiments.bench.tools`).

Example:
    >>> BenchConfig().device, BenchConfig().json
    ('auto', False)
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.config import ExperimentConfig, setting

__all__ = ["BenchConfig"]


@dataclass
class BenchConfig(ExperimentConfig):
    """The settings every benchmark shares: it times on the GPU when there is one, and can print JSON."""

    device: str = setting("auto", "torch device: auto (cuda when available), cpu, cuda, cuda:1, ...")
    json: bool = setting(False, "print the results as JSON (for tools) instead of the table")
