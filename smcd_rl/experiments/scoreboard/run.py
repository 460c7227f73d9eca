"""One table of every task: ``smcd-rl scoreboard RUN_DIR...``.

Each experiment writes into its ``results.json`` the cell of its table that stands for the task
(e.g. two-link at burn-in T = 10, horizon H = 1): the estimates of its methods for "none", "GD",
"SMCD (paper)", "SMCD (calibrated)" (by evidence), "SMCD (one-step)" and "combination", their
paired verdicts and their times per observation
(:func:`~smcd_rl.experiments.shared.scoreboard_entry.scoreboard_entry`). The scoreboard reads
those entries from the given run directories and writes tables of one row per task, narrow
enough for a docs page: its metric and cell; each strategy's mean with its 95 % CI; the verdicts
of the SMCD variants and the combination against none and GD (the experiment's own comparisons,
over the same trials); each strategy's median time per observation. ``results.csv`` holds every
number. A task that several runs have is labelled with each run's directory. The plot has a
panel per task in its own metric, two to a row. The entries are kept in ``scoreboard.json``,
from which :func:`render` draws the scoreboard again.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from smcd_rl.experiments.scoreboard.config import ScoreboardConfig
from smcd_rl.experiments.scoreboard.decisions import decision_table
from smcd_rl.experiments.scoreboard.entries import JSON_FORMAT, read_entries, run_entries
from smcd_rl.experiments.scoreboard.plot import draw
from smcd_rl.experiments.scoreboard.summary import milliseconds as _ms
from smcd_rl.experiments.scoreboard.summary import summary_table
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table, write_json
from smcd_rl.experiments.shared.scoreboard_entry import (
    COLUMNS,
    CORE_COLUMNS,
    CORE_VERDICTS,
    HEADERS,
    T_COLUMNS,
    TASK_MASKS,
    VERDICT_LABELS,
    VERDICTS,
)
from smcd_rl.experiments.shared.stats import Estimate

__all__ = ["ScoreboardConfig", "run", "render", "read_entries"]


def run(config: ScoreboardConfig, *, progress: bool = True) -> dict[str, Any]:
    """Read every run's scoreboard entries and write the tables, plot, report and ``scoreboard.json``."""
    config.validate()
    # Every input is read and checked before --out is made or anything in it is touched.
    entries = [(str(run_dir), entry) for run_dir in _run_dirs(config) for entry in run_entries(run_dir)]
    return _write(config, entries, progress=progress)


def render(path: str | Path, *, out: str | Path, progress: bool = True) -> dict[str, Any]:
    """Write a scoreboard again from the ``scoreboard.json`` an earlier one wrote, without its run directories.

    The tables, plot and report are those :func:`run` writes from the same entries, and the
    settings are the earlier run's (its run directories), so the report's settings fingerprint is
    unchanged: how the committed docs page is redrawn after a change of layout.

    Args:
        path: a ``scoreboard.json``.
        out: the output directory (not the one holding ``path``: its files would be replaced).
        progress: print the progress line.
    """
    path = Path(path)
    runs, entries = read_entries(path)
    note = json.loads(path.read_text()).get("note")
    config = ScoreboardConfig(runs=tuple(runs), out=str(out))
    config.validate()
    if Path(out).resolve() == path.parent.resolve():
        raise ValueError(f"--out {out} holds {path}, which this would replace; write to another directory")
    _check_out(config)
    return _write(config, entries, progress=progress, note=note if isinstance(note, str) else None)


def _write(
    config: ScoreboardConfig,
    entries: Sequence[tuple[str, Mapping[str, Any]]],
    *,
    progress: bool,
    note: str | None = None,
) -> dict[str, Any]:
    """The scoreboard of ``entries`` (run directory, entry): its tables, plot, report and ``scoreboard.json``.

    ``note``: where the entries came from, kept in ``scoreboard.json`` when they were not read from runs.
    """
    rows = _rows(entries)
    # Every table is made before anything is written: a row that cannot be drawn fails here, and
    # --out keeps what it had.
    tables = _tables(rows)
    with Experiment(config, progress=progress) as ex:
        write_json(
            ex.out / "scoreboard.json",
            {
                "format": JSON_FORMAT,
                **({"note": note} if note else {}),
                "runs": list(config.runs),
                "entries": [{"run": run_dir, "entry": dict(entry)} for run_dir, entry in entries],
            },
        )
        ex.write(
            experiment="scoreboard: every task, none / GD / SMCD (paper, calibrated, tuned) / combination",
            tables=tables,
            rows=[_csv_row(row) for row in rows],
            payload={"runs": list(config.runs)},
            plots={"scoreboard.png": lambda path: draw(rows, path)},
            files=["scoreboard.json"],
        )
    return ex.result


