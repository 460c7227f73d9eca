"""PETS with mbrl-lib's own planner on an SMCD model that adapts on every real step.

mbrl-lib's ``mbrl.algorithms.pets`` with the ensemble swapped for an adaptive model: random
transitions first, then step by step: fit every ``freq_train_model`` steps, plan with mbrl-lib's
``TrajectoryOptimizerAgent`` (CEM) on ``mbrl.models.ModelEnv`` through the adapter
(:mod:`smcd_rl.integrations.mbrl_lib`, TS-infinity over the mask posterior), adapt the model on
the real transition. Writes ``<out>/<run>/results.csv`` (mbrl-lib's logger: env step, episode
return), ``model.pt`` and ``summary.json``.

Resuming: the run is saved to ``<out>/<run>/checkpoint.pt`` after the random steps and after
every planned episode (``pets_loop(..., checkpoint=...)``); rerun the same command and it goes on
after the last saved episode, refusing a checkpoint that other options wrote. The result is bit
for bit that of an uninterrupted run; an interruption loses at most the episode that was running.

Needs mbrl-lib: ``bash scripts/install_mbrl_lib.sh``. Copy this file and edit it; run
``python scripts/pets_mbrl_lib.py --help`` for the settings, ``--tiny`` for a smoke run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium
import numpy as np
import torch
from torch import Tensor

import smcd_rl
from smcd_rl.integrations.mbrl_lib import pets_loop
from smcd_rl.integrations.script_options import parse_config, save_options


@dataclass
class Config:
    # "valid": the range an option must lie in, "[low, high]" with ( ) for open ends.
    env_id: str = field(default="InvertedPendulum-v5", metadata={"help": "gymnasium id (a key of TASKS below)"})
    seed: int = field(default=0, metadata={"help": "seeds torch, numpy, the env and the planner", "valid": "[0, inf)"})
    num_steps: int = field(default=3000, metadata={"help": "real steps planned by the agent", "valid": "[1, inf)"})
    initial_steps: int = field(default=1000, metadata={"help": "random exploration steps first", "valid": "[1, inf)"})
    freq_train_model: int = field(
        default=500, metadata={"help": "fit the model every this many steps", "valid": "[1, inf)"}
    )
    fit_epochs: int = field(default=20, metadata={"help": "epochs of each fit", "valid": "[1, inf)"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate", "valid": "(0, inf)"})
    hidden: int = field(default=128, metadata={"help": "units of each of the two hidden layers", "valid": "[1, inf)"})
    dropout: float = field(
        default=0.1, metadata={"help": "dropout probability of training and of the masks", "valid": "(0, 1)"}
    )
    filter_particles: int = field(default=50, metadata={"help": "SMCD mask particles", "valid": "[1, inf)"})
    noise_std: float = field(default=0.05, metadata={"help": "SMCD likelihood noise", "valid": "(0, inf)"})
    flip_prob: float = field(
        default=0.001, metadata={"help": "SMCD per-bit flip probability per step", "valid": "[0, 1]"}
    )
    propagation: str = field(default="fixed_model", metadata={"help": "fixed_model, random_model or expectation"})
    planning_horizon: int = field(default=15, metadata={"help": "CEM horizon", "valid": "[1, inf)"})
    cem_iterations: int = field(default=5, metadata={"help": "CEM iterations per action", "valid": "[1, inf)"})
    population_size: int = field(default=200, metadata={"help": "CEM candidates per iteration", "valid": "[1, inf)"})
    elite_ratio: float = field(default=0.1, metadata={"help": "CEM elite fraction", "valid": "(0, 1]"})
    alpha: float = field(default=0.1, metadata={"help": "CEM momentum", "valid": "[0, 1)"})
    num_particles: int = field(
        default=5, metadata={"help": "posterior masks per candidate (TS-infinity rows)", "valid": "[1, inf)"}
    )
    random_episodes: int = field(
        default=20, metadata={"help": "episodes of random actions, the baseline", "valid": "[1, inf)"}
    )
    threads: int = field(default=1, metadata={"help": "torch threads", "valid": "[1, inf)"})
    out: str = field(default="runs", metadata={"help": "output directory"})
    tiny: bool = field(default=False, metadata={"help": "a smoke run of seconds (overrides the sizes)"})


TINY = {"num_steps": 40, "initial_steps": 100, "freq_train_model": 20, "fit_epochs": 2, "hidden": 32,
        "filter_particles": 10, "planning_horizon": 3, "cem_iterations": 2, "population_size": 16,
        "num_particles": 2, "random_episodes": 2}  # fmt: skip


def inverted_pendulum_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    return (next_obs[..., 1].abs() <= 0.2).to(torch.float32)  # 1 per step while the pole is up


def inverted_pendulum_termination(next_obs: Tensor) -> Tensor:
    return ~(torch.isfinite(next_obs).all(-1) & (next_obs[..., 1].abs() <= 0.2))


# The planner's reward and termination per task, pure batched torch functions of the observation
# (add yours; smcd_rl.envs.crippled_ant.ant_reward / ant_termination fit as they are).
TASKS = {"InvertedPendulum-v5": (inverted_pendulum_reward, inverted_pendulum_termination)}


CHOICES = {"env_id": sorted(TASKS), "propagation": ["fixed_model", "random_model", "expectation"]}


def run_dir(config: Config) -> Path:
    return Path(config.out) / f"pets_{config.env_id.replace('/', '_')}_seed{config.seed}"


def parse_args() -> Config:
    """The options, checked (ranges, and a checkpoint's options when resuming) before any work: usage and exit 2 if not."""

    def check(config: Config) -> str | None:
        elites = math.ceil(config.population_size * config.elite_ratio)
        if config.cem_iterations > 1 and elites < 2:  # one elite has no variance: CEM's next iteration plans NaN
            return (
                f"argument --elite-ratio: --population-size {config.population_size} x --elite-ratio "
                f"{config.elite_ratio} keeps {elites} elite, but CEM with --cem-iterations {config.cem_iterations} "
                "needs at least 2; raise either, or pass --cem-iterations 1"
            )
        return None

    description = __doc__.split("\n")[0]
    return parse_config(Config, run_dir=run_dir, tiny=TINY, description=description, choices=CHOICES, check=check)


def random_returns(env: gymnasium.Env, episodes: int, seed: int) -> list[float]:
    returns = []
    env.action_space.seed(seed)
    for episode in range(episodes):
        env.reset(seed=seed + 10_000 + episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return returns


def main() -> None:
    config = parse_args()
    import mbrl.constants  # after --help: mbrl-lib takes a second to import
    import mbrl.util

    run = run_dir(config)
    run.mkdir(parents=True, exist_ok=True)
    resuming = (run / "checkpoint.pt").is_file()
    save_options(config, run)
    if resuming:
        print(f"resuming {run} from its checkpoint", flush=True)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    start = time.perf_counter()

    env = gymnasium.make(config.env_id)
    reward_fn, termination_fn = TASKS[config.env_id]
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    net = smcd_rl.MaskedMLP(obs_dim + act_dim, obs_dim, hidden=(config.hidden, config.hidden), dropout=config.dropout)
    smcd = smcd_rl.SMCD(
        num_particles=config.filter_particles,
        noise_std=config.noise_std,
        flip_prob=config.flip_prob,
        generator=torch.Generator().manual_seed(config.seed),
    )
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd)

    logger = mbrl.util.Logger(run)  # rewrites results.csv: a resumed pets_loop logs the saved episodes again
    logger.register_group(mbrl.constants.RESULTS_LOG_NAME, mbrl.constants.EVAL_LOG_FORMAT, color="green")

    def log_episode(env_step: int, episode_return: float, length: int) -> None:
        logger.log_data(mbrl.constants.RESULTS_LOG_NAME, {"env_step": env_step, "episode_reward": episode_return})

    returns = pets_loop(
        env,
        model,
        reward_fn,
        termination_fn,
        num_steps=config.num_steps,
        initial_steps=config.initial_steps,
        freq_train_model=config.freq_train_model,
        fit_epochs=config.fit_epochs,
        lr=config.lr,
        propagation=config.propagation,
        planning_horizon=config.planning_horizon,
        num_iterations=config.cem_iterations,
        population_size=config.population_size,
        elite_ratio=config.elite_ratio,
        alpha=config.alpha,
        num_particles=config.num_particles,
        seed=config.seed,
        on_episode=log_episode,
        checkpoint=run / "checkpoint.pt",
    )
    seconds = time.perf_counter() - start
    baseline = random_returns(env, config.random_episodes, config.seed)
    model.save(run / "model.pt")
    summary = {
        "config": dataclasses.asdict(config),
        "episode_returns": returns,
        "best_return": max(returns),
        "mean_return": float(np.mean(returns)),
        "random_mean_return": float(np.mean(baseline)),
        "resumed": resuming,
        "seconds": round(seconds, 1),  # of this session alone when resumed
        "ms_per_step": None if resuming else round(1000 * seconds / config.num_steps, 1),
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(
        f"{len(returns)} episodes in {seconds:.0f} s: best return {max(returns):.1f}, mean {np.mean(returns):.1f} "
        f"(random actions: {np.mean(baseline):.1f}); wrote {run}"
    )


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("interrupted; run the same command again to resume from the last checkpoint", file=sys.stderr)
        sys.exit(130)
