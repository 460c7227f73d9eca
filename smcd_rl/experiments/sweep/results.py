"""The results of ``smcd-rl sweep``: per-parameter summaries, the smcd study's statistics, the plot.

The summary describes the grid: per parameter value, the mean, std and min of a metric over all
combinations of the other parameters (the spread the paper's panels show). It is not a sampling
statistic, so it has no confidence interval. The smcd study also scores every grid point on the
same held-out arms, so each point's MSE gets a 95 % bootstrap interval over the arms, and SMCD is
compared, paired over those arms, with the same trained network without adaptation (M+N) and
with online gradient descent (M+G).
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.experiments.shared.stats import Estimate, cell_statistics, verdict_table
from smcd_rl.experiments.sweep.config import FILTER_STUDIES

__all__ = [
    "LABELS",
    "FIGURES",
    "MODEL_PARAMETERS",
    "NETWORKS",
    "method",
    "title",
    "summarise",
    "table",
    "smcd_statistics",
    "verdict_counts",
    "headline",
    "model_parameters",
    "reference_table",
    "plot",
]

LABELS = {
    "hidden": "latent dimension",
    "dropout": "dropout p",
    "lr": "learning rate",
    "batch_size": "batch size",
    "epochs": "epochs",
    "flip_prob": "bit-flip probability",
    "noise_std": "likelihood noise (m)",
    "particles": "particles N",
    "task_share": "task-mask share (0: random dropout)",
    "mask_groups": "mask bits per layer (0: one per unit)",
    "tasks": "training arms",
}

#: The paper figure of each study (the masks study has none).
FIGURES = {"training": 5, "smcd": 6, "drone": 12}
#: The trained model's parameters in each filter study (the others are the filter's).
MODEL_PARAMETERS = {"smcd": ("hidden", "dropout"), "masks": ("task_share", "mask_groups", "tasks")}
#: The network each filter study trains, as the methods' prefix: M (random dropout) or T (task masks).
NETWORKS = {"smcd": "M", "masks": "T"}


def method(study: str, kind: str) -> str:
    """A method's label in a filter study: its network's letter, then ``kind`` (N, G or S).

    Example:
        >>> method("smcd", "S"), method("masks", "G")
        ('M+S', 'T+G')
    """
    return f"{NETWORKS[study]}+{kind}"


def summarise(
    rows: Sequence[Mapping[str, Any]], parameters: Sequence[str], metrics: Sequence[str]
) -> list[dict[str, Any]]:
    """Per metric, parameter and value: trials, mean, std (population) and min over the other parameters.

    Example:
        >>> rows = [{"lr": 0.1, "hidden": 8, "loss": 1.0}, {"lr": 0.1, "hidden": 16, "loss": 3.0}]
        >>> summarise(rows, ["lr"], ["loss"])
        [{'metric': 'loss', 'parameter': 'lr', 'value': 0.1, 'trials': 2, 'mean': 2.0, 'std': 1.0, 'min': 1.0}]
    """
    summary = []
    for metric in metrics:
        for name in parameters:
            for value in dict.fromkeys(row[name] for row in rows):
                values = [float(row[metric]) for row in rows if row[name] == value]
                summary.append(
                    {
                        "metric": metric,
                        "parameter": name,
                        "value": value,
                        "trials": len(values),
                        "mean": statistics.fmean(values),
                        "std": statistics.pstdev(values),
                        "min": min(values),
                    }
                )
    return summary


def table(summary: Sequence[Mapping[str, Any]]) -> str:
    """The summary as a Markdown table (4 significant digits: losses and learning rates span decades).

    Example:
        >>> print(table([{"metric": "loss", "parameter": "lr", "value": 0.0001, "trials": 2, "mean": 2.0, "std": 1.0, "min": 1.0}]))
        | metric | parameter | value  | trials | mean | std | min |
        |--------|-----------|--------|--------|------|-----|-----|
        | loss   | lr        | 0.0001 | 2      | 2    | 1   | 1   |
    """
    header = ["metric", "parameter", "value", "trials", "mean", "std", "min"]
    body = [
        [row["metric"], row["parameter"], _number(row["value"]), row["trials"]] + [_number(row[k]) for k in header[4:]]
        for row in summary
    ]
    return format_table(body, header)


def _number(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def smcd_statistics(
    rows: list[dict[str, Any]],
    arms: Sequence[Mapping[str, torch.Tensor]],
    references: Mapping[tuple[Any, ...], Mapping[str, Mapping[str, torch.Tensor]]],
    parameters: Sequence[str],
    pairs: Sequence[tuple[int, int]],
    *,
    seed: int,
    study: str = "smcd",
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Add 95 % CIs to the grid points' rows; compare SMCD with N and G on its network, paired over the arms.

    Args:
        rows: one row per grid point (its parameters and metric means); gains ``{metric}_low`` and
            ``{metric}_high`` columns after each metric.
        arms: per grid point, metric -> per-arm MSE.
        references: the model's parameter values (the study's :data:`MODEL_PARAMETERS` present
            in ``parameters``) -> method (``M+N``, ``M+G``; ``T+...`` in the masks study) ->
            metric -> per-arm MSE.
        parameters: the grid's parameters.
        pairs: the (burn-in T, horizon H) of each metric, in the metrics' order.
        seed: the bootstrap seed.
        study: the filter study, which names the network (:data:`NETWORKS`).

    Returns:
        ``(reference_rows, comparisons)``: the reference methods' mean and 95 % CI per model and
        (T, H), and one row per paired comparison (``M+S`` against ``M+N`` and ``M+G`` per grid
        point and (T, H); ``M+G`` against ``M+N`` per model, with the filter's parameters empty).
    """
    model = model_parameters(parameters, study)
    none, gd, smcd = (method(study, kind) for kind in "NGS")
    cell = (*parameters, "burn_in", "horizon")
    metrics = [f"mse_T{t}_H{h}" for t, h in pairs]
    against_none: dict[tuple[Any, ...], dict[str, torch.Tensor]] = {}
    against_gd: dict[tuple[Any, ...], dict[str, torch.Tensor]] = {}
    for row, scores in zip(rows, arms, strict=True):
        reference = references[tuple(row[p] for p in model)]
        for (t, h), metric in zip(pairs, metrics, strict=True):
            key = (*(row[p] for p in parameters), t, h)
            against_none[key] = {none: reference[none][metric], smcd: scores[metric]}
            against_gd[key] = {gd: reference[gd][metric], smcd: scores[metric]}
    estimates, smcd_none = cell_statistics(
        against_none, cell=cell, baseline=none, adaptive=[smcd], metric="mse", seed=seed
    )
    _, smcd_gd = cell_statistics(against_gd, cell=cell, baseline=gd, adaptive=[smcd], metric="mse", seed=seed)
    model_scores = {
        (*values, t, h): {name: by_method[name][metric] for name in (none, gd)}
        for values, by_method in references.items()
        for (t, h), metric in zip(pairs, metrics, strict=True)
    }
    reference_rows, gd_none = cell_statistics(
        model_scores, cell=(*model, "burn_in", "horizon"), baseline=none, adaptive=[gd], metric="mse", seed=seed
    )
    interval = {tuple(e[c] for c in cell): (e["mse_low"], e["mse_high"]) for e in estimates if e["method"] == smcd}
    for i, row in enumerate(rows):
        point = tuple(row[p] for p in parameters)
        rows[i] = {p: row[p] for p in parameters}
        for (t, h), metric in zip(pairs, metrics, strict=True):
            low, high = interval[point + (t, h)]
            rows[i] |= {metric: row[metric], f"{metric}_low": low, f"{metric}_high": high}
    filters = {p: None for p in parameters if p not in model}
    return reference_rows, smcd_none + smcd_gd + [{**filters, **c} for c in gd_none]


