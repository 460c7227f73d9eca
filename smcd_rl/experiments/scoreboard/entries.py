"""The scoreboard's inputs, read and checked before anything is written: the runs' entries and ``scoreboard.json``.

Every entry must have the shape :func:`~smcd_rl.experiments.shared.scoreboard_entry.scoreboard_entry`
writes: known estimate columns with finite means and ``low <= high``, known verdict pairs, positive
times per observation. A bad one is refused with its file and entry named, and the scoreboard
writes nothing.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, VERDICTS

__all__ = ["JSON_FORMAT", "read_entries", "run_entries", "check_entry"]

#: The ``format`` entry of ``scoreboard.json``.
JSON_FORMAT = "smcd_rl.scoreboard/1"


def read_entries(path: str | Path) -> tuple[list[str], list[tuple[str, dict[str, Any]]]]:
    """The run directories and the (run directory, entry) pairs a ``scoreboard.json`` holds, checked."""
    path = Path(path)
    fix = "rerun smcd-rl scoreboard to rewrite it"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"no scoreboard.json at {path}; give the file a scoreboard run wrote") from None
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not readable as JSON ({err}); {fix}") from err
    if not isinstance(data, dict) or data.get("format") != JSON_FORMAT:
        raise ValueError(
            f"{path} is not a scoreboard.json (no format {JSON_FORMAT!r}); give the file a scoreboard wrote"
        )
    runs, items = data.get("runs"), data.get("entries")
    if not isinstance(runs, list) or not all(isinstance(r, str) for r in runs) or not runs:
        raise ValueError(f"{path}: 'runs' is not a list of run directories; {fix}")
    if not isinstance(items, list) or not items:
        raise ValueError(f"{path}: 'entries' is not a non-empty list; {fix}")
    entries = []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("run"), str):
            raise ValueError(f"{path}: entry {i} has no run directory 'run'; {fix}")
        check_entry(item.get("entry"), f"{path}: entry {i}")
        entries.append((item["run"], item["entry"]))
    return runs, entries


#: The keys of a scoreboard entry and their types (what :func:`scoreboard_entry` writes).
_ENTRY = {
    "task": str,
    "cell": dict,
    "metric": str,
    "unit": str,
    "lower_is_better": bool,
    "estimates": dict,
    "verdicts": dict,
}


def run_entries(run_dir: Path) -> list[dict[str, Any]]:
    """Every scoreboard entry of the run in ``run_dir``, checked, or a clear error."""
    if run_dir.is_file():
        raise ValueError(f"{run_dir} is a file; give the run's directory, e.g. {run_dir.parent}")
    path = run_dir / "results.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{run_dir}: no results.json; give the --out directory of a finished experiment run, e.g. runs/two-link"
        )
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not readable as JSON ({err}); rerun the experiment to rewrite it") from err
    if isinstance(results, dict) and str(results.get("experiment", "")).startswith("scoreboard"):
        raise ValueError(f"{run_dir} is a scoreboard's output, not an experiment run; leave it out of RUN_DIR")
    entries = results.get("scoreboard") if isinstance(results, dict) else None
    if entries is None:
        raise ValueError(
            f"{path}: no scoreboard entry; it was written by a command without one (bench, sweep) or an older "
            "version: rerun the experiment"
        )
    entries = entries if isinstance(entries, list) else [entries]
    if not entries:
        raise ValueError(f"{path}: its scoreboard list is empty; rerun the experiment to rewrite it")
    for i, entry in enumerate(entries):
        check_entry(entry, f"{path}: scoreboard entry {i}")
    return entries


def check_entry(entry: Any, where: str) -> None:
    """A clear error unless ``entry`` has the shape :func:`scoreboard_entry` writes."""
    fix = "rerun the experiment to rewrite it"
    if not isinstance(entry, dict):
        raise ValueError(f"{where} is a {type(entry).__name__}, not a mapping; {fix}")
    for key, kind in _ENTRY.items():
        if not isinstance(entry.get(key), kind):
            raise ValueError(f"{where} has no {kind.__name__} {key!r}; {fix}")
    known = f"the scoreboard's columns are {list(COLUMNS)}"
    if not entry["estimates"]:
        raise ValueError(f"{where} has no estimates: a row needs at least one strategy's mean; {fix}")
    for column, estimate in entry["estimates"].items():
        if column not in COLUMNS:
            raise ValueError(f"{where}: unknown estimate column {column!r} ({known}); {fix}")
        numbers = [estimate.get(k) if isinstance(estimate, dict) else None for k in ("mean", "low", "high")]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
            raise ValueError(f"{where}: the estimate of {column!r} needs numbers mean, low and high; {fix}")
        mean, low, high = (float(v) for v in numbers)  # type: ignore[arg-type]  # checked numbers above
        if not all(math.isfinite(v) for v in (mean, low, high)):
            raise ValueError(f"{where}: the estimate of {column!r} is not finite ({mean}, [{low}, {high}]); {fix}")
        if low > high:
            raise ValueError(f"{where}: the estimate of {column!r} has low {low} above high {high}; {fix}")
    pairs = {f"{method} vs {against}" for method, against in VERDICTS}
    for key, verdict in entry["verdicts"].items():
        if key not in pairs or not isinstance(verdict, str):
            what = f"unknown verdict {key!r}" if key not in pairs else f"verdict {key!r} is not a string"
            raise ValueError(f"{where}: {what} (the verdicts are {sorted(pairs)}); {fix}")
    pairs = entry.get("pairs", {})
    if not isinstance(pairs, dict):
        raise ValueError(f"{where}: 'pairs' is not a mapping of 'A vs B' -> paired verdict; {fix}")
    for key, verdict in pairs.items():
        a, sep, b = str(key).partition(" vs ")
        if not sep or a not in COLUMNS or b not in COLUMNS or not isinstance(verdict, str):
            raise ValueError(
                f"{where}: pair {key!r} is not 'A vs B' of two known columns with a verdict ({known}); {fix}"
            )
    ms = entry.get("ms_per_observation", {})
    if not isinstance(ms, dict) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in ms.values()
    ):
        raise ValueError(f"{where}: 'ms_per_observation' is not a mapping of strategy -> milliseconds (> 0); {fix}")
    unknown = [column for column in ms if column not in COLUMNS]
    if unknown:
        raise ValueError(f"{where}: 'ms_per_observation' has unknown columns {unknown} ({known}); {fix}")
