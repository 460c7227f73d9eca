"""Model-based control of the crippled-leg Ant (paper appendix C, Fig. 15): ``smcd-rl ant``.

Reads top to bottom: seed, collect transitions from the *healthy* Ant (random actions, or a
small stable-baselines3 SAC policy), fit one dropout dynamics model, then run every combination
of planner {CEM, MPPI, RS} x adaptation {none, GD, SMCD} on the healthy Ant and on the Ant with
a crippled leg, through :class:`~smcd_rl.agents.mpc.MPCAgent` and
:class:`~smcd_rl.integrations.gymnasium.AdaptationWrapper` (which calls ``model.observe`` on
every real step). All cells share the trained network (``model.with_adaptation``).

Writes ``results.csv`` (one row per planner, adaptation and condition: mean and spread of the
episode return), ``episodes.csv`` (every episode), ``results.json`` (settings, table, training
loss, timings, machine) and ``ant.png`` (Fig. 15: healthy and crippled panels, bars per planner
grouped by adaptation, error bars one standard deviation over episodes). Finished cells are
kept in ``partial.pt`` and skipped by a rerun with the same settings; the collected data and the
training run are resumable too.

Choices the paper leaves open, made here:

* Crippled condition: each episode cripples a leg drawn uniformly from ``--crippled-legs``
  (default all four: the model never saw any crippled leg, so all are out of distribution).
  Episode ``k`` uses the same env seed in every cell, hence the same initial state and the same
  leg: cells are compared on identical episodes.
* The task (``--task l2a``, default) is Learning to Adapt's, which the paper used: reward =
  forward velocity + 0.05 per step, no control or contact cost, and episodes never end early.
  ``--task ant-v5`` uses Ant-v5's reward (forward velocity + 1 while healthy - 0.5 |a|^2 -
  contact cost) and ends an episode when the Ant is unhealthy. The reported reward is the env's;
  the planners optimise :func:`~smcd_rl.envs.crippled_ant.ant_reward` with the same weights (the
  contact term, which needs contact forces, left out) and, for ant-v5,
  :func:`~smcd_rl.envs.crippled_ant.ant_termination`. On ant-v5, with a model fitted to random
  actions, the planners mostly keep the Ant standing: the control cost outweighs the forward
  velocity the model can predict.
* SMCD's likelihood noise is per observation dimension: the trained model's RMSE on held-out
  transitions times ``--noise-scale`` (default 3; at 1 the effective sample size collapses to
  about 15% of the particles after every step).
* Dropout: ``--full`` uses the paper's p = 0.5 on its 3 x 1024 network. The default network is
  five times narrower and underfits at p = 0.5 (held-out normalised MSE 0.46 on 10^5 random
  transitions, against 0.16 at the default p = 0.1), and planning on it barely moves the Ant.
* Planners get the same budget of model evaluations per step: CEM and MPPI ``iterations x
  candidates``, random shooting that many candidates in one round.

Example:
    >>> from smcd_rl.experiments.ant import AntConfig, CELLS
    >>> config = AntConfig()
    >>> len(CELLS), config.planners, config.adaptations, config.conditions
    (18, ('cem', 'mppi', 'rs'), ('none', 'gd', 'smcd'), ('healthy', 'crippled'))
"""

from __future__ import annotations

import functools
import itertools
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.mpc import MPCAgent
from smcd_rl.agents.planners import CEM, MPPI, Planner, RandomShooting
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    seed_everything,
    torch_threads,
    training_checkpoint,
    write_csv,
    write_json,
)
from smcd_rl.integrations.gymnasium import AdaptationWrapper, collect_transitions

__all__ = ["AntConfig", "FULL", "PLANNERS", "ADAPTATIONS", "CONDITIONS", "CELLS", "TASKS", "run", "table"]

#: Planner names and their labels in the table and plot.
PLANNERS: dict[str, str] = {"cem": "CEM", "mppi": "MPPI", "rs": "RS"}
#: Adaptation names and their labels.
ADAPTATIONS: dict[str, str] = {"none": "none", "gd": "GD", "smcd": "SMCD"}
#: Conditions: the Ant the model was trained on, and the Ant with one leg crippled per episode.
CONDITIONS: tuple[str, ...] = ("healthy", "crippled")
#: Every (planner, adaptation, condition) cell of Fig. 15.
CELLS: tuple[tuple[str, str, str], ...] = tuple(itertools.product(PLANNERS, ADAPTATIONS, CONDITIONS))