def verdict_counts(comparisons: Sequence[Mapping[str, Any]], smcd: str = "M+S") -> str:
    """SMCD's (``smcd``'s) verdicts against each reference, counted over the grid points, per (T, H).

    Example:
        >>> print(verdict_counts([{"burn_in": 1, "horizon": 5, "method": "M+S", "against": "M+N", "verdict": "better"}]))
        | T | H | M+S against | better | no significant difference | worse |
        |---|---|-------------|--------|---------------------------|-------|
        | 1 | 5 | M+N         | 1      | 0                         | 0     |
    """
    counts: dict[tuple[Any, Any, str], dict[str, int]] = {}
    for c in comparisons:
        if c["method"] == smcd:
            tally = counts.setdefault((c["burn_in"], c["horizon"], c["against"]), dict.fromkeys(_VERDICTS, 0))
            tally[c["verdict"]] += 1
    body = [[t, h, against, *tally.values()] for (t, h, against), tally in counts.items()]
    return format_table(body, ["T", "H", f"{smcd} against", *_VERDICTS])


_VERDICTS = ("better", "no significant difference", "worse")


def headline(comparisons: Sequence[Mapping[str, Any]], base: Mapping[str, Any], smcd: str = "M+S") -> str | None:
    """The verdict table of SMCD (``smcd``) at the ``base`` grid point against N and G, or ``None`` if it is not one."""
    chosen = [c for c in comparisons if c["method"] == smcd and all(c[k] == v for k, v in base.items())]
    return verdict_table(chosen, cell=("burn_in", "horizon")) if chosen else None


