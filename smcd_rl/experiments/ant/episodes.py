"""The crippled-leg Ant's episodes for ``smcd-rl ant``: data from the healthy Ant, and MPC episodes of one cell.

:mod:`smcd_rl.experiments.ant.run` reads top to bottom and calls these: :func:`collect` (transitions
from the healthy Ant for training), :func:`validation_error` (the trained model's held-out error,
which scales the paper-setting SMCD's likelihood noise) and :func:`run_cell` (the episodes of one planner x
adaptation x condition cell, through :class:`~smcd_rl.agents.mpc.MPCAgent` and
:class:`~smcd_rl.integrations.gymnasium.AdaptationWrapper`, which calls ``model.observe`` on
every real step).

``smcd_rl.envs.crippled_ant`` imports mujoco, an optional dependency: it is imported where it is
used, so that ``smcd-rl --help`` works without it.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.mpc import MPCAgent
from smcd_rl.agents.planners import CEM, MPPI, Planner, RandomShooting
from smcd_rl.experiments.ant.config import TASKS, RewardWeights
from smcd_rl.experiments.shared.video import headless_mujoco
from smcd_rl.integrations.gymnasium import AdaptationWrapper, collect_transitions

if TYPE_CHECKING:
    from smcd_rl.experiments.ant.config import AntConfig

__all__ = [
    "RewardWeights",
    "TASKS",
    "OBS_DIM",
    "ACTION_DIM",
    "make_env",
    "collect",
    "validation_error",
    "run_cell",
    "render_states",
]

#: The Ant's observation (without contact forces) and action sizes.
OBS_DIM, ACTION_DIM = 41, 8
_X = 0  # torso x position in the observation (OBS_SLICES["qpos"].start)


def make_env(
    task: str, legs: tuple[int, ...] | None, max_steps: int, *, render_mode: str | None = None
) -> gymnasium.Env[np.ndarray, np.ndarray]:
    """The task's Ant, crippling a leg drawn from ``legs`` per episode (``None``: healthy)."""
    from smcd_rl.envs.crippled_ant import CrippledAntEnv

    return gymnasium.wrappers.TimeLimit(
        CrippledAntEnv(crippled_legs=legs, render_mode=render_mode, **TASKS[task][0]), max_episode_steps=max_steps
    )


def _mujoco_state(env: gymnasium.Env[Any, Any]) -> np.ndarray:
    """The simulator's ``(qpos, qvel)``, concatenated: what a video needs to redraw the step."""
    data = env.unwrapped.data  # type: ignore[attr-defined]
    return np.concatenate([data.qpos, data.qvel])


def render_states(task: str, leg: int, states: np.ndarray, *, max_steps: int) -> tuple[list[np.ndarray], float]:
    """MuJoCo frames of recorded ``(qpos, qvel)`` states ``[T, nq + nv]`` of an episode with leg ``leg`` crippled (-1: none).

    The env is made with ``render_mode="rgb_array"`` and reset with that leg, then set to each
    state in turn (``MujocoEnv.set_state``) and rendered; nothing is simulated.

    Without a display and with no ``MUJOCO_GL`` chosen, MuJoCo renders through EGL (headless);
    gymnasium reads the variable when the renderer is made.

    Returns:
        The frames and the env's frame rate (``metadata["render_fps"]``).
    """
    headless_mujoco()
    env = make_env(task, None, max_steps, render_mode="rgb_array")
    env.reset(seed=0, options={"crippled_leg": None if leg < 0 else leg})
    mujoco_env = env.unwrapped
    nq = mujoco_env.model.nq  # type: ignore[attr-defined]
    frames = []
    for state in states:
        mujoco_env.set_state(state[:nq], state[nq:])  # type: ignore[attr-defined]
        frame = env.render()
        assert isinstance(frame, np.ndarray)
        frames.append(frame)
    fps = float(env.metadata.get("render_fps") or 20)
    env.close()
    return frames, fps


