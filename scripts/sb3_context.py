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

Copy this file and edit it; ``python scripts/sb3_context.py --help`` lists the settings,
``--tiny`` makes a smoke run.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
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
from smcd_rl.integrations.gymnasium import AdaptationWrapper, collect_transitions


@dataclass
class Config:
    seeds: int = field(default=3, metadata={"help": "agents per arm, seeds 0..seeds-1"})
    train_steps: int = field(default=6000, metadata={"help": "SAC environment steps per agent"})
    eval_episodes: int = field(default=10, metadata={"help": "evaluation episodes per agent (the same for both arms)"})
    context: int = field(default=4, metadata={"help": "size k of the mask projection (k + 1 numbers appended)"})
    data_steps: int = field(default=20000, metadata={"help": "random transitions the dynamics model is fitted on"})
    fit_epochs: int = field(default=20, metadata={"help": "epochs of the model fit"})
    hidden: int = field(default=128, metadata={"help": "units of each of the model's two hidden layers"})
    dropout: float = field(default=0.5, metadata={"help": "dropout probability of the model"})
    particles: int = field(default=100, metadata={"help": "SMCD mask particles"})
    noise_std: float = field(default=0.05, metadata={"help": "SMCD likelihood noise"})
    policy_hidden: int = field(default=64, metadata={"help": "units of each of SAC's two hidden layers"})
    threads: int = field(default=1, metadata={"help": "torch threads"})
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


def parse_args() -> Config:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for f in dataclasses.fields(Config):
        flag = "--" + f.name.replace("_", "-")
        if f.type in (bool, "bool"):
            parser.add_argument(flag, action="store_true", help=f.metadata["help"])
        else:
            kind = {"int": int, "float": float, "str": str}[str(f.type)]
            parser.add_argument(flag, type=kind, default=f.default, help=f"{f.metadata['help']} (default: {f.default})")
    config = Config(**vars(parser.parse_args()))
    return dataclasses.replace(config, **TINY) if config.tiny else config


def mean_ci(values: list[float]) -> dict[str, float]:
    """Mean and the half-width of its 95% Student-t confidence interval."""
    n = len(values)
    t95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}
    half = t95.get(n - 1, 1.96) * float(np.std(values, ddof=1)) / math.sqrt(n) if n > 1 else float("nan")
    return {"mean": float(np.mean(values)), "ci95": half, "n": n}


def main() -> None:
    config = parse_args()
    run = Path(config.out) / f"sb3_context_k{config.context}"
    run.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(config.threads)
    torch.manual_seed(0)
    start = time.perf_counter()

    # The dynamics model: fitted once on random transitions of many pendulums.
    data = collect_transitions(RandomPendulum(gymnasium.make("Pendulum-v1")), None, config.data_steps, seed=0)
    net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=(config.hidden, config.hidden), dropout=config.dropout)
    model = smcd_rl.AdaptiveDynamicsModel(net)
    smcd_rl.fit_dynamics(model, data, epochs=config.fit_epochs, batch_size=256, lr=1e-3, progress=False)
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

    rows: list[dict[str, Any]] = []
    for seed in range(config.seeds):
        for arm in ("context", "plain"):
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
        "seconds": round(time.perf_counter() - start, 1),
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
    main()
