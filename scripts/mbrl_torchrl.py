"""Model-based RL on torchrl: a collector whose policy is MPC (CEM) on an SMCD model that adapts on every step.

Reads top to bottom: random frames into a ``ReplayBuffer``; fit the model
(``fit_from_replay_buffer``); then a torchrl ``Collector`` runs torchrl's ``CEMPlanner`` on
``AdaptiveWorldModelEnv`` (the adaptive model as a model-based env) in the real env, which carries
``AdaptationTransform`` (``model.observe`` on every real step) and ``RewardSum`` (episode
returns). Every ``fit_every`` frames the model is fitted further on the whole buffer and saved
under ``<out>/<run>/checkpoints/``. Scalars go to torchrl's own logger (``CSVLogger`` by
default, ``--logger tensorboard`` if tensorboard is installed); ``summary.json`` holds the
episode returns and the time.

Resuming: after the first fit and after every collector batch the run is saved to
``<out>/<run>/checkpoint.pt`` (model, replay buffer, counters, returns, torch's generator);
rerun the same command and it goes on from there, refusing a checkpoint that other options
wrote. The episode that was running restarts from a reset, so a resumed run collects the same
number of frames and fits as often as an uninterrupted one, but is not the same run bit for bit.

Copy this file and edit it; ``python scripts/mbrl_torchrl.py --help`` lists the settings,
``--tiny`` makes a smoke run.
"""

from __future__ import annotations

import dataclasses
import json
import sys
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
from smcd_rl.files import load_file, save_file
from smcd_rl.integrations.script_options import parse_config, save_options
from smcd_rl.integrations.torchrl import AdaptationTransform, AdaptiveWorldModelEnv, fit_from_replay_buffer


