"""Time ``smcd_rl.tune`` against fitting the network it tunes, with and without its shortcuts, on a family no command uses.

A planar three-link arm whose link lengths change from arm to arm (each ~ U(0.5, 1.5) m): a
2 x 512 network with dropout 0.5 learns its forward kinematics from motor babbling of 100 arms,
then ``smcd_rl.tune`` (its defaults) chooses every strategy on 20 held-out episodes of 30
observations of fresh arms from the same distribution, once with its shortcuts (SMCD searched
with a quarter of the particles, its five best settings confirmed at full size) and once
without (the full search). Printed, side by side in one run: the machine and thread count, the
fit's wall time, each tune's wall time and its ratio to the fit, each kind's seconds, and each
kind's choice's one-step RMSE on 50 test arms under both searches, with their ratio.

    python scripts/bench_tune.py
    python scripts/bench_tune.py --threads 1 --seed 0
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.experiments.shared.runtime import machine_info
from smcd_rl.tuning.diagnostics import trace


def arms(count: int, steps: int, generator: torch.Generator) -> TensorDict:
    """``count`` arms, one babbling episode of ``steps`` joint configurations each: ``q`` and the end effector."""
    lengths = 0.5 + torch.rand(count, 1, 3, generator=generator)
    q = (torch.rand(count, 1, 3, generator=generator) * 2 - 1) * math.pi
    q = q + 0.3 * torch.randn(count, steps, 3, generator=generator).cumsum(1)  # a random walk of the joints
    angles = q.cumsum(-1)  # each link's absolute angle
    ee = torch.stack([(lengths * angles.cos()).sum(-1), (lengths * angles.sin()).sum(-1)], -1)
    ee = ee + 0.01 * torch.randn(ee.shape, generator=generator)
    return TensorDict({"q": q, "ee": ee}, [count, steps])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the data, the network and tune")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if hasattr(smcd_rl, "keep_freed_memory"):  # as a script of its own should (older versions have none)
        smcd_rl.keep_freed_memory()
    print({k: v for k, v in machine_info().items() if k in ("processor", "cpus", "torch_threads", "torch")})

    generator = torch.Generator().manual_seed(args.seed)
    train = torch.cat([arms(100, 10, generator) for _ in range(20)], 1)  # 100 arms x 200 samples
    held_out, test = arms(20, 30, generator), arms(50, 30, generator)
    torch.manual_seed(args.seed)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(3, 2, hidden=(512, 512), dropout=0.5), in_keys=["q"], out_key="ee")
    started = time.perf_counter()
    smcd_rl.fit(model, train, epochs=20, batch_size=256, lr=1e-3, seed=args.seed, progress=False)
    fit_seconds = time.perf_counter() - started
    print(f"fit: {fit_seconds:.1f} s (20 epochs of {train.numel()} samples)")

    results = {}
    for shortcuts in (True, False):
        started = time.perf_counter()
        result = smcd_rl.tune(model, held_out, seed=args.seed, progress=False, shortcuts=shortcuts)
        seconds = time.perf_counter() - started
        results[shortcuts] = result
        kinds = ", ".join(f"{kind} {s:.1f} s" for kind, s in result.kind_seconds.items())
        name = "with shortcuts" if shortcuts else "full search"
        print(f"tune {name}: {seconds:.1f} s, {seconds / fit_seconds:.2f}x the fit ({kinds})")
    print(results[True])
    for kind in results[True].best_of:
        fast, full = (trace(model, test, results[s].strategy(kind)).rmse for s in (True, False))
        print(f"test one-step RMSE, {kind}: shortcuts {fast:.4f}, full search {full:.4f}, ratio {fast / full:.3f}")


if __name__ == "__main__":
    main()
