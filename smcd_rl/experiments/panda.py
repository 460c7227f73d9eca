"""7-DOF Panda reaching with an unknown tool and sparse measurements (paper sec. 4.2, Fig. 3): ``smcd-rl panda``.

Reads top to bottom: seed, sample joint configurations with random tools, train one dropout
forward-kinematics network ``q (7) -> x (3)``, then for every method, measurement interval ``n``
and seed drive ``tasks`` arms at once from the ready pose towards random feasible goals with
:class:`~smcd_rl.agents.pd.JacobianPD` through the method's kinematics, and count the arms whose
true end effector gets within 5 cm of the goal within ``steps`` control steps.

Methods (Fig. 3): ``FK``, the analytic chain that does not know the tool (assumes ``l = 0``);
``M+N``, ``M+G``, ``M+S``, the trained network with no adaptation, online gradient descent and
SMCD (once per particle count in ``--particles``). At every n-th step (0, n, 2n, ...) the true
end effector is measured: the adaptive model observes ``(q, measured x)`` and the controller
corrects the measured error. In between, nothing is observed and the controller corrects the
error of its own kinematics' prediction (model-reference control). ``FK`` at ``n = 1`` is the
reference line of Fig. 3.

Writes ``results.csv`` (success rate, mean and std over seeds, per method and n),
``trials.csv`` (every arm: reached, steps, final distance, tool), ``results.json`` (settings,
table, training loss, held-out error, timings, machine) and ``panda.png`` (success rate against
n). Finished (method, n, seed) runs are kept in ``partial.pt`` and skipped by a rerun.

Choices the paper leaves open, made here:

* Control: ``u`` is a joint acceleration (``q_dot += dt u; q += dt q_dot``, dt = 0.05 s) with the
  Panda's acceleration, velocity and position limits, and the gains of the paper's two-link
  controller (K1 = 20, K2 = 5). With the true kinematics this reaches every one of 300 random
  goals, median 23 steps (``tests/envs/test_panda_reach.py`` checks >= 95 % of 50).
* Seeds: one trained network; each seed draws its own ``tasks`` tools and goals (the same for
  every method and n, so the methods are compared on identical tasks) and its own filter noise.
* Measurements are exact unless ``--measurement-noise`` is set; SMCD's likelihood noise
  (``--noise-std``) then stands for the network's own error.
* Adaptation settings were picked on 100 separate tuning tasks (not among the evaluated ones),
  at n = 5 and 20 with the default network, over small grids for both adaptive methods: SMCD
  noise {0.02, 0.05} m x flip probability {0.01, 0.05, 0.1} (best 0.02, 0.05), gradient descent
  learning rate {0.01, 0.1, 1} (best 0.1; 1 diverges).

Example:
    >>> from smcd_rl.experiments.panda import PandaConfig, method_labels
    >>> config = PandaConfig()
    >>> method_labels(config)
    ['FK', 'M+N', 'M+G', 'M+S (N=100)', 'M+S (N=300)']
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.pd import JacobianPD
from smcd_rl.envs.panda_reach import (
    DEFAULT_DT,
    GOAL_TOLERANCE,
    MAX_EPISODE_STEPS,
    READY_POSE,
    TOOL_RANGE,
    integrate_panda,
    panda_fk,
    panda_kinematics_data,
    sample_goals,
    sample_tool_lengths,
)
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    resolve_device,
    seed_everything,
    torch_threads,
    training_checkpoint,
    write_csv,
    write_json,
)

__all__ = ["PandaConfig", "FULL", "METHODS", "method_labels", "reach", "run", "table"]

#: Method families of Fig. 3 that this command runs.
METHODS = ("FK", "M+N", "M+G", "M+S")


@dataclass
class PandaConfig:
    """Settings of ``smcd-rl panda``; the defaults finish in minutes on 2 CPU cores."""

    out: str = option("runs/panda", "output directory (results, plot, trained model)")
    seed: int = option(0, "seed of data, training, tasks and filters")
    samples: int = option(50_000, "training samples (joint angles, end effector) with random tools")
    hidden: int = option(256, "width of each hidden layer")
    depth: int = option(3, "number of hidden layers")
    dropout: float = option(0.5, "dropout probability p used in training")
    epochs: int = option(30, "training epochs")
    batch_size: int = option(256, "training batch size")
    lr: float = option(1e-3, "Adam learning rate")
    tasks: int = option(50, "reaching tasks per seed (all run at once as one batch)")
    seeds: int = option(3, "seeds (each draws its own tasks)")
    intervals: tuple[int, ...] = option((1, 2, 5, 10, 20), "measurement intervals n: a measurement every n-th step")
    steps: int = option(MAX_EPISODE_STEPS, "control steps per task: success is reaching the goal within them")
    methods: tuple[str, ...] = option(METHODS, "methods to run: FK, M+N, M+G, M+S")
    particles: tuple[int, ...] = option((100, 300), "SMCD particle counts (one M+S line each)")
    flip_prob: float = option(0.05, "SMCD bit-flip probability per step")
    noise_std: float = option(0.02, "SMCD likelihood noise std (m)")
    gd_lr: float = option(0.1, "online gradient-descent learning rate (normalised units)")
    gd_steps: int = option(5, "gradient steps per observation")
    gd_window: int = option(10, "recent transitions in the gradient-descent loss")
    k1: float = option(20.0, "PD gain on the end-effector error")
    k2: float = option(5.0, "PD gain on the joint velocity")
    dt: float = option(DEFAULT_DT, "control period (s)")
    tolerance: float = option(GOAL_TOLERANCE, "success distance (m)")
    tool_range: float = option(TOOL_RANGE, "tools are drawn from U(-tool_range, tool_range) (m)")
    measurement_noise: float = option(0.0, "std of the end-effector measurement noise (m)")
    threads: int = option(1, "torch CPU threads (0: torch's default)")
    device: str = option("cpu", "torch device: cpu, cuda, cuda:1, auto")
    full: bool = option(False, "the paper's scale: 3 x 1024 network, 100000 samples, 100 tasks x 5 seeds")


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "samples": 100_000,
    "hidden": 1024,
    "epochs": 100,
    "batch_size": 64,
    "lr": 1e-4,
    "tasks": 100,
    "seeds": 5,
    "particles": (100, 1000),
    "threads": 0,
}


def method_labels(config: PandaConfig) -> list[str]:
    """The table's method rows: one per method, and one M+S row per particle count."""
    labels = []
    for name in config.methods:
        if name == "M+S":
            labels += [f"M+S (N={n})" for n in config.particles]
        else:
            labels.append(name)
    return labels


