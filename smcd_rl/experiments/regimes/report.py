"""The tables, plot and scoreboard entries of ``smcd-rl regimes``.

Example:
    >>> rows = [{"family": "pendulum", "regime": "T=1", "method": m, "rmse_mean": v} for m, v in (("N", 0.2), ("G", 0.1))]
    >>> best_single(rows, "pendulum", "T=1")
    'G'
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from smcd_rl.experiments.regimes.config import RegimesConfig, regime_names
from smcd_rl.experiments.regimes.families import FAMILIES, OTHER_NETWORKS, network_of, split_method, split_network
from smcd_rl.experiments.regimes.protocol import budgeted_label
from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.experiments.shared.scoreboard_entry import paired_verdict, scoreboard_entry
from smcd_rl.experiments.shared.task_family import task_verdict_table

__all__ = ["tables", "plot", "scoreboard_entries", "best_single", "SCOREBOARD_REGIMES"]

#: The regimes each family puts on the scoreboard: few and many observations, a switch, an outlier.
SCOREBOARD_REGIMES = ("T=3", "T=30", "switch: new task", "outlier")
#: The verdict of a difference whose 95 % interval holds 0 (the tables' word for "no significant difference").
TIE = "tie"
#: The single methods the combination is held against (afterwards, on the test tasks).
SINGLES = ("N", "G", "S", "L", "SL")
#: What T+S is paired with in its table (the pendulum network's methods carry no prefix).
TASK_AGAINST = ("S", "G", "R+G", "T+G", "T+N")


def best_single(rows: Sequence[Mapping[str, Any]], family: str, regime: str) -> str:
    """The single method (of :data:`SINGLES`) of lowest mean error in a cell: what the combination is held against."""
    found = {r["method"]: r["rmse_mean"] for r in rows if r["family"] == family and r["regime"] == regime}
    present = [m for m in SINGLES if m in found]
    return min(present, key=lambda m: found[m]) if present else ""


def tables(
    rows: Sequence[Mapping[str, Any]],
    comparisons: Sequence[Mapping[str, Any]],
    config: RegimesConfig,
    ms: Mapping[str, Mapping[str, float]],
    refused: Mapping[str, int],
) -> dict[str, str]:
    """Caption -> Markdown: per family the means, the paired verdicts, then the time per observation."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    pairs: dict[tuple[str, str], dict[tuple[str, str], Mapping[str, Any]]] = {}  # cell -> (method, against) -> row
    for c in comparisons:
        pairs.setdefault((c["family"], c["regime"]), {})[(c["method"], c["against"])] = c
    out: dict[str, str] = {}
    for family in config.families:
        body = []
        for regime in regime_names(config.burn_in, family):
            found = {r["method"]: r for r in rows if r["family"] == family and r["regime"] == regime}
            best = min(found, key=lambda m: found[m]["rmse_mean"]) if found else ""
            body.append([regime, *(_mean(found.get(m)) + (" *" if m == best else "") for m in methods)])
        unit = FAMILIES[family].unit
        out[f"{family}: RMSE ({unit}), mean over {config.trials} test tasks (* lowest; CIs in results.csv)"] = (
            format_table(body, ["regime", *methods])
        )
        verdicts = []
        for regime in regime_names(config.burn_in, family):
            best = best_single(rows, family, regime)
            cells = [
                _verdict(pairs, family, regime, "S", "G"),
                _verdict(pairs, family, regime, "S", "S(evidence)"),
                _verdict(pairs, family, regime, "C", best) + f" ({best})" if best and best != "C" else "-",
                _verdict(pairs, family, regime, budgeted_label("S", config), budgeted_label("G", config)),
                _verdict(pairs, family, regime, "L", "G"),
                _verdict(pairs, family, regime, "L", "S"),
                _verdict(pairs, family, regime, "SL", "S"),
            ]
            verdicts.append([regime, *cells])
        budget = f"{config.budget_ms:g} ms"
        out[
            f"{family}: paired over the same tasks, difference [95% CI] (negative: the first has the lower error; "
            f"{TIE}: the interval holds 0; C against the single method of lowest mean error, picked afterwards)"
        ] = format_table(
            verdicts,
            [
                "regime",
                "S vs G",
                "S vs S(evidence)",
                "C vs best single",
                f"S vs G within {budget}",
                "L vs G",
                "L vs S",
                "SL vs S",
            ],
        )
        readout, summary = readout_table(pairs, rows, family, regime_names(config.burn_in, family))
        if readout:
            out[
                f"{family}: SMCD with a Bayesian readout against its parts on the same network, paired over the "
                f"same tasks, difference [95% CI]; {summary}"
            ] = readout
        of_family = [c for c in comparisons if c["family"] == family]
        task = task_verdict_table(of_family, cell=("regime",), over="tasks", against=TASK_AGAINST)
        out |= {f"{family}: {caption}": text for caption, text in task.items()}
    networks = list(ms)
    timing = [[m, *(_ms(_ms_of(ms, m, net)) for net in networks)] for m in methods]
    note = f"; observations refused by diverging GD: {dict(refused)}" if refused else ""
    caption = (
        f"Median time per observation (ms; one stream, {config.threads} torch thread(s)), per network; "
        f"C: the sum of its members' times{note}"
    )
    out[caption] = format_table(timing, ["method", *networks])
    return out


