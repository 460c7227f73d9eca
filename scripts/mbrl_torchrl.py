"""Model-based RL on torchrl: a collector whose policy is MPC (CEM) on an SMCD model that adapts on every step.

Reads top to bottom: random frames into a ``ReplayBuffer``; fit the model
(``fit_from_replay_buffer``); then a torchrl ``Collector`` runs torchrl's ``CEMPlanner`` on
``AdaptiveWorldModelEnv`` (the adaptive model as a model-based env) in the real env, which carries
``AdaptationTransform`` (``model.observe`` on every real step) and ``RewardSum`` (episode
returns). Every ``fit_every`` frames the model is fitted further on the whole buffer and saved
under ``<out>/<run>/checkpoints/``. Scalars go to torchrl's own logger (``CSVLogger`` by
default, ``--logger tensorboard`` if tensorboard is installed); ``summary.json`` holds the
episode returns and the time.

Copy this file and edit it; ``python scripts/mbrl_torchrl.py --help`` lists the settings,
``--tiny`` makes a smoke run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, GymEnv, RewardSum, TransformedEnv
from torchrl.modules import CEMPlanner
from torchrl.record.loggers.csv import CSVLogger

import smcd_rl
from smcd_rl.integrations.torchrl import AdaptationTransform, AdaptiveWorldModelEnv, fit_from_replay_buffer


@dataclass
class Config:
    env_id: str = field(default="Pendulum-v1", metadata={"help": "gymnasium id (a key of REWARDS below)"})
    seed: int = field(default=0, metadata={"help": "seeds torch, the env and the collector"})
    total_frames: int = field(default=3000, metadata={"help": "frames collected by the MPC policy"})
    init_random_frames: int = field(default=1000, metadata={"help": "random frames collected first"})
    frames_per_batch: int = field(default=200, metadata={"help": "frames per collector batch"})
    fit_every: int = field(default=1000, metadata={"help": "fit the model every this many frames"})
    fit_epochs: int = field(default=20, metadata={"help": "epochs of each fit"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate"})
    hidden: int = field(default=128, metadata={"help": "units of each of the model's two hidden layers"})
    dropout: float = field(default=0.1, metadata={"help": "dropout probability of the model"})
    particles: int = field(default=50, metadata={"help": "SMCD mask particles"})
    noise_std: float = field(default=0.05, metadata={"help": "SMCD likelihood noise"})
    flip_prob: float = field(default=0.001, metadata={"help": "SMCD per-bit flip probability per step"})
    planning_horizon: int = field(default=15, metadata={"help": "CEM horizon"})
    optim_steps: int = field(default=5, metadata={"help": "CEM iterations per action"})
    num_candidates: int = field(default=200, metadata={"help": "CEM candidates per iteration"})
    top_k: int = field(default=20, metadata={"help": "CEM elites per iteration"})
    buffer_size: int = field(default=100_000, metadata={"help": "replay buffer capacity"})
    logger: str = field(default="csv", metadata={"help": "csv or tensorboard (needs the tensorboard package)"})
    threads: int = field(default=1, metadata={"help": "torch threads"})
    out: str = field(default="runs", metadata={"help": "output directory"})
    tiny: bool = field(default=False, metadata={"help": "a smoke run of seconds (overrides the sizes)"})


TINY = {"total_frames": 40, "init_random_frames": 100, "frames_per_batch": 20, "fit_every": 20, "fit_epochs": 2,
        "hidden": 32, "particles": 10, "planning_horizon": 3, "optim_steps": 2, "num_candidates": 16,
        "top_k": 4}  # fmt: skip


def pendulum_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    """Pendulum-v1's reward, of the state before the step: -(angle^2 + 0.1 speed^2 + 0.001 torque^2)."""
    angle = torch.atan2(obs[..., 1], obs[..., 0])
    return -(angle.square() + 0.1 * obs[..., 2].square() + 0.001 * action[..., 0].square())


# The planner's reward per task, a pure batched torch function (add yours).
REWARDS = {"Pendulum-v1": pendulum_reward}


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


