"""The Fetch families' episodes for ``smcd-rl fetch``: training data, tuning episodes and MPC episodes of one cell.

:mod:`smcd_rl.experiments.fetch.run` reads top to bottom and calls these: :func:`collect` (transitions
from many draws of a family, for training), :func:`tuning_episodes` (random-action episodes of
fresh training draws, for the fair protocol), :func:`validation_error` (the trained network's
held-out one-step RMSE) and :func:`run_cell` (the MPC episodes of one family x planner x
adaptation cell, through :class:`~smcd_rl.agents.mpc.MPCAgent`, with ``model.observe`` of every
real step; an observation on which gradient descent diverges is skipped and counted), and :func:`random_cell` (the same test draws under uniform random actions).

gymnasium-robotics and mujoco are optional dependencies: the families are made through
``gymnasium.make``, and ``smcd_rl.integrations.robotics`` is imported only where it is used, so
``smcd-rl --help`` works without them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.mpc import MPCAgent
from smcd_rl.agents.planners import CEM, MPPI, Planner
from smcd_rl.experiments.fetch.config import FAMILIES
from smcd_rl.experiments.shared.video import headless_mujoco, write_gif
from smcd_rl.integrations.gymnasium import collect_transitions

if TYPE_CHECKING:
    from smcd_rl.experiments.fetch.config import FetchConfig

__all__ = [
    "make_env",
    "collect",
    "tuning_episodes",
    "validation_error",
    "run_cell",
    "random_cell",
    "scripted_push",
]


def make_env(
    family: str, config: FetchConfig, max_steps: int, *, render_mode: str | None = None
) -> gymnasium.Env[Any, Any]:
    """The family's env with the dense reward (``-distance``, which the planners rank by), truncated at ``max_steps``.

    With ``render_mode="rgb_array"`` and no display, MuJoCo renders through EGL (headless), unless
    ``MUJOCO_GL`` already names a backend; rendering changes nothing of the physics.
    """
    import smcd_rl.integrations.robotics  # noqa: F401  (registers the families; needs gymnasium-robotics)

    if render_mode is not None:
        headless_mujoco()
    kwargs: dict[str, Any] = {"reward_type": "dense", "max_episode_steps": max_steps, "render_mode": render_mode}
    if family == "reach":
        kwargs["rotation"] = (-config.rotation, config.rotation)
    return gymnasium.make(FAMILIES[family], **kwargs)


def scripted_push(rng: np.random.Generator) -> Callable[[dict[str, np.ndarray]], np.ndarray]:
    """A noisy push policy: towards the block (``observation[6:9]``, block minus gripper) plus uniform noise.

    Random actions alone seldom touch the block, so a model trained on them never sees it move.
    """

    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
        towards = 10.0 * np.asarray(obs["observation"][6:9], dtype=np.float64)
        noise = rng.uniform(-1.0, 1.0, size=3)
        return np.clip(np.append(towards + noise, 0.0), -1.0, 1.0).astype(np.float32)

    return act


def _policy(family: str, seed: int) -> Callable[[dict[str, np.ndarray]], np.ndarray] | None:
    """The data policy: uniform random actions for reach, :func:`scripted_push` for push."""
    return scripted_push(np.random.default_rng(seed)) if family == "push" else None


def collect(family: str, config: FetchConfig, *, progress: bool) -> dict[str, Any]:
    """``--transitions`` transitions from draws of the family, one draw per episode of ``--data-episode-steps``.

    Returns ``{"data": TensorDict [transitions], "seconds": ...}``; ``data["task"]`` numbers each
    transition's draw (the task the T network's masks are trained to identify).
    """
    env = make_env(family, config, config.data_episode_steps)
    started = time.perf_counter()
    chunks = []
    sizes = [config.data_episode_steps] * (config.transitions // config.data_episode_steps)
    if config.transitions % config.data_episode_steps:
        sizes.append(config.transitions % config.data_episode_steps)
    policy = _policy(family, config.seed)
    for i, size in enumerate(tqdm(sizes, desc=f"collect {family}", unit="ep", disable=not progress)):
        # Seeding only the first call makes the whole collection one repeatable stream.
        chunk = collect_transitions(env, policy, size, seed=config.seed if i == 0 else None)
        chunk["task"] = torch.full((size,), i, dtype=torch.int64)  # one draw per episode: T's task id
        chunks.append(chunk)
    env.close()
    data = cast(TensorDict, torch.cat(chunks)).select("observation", "action", ("next", "observation"), "task")
    return {"data": data, "seconds": time.perf_counter() - started}


def tuning_episodes(family: str, config: FetchConfig, *, seed: int) -> TensorDict:
    """``--tuning-episodes`` episodes of ``--tuning-steps`` data-policy actions, each on a fresh draw: ``[E, T]``.

    Episode ``k`` resets with env seed ``seed + k`` (its draw and goal) and draws its actions from a
    generator of the same seed; the seeds are the fair protocol's own, neither training nor test.
    """
    env = make_env(family, config, config.tuning_steps)
    observations, actions = [], []
    for k in range(config.tuning_episodes):
        obs, _ = env.reset(seed=seed + k)
        rng = np.random.default_rng(seed + k)
        scripted = scripted_push(rng) if family == "push" else None
        states, taken = [obs["observation"]], []
        for _ in range(config.tuning_steps):
            action = (
                scripted(obs)
                if scripted is not None
                else rng.uniform(-1.0, 1.0, size=env.action_space.shape).astype(np.float32)
            )
            obs, *_ = env.step(action)
            states.append(obs["observation"])
            taken.append(action)
        observations.append(torch.as_tensor(np.stack(states), dtype=torch.float32))
        actions.append(torch.as_tensor(np.stack(taken), dtype=torch.float32))
    env.close()
    logged = torch.stack(observations)
    return TensorDict(
        {"observation": logged[:, :-1], "action": torch.stack(actions), "next": {"observation": logged[:, 1:]}},
        batch_size=[config.tuning_episodes, config.tuning_steps],
    )


@torch.no_grad()
def validation_error(model: smcd_rl.AdaptiveDynamicsModel, val: TensorDict) -> torch.Tensor:
    """Per-dimension one-step RMSE (observation units) of the trained model on the held-out transitions."""
    model.reset()
    predicted = model(val.select("observation", "action").clone()).get(("next", "observation"))
    error = predicted - val.get(("next", "observation")).to(predicted.dtype)
    return error.square().mean(0).sqrt().cpu()


def _make_planner(
    name: str, config: FetchConfig, env: gymnasium.Env[Any, Any], generator: torch.Generator, device: torch.device
) -> Planner:
    box = env.action_space
    assert isinstance(box, gymnasium.spaces.Box)
    common: dict[str, Any] = {
        "action_low": box.low.tolist(),
        "action_high": box.high.tolist(),
        "horizon": config.horizon,
        "device": device,
        "generator": generator,
    }
    if name == "cem":
        return CEM(num_candidates=config.candidates, num_elites=config.elites, iterations=config.iterations, **common)
    return MPPI(
        num_candidates=config.candidates,
        iterations=config.iterations,
        temperature=config.temperature,
        noise_std=config.mppi_noise,
        **common,
    )


def _record(
    k: int, seed: int, obs: dict[str, np.ndarray], info: dict[str, Any], task: dict[str, Any]
) -> dict[str, Any]:
    distance = float(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]))
    return {
        "episode": k,
        "seed": seed,
        "success": float(info["is_success"]),
        "distance": distance,
        **{f"task {name}": float(value) for name, value in task.items()},
    }


def _transition(
    obs: dict[str, np.ndarray], action: np.ndarray, next_obs: dict[str, np.ndarray], device: torch.device
) -> TensorDict:
    """One real transition of the ``observation`` entry, as ``model.observe`` takes it."""

    def tensor(value: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(value), dtype=torch.float32, device=device)

    return TensorDict(
        {
            "observation": tensor(obs["observation"]),
            "action": tensor(action),
            "next": {"observation": tensor(next_obs["observation"])},
        },
        batch_size=[],
    )


def run_cell(
    model: smcd_rl.AdaptiveDynamicsModel,
    family: str,
    planner: str,
    config: FetchConfig,
    strategy: smcd_rl.Adaptation,
    *,
    planner_seed: int,
    episode_seeds: Sequence[int],
    device: torch.device,
    progress: bool,
    video: int = 0,
    video_path: Callable[[int], Path] | None = None,
) -> dict[str, Any]:
    """The MPC episodes of one (family, planner, adaptation) cell: ``{"episodes": [one record per episode]}``.

    With ``video`` > 0 the first ``video`` episodes are rendered and written as GIFs to
    ``video_path(k)``; their paths are in the result's ``"videos"``.

    Each episode resets with its env seed (the draw and the goal, the same in every cell) and
    resets the adapted copy of the model; the planner (seeded once per cell) ranks candidates by the
    family's dense reward on the model's predicted ``observation``. A record holds the env's
    ``is_success`` and the distance of the achieved goal to the goal after the last step.
    """
    adapted = model.with_adaptation(strategy)
    assert isinstance(adapted, smcd_rl.AdaptiveDynamicsModel)
    env = make_env(family, config, config.episode_steps, render_mode="rgb_array" if video else None)
    generator = torch.Generator(device=device).manual_seed(planner_seed)
    videos: list[str] = []
    agent = MPCAgent.from_goal_env(adapted, _make_planner(planner, config, env, generator, device), env, device=device)
    episodes = []
    bar = tqdm(
        total=len(episode_seeds) * config.episode_steps,
        desc=f"{family}/{planner}",
        unit="step",
        leave=False,
        disable=not progress,
    )
    for k, seed in enumerate(episode_seeds):
        started = time.perf_counter()
        obs, info = env.reset(seed=seed)
        adapted.reset()
        agent.reset()
        task = dict(info["task"])
        done, refused = False, 0
        frames: list[np.ndarray] = [_frame(env)] if k < video else []
        while not done:
            action = agent.act(obs)
            next_obs, _, terminated, truncated, info = env.step(action)
            if k < video:
                frames.append(_frame(env))
            try:
                adapted.observe(_transition(obs, action, next_obs, device))
            except ValueError:  # gradient descent diverged: it keeps its state and goes on
                refused += 1
            obs, done = next_obs, terminated or truncated
            bar.update(1)
        episodes.append(
            {**_record(k, seed, obs, info, task), "refused": refused, "seconds": time.perf_counter() - started}
        )
        if frames and video_path is not None:
            videos.append(str(write_gif(frames, video_path(k), fps=env.metadata.get("render_fps", 25))))
    bar.close()
    env.close()
    return {"episodes": episodes, **({"videos": videos} if video else {})}


def _frame(env: gymnasium.Env[Any, Any]) -> np.ndarray:
    frame = env.render()
    assert isinstance(frame, np.ndarray), "the env was made with render_mode='rgb_array'"
    return frame


def random_cell(family: str, config: FetchConfig, *, episode_seeds: Sequence[int]) -> dict[str, Any]:
    """The test draws under uniform random actions (a reference: what no planning reaches)."""
    env = make_env(family, config, config.episode_steps)
    episodes = []
    for k, seed in enumerate(episode_seeds):
        obs, info = env.reset(seed=seed)
        task = dict(info["task"])
        rng = np.random.default_rng(seed)
        done = False
        while not done:
            action = rng.uniform(-1.0, 1.0, size=env.action_space.shape).astype(np.float32)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        episodes.append(_record(k, seed, obs, info, task))
    env.close()
    return {"episodes": episodes}
