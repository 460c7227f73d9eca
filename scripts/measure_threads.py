"""Measure which torch thread count runs the experiments' work fastest, on an idle and on a busy machine.

Times the two kinds of work every experiment spends its time on, at each thread count, side by
side in one run: a training epoch of the two-link network (2 x 512, batch 256) and one SMCD
update of 100 independent filters of 1000 particles each. It measures the idle machine first,
then the same while another CPU-bound process (a Python busy loop) occupies one core, as when a
second job shares the machine. Each (thread count, work) pair is timed ``--repeats`` times,
interleaved. The table gives each count's median and its time over one thread's.

    python scripts/measure_threads.py --threads 1 2 --out docs/benchmarks/threads.md
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.experiments.shared.runtime import machine_info
from smcd_rl.files import write_text


def _spin() -> None:  # pragma: no cover - runs in the busy process
    while True:
        pass


def _model() -> smcd_rl.AdaptiveModel:
    net = smcd_rl.MaskedMLP(2, 2, hidden=(512, 512), dropout=0.5)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(1000, noise_std=0.05))
    model.fitted = True  # a random network: the work is what is timed, not the predictions
    return model


def time_epoch(model: smcd_rl.AdaptiveModel, data: TensorDict) -> float:
    started = time.perf_counter()
    smcd_rl.fit(model, data, epochs=1, batch_size=256, lr=1e-3, progress=False)
    return time.perf_counter() - started


def time_update(model: smcd_rl.AdaptiveModel, transition: TensorDict) -> float:
    model.reset(batch_shape=(100,))
    started = time.perf_counter()
    for _ in range(5):
        model.observe(transition)
    return (time.perf_counter() - started) / 5


def measure(threads: list[int], repeats: int, *, busy: bool) -> dict[tuple[int, str], float]:
    """Median seconds of each (thread count, work), with one core kept busy by another process if ``busy``."""
    generator = torch.Generator().manual_seed(0)
    data = TensorDict({"q": torch.randn(20_000, 2, generator=generator), "ee": torch.randn(20_000, 2)}, [20_000])
    transition = TensorDict({"q": torch.randn(100, 2), "ee": torch.randn(100, 2)}, [100])
    model = _model()
    spinner = multiprocessing.Process(target=_spin, daemon=True) if busy else None
    if spinner:
        spinner.start()
        time.sleep(1.0)
    times: dict[tuple[int, str], list[float]] = {}
    try:
        for _ in range(repeats):
            for count in threads:
                torch.set_num_threads(count)
                times.setdefault((count, "epoch"), []).append(time_epoch(model, data))
                times.setdefault((count, "update"), []).append(time_update(model, transition))
    finally:
        if spinner:
            spinner.terminate()
    return {key: statistics.median(values) for key, values in times.items()}


def report(threads: list[int], repeats: int, medians: dict[bool, dict[tuple[int, str], float]]) -> str:
    """The Markdown table: each machine state and thread count, its medians and their ratio to one thread's."""
    machine = machine_info()
    lines = [
        f"{machine['processor']}, {machine['cpus']} CPUs, torch {machine['torch']}; median of {repeats} "
        f"(`python scripts/measure_threads.py --threads {' '.join(map(str, threads))}`)",
        "",
        "| threads | machine | training epoch (20k samples) s | over 1 thread | SMCD update (100 x 1000 particles) ms "
        "| over 1 thread |",
        "|---|---|---|---|---|---|",
    ]
    for busy, times in medians.items():
        base = times.get((1, "epoch")), times.get((1, "update"))
        for count in threads:
            epoch, update = times[count, "epoch"], times[count, "update"]
            ratios = [f"{value / one:.2f}x" if one else "-" for value, one in zip((epoch, update), base, strict=True)]
            state = "one core busy" if busy else "idle"
            lines.append(f"| {count} | {state} | {epoch:.2f} | {ratios[0]} | {1000 * update:.0f} | {ratios[1]} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts to compare")
    parser.add_argument("--repeats", type=int, default=5, help="timings per thread count and kind of work")
    parser.add_argument("--out", help="also write the table to this Markdown file")
    args = parser.parse_args()
    medians = {busy: measure(args.threads, args.repeats, busy=busy) for busy in (False, True)}
    text = report(args.threads, args.repeats, medians)
    print(text, end="")
    if args.out:
        write_text(args.out, text, what="report")


if __name__ == "__main__":
    main()