def _tables(rows: Sequence[Mapping[str, Any]]) -> dict[str, str]:
    """The report's tables of the scoreboard ``rows``, caption -> Markdown (an empty table: not shown)."""
    tasks = [
        [row["task"], row["metric"] + ("" if row["lower_is_better"] else ", higher is better"), row["cell"]]
        for row in rows
    ]
    means = [[row["task"], *(row[f"{c} text"] for c in CORE_COLUMNS)] for row in rows]
    verdicts = [[row["task"], *(row[f"{m} vs {a}"] for m, a in CORE_VERDICTS)] for row in rows]
    # Experiments tuned by smcd_rl.tune add SMCD by one-step error, the combination and the
    # time per observation: tables of their own, of the tasks that have them.
    extra_columns = ["SMCD (one-step)", "combination"]
    tuned = [row for row in rows if any(math.isfinite(row[c]) for c in extra_columns)]
    extra_verdicts = [v for v in VERDICTS if v[0] in extra_columns]
    task_verdicts = [v for v in VERDICTS if v[0] == TASK_MASKS]
    task_rows = [row for row in rows if math.isfinite(row[TASK_MASKS])]
    t_rows = [row for row in rows if any(math.isfinite(row[c]) for c in T_COLUMNS)]
    timed = [row for row in rows if row["ms"]]
    timed_columns = [c for c in TIMED if any(c in row["ms"] for row in timed)]
    # Narrow tables, not one wide one: each fits the width of a docs page.
    return {
        "In short: each task's best mean; SMCD tuned like GD (by each task's criterion), SMCD on task-trained masks (T+S) "
        "and the combination against tuned GD (paired verdicts over the same trials; tie: no significant "
        "difference); median ms per observation": summary_table(rows),
        # Between section markers, so that pages include it alone (pymdownx.snippets).
        DECISIONS_CAPTION: f"<!-- --8<-- [start:decisions] -->\n{decision_table(rows)}\n<!-- --8<-- [end:decisions] -->",
        "Each task's headline metric and cell (every number of the tables below: results.csv)": format_table(
            tasks, ["task", "metric", "cell"]
        ),
        "Mean [95% CI]": format_table(means, ["task", *CORE_COLUMNS]),
        "Paired verdicts, over the same trials (difference [95% CI], method minus against)": format_table(
            verdicts, ["task", *(VERDICT_LABELS[v] for v in CORE_VERDICTS)]
        ),
        "SMCD tuned like GD, by each task's criterion (look-ahead or one-step error), and the combination, where "
        "they ran: mean [95% CI] and paired verdict against GD": format_table(
            [
                [
                    row["task"],
                    *(row[f"{c} text"] for c in extra_columns),
                    *(row[f"{m} vs {a}"] for m, a in extra_verdicts),
                ]
                for row in tuned
            ],
            ["task", *(HEADERS.get(c, c) for c in extra_columns), *(VERDICT_LABELS[v] for v in extra_verdicts)],
        )
        if tuned
        else "",
        **{
            f"{READOUT_CAPTIONS[column]}, where it ran: mean [95% CI], paired verdicts and median ms per "
            "observation": _readout_table(rows, column)
            for column in READOUT_COLUMNS
        },
        "SMCD on a network whose masks were trained to identify the task (T+S), where it ran: mean [95% CI], "
        "paired verdicts and median ms per observation": format_table(
            [
                [
                    row["task"],
                    row[f"{TASK_MASKS} text"],
                    *(row[f"{m} vs {a}"] for m, a in task_verdicts),
                    _ms(row["ms"].get(TASK_MASKS)),
                ]
                for row in task_rows
            ],
            ["task", TASK_MASKS, *(VERDICT_LABELS[v] for v in task_verdicts), "ms / observation"],
        )
        if task_rows
        else "",
        "The task-mask network's other strategies, where they ran: mean [95% CI] (T+N: no adaptation)": format_table(
            [[row["task"], *(row[f"{c} text"] for c in T_COLUMNS)] for row in t_rows], ["task", *T_COLUMNS]
        )
        if t_rows
        else "",
        "Notes: what to know before comparing a task's strategies": format_table(
            [[row["task"], row["note"]] for row in rows if row["note"]], ["task", "note"]
        )
        if any(row["note"] for row in rows)
        else "",
        # Not "none": a forward pass, a fraction of a millisecond everywhere (results.csv has it).
        "Median time per observation (ms; one stream, one thread), where the experiment measured it": format_table(
            [[row["task"], *(_ms(row["ms"].get(c)) for c in timed_columns)] for row in timed],
            ["task", *(HEADERS.get(c, c) for c in timed_columns)],
        )
        if timed
        else "",
    }