def model_parameters(parameters: Sequence[str], study: str) -> list[str]:
    """The grid's parameters that change the trained network in a filter study (the others are the filter's).

    Example:
        >>> model_parameters(["task_share", "particles"], "masks")
        ['task_share']
    """
    return [p for p in parameters if p in MODEL_PARAMETERS[study]]


def title(study: str) -> str:
    """The study's name in reports and plots, with the paper figure it reproduces.

    Example:
        >>> title("smcd"), title("masks")
        ('study smcd (cf. paper Fig. 6)', 'study masks')
    """
    return f"study {study} (cf. paper Fig. {FIGURES[study]})" if study in FIGURES else f"study {study}"


def reference_table(reference_rows: Sequence[Mapping[str, Any]], model: Sequence[str]) -> str:
    """The reference methods' look-ahead MSE, mean [95% CI] over the arms, per model and (T, H)."""
    columns = list(dict.fromkeys((r["burn_in"], r["horizon"]) for r in reference_rows))
    lookup = {
        (*(r[p] for p in model), r["method"], r["burn_in"], r["horizon"]): str(
            Estimate(r["mse_mean"], r["mse_low"], r["mse_high"], r["trials"])
        )
        for r in reference_rows
    }
    keys = list(dict.fromkeys((*(r[p] for p in model), r["method"]) for r in reference_rows))
    body = [[*key, *(lookup[key + (t, h)] for t, h in columns)] for key in keys]
    return format_table(body, [*model, "method", *(f"T={t}, H={h}" for t, h in columns)])


def plot(
    rows: Sequence[Mapping[str, Any]],
    summary: Sequence[Mapping[str, Any]],
    parameters: Sequence[str],
    metrics: Sequence[str],
    study: str,
    path: Path,
) -> None:
    """One panel per parameter: every grid point as a dot (one metric), mean ± std and min per value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(parameters), figsize=(3.0 * len(parameters), 3.4), sharey=True, squeeze=False)
    for ax, name in zip(axes[0], parameters, strict=True):
        values = list(dict.fromkeys(row[name] for row in rows))
        positions = range(len(values))
        if len(metrics) == 1:  # every trial as a dot: the spread the paper's panels show
            for x, value in zip(positions, values, strict=True):
                ys = [row[metrics[0]] for row in rows if row[name] == value]
                jitter = [x + 0.25 * ((k + 0.5) / len(ys) - 0.5) for k in range(len(ys))]
                ax.scatter(jitter, ys, s=8, color="0.6", zorder=1)
        for metric in metrics:
            sel = {row["value"]: row for row in summary if row["metric"] == metric and row["parameter"] == name}
            line = ax.errorbar(
                positions,
                [sel[v]["mean"] for v in values],
                yerr=[sel[v]["std"] for v in values],
                marker="o",
                capsize=3,
                label=f"{_metric_label(metric)} mean",
                zorder=3,
            )
            ax.plot(positions, [sel[v]["min"] for v in values], ls=":", marker="v", color=line[0].get_color(), zorder=3)
        ax.set_xticks(list(positions), [_number(v) for v in values])
        ax.set_xlabel(LABELS[name])
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("look-ahead MSE (m$^2$)" if study in FILTER_STUDIES else "training loss (normalised MSE)")
    axes[0][-1].legend(fontsize=7, title="dotted: min", title_fontsize=7)
    fig.suptitle(f"Sweep, {title(study)}: mean ± std and min over the other parameters")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def _metric_label(metric: str) -> str:
    if metric.startswith("mse_T"):
        t, h = metric[len("mse_T") :].split("_H")
        return f"T={t}, H={h}"
    return metric.replace("_", " ")
