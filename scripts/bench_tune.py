"""Time ``smcd_rl.tune`` against fitting the network it tunes, and check its choices and
``smcd_rl.calibrate``'s on test tasks of a family no command uses.

A planar three-link arm whose link lengths change from arm to arm (each ~ U(0.5, 1.5) m): a
2 x 512 network with dropout 0.5 learns its forward kinematics from motor babbling of 100 arms
with ``smcd_rl.fit`` at its own defaults, then ``smcd_rl.tune`` (its defaults) chooses every
strategy on 20 held-out episodes of 30 observations of fresh arms from the same distribution,
once with its shortcuts and once without (the full search). Measured side by side in one run and
written as a Markdown report (``--out``) and printed:

* the machine and thread count, the fit's wall time, each tune's wall time, its ratio to the fit
  and each kind's seconds;
* each kind's choice's one-step RMSE on 50 test arms under both searches, their ratio, and the
  best strategy of the shortcut search against the best of the full search;
* ``smcd_rl.calibrate(criterion="lookahead", horizon=10)`` (the noise's shape searched, and the
  residual's proportions alone, ``noise_shape="proportional"``) against SMCD at each single noise
  of a sweep: the test arms' 10-step look-ahead RMSE.

    python scripts/bench_tune.py
    python scripts/bench_tune.py --threads 1 --seed 0 --out docs/benchmarks/tune.md
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.experiments.shared.outputs import Transcript
from smcd_rl.tuning.criteria import checked_criterion
from smcd_rl.tuning.diagnostics import trace
from smcd_rl.tuning.scoring import Scorer

#: The single noises (normalised units) the calibration is compared with, at its flip probability.
FIXED_NOISES = (0.02, 0.05, 0.1, 0.2, 0.4)
HORIZON = 10


def arms(count: int, steps: int, generator: torch.Generator) -> TensorDict:
    """``count`` arms, one babbling episode of ``steps`` joint configurations each: ``q`` and the end effector."""
    lengths = 0.5 + torch.rand(count, 1, 3, generator=generator)
    q = (torch.rand(count, 1, 3, generator=generator) * 2 - 1) * math.pi
    q = q + 0.3 * torch.randn(count, steps, 3, generator=generator).cumsum(1)  # a random walk of the joints
    angles = q.cumsum(-1)  # each link's absolute angle
    ee = torch.stack([(lengths * angles.cos()).sum(-1), (lengths * angles.sin()).sum(-1)], -1)
    ee = ee + 0.01 * torch.randn(ee.shape, generator=generator)
    return TensorDict({"q": q, "ee": ee}, [count, steps])


def seeded(seed: int) -> torch.Generator:
    """A filter's own random stream, as ``calibrate`` seeds each of its runs."""
    return torch.Generator().manual_seed(seed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the data, the network and tune")
    parser.add_argument("--out", type=Path, default=None, help="also write the report here (Markdown)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if hasattr(smcd_rl, "keep_freed_memory"):  # as a script of its own should (older versions have none)
        smcd_rl.keep_freed_memory()
    transcript = Transcript("python scripts/bench_tune.py")
    say = transcript.say

    generator = torch.Generator().manual_seed(args.seed)
    train = torch.cat([arms(100, 10, generator) for _ in range(20)], 1)  # 100 arms x 200 samples
    held_out, test = arms(20, 30, generator), arms(50, 30, generator)
    torch.manual_seed(args.seed)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(3, 2, hidden=(512, 512), dropout=0.5), in_keys=["q"], out_key="ee")
    started = time.perf_counter()
    smcd_rl.fit(model, train, seed=args.seed, progress=False)
    fit_seconds = time.perf_counter() - started

    say("| | wall time | / fit | seconds per kind |")
    say("|---|---|---|---|")
    say(f"| `fit` at its defaults ({train.numel()} samples) | {fit_seconds:.1f} s | 1 | |")
    results = {}
    for shortcuts in (True, False):
        started = time.perf_counter()
        results[shortcuts] = result = smcd_rl.tune(model, held_out, seed=args.seed, progress=False, shortcuts=shortcuts)
        seconds = time.perf_counter() - started
        kinds = ", ".join(f"{kind} {s:.1f}" for kind, s in result.kind_seconds.items())
        name = "`tune`" if shortcuts else "`tune(shortcuts=False)`"
        say(f"| {name} | {seconds:.1f} s | {seconds / fit_seconds:.2f} | {kinds} |")

    say()
    say("Test one-step RMSE (m) on 50 fresh arms of each kind's choice:")
    say()
    say("| kind | `tune` | `tune(shortcuts=False)` | ratio |")
    say("|---|---|---|---|")
    errors = {s: {} for s in results}
    for kind in results[True].best_of:
        for s in results:
            errors[s][kind] = trace(model, test, results[s].strategy(kind)).rmse
        fast, full = errors[True][kind], errors[False][kind]
        say(f"| {kind} | {fast:.4f} | {full:.4f} | {fast / full:.3f} |")
    fast, full = min(errors[True].values()), min(errors[False].values())
    say(f"| the best of every kind | {fast:.4f} | {full:.4f} | {fast / full:.3f} |")

    say()
    say(
        f"SMCD's {HORIZON}-step look-ahead RMSE (m) on the test arms, calibrated on the held-out episodes by look-ahead:"
    )
    say()
    say("| SMCD | noise | flip | test look-ahead RMSE |")
    say("|---|---|---|---|")
    ahead = Scorer(model, test, checked_criterion("lookahead", HORIZON), "bench_tune")
    calibrated = {}
    for shape in ("search", "proportional"):
        calibration = smcd_rl.calibrate(
            model, held_out, criterion="lookahead", horizon=HORIZON, noise_shape=shape, seed=args.seed, progress=False
        )
        noise = calibration.noise_std
        shown = f"{noise:.3g}" if isinstance(noise, float) else "[" + ", ".join(f"{v:.3g}" for v in noise) + "]"
        strategy = smcd_rl.SMCD(noise_std=noise, flip_prob=calibration.flip_prob, generator=seeded(args.seed))
        calibrated[shape] = error = ahead.score(ahead.run(strategy))
        say(
            f"| `calibrate(noise_shape={shape!r})`, {calibration.noise_shape} | {shown} | {calibration.flip_prob:g} | {error:.4f} |"
        )
    flip = smcd_rl.SMCD().flip_prob
    fixed = {}
    for noise in FIXED_NOISES:
        fixed[noise] = ahead.score(
            ahead.run(smcd_rl.SMCD(noise_std=noise, flip_prob=flip, generator=seeded(args.seed)))
        )
        say(f"| a single noise | {noise:g} | {flip:g} | {fixed[noise]:.4f} |")
    best = min(fixed.values())
    say()
    say(
        f"`calibrate` by look-ahead / the best single noise: {calibrated['search'] / best:.3f} "
        f"(the residual's proportions alone: {calibrated['proportional'] / best:.3f})."
    )
    transcript.write(args.out)


if __name__ == "__main__":
    main()