# The Ant's sizes (smcd_rl.envs.crippled_ant imports mujoco, an optional dependency: it is
# imported where it is used, so that `smcd-rl --help` works without it).
_OBS_DIM, _ACTION_DIM = 41, 8
_X = 0  # torso x position in the observation (OBS_SLICES["qpos"].start)
#: Per task: CrippledAntEnv arguments, the planners' reward weights, whether episodes end on a fall.
TASKS: dict[str, tuple[dict[str, Any], dict[str, float], bool]] = {
    "l2a": (
        {
            "ctrl_cost_weight": 0.0,
            "contact_cost_weight": 0.0,
            "healthy_reward": 0.05,
            "terminate_when_unhealthy": False,
        },
        {"ctrl_cost_weight": 0.0, "healthy_reward": 0.05},
        False,
    ),
    "ant-v5": ({}, {}, True),
}


@dataclass
class AntConfig:
    """Settings of ``smcd-rl ant``; the defaults finish in under 20 minutes on 2 CPU cores."""

    out: str = option("runs/ant", "output directory (results, plot, data, trained model)")
    seed: int = option(0, "seed of data, training, planners, filters and evaluation episodes")
    task: str = option("l2a", "reward and episode end: l2a (Learning to Adapt's, the paper's) or ant-v5")
    data_policy: str = option("random", "policy that collects the training data: random or sac")
    sac_steps: int = option(5000, "training steps of the SAC data policy (--data-policy sac)")
    transitions: int = option(100_000, "transitions collected from the healthy Ant (see --validation)")
    data_episode_steps: int = option(200, "steps per data-collection episode")
    hidden: int = option(200, "width of each hidden layer")
    depth: int = option(2, "number of hidden layers")
    dropout: float = option(0.1, "dropout probability p used in training (the paper's 0.5 with --full)")
    epochs: int = option(40, "training epochs")
    batch_size: int = option(256, "training batch size")
    lr: float = option(1e-3, "Adam learning rate")
    validation: float = option(0.1, "fraction of the transitions held out (validation RMSE, SMCD noise)")
    planners: tuple[str, ...] = option(tuple(PLANNERS), "planners to run: cem, mppi, rs")
    adaptations: tuple[str, ...] = option(tuple(ADAPTATIONS), "adaptations to run: none, gd, smcd")
    conditions: tuple[str, ...] = option(CONDITIONS, "conditions to run: healthy, crippled")
    crippled_legs: tuple[int, ...] = option((0, 1, 2, 3), "legs the crippled leg is drawn from per episode")
    episodes: int = option(6, "evaluation episodes per cell")
    episode_steps: int = option(200, "steps per evaluation episode (ant-v5: a fall ends it sooner)")
    horizon: int = option(10, "planning horizon H (steps)")
    candidates: int = option(200, "action sequences per planner iteration (RS: times --iterations, once)")
    elites: int = option(20, "CEM elites per iteration")
    iterations: int = option(3, "CEM and MPPI iterations per step")
    temperature: float = option(1.0, "MPPI temperature (units of the predicted return)")
    mppi_noise: float = option(0.5, "MPPI perturbation std (actions lie in [-1, 1])")
    particles: int = option(100, "SMCD mask particles")
    flip_prob: float = option(0.01, "SMCD bit-flip probability per step")
    noise_scale: float = option(3.0, "SMCD likelihood noise, in units of the held-out RMSE per dimension")
    gd_lr: float = option(0.01, "online gradient-descent learning rate (normalised units)")
    gd_steps: int = option(5, "gradient steps per observation")
    gd_window: int = option(10, "recent transitions in the gradient-descent loss")
    threads: int = option(1, "torch CPU threads (small networks run fastest on one; 0: torch's default)")
    device: str = option("cpu", "torch device of the model and planners")
    full: bool = option(False, "the paper's scale: 3 x 1024 model, 10^6 transitions, 110 episodes of 1000 steps")


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "transitions": 1_000_000,
    "data_episode_steps": 1000,
    "hidden": 1024,
    "depth": 3,
    "dropout": 0.5,
    "epochs": 100,
    "lr": 1e-4,
    "episodes": 110,
    "episode_steps": 1000,
    "horizon": 15,
    "candidates": 500,
    "elites": 50,
    "iterations": 5,
    "particles": 1000,
    "threads": 0,
}


