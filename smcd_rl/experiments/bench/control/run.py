"""Control-loop speed of Panda reaching: ``smcd-rl bench control``.

Reads top to bottom: seed, build the forward-kinematics network ``q (7) -> x (3)`` (default the
paper's ``MaskedMLP(7 -> 1024 -> 1024 -> 1024 -> 3)``, dropout 0.5, masks on every hidden layer)
or load a trained one (``--model``, e.g. ``runs/panda/model.pt``), then time, interleaved step
by step in one run so that all see the same machine load, one control step of the reaching loop
of ``smcd-rl panda`` with a measurement every step:

* ``M+S``: SMCD with ``--particles`` masks (default 1000): observe ``(q, measured x)``, the
  Jacobian of the adapted network, the PD law, the joint update;
* ``M+G``: the same with online gradient descent as the strategy;
* ``M+N``: the network with no adaptation (Jacobian, PD and update only: what the network
  costs without any adaptation);
* ``analytic``: the same loop on the analytic chain :func:`~smcd_rl.envs.panda_reach.panda_fk`
  (Jacobian, PD and update; nothing to adapt).

Each contender drives its own ``--batch`` arms from the ready pose towards random goals with
:class:`~smcd_rl.agents.pd.JacobianPD`. With random weights the "true" end effector is the network
itself under a hidden mask (as in ``smcd-rl bench filter``), so SMCD's posterior concentrates as
it does on a real task; with ``--model`` it is the Panda with a random tool. Reports control steps
per second (from the mean step time), the median step time and the ratios between contenders.
Writes ``results.json`` and ``results.csv``; ``--json`` prints the JSON instead of the table.
Timings are never asserted by the tests.

One thread by default: the Jacobian's backward passes multiply a few rows by each weight matrix
(``[3, 1024] @ [1024, 1024]``), and on the 2-core reference machine torch spreads such a product
over both threads at a great loss (16 ms on 2 threads against 0.15 ms on one), which made every
network loop 10-30 times slower. ``--threads 2`` shows it.

Example:
    >>> from smcd_rl.experiments.bench.control.run import BenchControlConfig
    >>> config = BenchControlConfig()
    >>> config.hidden, config.particles, config.batch
    ((1024, 1024, 1024), 1000, 1)
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor

import smcd_rl
from smcd_rl.agents.pd import JacobianPD
from smcd_rl.envs.panda_reach import (
    DEFAULT_DT,
    READY_POSE,
    integrate_panda,
    panda_fk,
    panda_kinematics_data,
    sample_goals,
    sample_tool_lengths,
)
from smcd_rl.experiments.bench.control.config import FULL, BenchControlConfig
from smcd_rl.experiments.bench.tools import machine_line, publish, scale_to_unit_spread
from smcd_rl.experiments.shared.adaptations import make_adaptation
from smcd_rl.experiments.shared.config import config_dict
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import format_table
from smcd_rl.experiments.shared.runtime import interleaved_times, machine_info

__all__ = ["BenchControlConfig", "CONTENDERS", "FULL", "run"]

#: The timed loops, in table order.
CONTENDERS = ("M+S", "M+G", "M+N", "analytic")


def run(config: BenchControlConfig, *, progress: bool = True) -> dict[str, Any]:
    """Time the control loops, print the table and ratios (or JSON), write the files; returns the payload."""
    with Experiment(config, progress=progress) as ex:
        # --- seed, the network and the world it is timed on -------------------------------------
        device, generator = ex.device, ex.generator
        tools = sample_tool_lengths(config.batch, generator=generator)
        goals = sample_goals(tools, generator=generator).to(device)
        tools = tools.to(device)
        model, world = _model_and_world(config, tools, generator, device)

        # --- the contenders: one control step each, every one with its own arms ------------------
        contenders: dict[str, Callable[[], None]] = {}
        for name in CONTENDERS:
            if name == "analytic":
                contenders[name] = _control_step(
                    lambda q: panda_fk(q, tools), None, lambda q: panda_fk(q, tools), goals
                )
            else:
                adapted = model.with_adaptation(_strategy(name, config, device))
                adapted.reset(batch_shape=(config.batch,))
                contenders[name] = _control_step(adapted.predict, None if name == "M+N" else adapted, world, goals)
        # One stage: the contenders are timed interleaved, step by step, so the loop cannot be split.
        ex.plan({"time": 1.0})
        with ex.stage("time"):
            times = interleaved_times(
                contenders, config.steps, warmup=config.warmup, device=device, desc="bench control", progress=progress
            )

        # --- results ----------------------------------------------------------------------------
        rows = [_timing_row(name, samples) for name, samples in times.items()]
        rate = {row["loop"]: row["steps_per_s"] for row in rows}
        ratios = {
            "analytic_over_smcd": rate["analytic"] / rate["M+S"],
            "smcd_over_gd": rate["M+S"] / rate["M+G"],
            "no_adaptation_over_smcd": rate["M+N"] / rate["M+S"],
            "analytic_over_gd": rate["analytic"] / rate["M+G"],
        }
        net = model.net
        payload = {
            "benchmark": "Panda reaching control steps per second: observe + Jacobian + PD + joint update, batch of arms",
            "config": config_dict(config),
            "device": str(device),
            "machine": machine_info(),
            "network": {
                "in": net.in_features,
                "hidden": list(net.hidden),
                "out": net.out_features,
                "mask_dim": net.mask_dim,
                "trained": bool(config.model),
            },
            "results": rows,
            "ratios": ratios,
        }
        publish(ex.out, payload, rows, _report(payload), as_json=config.json)
    return payload


def _strategy(name: str, config: BenchControlConfig, device: torch.device) -> smcd_rl.Adaptation:
    return make_adaptation(
        name[2], config, particles=config.particles, noise_std=config.noise_std, seed=config.seed + 1, device=device
    )


def _timing_row(name: str, samples: list[float]) -> dict[str, Any]:
    mean = statistics.fmean(samples)
    return {
        "loop": name,
        "steps_per_s": 1.0 / mean,
        "mean_ms": mean * 1e3,
        "median_ms": statistics.median(samples) * 1e3,
        "min_ms": min(samples) * 1e3,
        "steps": len(samples),
    }


def _model_and_world(
    config: BenchControlConfig, tools: Tensor, generator: torch.Generator, device: torch.device
) -> tuple[smcd_rl.AdaptiveModel, Callable[[Tensor], Tensor]]:
    """The timed model, and the world's end effector ``q -> x`` that the measurements come from."""
    if config.model:
        model = smcd_rl.load(config.model).to(device)
        if model.net.in_features != 7 or model.net.out_features != 3:
            raise ValueError(
                f"--model must map 7 joint angles to a 3-d position, got {model.net.in_features} -> "
                f"{model.net.out_features}"
            )
        return model, lambda q: panda_fk(q, tools)
    net = smcd_rl.MaskedMLP(7, 3, hidden=config.hidden, dropout=config.dropout, device=device).eval()
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    # Zero epochs only fit the normalisers: inputs in radians, outputs in metres as for a trained model.
    smcd_rl.fit(model, panda_kinematics_data(4096, generator=generator).to(device), epochs=0, progress=False)
    scale_to_unit_spread(net, generator)
    model.fitted = True  # random weights on purpose: the benchmark times the loop, not the predictions
    true_mask = (torch.rand(config.batch, net.mask_dim, generator=generator) < net.keep_prob).to(device)

    def world(q: Tensor) -> Tensor:
        return model.predict(q, mask=true_mask)

    model.reset()
    return model, world