@dataclass
class Config:
    # "valid": the range an option must lie in, "[low, high]" with ( ) for open ends.
    env_id: str = field(default="Pendulum-v1", metadata={"help": "gymnasium id (a key of REWARDS below)"})
    seed: int = field(default=0, metadata={"help": "seeds torch, the env and the collector", "valid": "[0, inf)"})
    total_frames: int = field(
        default=3000, metadata={"help": "frames collected by the MPC policy", "valid": "[1, inf)"}
    )
    init_random_frames: int = field(
        default=1000, metadata={"help": "random frames collected first", "valid": "[1, inf)"}
    )
    frames_per_batch: int = field(default=200, metadata={"help": "frames per collector batch", "valid": "[1, inf)"})
    fit_every: int = field(default=1000, metadata={"help": "fit the model every this many frames", "valid": "[1, inf)"})
    fit_epochs: int = field(default=20, metadata={"help": "epochs of each fit", "valid": "[1, inf)"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate", "valid": "(0, inf)"})
    hidden: int = field(
        default=128, metadata={"help": "units of each of the model's two hidden layers", "valid": "[1, inf)"}
    )
    dropout: float = field(default=0.1, metadata={"help": "dropout probability of the model", "valid": "(0, 1)"})
    particles: int = field(default=50, metadata={"help": "SMCD mask particles", "valid": "[1, inf)"})
    noise_std: float = field(default=0.05, metadata={"help": "SMCD likelihood noise", "valid": "(0, inf)"})
    flip_prob: float = field(
        default=0.001, metadata={"help": "SMCD per-bit flip probability per step", "valid": "[0, 1]"}
    )
    planning_horizon: int = field(default=15, metadata={"help": "CEM horizon", "valid": "[1, inf)"})
    optim_steps: int = field(default=5, metadata={"help": "CEM iterations per action", "valid": "[1, inf)"})
    num_candidates: int = field(default=200, metadata={"help": "CEM candidates per iteration", "valid": "[1, inf)"})
    top_k: int = field(
        default=20, metadata={"help": "CEM elites per iteration (at most --num-candidates)", "valid": "[1, inf)"}
    )
    buffer_size: int = field(default=100_000, metadata={"help": "replay buffer capacity", "valid": "[1, inf)"})
    logger: str = field(default="csv", metadata={"help": "csv or tensorboard (needs the tensorboard package)"})
    threads: int = field(default=1, metadata={"help": "torch threads", "valid": "[1, inf)"})
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


CHOICES = {"env_id": sorted(REWARDS), "logger": ["csv", "tensorboard"]}


def run_dir(config: Config) -> Path:
    return Path(config.out) / f"mbrl_{config.env_id.replace('/', '_')}_seed{config.seed}"


def parse_args() -> Config:
    """The options, checked (ranges, and a checkpoint's options when resuming) before any work: usage and exit 2 if not."""

    def check(config: Config) -> str | None:
        if config.top_k > config.num_candidates:
            return f"argument --top-k: must be at most --num-candidates ({config.num_candidates}), got {config.top_k}"
        return None

    description = __doc__.split("\n")[0]
    return parse_config(Config, run_dir=run_dir, tiny=TINY, description=description, choices=CHOICES, check=check)


def main() -> None:
    config = parse_args()
    run = run_dir(config)
    run_name = run.name
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    resume = run / "checkpoint.pt"
    resuming = resume.is_file()
    save_options(config, run)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    if config.logger == "tensorboard":
        from torchrl.record.loggers.tensorboard import TensorboardLogger

        logger = TensorboardLogger(run_name, log_dir=str(run / "logs"))
    else:
        logger = CSVLogger(run_name, log_dir=str(run / "logs"))  # appends to the files of a resumed run
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
    episode_returns: list[float] = []
    frames, last_fit, fits = 0, 0, 0

    def fit() -> None:
        nonlocal fits
        losses = fit_from_replay_buffer(model, buffer, epochs=config.fit_epochs, lr=config.lr, seed=config.seed + fits)
        fits += 1
        logger.log_scalar("fit_loss", losses[-1], step=len(buffer))
        model.save(run / "checkpoints" / f"model_{len(buffer)}.pt")

    def save() -> None:
        state = {"format": "mbrl_torchrl/1", "model": model.checkpoint(), "buffer": buffer.state_dict(), "frames": frames,
                 "last_fit": last_fit, "fits": fits, "episode_returns": episode_returns,
                 "torch_rng": torch.get_rng_state()}  # fmt: skip
        save_file(state, resume, what="run checkpoint")  # atomic: a kill while saving keeps the last checkpoint

    if resuming:
        fix = "delete it to start afresh, or use another --out"
        state = load_file(resume, what="mbrl_torchrl.py run checkpoint", expect_format="mbrl_torchrl/1", fix=fix)
        model.load_checkpoint(state["model"])
        buffer.load_state_dict(state["buffer"])
        frames, last_fit, fits = state["frames"], state["last_fit"], state["fits"]
        episode_returns = state["episode_returns"]
        torch.set_rng_state(state["torch_rng"])
        print(f"resuming {run} after {frames} of {config.total_frames} MPC frames", flush=True)
        base_env.set_seed(config.seed + frames)  # the interrupted episode restarts from a new reset
    else:
        # 1. Random frames (policy None), then the first fit. total_frames=-1: a collector that
        # reaches its total closes the env, which the MPC collector still needs.
        random_collector = Collector(base_env, None, frames_per_batch=config.init_random_frames, total_frames=-1)
        buffer.extend(next(iter(random_collector)).select(*keys).reshape(-1))
        random_collector.shutdown(close_env=False)
        fit()
        save()

    # 2. MPC on the adaptive model, adapting on every real step.
    if frames < config.total_frames:
        world = AdaptiveWorldModelEnv.from_env(model, base_env, REWARDS[config.env_id])
        planner = CEMPlanner(world, config.planning_horizon, config.optim_steps, config.num_candidates, config.top_k)
        env = TransformedEnv(base_env, Compose(AdaptationTransform(model), RewardSum()))
        collector = Collector(
            env,
            planner,
            frames_per_batch=config.frames_per_batch,
            total_frames=config.total_frames - frames,
            auto_register_policy_transforms=False,  # the planner needs no InitTracker
        )
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
                print(
                    f"{frames} frames, {len(episode_returns)} episodes, last return {episode_returns[-1:]}", flush=True
                )
            save()
        collector.shutdown()

    seconds = time.perf_counter() - start
    summary = {
        "config": dataclasses.asdict(config),
        "episode_returns": episode_returns,
        "mean_return": float(np.mean(episode_returns)) if episode_returns else None,
        "frames": frames,
        "fits": fits,
        "resumed": resuming,
        "seconds": round(seconds, 1),  # of this session alone when resumed
    }
    (run / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(
        f"{frames} MPC frames, {len(episode_returns)} finished episodes, returns {[round(r, 1) for r in episode_returns]}; "
        f"{seconds:.0f} s; wrote {run}"
    )


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:
        print("interrupted; run the same command again to resume from the last checkpoint", file=sys.stderr)
        sys.exit(130)