def run(config: AntConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    _check(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(config.device)
    with torch_threads(config.threads):
        return _run(config, out, device, progress=progress)


def _run(config: AntConfig, out: Path, device: torch.device, *, progress: bool) -> dict[str, Any]:
    started_run = time.perf_counter()

    # --- seed, data from the healthy Ant ----------------------------------------------------
    seed_everything(config.seed)
    data_settings = {
        k: getattr(config, k) for k in ("seed", "task", "data_policy", "sac_steps", "transitions", "data_episode_steps")
    }
    data_cache = ResultCache(out / "data.pt", data_settings)
    collected = data_cache.get("transitions")
    if collected is None:
        collected = _collect(config, progress=progress)
        data_cache.put("transitions", collected)
    data: TensorDict = collected["data"]
    n_val = max(1, int(round(config.validation * config.transitions)))
    train, val = data[:-n_val], data[-n_val:]

    # --- one dropout dynamics model for every cell --------------------------------------------
    torch.manual_seed(config.seed)
    net = smcd_rl.MaskedMLP(
        _OBS_DIM + _ACTION_DIM, _OBS_DIM, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=device
    )
    model = smcd_rl.AdaptiveDynamicsModel(net)
    train_settings = {
        **data_settings,
        **{
            k: getattr(config, k)
            for k in ("hidden", "depth", "dropout", "epochs", "batch_size", "lr", "validation", "device")
        },
    }
    started = time.perf_counter()
    losses = smcd_rl.fit_dynamics(
        model,
        train.to(device),
        epochs=config.epochs,
        batch_size=config.batch_size,
        lr=config.lr,
        seed=config.seed,
        checkpoint=training_checkpoint(out, "train", train_settings),
        progress=progress,
    )
    train_seconds = time.perf_counter() - started
    model.save(out / "model.pt")
    val_rmse, val_nmse = _validation_error(model, val.to(device))
    noise_std = (config.noise_scale * val_rmse).clamp_min(1e-4)

    # --- every (planner, adaptation, condition) cell -----------------------------------------
    # A cell's result does not depend on which other cells run: a subset rerun reuses them.
    ignored = ("out", "full", "threads", "planners", "adaptations", "conditions")
    settings = {k: v for k, v in config_dict(config).items() if k not in ignored}
    cache = ResultCache(out / "partial.pt", settings)
    cells = [c for c in CELLS if c[0] in config.planners and c[1] in config.adaptations and c[2] in config.conditions]
    done: dict[tuple[str, str, str], dict[str, Any]] = {}
    bar = tqdm(cells, desc="cells", unit="cell", disable=not progress)
    for cell in bar:
        key = "/".join(cell)
        bar.set_postfix_str(key)
        result = cache.get(key)
        if result is None:
            result = _run_cell(model, cell, config, noise_std, progress=progress)
            cache.put(key, result)
        done[cell] = result

    # --- results ------------------------------------------------------------------------------
    rows, episode_rows = [], []
    for (planner, adaptation, condition), result in done.items():
        returns = torch.tensor([e["return"] for e in result["episodes"]], dtype=torch.float64)
        std = float(returns.std(correction=1)) if len(returns) > 1 else 0.0
        rows.append(
            {
                "planner": PLANNERS[planner],
                "adaptation": ADAPTATIONS[adaptation],
                "condition": condition,
                "return_mean": float(returns.mean()),
                "return_std": std,
                "return_sem": std / math.sqrt(len(returns)),
                "steps_mean": float(np.mean([e["steps"] for e in result["episodes"]])),
                "distance_mean": float(np.mean([e["distance"] for e in result["episodes"]])),
                "episodes": len(returns),
                "seconds": result["seconds"],
            }
        )
        episode_rows += [
            {"planner": PLANNERS[planner], "adaptation": ADAPTATIONS[adaptation], "condition": condition, **e}
            for e in result["episodes"]
        ]
    write_csv(out / "results.csv", rows)
    write_csv(out / "episodes.csv", episode_rows)
    payload = {
        "experiment": "crippled-leg Ant, model-based control with adaptation (paper appendix C, Fig. 15)",
        "config": config_dict(config),
        "machine": machine_info(),
        "data": {
            "policy": config.data_policy,
            "transitions": config.transitions,
            "held_out": n_val,
            "collect_seconds": collected["seconds"],
            "sac_seconds": collected.get("sac_seconds"),
        },
        "training": {
            "loss": losses,
            "seconds": train_seconds,
            "validation_nmse": val_nmse,
            "validation_rmse": val_rmse.tolist(),
            "smcd_noise_std": noise_std.tolist(),
        },
        "wall_seconds": time.perf_counter() - started_run,  # of this invocation (resumed cells excluded)
        "cells_seconds": sum(r["seconds"] for r in rows),
        "results": rows,
    }
    write_json(out / "results.json", payload)
    _plot(rows, config, out / "ant.png")
    print(table(rows))
    print(
        f"\nepisode return (task {config.task}), mean ± std over {config.episodes} episode(s) "
        f"of up to {config.episode_steps} steps"
    )
    print(f"wrote {out}/results.csv, episodes.csv, results.json, ant.png")
    return payload


def table(rows: list[dict[str, Any]]) -> str:
    """Episode return ``mean ± std`` per planner and adaptation (down), per condition (across)."""
    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    lookup = {(r["planner"], r["adaptation"], r["condition"]): r for r in rows}
    pairs = list(dict.fromkeys((r["planner"], r["adaptation"]) for r in rows))
    body = []
    for planner, adaptation in pairs:
        cells = []
        for condition in conditions:
            r = lookup.get((planner, adaptation, condition))
            cells.append("-" if r is None else f"{r['return_mean']:.1f} ± {r['return_std']:.1f}")
        body.append([planner, adaptation, *cells])
    return format_table(body, ["planner", "adaptation", *conditions])


# ------------------------------------------------------------------------------- pieces
def _check(config: AntConfig) -> None:
    for field, allowed in (("planners", PLANNERS), ("adaptations", ADAPTATIONS), ("conditions", CONDITIONS)):
        unknown = set(getattr(config, field)) - set(allowed)
        if unknown:
            raise ValueError(f"unknown {field} {sorted(unknown)}; choose from {list(allowed)}")
    if config.task not in TASKS:
        raise ValueError(f"unknown task {config.task!r}; choose from {list(TASKS)}")
    if config.data_policy not in ("random", "sac"):
        raise ValueError(f"unknown data policy {config.data_policy!r}; choose random or sac")
    bad_legs = set(config.crippled_legs) - {0, 1, 2, 3}
    if bad_legs or not config.crippled_legs:
        raise ValueError(f"crippled legs must be a non-empty subset of 0..3, got {list(config.crippled_legs)}")
    if not 0.0 < config.validation < 1.0:
        raise ValueError(f"validation must be a fraction in (0, 1), got {config.validation}")
    positive = (
        "transitions",
        "data_episode_steps",
        "episodes",
        "episode_steps",
        "horizon",
        "candidates",
        "elites",
        "iterations",
        "particles",
        "gd_steps",
        "gd_window",
        "sac_steps",
    )
    small = [f"{name}={getattr(config, name)}" for name in positive if getattr(config, name) < 1]
    if small:
        raise ValueError(f"these options must be >= 1: {', '.join(small)}")
    if config.elites > config.candidates:
        raise ValueError(f"elites ({config.elites}) must be <= candidates ({config.candidates})")
    if config.transitions * config.validation < 1 or config.transitions * (1 - config.validation) < 2:
        raise ValueError(f"{config.transitions} transitions are too few to hold out {config.validation:.0%}")


def _env(task: str, legs: tuple[int, ...] | None, max_steps: int) -> gymnasium.Env[np.ndarray, np.ndarray]:
    """The task's Ant, crippling a leg drawn from ``legs`` per episode (``None``: healthy)."""
    from smcd_rl.envs.crippled_ant import CrippledAntEnv

    return gymnasium.wrappers.TimeLimit(
        CrippledAntEnv(crippled_legs=legs, **TASKS[task][0]), max_episode_steps=max_steps
    )


def _collect(config: AntConfig, *, progress: bool) -> dict[str, Any]:
    """Transitions from the healthy Ant, one ``collect_transitions`` call per episode-long chunk."""
    env = _env(config.task, None, config.data_episode_steps)
    policy = None
    sac_seconds = None
    if config.data_policy == "sac":
        from stable_baselines3 import SAC  # optional dependency: smcd-rl[sb3]

        started = time.perf_counter()
        policy = SAC("MlpPolicy", env, buffer_size=config.sac_steps, seed=config.seed, device="cpu")
        policy.learn(config.sac_steps, progress_bar=False)
        sac_seconds = time.perf_counter() - started
        env = _env(config.task, None, config.data_episode_steps)  # a fresh env: collection starts from a seeded reset
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
def _validation_error(model: smcd_rl.AdaptiveDynamicsModel, val: TensorDict) -> tuple[torch.Tensor, float]:
    """Per-dimension RMSE (observation units) and the normalised MSE of the trained model on ``val``."""
    model.reset()
    predicted = model(val.select("observation", "action").clone()).get(("next", "observation"))
    error = predicted - val.get(("next", "observation")).to(predicted.dtype)
    rmse = error.square().mean(0).sqrt().cpu()
    nmse = float((error / model.output_norm.std).square().mean())
    return rmse, nmse


def _make_planner(name: str, config: AntConfig, generator: torch.Generator) -> Planner:
    common: dict[str, Any] = {
        "action_low": [-1.0] * _ACTION_DIM,  # Ant's action box
        "action_high": [1.0] * _ACTION_DIM,
        "horizon": config.horizon,
        "device": config.device,
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


def _make_adaptation(name: str, config: AntConfig, noise_std: torch.Tensor) -> smcd_rl.Adaptation:
    if name == "gd":
        return smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window)
    if name == "smcd":
        return smcd_rl.SMCD(
            num_particles=config.particles,
            flip_prob=config.flip_prob,
            noise_std=noise_std.tolist(),
            generator=torch.Generator(device=config.device).manual_seed(config.seed + 11),
        )
    return smcd_rl.NoAdaptation()


def _run_cell(
    model: smcd_rl.AdaptiveDynamicsModel,
    cell: tuple[str, str, str],
    config: AntConfig,
    noise_std: torch.Tensor,
    *,
    progress: bool,
) -> dict[str, Any]:
    """Episodes of one (planner, adaptation, condition) cell; returns their records and wall time."""
    from smcd_rl.envs.crippled_ant import ant_reward, ant_termination

    planner_name, adaptation_name, condition = cell
    started = time.perf_counter()
    adapted = model.with_adaptation(_make_adaptation(adaptation_name, config, noise_std))
    assert isinstance(adapted, smcd_rl.AdaptiveDynamicsModel)
    legs = config.crippled_legs if condition == "crippled" else None
    env = AdaptationWrapper(_env(config.task, legs, config.episode_steps), adapted)
    # The same planner seed in every adaptation and condition: cells differ by what they vary only.
    generator = torch.Generator(device=config.device).manual_seed(
        config.seed + 1000 * (1 + list(PLANNERS).index(planner_name))
    )
    _, weights, terminates = TASKS[config.task]
    agent = MPCAgent(
        adapted,
        _make_planner(planner_name, config, generator),
        functools.partial(ant_reward, **weights),
        ant_termination if terminates else None,
    )
    episodes = []
    bar = tqdm(
        total=config.episodes * config.episode_steps,
        desc="/".join(cell),
        unit="step",
        leave=False,
        disable=not progress,
    )
    for k in range(config.episodes):
        episode_seed = config.seed + 1_000_003 + k  # the same episodes (start state, leg) in every cell
        episode_started = time.perf_counter()
        obs, info = env.reset(seed=episode_seed)
        agent.reset()
        x0, total, steps, terminated, truncated = float(obs[_X]), 0.0, 0, False, False
        while not (terminated or truncated):
            obs, reward, terminated, truncated, info = env.step(agent.act(obs))
            total += float(reward)
            steps += 1
            bar.update(1)
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
    return {"episodes": episodes, "seconds": time.perf_counter() - started}


def _plot(rows: list[dict[str, Any]], config: AntConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conditions = list(dict.fromkeys(r["condition"] for r in rows))
    adaptations = list(dict.fromkeys(r["adaptation"] for r in rows))
    planners = list(dict.fromkeys(r["planner"] for r in rows))
    lookup = {(r["planner"], r["adaptation"], r["condition"]): r for r in rows}
    width = 0.8 / len(planners)
    fig, axes = plt.subplots(1, len(conditions), figsize=(4.2 * len(conditions), 3.6), sharey=True, squeeze=False)
    for ax, condition in zip(axes[0], conditions, strict=True):
        for i, planner in enumerate(planners):
            sel = [lookup.get((planner, a, condition)) for a in adaptations]
            xs = [j + (i - (len(planners) - 1) / 2) * width for j in range(len(adaptations))]
            ax.bar(
                xs,
                [r["return_mean"] if r else float("nan") for r in sel],
                width,
                yerr=[r["return_std"] if r else 0.0 for r in sel],
                capsize=3,
                label=planner,
            )
        ax.set_xticks(range(len(adaptations)), adaptations)
        ax.set_title("all legs functional" if condition == "healthy" else "one leg crippled")
        ax.set_xlabel("adaptation")
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("episode return")
    axes[0][-1].legend(title="planner")
    fig.suptitle(f"Ant MPC ({config.episodes} episodes of up to {config.episode_steps} steps, ± 1 std)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
