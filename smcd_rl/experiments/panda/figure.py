"""``panda.png``: Fig. 3's success rate against the measurement interval, one line per method.

Example:
    >>> import tempfile, pathlib
    >>> from smcd_rl.experiments.panda.config import PandaConfig
    >>> row = {"method": "M+S", "interval": 5, "success_mean": 0.5, "success_low": 0.4, "success_high": 0.6}
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "panda.png"
    >>> plot([row, {**row, "method": "FK", "interval": 1}], PandaConfig(intervals=(5,)), path)
    >>> path.exists()
    True
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

from smcd_rl.experiments.panda.config import PandaConfig
from smcd_rl.experiments.shared.outputs import save_figure

__all__ = ["plot"]


def plot(rows: list[dict[str, Any]], config: PandaConfig, path: Path) -> None:
    """``panda.png``: success rate against the measurement interval n, per method, with FK's n = 1 line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    intervals = sorted(set(config.intervals))
    # Orange is the reference line's, as in Fig. 3; the methods take the other colours.
    colours = itertools.cycle(
        ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan"]
    )
    for label in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == label and r["interval"] in intervals]
        ax.errorbar(
            [r["interval"] for r in sel],
            [r["success_mean"] for r in sel],
            color=next(colours),
            yerr=[
                [r["success_mean"] - r["success_low"] for r in sel],
                [r["success_high"] - r["success_mean"] for r in sel],
            ],
            marker="o",
            capsize=2,
            label=label,
        )
    reference = [r for r in rows if r["method"] == "FK" and r["interval"] == 1]
    if reference:
        ax.axhline(reference[0]["success_mean"], color="tab:orange", linestyle="--", label="FK, measured every step")
    ax.set_xscale("log")
    ax.set_xticks(intervals, [str(n) for n in intervals])
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("measurement interval n (steps)")
    ax.set_ylabel(f"success rate (within {100 * config.tolerance:.0f} cm in {config.steps} steps)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title(f"Panda reaching, unknown tool ({config.tasks} tasks x {config.seeds} seeds)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