#: The caption of the computed decision table (:mod:`~smcd_rl.experiments.scoreboard.decisions`).
DECISIONS_CAPTION = (
    "What to use when, computed from the rows below by written rules: a strategy is recommended where, on every row "
    "the situation cites, it is best or tied with the best of the strategies that situation allows (paired verdict, "
    "else overlapping intervals) and never significantly worse than one of them"
)
#: The readouts' columns, each in a table of its own where it ran, with its verdicts against GD and SMCD.
READOUT_COLUMNS = ("last layer", "SMCD + last layer")
READOUT_CAPTIONS = {
    "last layer": "The Bayesian last layer",
    "SMCD + last layer": "SMCD with a Bayesian readout",
}


def _readout_table(rows: Sequence[Mapping[str, Any]], column: str) -> str:
    """``column``'s mean, its paired verdicts against GD and SMCD (one-step) and its median ms per
    observation, for the tasks that ran it."""
    verdicts = [v for v in VERDICTS if v[0] == column]
    ran = [row for row in rows if math.isfinite(row[column])]
    if not ran:
        return ""
    body = [
        [row["task"], row[f"{column} text"], *(row[f"{m} vs {a}"] for m, a in verdicts), _ms(row["ms"].get(column))]
        for row in ran
    ]
    return format_table(body, ["task", column, *(VERDICT_LABELS[v] for v in verdicts), "ms / observation"])


def _rows(entries: Sequence[tuple[str, Mapping[str, Any]]]) -> list[dict[str, Any]]:
    """One row per entry; a task that several runs have is labelled with each one's run directory."""
    counts = Counter(entry["task"] for _, entry in entries)
    rows = []
    for run_dir, entry in entries:
        row = _row(entry)
        if counts[entry["task"]] > 1:
            row["task"] = f"{entry['task']} ({run_dir})"
        rows.append(row)
    return rows


def _run_dirs(config: ScoreboardConfig) -> list[Path]:
    """The run directories, each once, none of them ``--out`` (whose results the scoreboard would replace)."""
    out = Path(config.out).resolve()
    seen: dict[Path, str] = {}
    for given in config.runs:
        path = Path(given)
        if path.resolve() in seen:
            raise ValueError(f"RUN_DIR {given} is the same directory as {seen[path.resolve()]}; give each run once")
        if path.resolve() == out:
            raise ValueError(
                f"--out {config.out} is one of the run directories: the scoreboard would replace that run's results; "
                "pick another, e.g. --out runs/scoreboard"
            )
        seen[path.resolve()] = given
    _check_out(config)
    return [Path(given) for given in seen.values()]


def _check_out(config: ScoreboardConfig) -> None:
    """Never replace an experiment's results with the scoreboard's: refuse an ``--out`` that holds them."""
    out = Path(config.out)
    earlier = out / "results.json"
    if earlier.is_file():
        try:
            experiment = json.loads(earlier.read_text()).get("experiment", "")
        except (OSError, ValueError, AttributeError):
            experiment = ""
        if not str(experiment).startswith("scoreboard"):
            raise ValueError(
                f"--out {config.out} holds the results of another command ({experiment or 'unreadable'}); "
                "pick another, e.g. --out runs/scoreboard"
            )


def _row(entry: Mapping[str, Any]) -> dict[str, Any]:
    """One scoreboard row from one entry: each strategy's estimate and the verdicts."""
    row: dict[str, Any] = {
        "task": entry["task"],
        "cell": ", ".join(f"{k}={v}" for k, v in entry["cell"].items()),
        "metric": f"{entry['metric']} ({entry['unit']})",
        "lower_is_better": entry["lower_is_better"],
    }
    for column in COLUMNS:
        e = entry["estimates"].get(column)
        mean, low, high = (e["mean"], e["low"], e["high"]) if e else (math.nan,) * 3
        row[column], row[f"{column} low"], row[f"{column} high"] = mean, low, high
        row[f"{column} text"] = str(Estimate(mean, low, high, 0)) if e else "not run"
    for method, against in VERDICTS:
        row[f"{method} vs {against}"] = entry["verdicts"].get(f"{method} vs {against}", "not compared")
    row["pairs"] = dict(entry.get("pairs", {}))
    row["ms"] = dict(entry.get("ms_per_observation", {}))
    row["note"] = str(entry.get("note", ""))
    return row


def _csv_row(row: Mapping[str, Any]) -> dict[str, Any]:
    """A row of results.csv: the numbers and verdicts, each time per observation a column of its own."""
    flat = {k: v for k, v in row.items() if not k.endswith(" text") and k not in ("ms", "pairs")}
    return {**flat, **{f"{column} ms": row["ms"].get(column) for column in COLUMNS}}


#: The strategies whose times the report's table shows (SMCD on task masks and the readouts: in their own tables).
TIMED = tuple(c for c in COLUMNS if c not in ("none", TASK_MASKS, *READOUT_COLUMNS, *T_COLUMNS))
