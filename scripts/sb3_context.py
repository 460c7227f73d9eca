"""stable-baselines3 SAC with and without the SMCD context, on a Pendulum whose mass and length change per episode.

The task family: Pendulum-v1 with mass ``m ~ U(0.5, 2)`` and length ``l ~ U(0.5, 1.5)`` drawn at
every reset (:class:`RandomPendulum` below), so the torque needed to swing up differs per
episode and a policy gains from knowing the episode's pendulum. A dynamics model with dropout is
fitted on random transitions of many pendulums; ``AdaptationWrapper(env, model, context=k)``
adapts it (SMCD) on every real step and appends ``k + 1`` numbers (a projection of the adapted
mask, and the filter's ESS fraction) to the observation. The same SAC, seeds and evaluation
episodes are run with the context and without it. Writes ``<out>/<run>/eval.csv`` (one row per
evaluation episode), SB3's ``progress.csv`` per agent, ``model.pt`` and ``summary.json`` (mean
returns with 95% confidence intervals over seeds and over episodes, and the paired difference).

Resuming: the model fit is saved after every epoch (``fit_dynamics(..., checkpoint=...)``) and the
evaluation rows after every agent, to ``<out>/<run>/fit.pt`` and ``checkpoint.pt``; rerun the
same command and it goes on with the first unfinished agent, refusing a checkpoint that other
options wrote. Each agent is seeded on its own, so the result is that of an uninterrupted run;
an interruption loses at most the agent that was training.

Copy this file and edit it; ``python scripts/sb3_context.py --help`` lists the settings,
``--tiny`` makes a smoke run.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.logger import configure

import smcd_rl
from smcd_rl.files import load_file, save_file
from smcd_rl.integrations.gymnasium import AdaptationWrapper, collect_transitions
from smcd_rl.integrations.script_options import parse_config, save_options


@dataclass
class Config:
    # "valid": the range an option must lie in, "[low, high]" with ( ) for open ends.
    seeds: int = field(default=3, metadata={"help": "agents per arm, seeds 0..seeds-1", "valid": "[1, inf)"})
    train_steps: int = field(default=6000, metadata={"help": "SAC environment steps per agent", "valid": "[1, inf)"})
    eval_episodes: int = field(
        default=10, metadata={"help": "evaluation episodes per agent (the same for both arms)", "valid": "[1, inf)"}
    )
    context: int = field(
        default=4, metadata={"help": "size k of the mask projection (k + 1 numbers appended)", "valid": "[1, inf)"}
    )
    data_steps: int = field(
        default=20000, metadata={"help": "random transitions the dynamics model is fitted on", "valid": "[1, inf)"}
    )
    fit_epochs: int = field(default=20, metadata={"help": "epochs of the model fit", "valid": "[1, inf)"})
    hidden: int = field(
        default=128, metadata={"help": "units of each of the model's two hidden layers", "valid": "[1, inf)"}
    )
    dropout: float = field(default=0.5, metadata={"help": "dropout probability of the model", "valid": "(0, 1)"})
    particles: int = field(default=100, metadata={"help": "SMCD mask particles", "valid": "[1, inf)"})
    noise_std: float = field(default=0.05, metadata={"help": "SMCD likelihood noise", "valid": "(0, inf)"})
    policy_hidden: int = field(
        default=64, metadata={"help": "units of each of SAC's two hidden layers", "valid": "[1, inf)"}
    )
    threads: int = field(default=1, metadata={"help": "torch threads", "valid": "[1, inf)"})
    out: str = field(default="runs", metadata={"help": "output directory"})
    tiny: bool = field(default=False, metadata={"help": "a smoke run of seconds (overrides the sizes)"})


TINY = {"seeds": 2, "train_steps": 250, "eval_episodes": 2, "data_steps": 400, "fit_epochs": 1, "hidden": 32,
        "particles": 10, "policy_hidden": 16}  # fmt: skip
MASS, LENGTH = (0.5, 2.0), (0.5, 1.5)
EVAL_SEED = 1_000_000  # evaluation episode i of every agent resets with seed EVAL_SEED + i


class RandomPendulum(gymnasium.Wrapper):
    """Pendulum-v1 with the mass and length drawn from the env's own generator at every reset."""

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        pendulum: Any = self.env.unwrapped
        pendulum.m = float(self.np_random.uniform(*MASS))
        pendulum.l = float(self.np_random.uniform(*LENGTH))
        return obs, {**info, "mass": pendulum.m, "length": pendulum.l}


def run_dir(config: Config) -> Path:
    return Path(config.out) / f"sb3_context_k{config.context}"


def parse_args() -> Config:
    """The options, checked (ranges, and a checkpoint's options when resuming) before any work: usage and exit 2 if not."""
    return parse_config(
        Config, run_dir=run_dir, tiny=TINY, description=__doc__.split("\n")[0], checkpoints=("checkpoint.pt", "fit.pt")
    )


