"""Where and how an experiment runs: its device, torch threads, seeds, the machine, side-by-side timing.

Example:
    >>> with torch_threads(1):
    ...     resolve_device("cpu"), torch.get_num_threads()
    ('cpu', 1)
"""

from __future__ import annotations

import contextlib
import os
import platform
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

__all__ = ["machine_info", "resolve_device", "torch_threads", "seed_everything", "interleaved_times"]


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