def run(config: PandaConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    _check(config)
    with torch_threads(config.threads):
        return _run(config, progress=progress)


def _check(config: PandaConfig) -> None:
    unknown = set(config.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")
    if not config.methods:
        raise ValueError(f"no methods given; choose from {list(METHODS)}")
    if not config.intervals or min(config.intervals) < 1:
        raise ValueError(f"measurement intervals must be >= 1 (1: every step), got {list(config.intervals)}")
    if "M+S" in config.methods and (not config.particles or min(config.particles) < 1):
        raise ValueError(f"M+S needs particle counts >= 1, got {list(config.particles)}")
    counts = {
        k: getattr(config, k) for k in ("samples", "hidden", "depth", "epochs", "batch_size", "tasks", "seeds", "steps")
    }
    small = [f"{k}={v}" for k, v in counts.items() if v < 1]
    if small:
        raise ValueError(f"sizes and counts must be >= 1: {', '.join(small)}")
    if config.noise_std <= 0 or config.tolerance <= 0 or config.dt <= 0:
        raise ValueError(
            f"need noise_std, tolerance and dt > 0, got {config.noise_std}, {config.tolerance}, {config.dt}"
        )
    resolve_device(config.device)


def _run(config: PandaConfig, *, progress: bool) -> dict[str, Any]:
    started_run = time.perf_counter()
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(resolve_device(config.device))

    # --- seed, data, model --------------------------------------------------------------------
    generator = seed_everything(config.seed)
    data = panda_kinematics_data(config.samples, tool_range=config.tool_range, generator=generator)
    held_out = panda_kinematics_data(2000, tool_range=config.tool_range, generator=generator)
    net = smcd_rl.MaskedMLP(7, 3, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=device)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    train_keys = ("seed", "samples", "hidden", "depth", "dropout", "epochs", "batch_size", "lr", "tool_range", "device")
    started = time.perf_counter()
    losses = smcd_rl.fit(
        model,
        data.to(device),
        epochs=config.epochs,
        batch_size=config.batch_size,
        lr=config.lr,
        seed=config.seed,
        checkpoint=training_checkpoint(out, "train", {k: getattr(config, k) for k in train_keys}),
        progress=progress,
    )
    train_seconds = time.perf_counter() - started
    model.save(out / "model.pt")
    held_out_rmse = _held_out_rmse(model, held_out.to(device))

    # --- every (method, n, seed) run ----------------------------------------------------------
    # FK with a measurement every step is the reference line of Fig. 3, so it always runs.
    intervals = sorted(set(config.intervals) | ({1} if "FK" in config.methods else set()))
    labels = method_labels(config)
    ignored = ("out", "full", "threads", "methods", "particles", "intervals")
    cache = ResultCache(out / "partial.pt", {k: v for k, v in config_dict(config).items() if k not in ignored})
    runs = [
        (label, n, s)
        for label in labels
        for n in (intervals if label == "FK" else sorted(config.intervals))
        for s in range(config.seeds)
    ]
    results: dict[tuple[str, int, int], dict[str, Any]] = {}
    bar = tqdm(runs, desc="panda", unit="run", disable=not progress)
    for label, n, s in bar:
        key = f"{label}|n={n}|seed={s}"
        bar.set_postfix_str(key)
        result = cache.get(key)
        if result is None:
            tools, goals = _tasks(config, s, device)
            kinematics, observe = _method(label, model, tools, config, s, device)
            started = time.perf_counter()
            # Measurement noise (if any) from the seed alone: every method and n sees the same draws.
            noise = torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + 104_729 * (s + 1))
            outcome = reach(kinematics, observe, tools, goals, interval=n, config=config, generator=noise)
            result = {
                **{k: v.cpu() for k, v in outcome.items()},
                "tools": tools.cpu(),
                "seconds": time.perf_counter() - started,
            }
            cache.put(key, result)
        results[(label, n, s)] = result

    # --- results ------------------------------------------------------------------------------
    rows, trial_rows = [], []
    for label in labels:
        for n in intervals if label == "FK" else sorted(config.intervals):
            per_seed = [results[(label, n, s)] for s in range(config.seeds)]
            rates = torch.tensor([float(r["reached"].float().mean()) for r in per_seed], dtype=torch.float64)
            reached = torch.cat([r["reached"] for r in per_seed])
            steps_taken = torch.cat([r["steps"] for r in per_seed]).double()
            rows.append(
                {
                    "method": label,
                    "interval": n,
                    "success_mean": float(rates.mean()),
                    "success_std": float(rates.std(correction=1)) if len(rates) > 1 else 0.0,
                    "steps_mean": float(steps_taken[reached].mean()) if bool(reached.any()) else None,
                    "final_distance_median": float(torch.cat([r["final_distance"] for r in per_seed]).median()),
                    "seeds": len(rates),
                    "tasks": config.tasks,
                    "seconds": sum(r["seconds"] for r in per_seed),
                }
            )
            for s, r in enumerate(per_seed):
                trial_rows += [
                    {
                        "method": label,
                        "interval": n,
                        "seed": s,
                        "task": k,
                        "reached": bool(r["reached"][k]),
                        "steps": int(r["steps"][k]),
                        "final_distance": float(r["final_distance"][k]),
                        "tool_length": float(r["tools"][k]),
                    }
                    for k in range(config.tasks)
                ]
    write_csv(out / "results.csv", rows)
    write_csv(out / "trials.csv", trial_rows)
    payload = {
        "experiment": "7-DOF Panda reaching with an unknown tool and sparse measurements (paper Fig. 3)",
        "config": config_dict(config),
        "machine": machine_info(),
        "train_loss": losses,
        "train_seconds": train_seconds,
        "held_out_rmse_m": held_out_rmse,
        "method_seconds": {label: sum(r["seconds"] for k, r in results.items() if k[0] == label) for label in labels},
        "total_seconds": time.perf_counter() - started_run,
        "results": rows,
    }
    write_json(out / "results.json", payload)
    _plot(rows, config, out / "panda.png")
    print(table(rows, config))
    print(
        f"\nnetwork held-out RMSE (mean mask): {held_out_rmse:.3f} m; wrote {out}/results.csv, trials.csv, "
        "results.json, panda.png"
    )
    return payload


def table(rows: list[dict[str, Any]], config: PandaConfig) -> str:
    """Success rate (mean +- std over seeds), method down and measurement interval n across."""
    intervals = sorted(set(config.intervals))
    lookup = {(r["method"], r["interval"]): r for r in rows}
    body = []
    for label in dict.fromkeys(r["method"] for r in rows):
        cells = []
        for n in intervals:
            r = lookup.get((label, n))
            cells.append("-" if r is None else f"{r['success_mean']:.2f} ± {r['success_std']:.2f}")
        body.append([label, *cells])
    return format_table(body, ["method", *[f"n={n}" for n in intervals]])


def _held_out_rmse(model: smcd_rl.AdaptiveModel, data: TensorDict) -> float:
    """RMSE (m) of the unadapted network's prediction on fresh samples with random tools."""
    model.reset()
    with torch.no_grad():
        error = model.predict(data["q"]) - data["ee"]
    return float(error.square().sum(-1).mean().sqrt())


def _tasks(config: PandaConfig, seed: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """One seed's tools ``[tasks]`` and goals ``[tasks, 3]``, disjoint from the training data's draws."""
    generator = torch.Generator().manual_seed(config.seed * 1_000_003 + 7919 * (seed + 1))
    tools = sample_tool_lengths(config.tasks, tool_range=config.tool_range, generator=generator)
    goals = sample_goals(tools, generator=generator)
    return tools.to(device), goals.to(device)


Kinematics = Callable[[Tensor], Tensor]
Observe = Callable[[Tensor, Tensor], None]


def _method(
    label: str, model: smcd_rl.AdaptiveModel, tools: Tensor, config: PandaConfig, seed: int, device: torch.device
) -> tuple[Kinematics, Observe | None]:
    """The controller's kinematics and, for adaptive models, what a measurement updates."""
    if label == "FK":
        return (lambda q: panda_fk(q, 0.0)), None  # the tool is unknown: assume none
    if label == "M+N":
        strategy: smcd_rl.Adaptation = smcd_rl.NoAdaptation()
    elif label == "M+G":
        strategy = smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window)
    else:
        particles = int(label.split("N=")[1].rstrip(")"))
        strategy = smcd_rl.SMCD(
            num_particles=particles,
            flip_prob=config.flip_prob,
            noise_std=config.noise_std,
            generator=torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + seed),
        )
    adapted = model.with_adaptation(strategy)
    adapted.reset(batch_shape=(tools.shape[0],))

    def observe(q: Tensor, measured: Tensor) -> None:
        adapted.observe(TensorDict({"q": q, "ee": measured}, [q.shape[0]]))

    return adapted.predict, observe


