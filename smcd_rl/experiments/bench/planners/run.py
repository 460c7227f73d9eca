"""Planner speed: our CEM against torchrl's ``CEMPlanner`` on the same model: ``smcd-rl bench planners``.

Reads top to bottom: seed, build one Ant-sized adaptive dynamics model (default
``MaskedMLP(27 + 8 -> 256 -> 256 -> 27)``, the Ant-v5 sizes of the reference setting), then time,
interleaved in one run so that all see the same machine load:

* ``torchrl``: ``torchrl.modules.CEMPlanner`` on an
  :class:`~smcd_rl.integrations.torchrl.AdaptiveWorldModelEnv` over the model;
* ``ours``: :class:`smcd_rl.agents.planners.CEM` on
  :func:`smcd_rl.agents.mpc.model_reward_objective` over the same model (what
  :class:`~smcd_rl.agents.mpc.MPCAgent` runs);
* ``ours, plain objective``: the same CEM on a hand-written objective that rolls the network
  forward with no TensorDicts and no input checks, to show what the checks and plumbing cost;
* ``floor``: the bare network forwards that any CEM of this size must do, ``horizon x steps``
  forwards of ``candidates`` inputs through the model's adapted network, and nothing else.

All planners use the same horizon, candidates, elites (``top_k``) and iterations, and the same
pure reward (the first observation, a stand-in for forward velocity, minus a control cost).
Reports medians over the repeats (with min and quartiles) and the ratios ``torchrl / ours`` and
``ours / floor`` against the goal of issue 3: ours at least 2x faster than torchrl's and within
1.3x of the floor. Writes ``results.json`` and ``results.csv``; ``--json`` prints the JSON
instead of the table, for tools. Timings are never asserted by the tests.

Example:
    >>> from smcd_rl.experiments.bench.planners.run import BenchPlannersConfig
    >>> config = BenchPlannersConfig()
    >>> config.horizon, config.candidates, config.top_k, config.steps, config.hidden
    (15, 500, 50, 5, (256, 256))
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

import smcd_rl
from smcd_rl.agents.mpc import model_reward_objective
from smcd_rl.agents.planners import CEM
from smcd_rl.experiments.bench.planners.config import FULL, BenchPlannersConfig
from smcd_rl.experiments.bench.tools import machine_line, publish
from smcd_rl.experiments.shared.config import config_dict
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table
from smcd_rl.experiments.shared.runtime import interleaved_times, machine_info

__all__ = ["BenchPlannersConfig", "FULL", "GOAL_SPEEDUP", "GOAL_FLOOR", "run", "bench_reward"]

#: Goal of issue 3: ours at least this many times faster than torchrl's CEMPlanner ...
GOAL_SPEEDUP = 2.0
#: ... and at most this many times the bare model-forward floor.
GOAL_FLOOR = 1.3


def bench_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    """The benchmark's pure batched reward: ``next_obs[..., 0] - 0.1 * |action|^2``.

    Example:
        >>> import torch
        >>> bench_reward(torch.zeros(2, 3), torch.ones(2, 1), torch.ones(2, 3))
        tensor([0.9000, 0.9000])
    """
    return next_obs[..., 0] - 0.1 * action.square().sum(-1)


def run(config: BenchPlannersConfig, *, progress: bool = True) -> dict[str, Any]:
    """Time the planners, print the table and ratios (or JSON), write the files; returns the payload."""
    with Experiment(config, progress=progress) as ex:
        # --- seed and the shared model --------------------------------------------------------
        device, generator = ex.device, ex.generator
        obs_dim, action_dim = config.observation, config.action
        net = smcd_rl.MaskedMLP(obs_dim + action_dim, obs_dim, hidden=config.hidden, device=device)
        adaptation: smcd_rl.Adaptation = (
            smcd_rl.SMCD(
                num_particles=config.particles, generator=torch.Generator(device=device).manual_seed(config.seed)
            )
            if config.adaptation == "smcd"
            else smcd_rl.NoAdaptation()
        )
        model = smcd_rl.AdaptiveDynamicsModel(net, adaptation)
        model.fitted = True  # random weights on purpose: the benchmark times forwards, not predictions
        model.reset()
        obs = torch.randn(obs_dim, generator=generator).to(device)

        # --- the contenders, timed side by side ------------------------------------------------
        contenders = _contenders(model, obs, config, device, generator)
        # One stage: the contenders are timed interleaved, step by step, so the loop cannot be split.
        ex.plan({"time": 1.0})
        with ex.stage("time"):
            times = interleaved_times(
                contenders,
                config.repeats,
                warmup=config.warmup,
                device=device,
                desc="bench planners",
                progress=progress,
            )

        # --- results ------------------------------------------------------------------------------
        rows = [_timing_row(name, samples) for name, samples in times.items()]
        median = {row["planner"]: row["median_ms"] for row in rows}
        torchrl_ms, ours_ms = median["torchrl CEMPlanner"], median["ours: CEM + model_reward_objective"]
        plain_ms, floor_ms = median["ours: CEM + plain objective"], median["floor: bare forwards"]
        ratios = {
            "torchrl_over_ours": torchrl_ms / ours_ms,
            "ours_over_floor": ours_ms / floor_ms,
            "torchrl_over_floor": torchrl_ms / floor_ms,
            "torchrl_over_plain": torchrl_ms / plain_ms,
            "plain_over_floor": plain_ms / floor_ms,
        }
        goals = {
            "ours_at_least_2x_faster_than_torchrl": ratios["torchrl_over_ours"] >= GOAL_SPEEDUP,
            "ours_within_1.3x_of_floor": ratios["ours_over_floor"] <= GOAL_FLOOR,
            # No planner that does the floor's forwards can beat torchrl by more than torchrl / floor.
            "speedup_goal_reachable": ratios["torchrl_over_floor"] >= GOAL_SPEEDUP,
        }
        payload = {
            "benchmark": "CEM planning on one adaptive dynamics model: ours vs torchrl's CEMPlanner vs bare forwards",
            "config": config_dict(config),
            "device": str(device),
            "machine": machine_info(),
            "model": {
                "in": obs_dim + action_dim,
                "hidden": list(config.hidden),
                "out": obs_dim,
                "adaptation": config.adaptation,
                "forwards_per_plan": config.horizon * config.steps,
            },
            "results": rows,
            "ratios": ratios,
            "goals": goals,
        }
        publish(ex.out, payload, rows, _report(payload), as_json=config.json)
    return payload


def _contenders(
    model: smcd_rl.AdaptiveDynamicsModel,
    obs: Tensor,
    config: BenchPlannersConfig,
    device: torch.device,
    generator: torch.Generator,
) -> dict[str, Callable[[], None]]:
    """One plan of each planner from ``obs`` on ``model``, and the bare forwards they all must do."""
    from torchrl.modules import CEMPlanner

    from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv

    world = AdaptiveWorldModelEnv(model, bench_reward, action_low=-1.0, action_high=1.0, device=device)
    torchrl_cem = CEMPlanner(
        world,
        planning_horizon=config.horizon,
        optim_steps=config.steps,
        num_candidates=config.candidates,
        top_k=config.top_k,
    )
    start = world.reset()
    start.set(model.in_keys[0], obs.clone())
    ours = CEM(
        action_low=[-1.0] * config.action,
        action_high=[1.0] * config.action,
        horizon=config.horizon,
        num_candidates=config.candidates,
        num_elites=config.top_k,
        iterations=config.steps,
        warm_start=False,  # torchrl's planner has none; both start every plan from scratch
        device=device,
        generator=torch.Generator(device=device).manual_seed(config.seed + 1),
    )
    objective = model_reward_objective(model, obs, bench_reward)
    plain = _plain_objective(model, obs)
    floor_input = torch.randn(config.candidates, config.observation + config.action, generator=generator).to(device)

    def run_torchrl() -> None:
        torchrl_cem(start.clone())

    def run_ours() -> None:
        ours.plan(objective)

    def run_plain() -> None:
        ours.plan(plain)

    def run_floor() -> None:
        for _ in range(config.horizon * config.steps):
            model.adaptation.predict(floor_input)

    return {
        "torchrl CEMPlanner": run_torchrl,
        "ours: CEM + model_reward_objective": run_ours,
        "ours: CEM + plain objective": run_plain,
        "floor: bare forwards": run_floor,
    }


def _timing_row(name: str, samples: list[float]) -> dict[str, Any]:
    quartiles = statistics.quantiles(samples, n=4) if len(samples) > 1 else [samples[0]] * 3
    return {
        "planner": name,
        "median_ms": statistics.median(samples) * 1e3,
        "min_ms": min(samples) * 1e3,
        "q25_ms": quartiles[0] * 1e3,
        "q75_ms": quartiles[2] * 1e3,
        "repeats": len(samples),
    }


def _plain_objective(model: smcd_rl.AdaptiveDynamicsModel, obs: Tensor) -> Callable[[Tensor], Tensor]:
    """Predicted return of ``[P, H, A]`` actions, rolling the network with no TensorDicts or checks."""
    in_norm, out_norm, predict = model.input_norm, model.output_norm, model.adaptation.predict

    def objective(actions: Tensor) -> Tensor:
        state = obs.expand(actions.shape[0], obs.shape[-1])
        total = torch.zeros(actions.shape[0], device=actions.device, dtype=actions.dtype)
        for t in range(actions.shape[-2]):
            action = actions[:, t]
            next_state = state + out_norm.inverse(predict(in_norm(torch.cat([state, action], -1))))
            total = total + bench_reward(state, action, next_state)
            state = next_state
        return total

    return objective


def _report(payload: dict[str, Any]) -> str:
    config, ratios, goals = payload["config"], payload["ratios"], payload["goals"]
    lines = [machine_line(payload)]
    model = payload["model"]
    lines.append(
        f"model: MaskedMLP {model['in']} -> {' -> '.join(map(str, model['hidden']))} -> {model['out']}, "
        f"adaptation {model['adaptation']}; CEM horizon {config['horizon']}, {config['candidates']} candidates, "
        f"top {config['top_k']}, {config['steps']} steps = {model['forwards_per_plan']} forwards per plan"
    )
    lines.append("")
    body = [
        [r["planner"], r["median_ms"], r["min_ms"], r["q25_ms"], r["q75_ms"], r["repeats"]] for r in payload["results"]
    ]
    lines.append(format_table(body, ["planner (one plan)", "median ms", "min ms", "q25 ms", "q75 ms", "repeats"]))
    lines.append("")
    lines.append(
        f"torchrl / ours = {ratios['torchrl_over_ours']:.2f}x (goal >= {GOAL_SPEEDUP}x: "
        f"{'met' if goals['ours_at_least_2x_faster_than_torchrl'] else 'NOT met'})"
    )
    lines.append(
        f"ours / floor   = {ratios['ours_over_floor']:.2f}x (goal <= {GOAL_FLOOR}x: "
        f"{'met' if goals['ours_within_1.3x_of_floor'] else 'NOT met'})"
    )
    lines.append(
        f"plain objective: torchrl / plain = {ratios['torchrl_over_plain']:.2f}x, "
        f"plain / floor = {ratios['plain_over_floor']:.2f}x; torchrl / floor = {ratios['torchrl_over_floor']:.2f}x"
    )
    if ratios["torchrl_over_floor"] < GOAL_SPEEDUP:
        lines.append(
            f"the {GOAL_SPEEDUP}x goal cannot be met here: torchrl's planner takes only "
            f"{ratios['torchrl_over_floor']:.2f}x the bare forwards, which every planner of this size must do"
        )
    return "\n".join(lines)
