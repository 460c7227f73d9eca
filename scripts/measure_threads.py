"""Measure which torch thread count runs the experiments' work fastest, on an idle and on a busy machine.

Times the two kinds of work every experiment spends its time on, at each thread count, side by
side in one run: a training epoch of the two-link network (2 x 512, batch 256) and one SMCD
update of 100 independent filters of 1000 particles each. ``--busy`` runs the same measurement
while another CPU-bound process (a Python busy loop) occupies one core, as when a second job
shares the machine. Each (thread count, work) pair is timed ``--repeats`` times, interleaved.

    python scripts/measure_threads.py --threads 1 2            # idle machine
    python scripts/measure_threads.py --threads 1 2 --busy     # one core taken by another process
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts to compare")
    parser.add_argument("--repeats", type=int, default=5, help="timings per thread count and kind of work")
    parser.add_argument("--busy", action="store_true", help="keep one core busy with another process meanwhile")
    args = parser.parse_args()

    generator = torch.Generator().manual_seed(0)
    data = TensorDict({"q": torch.randn(20_000, 2, generator=generator), "ee": torch.randn(20_000, 2)}, [20_000])
    transition = TensorDict({"q": torch.randn(100, 2), "ee": torch.randn(100, 2)}, [100])
    model = _model()
    busy = multiprocessing.Process(target=_spin, daemon=True) if args.busy else None
    if busy:
        busy.start()
        time.sleep(1.0)
    times: dict[tuple[int, str], list[float]] = {}
    try:
        for _ in range(args.repeats):
            for threads in args.threads:
                torch.set_num_threads(threads)
                times.setdefault((threads, "epoch"), []).append(time_epoch(model, data))
                times.setdefault((threads, "update"), []).append(time_update(model, transition))
    finally:
        if busy:
            busy.terminate()
    machine = machine_info()
    print(
        f"{machine['processor']}, {machine['cpus']} CPUs, torch {machine['torch']}, "
        f"{'one core busy with another process' if args.busy else 'idle'}; median of {args.repeats}"
    )
    print("| threads | training epoch (20k samples) s | SMCD update (100 x 1000 particles) ms |")
    print("|---|---|---|")
    for threads in args.threads:
        epoch, update = statistics.median(times[threads, "epoch"]), statistics.median(times[threads, "update"])
        print(f"| {threads} | {epoch:.2f} | {1000 * update:.0f} |")


if __name__ == "__main__":
    main()
