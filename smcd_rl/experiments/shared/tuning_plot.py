"""``tuning-<model>.png``: each tuned strategy's diagnosis on the tuning episodes, step by step.

Example:
    >>> import tempfile, pathlib
    >>> trace = {"one_step_rmse": [0.3, 0.2], "ess": [0.9, 0.5], "log_evidence": [-1.0, -2.0], "kept": [0.5, 0.5]}
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "tuning-M.png"
    >>> plot_traces("M", {"S": trace, "N": {**trace, "ess": [], "log_evidence": [], "kept": []}}, 2, path)
    >>> path.exists()
    True
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from smcd_rl.experiments.shared.outputs import save_figure

__all__ = ["plot_traces"]

#: (trace key, panel title, first step): one panel each.
PANELS = [
    ("one_step_rmse", "one-step RMSE", 2),
    ("ess", "ESS / particles (before resampling)", 1),
    ("log_evidence", "log evidence so far / episode", 1),
    ("kept", "share of units the mask keeps", 1),
]


def plot_traces(name: str, traces: Mapping[str, Mapping[str, Any]], episodes: int, path: Path) -> None:
    """Plot each variant's :class:`~smcd_rl.tuning.diagnostics.Trace` (as a dict) of model ``name`` to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(15, 3.4))
    for ax, (key, label, first) in zip(axes, PANELS, strict=True):
        for i, (variant, t) in enumerate(traces.items()):
            if t[key]:  # a colour per strategy in every panel, also where some have no values
                steps = range(first, first + len(t[key]))
                ax.plot(steps, t[key], marker=".", color=f"C{i}", label=f"{name}+{variant}")
        ax.set_xlabel("step")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[2].set_yscale("symlog")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{name}: strategies on {episodes} held-out training-task episodes (diagnosis)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
