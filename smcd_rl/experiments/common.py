"""Plumbing shared by the experiment commands: configs, result files, resumable caches, tables."""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import os
import platform
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from smcd_rl.experiments.configs import config_dict
from smcd_rl.files import write_atomic, write_text

__all__ = [
    "config_dict",
    "machine_info",
    "write_csv",
    "write_json",
    "write_text",
    "save_figure",
    "format_table",
    "seed_everything",
    "resolve_device",
    "torch_threads",
    "interleaved_times",
    "settings_fingerprint",
]


def machine_info() -> dict[str, Any]:
    """Where a number was measured: CPU, thread count, torch version, GPU if any."""
    info: dict[str, Any] = {
        "machine": platform.machine(),
        "processor": _cpu_name(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def resolve_device(name: str) -> str:
    """``"auto"`` becomes ``"cuda"`` when a GPU is available, else ``"cpu"``; a CUDA name without CUDA is an error.

    Example:
        >>> resolve_device("cpu")
        'cpu'
    """
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"unknown device {name!r}: use auto, cpu, cuda or cuda:N") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"--device {name}: this machine has no CUDA device (or torch is a CPU build); use --device cpu"
        )
    return name


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with ``count`` torch CPU threads (0: torch's setting as it is), then restore it.

    Example:
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
    """
    before = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def seed_everything(seed: int) -> torch.Generator:
    """Seed torch's global generator and return a fresh generator seeded with ``seed``."""
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def settings_fingerprint(settings: Mapping[str, Any]) -> str:
    """A hex digest that changes whenever a setting does: names caches and checkpoints by their settings.

    Example:
        >>> settings_fingerprint({"seed": 0}) == settings_fingerprint({"seed": 0}) != settings_fingerprint({"seed": 1})
        True
    """
    return hashlib.sha256(json.dumps(dict(settings), sort_keys=True, default=str).encode()).hexdigest()


def write_csv(path: str | os.PathLike[str], rows: Sequence[Mapping[str, Any]]) -> None:
    """Write dict rows to a CSV file; its columns are every row's keys in order of appearance, blank where a row has none."""
    if not rows:
        raise ValueError(f"no rows to write to {path}")
    columns = list(dict.fromkeys(key for row in rows for key in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, text.getvalue(), what="table")


def write_json(path: str | os.PathLike[str], payload: Any) -> None:
    """Write ``payload`` as indented JSON (values JSON cannot hold as their ``str``), atomically."""
    write_text(path, json.dumps(payload, indent=2, default=str) + "\n", what="JSON file")


def save_figure(fig: Any, path: str | os.PathLike[str], **options: Any) -> None:
    """Save a matplotlib figure atomically, in the format of ``path``'s suffix (``.png``): ``fig.savefig(..., **options)``.

    A full disk or an unwritable directory is a :class:`~smcd_rl.files.FileWriteError` naming the
    file (and the space it needs), and no truncated picture is left behind.
    """
    suffix = Path(path).suffix.lstrip(".").lower() or "png"
    write_atomic(path, lambda handle: fig.savefig(handle, format=suffix, **options), what="plot")


def format_table(rows: Iterable[Sequence[Any]], header: Sequence[str]) -> str:
    """A Markdown table (it reads in a terminal and pastes into the README as is)."""
    cells = [[str(h) for h in header]] + [[_cell(v) for v in row] for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |" for row in cells]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def _cell(value: Any) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def interleaved_times(
    contenders: Mapping[str, Callable[[], object]],
    rounds: int,
    *,
    warmup: int = 0,
    device: torch.device | str = "cpu",
    desc: str = "bench",
    progress: bool = True,
) -> dict[str, list[float]]:
    """Wall seconds of every call of each contender, measured side by side.

    Each round calls every contender once, in an order that rotates from round to round, so slow
    drifts of the machine (other jobs, clock changes) fall on all contenders alike. The first
    ``warmup`` rounds are not recorded. CUDA work is synchronised around every call.

    Example:
        >>> times = interleaved_times({"a": lambda: None, "b": lambda: None}, rounds=3, progress=False)
        >>> {name: len(t) for name, t in times.items()}
        {'a': 3, 'b': 3}
    """
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    names = list(contenders)
    times: dict[str, list[float]] = {name: [] for name in names}
    with torch.no_grad():
        for i in tqdm(range(warmup + rounds), desc=desc, unit="round", disable=not progress):
            for name in names[i % len(names) :] + names[: i % len(names)]:
                sync()
                started = time.perf_counter()
                contenders[name]()
                sync()
                if i >= warmup:
                    times[name].append(time.perf_counter() - started)
    return times