#: SMCD with a Bayesian readout and its parts, on each network that runs them: (SL, S, L).
READOUT_PARTS = (("SL", "S", "L"), ("T+SL", "T+S", "T+L"))


def readout_table(
    pairs: Mapping[tuple[str, str], Mapping[tuple[str, str], Mapping[str, Any]]],
    rows: Sequence[Mapping[str, Any]],
    family: str,
    regimes: Sequence[str],
) -> tuple[str, str]:
    """SL against S and against L per regime and network, and the count of rows where SL is
    significantly worse than the better of its parts (the one of lower mean) or better than both.

    Returns the Markdown table (empty where no network ran all three) and the counts in words.
    """
    means = {(r["regime"], r["method"]): r["rmse_mean"] for r in rows if r["family"] == family}
    ran = [parts for parts in READOUT_PARTS if all((regimes[0], m) in means for m in parts)]
    body, worse, better, cells = [], 0, 0, 0
    for regime in regimes:
        line = [regime]
        for both, smcd, readout in ran:
            verdicts = {part: _verdict(pairs, family, regime, both, part) for part in (smcd, readout)}
            line += list(verdicts.values())
            better_part = min((smcd, readout), key=lambda m: means[(regime, m)])
            cells += 1
            worse += verdicts[better_part].startswith("worse")
            better += all(v.startswith("better") for v in verdicts.values())
        body.append(line)
    if not ran:
        return "", ""
    header = ["regime", *(f"{both} vs {part}" for both, smcd, readout in ran for part in (smcd, readout))]
    summary = f"worse than the better part in {worse} of {cells} rows, better than both in {better}"
    return format_table(body, header), summary


def _ms_of(ms: Mapping[str, Mapping[str, float]], method: str, network: str) -> float | None:
    """``method``'s time on ``network``: ``T+S`` is ``S`` on the task-mask network, nothing on the others."""
    prefix, variant = split_method(method)
    kind = split_network(network)[1]  # "" for a base network, "task" or "reptile" for another
    if prefix:
        return ms[network].get(variant) if OTHER_NETWORKS[prefix] == kind else None
    return None if kind else ms[network].get(method)


def _mean(row: Mapping[str, Any] | None) -> str:
    return "-" if row is None else f"{row['rmse_mean']:.4g}"


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.3g}"


def _verdict(
    pairs: Mapping[tuple[str, str], Mapping[tuple[str, str], Mapping[str, Any]]],
    family: str,
    regime: str,
    a: str,
    b: str,
) -> str:
    """``a`` minus ``b`` in one cell with its interval and verdict (``tie`` for no significant difference)."""
    text = paired_verdict(pairs.get((family, regime), {}), a, b)
    if text == "not compared":
        return "-"
    return text.replace("no significant difference", TIE, 1)


def scoreboard_entries(
    rows: Sequence[Mapping[str, Any]], comparisons: Sequence[Mapping[str, Any]], config: RegimesConfig
) -> list[dict[str, Any]]:
    """One scoreboard entry per family and regime of :data:`SCOREBOARD_REGIMES` that ran."""
    entries = []
    for family in config.families:
        for regime in SCOREBOARD_REGIMES:
            if not any(r["family"] == family and r["regime"] == regime for r in rows):
                continue
            cell = [r for r in rows if r["family"] == family and r["regime"] == regime]
            entry = scoreboard_entry(
                f"{family} {regime}",
                rows,
                comparisons,
                cell={"family": family, "regime": regime},
                metric="rmse",
                unit=FAMILIES[family].unit,
                prefix="",  # the regimes' methods carry no network prefix
                ms={r["method"]: r["ms_per_observation"] for r in cell if r.get("ms_per_observation") is not None},
            )
            entries.append(entry)
    return entries


def plot(rows: Sequence[Mapping[str, Any]], config: RegimesConfig, path: Path) -> None:
    """``regimes.png``: per family, each method's mean error with its 95 % CI in every regime (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(r["method"] for r in rows))
    regimes = regime_names(config.burn_in)
    fig, axes = plt.subplots(len(config.families), 1, figsize=(11, 3.3 * len(config.families)), squeeze=False)
    width = 0.8 / len(methods)
    for ax, family in zip(axes[:, 0], config.families, strict=True):
        for j, method in enumerate(methods):
            found = {r["regime"]: r for r in rows if r["family"] == family and r["method"] == method}
            xs = [i + (j - (len(methods) - 1) / 2) * width for i, regime in enumerate(regimes) if regime in found]
            cells = [found[regime] for regime in regimes if regime in found]
            means = [c["rmse_mean"] for c in cells]
            errors = [[c["rmse_mean"] - c["rmse_low"] for c in cells], [c["rmse_high"] - c["rmse_mean"] for c in cells]]
            budgeted = "@" in method
            ax.bar(
                xs, means, width, yerr=errors, capsize=1.5, color=f"C{j}", label=method, hatch="//" if budgeted else ""
            )
        ax.set_xticks(range(len(regimes)), regimes, fontsize=9)
        ax.set_yscale("log")
        ax.set_ylabel(f"RMSE ({FAMILIES[family].unit})", fontsize=9)
        ax.set_title(f"{family} (network: {network_of(family)})", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(fontsize=8, ncol=len(methods), loc="lower center", bbox_to_anchor=(0.5, 1.12))
    fig.suptitle(f"Mean error and 95% CI over {config.trials} test tasks per regime", fontsize=11, y=1.0)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