def mean_ci(values: list[float]) -> dict[str, float]:
    """Mean and the half-width of its 95% Student-t confidence interval."""
    n = len(values)
    t95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}
    half = t95.get(n - 1, 1.96) * float(np.std(values, ddof=1)) / math.sqrt(n) if n > 1 else float("nan")
    return {"mean": float(np.mean(values)), "ci95": half, "n": n}


def main() -> None:
    config = parse_args()
    run = run_dir(config)
    run.mkdir(parents=True, exist_ok=True)
    resume = run / "checkpoint.pt"
    resuming = resume.is_file() or (run / "fit.pt").is_file()
    save_options(config, run)
    torch.set_num_threads(config.threads)
    torch.manual_seed(0)
    start = time.perf_counter()

    # The dynamics model: fitted once on random transitions of many pendulums.
    data = collect_transitions(RandomPendulum(gymnasium.make("Pendulum-v1")), None, config.data_steps, seed=0)
    net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=(config.hidden, config.hidden), dropout=config.dropout)
    model = smcd_rl.AdaptiveDynamicsModel(net)
    # Resumes after the last finished epoch of an interrupted fit (or loads a finished one) from fit.pt.
    smcd_rl.fit_dynamics(
        model, data, epochs=config.fit_epochs, batch_size=256, lr=1e-3, progress=False, checkpoint=run / "fit.pt"
    )
    model.save(run / "model.pt")

    def make_env(arm: str, seed: int) -> gymnasium.Env:
        env = RandomPendulum(gymnasium.make("Pendulum-v1"))
        if arm == "plain":
            return env
        # Each env gets its own adaptation state; the trained network is shared.
        smcd = smcd_rl.SMCD(
            num_particles=config.particles, noise_std=config.noise_std, generator=torch.Generator().manual_seed(seed)
        )
        return AdaptationWrapper(env, model.with_adaptation(smcd), context=config.context)

    rows: list[dict[str, Any]] = []  # one per evaluation episode, saved after each agent
    if resume.is_file():
        rows = load_file(resume, what="sb3_context.py run checkpoint", expect_format="sb3_context/1",
                         fix="delete it to start afresh, or use another --out")["rows"]  # fmt: skip
        print(f"resuming {run}: {len(rows) // config.eval_episodes} agents finished", flush=True)
    for seed in range(config.seeds):
        for arm in ("context", "plain"):
            if any(r["arm"] == arm and r["seed"] == seed for r in rows):
                continue  # finished before an interruption; each agent is seeded on its own
            agent = SAC(
                "MlpPolicy",
                make_env(arm, seed),
                seed=seed,
                learning_starts=min(100, config.train_steps // 2),
                policy_kwargs={"net_arch": [config.policy_hidden] * 2},
                verbose=0,
            )
            agent.set_logger(configure(str(run / f"{arm}_seed{seed}"), ["csv"]))
            agent.learn(config.train_steps, log_interval=1)  # progress.csv after every episode
            env = make_env(arm, seed + 10_000)
            for episode in range(config.eval_episodes):
                obs, info = env.reset(seed=EVAL_SEED + episode)
                total, done = 0.0, False
                while not done:
                    action, _ = agent.predict(obs, deterministic=True)
                    obs, reward, terminated, truncated, _ = env.step(action)
                    total, done = total + float(reward), terminated or truncated
                rows.append({"arm": arm, "seed": seed, "episode": episode, "mass": info["mass"],
                             "length": info["length"], "return": total})  # fmt: skip
            save_file({"format": "sb3_context/1", "rows": rows}, resume, what="run checkpoint")  # atomic
            print(
                f"seed {seed} {arm}: mean evaluation return {np.mean([r['return'] for r in rows[-config.eval_episodes :]]):.1f}"
            )

    with (run / "eval.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    def returns(arm: str) -> list[float]:
        return [r["return"] for r in rows if r["arm"] == arm]

    def per_seed(arm: str) -> list[float]:
        return [
            float(np.mean([r["return"] for r in rows if r["arm"] == arm and r["seed"] == s]))
            for s in range(config.seeds)
        ]

    paired = [c - p for c, p in zip(returns("context"), returns("plain"), strict=True)]
    summary = {
        "config": dataclasses.asdict(config),
        "over_seeds": {arm: mean_ci(per_seed(arm)) for arm in ("context", "plain")},
        "over_episodes": {arm: mean_ci(returns(arm)) for arm in ("context", "plain")},
        "paired_difference": mean_ci(paired),
        "resumed": resuming,
        "seconds": round(time.perf_counter() - start, 1),  # of this session alone when resumed
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for arm in ("context", "plain"):
        s, e = summary["over_seeds"][arm], summary["over_episodes"][arm]
        print(
            f"{arm:8s} return {s['mean']:8.1f} +- {s['ci95']:.1f} (95% CI over {s['n']} seeds; +- {e['ci95']:.1f} over {e['n']} episodes)"
        )
    d = summary["paired_difference"]
    print(
        f"context - plain: {d['mean']:.1f} +- {d['ci95']:.1f} (paired episodes); {summary['seconds']:.0f} s; wrote {run}"
    )


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("interrupted; run the same command again to resume from the last checkpoint", file=sys.stderr)
        sys.exit(130)