def collect(config: AntConfig, *, progress: bool) -> dict[str, Any]:
    """Transitions from the healthy Ant, one ``collect_transitions`` call per episode-long chunk.

    Returns ``{"data": TensorDict [transitions], "seconds": ..., "sac_seconds": ... or None}``.
    """
    env = make_env(config.task, None, config.data_episode_steps)
    policy = None
    sac_seconds = None
    if config.data_policy == "sac":
        from stable_baselines3 import SAC  # optional dependency: smcd-rl[sb3]

        started = time.perf_counter()
        policy = SAC("MlpPolicy", env, buffer_size=config.sac_steps, seed=config.seed, device="cpu")
        policy.learn(config.sac_steps, progress_bar=False)
        sac_seconds = time.perf_counter() - started
        env = make_env(
            config.task, None, config.data_episode_steps
        )  # a fresh env: collection starts from a seeded reset
    started = time.perf_counter()
    chunks = []
    sizes = [config.data_episode_steps] * (config.transitions // config.data_episode_steps)
    if config.transitions % config.data_episode_steps:
        sizes.append(config.transitions % config.data_episode_steps)
    for i, size in enumerate(tqdm(sizes, desc=f"collect ({config.data_policy})", unit="ep", disable=not progress)):
        # Seeding only the first call makes the whole collection one repeatable stream.
        chunks.append(collect_transitions(env, policy, size, seed=config.seed if i == 0 else None))
    env.close()
    data = torch.cat(chunks)
    return {"data": data, "seconds": time.perf_counter() - started, "sac_seconds": sac_seconds}


@torch.no_grad()
def validation_error(model: smcd_rl.AdaptiveDynamicsModel, val: TensorDict) -> tuple[torch.Tensor, float]:
    """Per-dimension RMSE (observation units) and the normalised MSE of the trained model on ``val``."""
    model.reset()
    predicted = model(val.select("observation", "action").clone()).get(("next", "observation"))
    error = predicted - val.get(("next", "observation")).to(predicted.dtype)
    rmse = error.square().mean(0).sqrt().cpu()
    nmse = float((error / model.output_norm.std).square().mean())
    return rmse, nmse


def _make_planner(name: str, config: AntConfig, generator: torch.Generator, device: torch.device) -> Planner:
    common: dict[str, Any] = {
        "action_low": [-1.0] * ACTION_DIM,  # Ant's action box
        "action_high": [1.0] * ACTION_DIM,
        "horizon": config.horizon,
        "device": device,
        "generator": generator,
    }
    if name == "cem":
        return CEM(num_candidates=config.candidates, num_elites=config.elites, iterations=config.iterations, **common)
    if name == "mppi":
        return MPPI(
            num_candidates=config.candidates,
            iterations=config.iterations,
            temperature=config.temperature,
            noise_std=config.mppi_noise,
            **common,
        )
    return RandomShooting(num_candidates=config.candidates * config.iterations, **common)


def run_cell(
    model: smcd_rl.AdaptiveDynamicsModel,
    cell: tuple[str, str, str],
    config: AntConfig,
    strategy: smcd_rl.Adaptation,
    *,
    planner_seed: int,
    episode_seeds: Sequence[int],
    device: torch.device,
    progress: bool,
    record: int = 0,
) -> dict[str, Any]:
    """The episodes of one (planner, adaptation, condition) cell: ``{"episodes": [one record per episode]}``.

    Args:
        model: the trained dynamics model; the cell adapts a copy (``model.with_adaptation``).
        cell: planner (cem, mppi, rs), adaptation (one of the VARIANTS: N, G, S, S(evidence), S(paper), C) and
            condition (healthy, crippled).
        config: the experiment's settings (planner and episode sizes).
        strategy: a fresh strategy of the cell's adaptation, with its tuned settings (the fair
            protocol, :func:`smcd_rl.experiments.shared.tuning.tune`).
        planner_seed: seed of the planner's generator.
        episode_seeds: one env seed per episode (its start state and, crippled, its leg).
        device: torch device of the model and planner.
        progress: show a progress bar over the cell's steps.
        record: keep the simulator states of the first ``record`` episodes, under ``"video"``
            (``{"leg": ..., "states": [steps + 1, nq + nv]}`` each, for :func:`render_states`);
            recording changes no number.
    """
    from smcd_rl.envs.crippled_ant import ant_reward, ant_termination

    planner_name, _, condition = cell
    adapted = model.with_adaptation(strategy)
    assert isinstance(adapted, smcd_rl.AdaptiveDynamicsModel)
    legs = config.crippled_legs if condition == "crippled" else None
    env = AdaptationWrapper(make_env(config.task, legs, config.episode_steps), adapted)
    generator = torch.Generator(device=device).manual_seed(planner_seed)
    _, weights, terminates = TASKS[config.task]
    agent = MPCAgent(
        adapted,
        _make_planner(planner_name, config, generator, device),
        functools.partial(ant_reward, **weights),
        ant_termination if terminates else None,
    )
    episodes, videos = [], []
    bar = tqdm(
        total=len(episode_seeds) * config.episode_steps,
        desc="/".join(cell),
        unit="step",
        leave=False,
        disable=not progress,
    )
    for k, episode_seed in enumerate(episode_seeds):
        episode_started = time.perf_counter()
        obs, info = env.reset(seed=episode_seed)
        agent.reset()
        x0, total, steps, terminated, truncated = float(obs[_X]), 0.0, 0, False, False
        states = [_mujoco_state(env)] if k < record else None
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = env.step(agent.act(obs))
            total += float(reward)
            steps += 1
            bar.update(1)
            if states is not None:
                states.append(_mujoco_state(env))
        if states is not None:
            videos.append({"leg": int(info["crippled_leg"]), "states": np.stack(states)})
        bar.update(config.episode_steps - steps)
        episodes.append(
            {
                "episode": k,
                "seed": episode_seed,
                "leg": int(info["crippled_leg"]),
                "return": total,
                "steps": steps,
                "terminated": bool(terminated),
                "distance": float(obs[_X]) - x0,
                "seconds": time.perf_counter() - episode_started,
            }
        )
    bar.close()
    env.close()
    return {"episodes": episodes, **({"video": videos} if record else {})}