def _control_step(
    kinematics: Callable[[Tensor], Tensor],
    model: smcd_rl.AdaptiveModel | None,
    world: Callable[[Tensor], Tensor],
    goals: Tensor,
) -> Callable[[], None]:
    """One step of the reaching loop with a measurement: [observe] + Jacobian + PD + joint update."""
    pd = JacobianPD(kinematics, k1=20.0, k2=5.0)
    q = torch.tensor(READY_POSE, device=goals.device, dtype=goals.dtype).expand(goals.shape[0], -1).clone()
    state = {"q": q, "q_dot": torch.zeros_like(q)}

    def step() -> None:
        q, q_dot = state["q"], state["q_dot"]
        measured = world(q)
        if model is not None:
            model.observe(TensorDict({"q": q, "ee": measured}, [q.shape[0]]))
        u = pd(q, q_dot, goals, measured)
        state["q"], state["q_dot"] = integrate_panda(q, q_dot, u, DEFAULT_DT)

    return step


def _report(payload: dict[str, Any]) -> str:
    config, ratios, net = payload["config"], payload["ratios"], payload["network"]
    lines = [machine_line(payload)]
    lines.append(
        f"network: MaskedMLP {net['in']} -> {' -> '.join(map(str, net['hidden']))} -> {net['out']} "
        f"({'trained' if net['trained'] else 'random weights'}), {net['mask_dim']} mask bits; {config['batch']} arm(s) "
        f"per contender; SMCD N={config['particles']}; gradient descent {config['gd_steps']} steps on the last "
        f"{config['gd_window']}; a measurement every step"
    )
    lines.append("")
    body = [
        [r["loop"], f"{r['steps_per_s']:.1f}", r["mean_ms"], r["median_ms"], r["min_ms"], r["steps"]]
        for r in payload["results"]
    ]
    lines.append(format_table(body, ["control loop", "steps/s", "mean ms", "median ms", "min ms", "steps"]))
    lines.append("")
    lines.append(f"analytic / M+S = {ratios['analytic_over_smcd']:.1f}x the steps per second")
    lines.append(f"M+S / M+G      = {ratios['smcd_over_gd']:.2f}x the steps per second (> 1: SMCD's loop is faster)")
    lines.append(
        f"M+N / M+S      = {ratios['no_adaptation_over_smcd']:.2f}x (the network without adaptation against SMCD)"
    )
    return "\n".join(lines)