def reach(
    kinematics: Kinematics,
    observe: Observe | None,
    tools: Tensor,
    goals: Tensor,
    *,
    interval: int,
    config: PandaConfig,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """Drive a batch of arms from the ready pose towards their goals with Jacobian PD control.

    At steps ``0, interval, 2 interval, ...`` the true end effector is measured: ``observe(q, x)``
    adapts the model (if any) and the controller corrects the measured error; at other steps it
    corrects its kinematics' own prediction (model-reference control).

    Args:
        kinematics: the controller's ``q [B, 7] -> x [B, 3]`` (row-wise).
        observe: called with ``(q, measured x)`` at every measurement, or ``None``.
        tools: the true tool of each arm ``[B]``.
        goals: ``[B, 3]``.
        interval: a measurement every ``interval``-th step.
        config: gains, step, tolerance, step count and measurement noise.
        generator: random source of the measurement noise.

    Returns:
        ``reached`` (bool ``[B]``: within ``config.tolerance`` at some step), ``steps`` (the first
        such step, ``config.steps + 1`` if never) and ``final_distance`` (m) after the last step
        (``config.steps``, or earlier once every arm has reached its goal).

    Example:
        >>> import torch
        >>> from smcd_rl.experiments.panda import PandaConfig, reach
        >>> from smcd_rl.envs.panda_reach import panda_fk, sample_goals
        >>> tools = torch.tensor([0.3, -0.2])
        >>> goals = sample_goals(tools, generator=torch.Generator().manual_seed(0))
        >>> result = reach(lambda q: panda_fk(q, tools), None, tools, goals, interval=1, config=PandaConfig())
        >>> result["reached"]  # the true kinematics, measured every step
        tensor([True, True])
    """
    batch = tools.shape[0]
    pd = JacobianPD(kinematics, k1=config.k1, k2=config.k2)
    q = torch.tensor(READY_POSE, device=tools.device, dtype=tools.dtype).expand(batch, -1).clone()
    q_dot = torch.zeros_like(q)
    reached = torch.zeros(batch, dtype=torch.bool, device=tools.device)
    first = torch.full((batch,), config.steps + 1, device=tools.device)
    for t in range(config.steps):
        position = None
        if t % interval == 0:
            position = panda_fk(q, tools)
            if config.measurement_noise > 0:
                noise = torch.randn(position.shape, generator=generator, device=position.device)
                position = position + config.measurement_noise * noise
            if observe is not None:
                observe(q, position)
        with torch.no_grad():
            try:
                u = pd(q, q_dot, goals, position)
            except torch.linalg.LinAlgError as err:  # the pseudo-inverse of a NaN Jacobian
                raise ValueError(
                    f"the controller's kinematics became non-finite at step {t} (a diverged adaptation, e.g. "
                    "gradient descent with too high a learning rate: lower --gd-lr)"
                ) from err
            q, q_dot = integrate_panda(q, q_dot, u, config.dt)
            close = (panda_fk(q, tools) - goals).norm(dim=-1) < config.tolerance
        first = torch.where(close & ~reached, torch.full_like(first, t + 1), first)
        reached |= close
        if bool(reached.all()):  # success is decided at the first arrival: nothing left to learn
            break
    final = (panda_fk(q, tools) - goals).norm(dim=-1)
    return {"reached": reached, "steps": first, "final_distance": final}


def _plot(rows: list[dict[str, Any]], config: PandaConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    intervals = sorted(set(config.intervals))
    # Orange is the reference line's, as in Fig. 3; the methods take the other colours.
    colours = itertools.cycle(
        ["tab:blue", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan"]
    )
    for label in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == label and r["interval"] in intervals]
        ax.errorbar(
            [r["interval"] for r in sel],
            [r["success_mean"] for r in sel],
            color=next(colours),
            yerr=[r["success_std"] for r in sel],
            marker="o",
            capsize=2,
            label=label,
        )
    reference = [r for r in rows if r["method"] == "FK" and r["interval"] == 1]
    if reference:
        ax.axhline(reference[0]["success_mean"], color="tab:orange", linestyle="--", label="FK, measured every step")
    ax.set_xscale("log")
    ax.set_xticks(intervals, [str(n) for n in intervals])
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("measurement interval n (steps)")
    ax.set_ylabel(f"success rate (within {100 * config.tolerance:.0f} cm in {config.steps} steps)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title(f"Panda reaching, unknown tool ({config.tasks} tasks x {config.seeds} seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