def main() -> None:
    config = parse_args()
    run_name = f"mbrl_{config.env_id.replace('/', '_')}_seed{config.seed}"
    run = Path(config.out) / run_name
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    if config.logger == "tensorboard":
        from torchrl.record.loggers.tensorboard import TensorboardLogger

        logger = TensorboardLogger(run_name, log_dir=str(run / "logs"))
    else:
        logger = CSVLogger(run_name, log_dir=str(run / "logs"))
    start = time.perf_counter()

    base_env = GymEnv(config.env_id)
    base_env.set_seed(config.seed)
    obs_dim = base_env.observation_spec["observation"].shape[-1]
    act_dim = base_env.action_spec.shape[-1]
    net = smcd_rl.MaskedMLP(obs_dim + act_dim, obs_dim, hidden=(config.hidden, config.hidden), dropout=config.dropout)
    smcd = smcd_rl.SMCD(
        num_particles=config.particles,
        noise_std=config.noise_std,
        flip_prob=config.flip_prob,
        generator=torch.Generator().manual_seed(config.seed),
    )
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd)
    keys = [*model.in_keys, model.target_key, ("next", "reward"), ("next", "done")]
    buffer = ReplayBuffer(storage=LazyTensorStorage(config.buffer_size))

    # 1. Random frames (policy None), then the first fit. total_frames=-1: a collector that
    # reaches its total closes the env, which the MPC collector still needs.
    random_collector = Collector(base_env, None, frames_per_batch=config.init_random_frames, total_frames=-1)
    buffer.extend(next(iter(random_collector)).select(*keys).reshape(-1))
    random_collector.shutdown(close_env=False)
    fits = 0

    def fit() -> None:
        nonlocal fits
        losses = fit_from_replay_buffer(model, buffer, epochs=config.fit_epochs, lr=config.lr, seed=config.seed + fits)
        fits += 1
        logger.log_scalar("fit_loss", losses[-1], step=len(buffer))
        model.save(run / "checkpoints" / f"model_{len(buffer)}.pt")

    fit()

    # 2. MPC on the adaptive model, adapting on every real step.
    world = AdaptiveWorldModelEnv.from_env(model, base_env, REWARDS[config.env_id])
    planner = CEMPlanner(world, config.planning_horizon, config.optim_steps, config.num_candidates, config.top_k)
    env = TransformedEnv(base_env, Compose(AdaptationTransform(model), RewardSum()))
    collector = Collector(
        env,
        planner,
        frames_per_batch=config.frames_per_batch,
        total_frames=config.total_frames,
        auto_register_policy_transforms=False,  # the planner needs no InitTracker
    )
    episode_returns: list[float] = []
    frames, last_fit = 0, 0
    for batch in collector:
        buffer.extend(batch.select(*keys).reshape(-1))
        frames += batch.numel()
        done = batch["next", "done"].squeeze(-1)
        for value in batch["next", "episode_reward"][done].flatten().tolist():
            episode_returns.append(value)
            logger.log_scalar("episode_return", value, step=frames)
        logger.log_scalar("batch_mean_reward", float(batch["next", "reward"].mean()), step=frames)
        logger.log_scalar("smcd_ess", float(batch["next", "smcd_ess"].float().mean()), step=frames)
        if frames - last_fit >= config.fit_every:
            fit()
            last_fit = frames
            print(f"{frames} frames, {len(episode_returns)} episodes, last return {episode_returns[-1:]}", flush=True)
    collector.shutdown()

    seconds = time.perf_counter() - start
    summary = {
        "config": dataclasses.asdict(config),
        "episode_returns": episode_returns,
        "mean_return": float(np.mean(episode_returns)) if episode_returns else None,
        "frames": frames,
        "seconds": round(seconds, 1),
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(
        f"{frames} MPC frames, {len(episode_returns)} finished episodes, returns {[round(r, 1) for r in episode_returns]}; "
        f"{seconds:.0f} s; wrote {run}"
    )


if __name__ == "__main__":
    main()
