"""SMCD update speed and memory: ``smcd-rl bench filter``.

Reads top to bottom: build the paper's network (default ``MaskedMLP(4 -> 1024 -> 1024 -> 2)``, masks
on both hidden layers, dropout 0.5) with random weights, draw a *true* mask and make observations
``z_t = f(x_t; true mask) + noise`` for random inputs, so that the posterior has a known answer to
concentrate on. Then, for each particle count ``N``, time side by side in one run:

* ``ours``: one full update of :class:`smcd_rl.SMCD` as shipped (propagate, particle forward,
  likelihood, reweight, resample) plus the MMSE mask, on its default path (``forward_path="auto"``);
* ``ours, dense path``: the same update forced onto the dense particle forward (the reference the
  incremental path is tested against);
* ``naive``: :class:`NaiveSMCD`, the straightforward update kept here as the yardstick (dense
  uniform bit flips, bool-multiply masking of every particle from the input on, multinomial
  resampling);
* ``matmul``: one dense fp32 ``(N x 1024) @ (1024 x 1024)`` matmul, the size of the network's
  largest layer for ``N`` particles.

in two regimes: *realistic*, a ``steps``-step adaptation run in which the posterior concentrates
(the mean number of distinct parents per step is printed), and *worst case*, a likelihood so flat
that the weights are uniform and every particle stays distinct; and under two schedules (see
:data:`SCHEDULES`): *interleaved*, every contender once per step, so all see the same machine load
but each update finds caches the others have just filled, and *back to back*, each contender's
whole run in one block, so each finds its own data in cache. Ratios against the matmul and the
naive update are checked against the goals of issue 4, per schedule. Finally the extra peak memory
of one update at ``memory_particles`` particles on a ``memory_hidden`` network is measured in a
fresh process (peak resident memory during the updates minus the memory before them; on CUDA the
allocator's peak). Writes ``results.json`` and ``results.csv``; ``--json`` prints the JSON.
Timings are never asserted by the tests.

Example:
    >>> from smcd_rl.experiments.bench.filter.run import BenchFilterConfig
    >>> config = BenchFilterConfig()
    >>> config.particles, config.hidden, config.threads
    ((100, 1000, 5000), (1024, 1024), 2)
"""

from __future__ import annotations

import math
import multiprocessing
import re
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import smcd_rl
from smcd_rl.experiments.bench.filter.config import FULL, BenchFilterConfig
from smcd_rl.experiments.bench.filter.report import GOAL_PARTICLES, GOALS, SCHEDULES, goals, report
from smcd_rl.experiments.bench.tools import publish, scale_to_unit_spread
from smcd_rl.experiments.shared.config import config_dict
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.runtime import machine_info, seed_everything
from smcd_rl.experiments.shared.stages import estimate, mlp_flops
from smcd_rl.strategies.particle_forward import ParticlePath

__all__ = ["BenchFilterConfig", "FULL", "GOALS", "GOAL_PARTICLES", "NaiveSMCD", "SCHEDULES", "run"]


#: A likelihood noise this large makes every particle's weight equal in float32: the worst case.
_FLAT_NOISE = 1e6


class NaiveSMCD:
    """The straightforward SMCD update, kept as the benchmark's yardstick (not for use).

    Every step: one uniform per bit for the flips, every particle's full forward pass from the
    input with bool-multiplied masks, a Gaussian likelihood, multinomial resampling and the mean
    mask. The same algorithm as :class:`smcd_rl.SMCD`, none of its shortcuts.
    """

    def __init__(
        self, net: smcd_rl.MaskedMLP, num_particles: int, flip_prob: float, noise_std: float, generator: torch.Generator
    ) -> None:
        self.net, self.n, self.flip_prob, self.noise_std, self.generator = (
            net,
            num_particles,
            flip_prob,
            noise_std,
            generator,
        )
        self.device = next(net.parameters()).device
        self.masks = torch.empty(0)
        self.log_weights = torch.empty(0)

    def reset(self) -> None:
        self.masks = (
            torch.rand(self.n, self.net.mask_dim, generator=self.generator, device=self.device) < self.net.keep_prob
        )
        self.log_weights = torch.full((self.n,), -math.log(self.n), device=self.device)

    def update(self, x: Tensor, z: Tensor) -> Tensor:
        flips = torch.rand(self.masks.shape, generator=self.generator, device=self.device) < self.flip_prob
        self.masks = self.masks ^ flips
        h = x.expand(self.n, -1)
        for i, linear in enumerate(self.net.linears[:-1]):
            h = self.net.act(linear(h))
            sl = self.net.mask_slices[i]
            if sl is not None:
                h = h * self.masks[:, sl] / self.net.keep_prob
        prediction = self.net.linears[-1](h)
        log_likelihood = -0.5 * ((z - prediction) / self.noise_std).square().sum(-1)
        weights = torch.softmax(self.log_weights + log_likelihood, dim=0)
        idx = torch.multinomial(weights, self.n, replacement=True, generator=self.generator)
        self.masks = self.masks[idx]
        return self.masks.float().mean(0)  # MMSE mask after resampling (uniform weights)


def run(config: BenchFilterConfig, *, progress: bool = True) -> dict[str, Any]:
    """Time the updates, print the table and ratios (or JSON), write the files; returns the payload."""
    with Experiment(config, progress=progress) as ex:
        # --- seed, the network and the observations it is filtered on ---------------------------
        device = ex.device
        net, observations = _problem(config, config.hidden, config.steps + config.warmup, device, ex.generator)

        # --- every particle count, regime and schedule; then the memory in a fresh process ------
        ex.plan(stage_costs(config))
        rows = []
        with torch.no_grad():
            for n in config.particles:  # each N prints its stage line: the progress bar it replaces
                with ex.stage(f"N={n}"):
                    for regime in ("realistic", "worst"):
                        for schedule in SCHEDULES:
                            rows.append(_time_regime(net, observations, n, regime, schedule, config, device))
        memory = None
        if config.memory_particles > 0:
            with ex.stage("memory"):
                memory = _memory(config, device)

        # --- results ----------------------------------------------------------------------------
        payload = {
            "benchmark": "one full SMCD update (propagate, particle forward, likelihood, reweight, resample, MMSE)",
            "config": config_dict(config),
            "device": str(device),
            "machine": machine_info(),
            "network": {
                "in": config.inputs,
                "hidden": list(config.hidden),
                "out": config.outputs,
                "mask_dim": net.mask_dim,
                "dropout": config.dropout,
            },
            "results": rows,
            "memory": memory,
            "goals": goals(rows, memory),
        }
        publish(ex.out, payload, rows, report(payload), as_json=config.json)
    return payload


def stage_costs(config: BenchFilterConfig) -> dict[str, float]:
    """Each stage's rough seconds at ``config`` (see :func:`~smcd_rl.experiments.shared.stages.estimate`), in run order.

    Each particle count N times, in both regimes and both schedules (back to back: two rounds),
    ``warmup`` plus ``steps`` (realistic) or ``repeats`` (worst case) updates of the four contenders,
    each about N forwards (the naive filter about 2 N); the memory stage starts two fresh
    processes (about 3 s each) that run ``warmup + 5`` updates of ``memory_particles`` particles.

    Example:
        >>> list(stage_costs(BenchFilterConfig()))
        ['N=100', 'N=1000', 'N=5000', 'memory']
    """
    flops = mlp_flops(config.inputs, config.hidden, config.outputs)
    updates = sum(3 * (config.warmup + steps) for steps in (config.steps, config.repeats))
    costs = {f"N={n}": estimate(steps=4 * updates, forwards=5 * n * updates, flops=flops) for n in config.particles}
    if config.memory_particles > 0:
        flops = mlp_flops(config.inputs, config.memory_hidden, config.outputs)
        updates = config.warmup + 5
        costs["memory"] = estimate(steps=2000, forwards=3 * updates * config.memory_particles, flops=flops)
    return costs


def _problem(
    config: BenchFilterConfig,
    hidden: tuple[int, ...],
    steps: int,
    device: torch.device,
    generator: torch.Generator,
) -> tuple[smcd_rl.MaskedMLP, list[tuple[Tensor, Tensor]]]:
    """A random network with every hidden layer masked, and observations made with a known true mask.

    The output layer is scaled so that predictions under random masks have unit std, the scale of a
    network trained on normalised targets, in which ``noise_std`` is given. The weights come from
    torch's global generator and the rest from ``generator``, both freshly seeded with ``seed``.
    """
    net = smcd_rl.MaskedMLP(config.inputs, config.outputs, hidden=hidden, dropout=config.dropout, device=device).eval()
    true_mask = (torch.rand(net.mask_dim, generator=generator) < net.keep_prob).to(device)
    xs = torch.randn(steps, config.inputs, generator=generator).to(device)
    noise = torch.randn(steps, config.outputs, generator=generator).to(device) * config.noise_std
    scale_to_unit_spread(net, generator)
    with torch.no_grad():
        zs = net(xs, mask=true_mask.expand(steps, -1)) + noise
    return net, list(zip(xs, zs, strict=True))


def _contenders(
    net: smcd_rl.MaskedMLP, n: int, noise_std: float, config: BenchFilterConfig, device: torch.device
) -> tuple[dict[str, Callable[[Tensor, Tensor], Any]], Callable[[], int]]:
    """Fresh contenders for one run and a probe of ours' distinct parents before its next update."""
    ours, dense = _smcd(net, n, noise_std, config, device), _smcd(net, n, noise_std, config, device, path="dense")
    naive = _naive(net, n, noise_std, config, device)
    layer_in = torch.rand(n, config.hidden[0], device=device)
    weight = torch.randn(config.hidden[-1], config.hidden[0], device=device)

    contenders = {
        "ours": _update(ours),
        "ours, dense path": _update(dense),
        "naive": naive.update,
        "matmul": lambda x, z: layer_in @ weight.t(),
    }

    def distinct_parents() -> int:  # of ours' last update
        return ours.particle_forward.last_distinct_parents or n  # type: ignore[union-attr]

    return contenders, distinct_parents


def _smcd(
    net: smcd_rl.MaskedMLP,
    n: int,
    noise_std: float,
    config: BenchFilterConfig,
    device: torch.device,
    path: ParticlePath = "auto",
) -> smcd_rl.SMCD:
    generator = torch.Generator(device=device).manual_seed(config.seed + 1)
    adaptation = smcd_rl.SMCD(
        num_particles=n, flip_prob=config.flip_prob, noise_std=noise_std, generator=generator, forward_path=path
    )
    adaptation.bind(net, torch.ones(config.outputs, device=device))
    adaptation.reset(())
    return adaptation


def _update(adaptation: smcd_rl.SMCD) -> Callable[[Tensor, Tensor], Tensor]:
    """One full update: the filter step and the MMSE mask."""

    def step(x: Tensor, z: Tensor) -> Tensor:
        adaptation.observe(x, z)
        return adaptation.mask

    return step


def _naive(
    net: smcd_rl.MaskedMLP, n: int, noise_std: float, config: BenchFilterConfig, device: torch.device
) -> NaiveSMCD:
    naive = NaiveSMCD(net, n, config.flip_prob, noise_std, torch.Generator(device=device).manual_seed(config.seed + 1))
    naive.reset()
    return naive


def _time_regime(
    net: smcd_rl.MaskedMLP,
    observations: list[tuple[Tensor, Tensor]],
    n: int,
    regime: str,
    schedule: str,
    config: BenchFilterConfig,
    device: torch.device,
) -> dict[str, Any]:
    """Mean and median ms per update of every contender, under one schedule.

    ``interleaved``: every contender once per step, who goes first rotating. ``back to back``: each
    contender's whole run in one block, in two rounds of fresh contenders, the second in reverse
    order so that neither drift nor position favours one.
    """
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    noise_std = config.noise_std if regime == "realistic" else _FLAT_NOISE
    steps = config.steps if regime == "realistic" else config.repeats
    run = observations[config.warmup : config.warmup + steps]
    # Warm up on throwaway contenders, then time fresh ones from the prior (the run starts at step 0).
    warm, _ = _contenders(net, n, noise_std, config, device)
    for x, z in observations[: config.warmup]:
        for fn in warm.values():
            fn(x, z)
    times: dict[str, list[float]] = {name: [] for name in warm}
    parents: list[int] = []

    def timed(name: str, fn: Callable[[Tensor, Tensor], Any], x: Tensor, z: Tensor) -> None:
        sync()
        started = time.perf_counter()
        fn(x, z)
        sync()
        times[name].append(time.perf_counter() - started)

    if schedule == "interleaved":
        contenders, distinct_parents = _contenders(net, n, noise_std, config, device)
        names = list(contenders)
        for t, (x, z) in enumerate(run):
            for name in names[t % len(names) :] + names[: t % len(names)]:  # rotate who goes first
                timed(name, contenders[name], x, z)
            parents.append(distinct_parents())
    else:
        for round_ in range(2):
            contenders, distinct_parents = _contenders(net, n, noise_std, config, device)
            names = list(contenders) if round_ == 0 else list(reversed(contenders))
            for name in names:
                for x, z in run:
                    timed(name, contenders[name], x, z)
                    if name == "ours":
                        parents.append(distinct_parents())
    median = {name: statistics.median(v) * 1e3 for name, v in times.items()}
    mean = {name: statistics.fmean(v) * 1e3 for name, v in times.items()}
    return {
        "N": n,
        "regime": regime,
        "schedule": schedule,
        "steps": steps,
        "ours_ms": mean["ours"],
        "ours_median_ms": median["ours"],
        "dense_path_ms": mean["ours, dense path"],
        "naive_ms": mean["naive"],
        "matmul_ms": median["matmul"],
        "ours_over_matmul": mean["ours"] / median["matmul"],
        "naive_over_ours": mean["naive"] / mean["ours"],
        "dense_path_over_ours": mean["ours, dense path"] / mean["ours"],
        "mean_distinct_parents": statistics.fmean(parents),
    }


def _memory(config: BenchFilterConfig, device: torch.device) -> dict[str, Any] | None:
    """Extra peak memory of SMCD and naive updates, each measured in a fresh process."""
    results: dict[str, Any] = {"particles": config.memory_particles, "hidden": list(config.memory_hidden)}
    context = multiprocessing.get_context("spawn")
    with context.Pool(1, maxtasksperchild=1) as pool:
        for contender in ("ours", "naive"):
            mb = pool.apply(_peak_extra_mb, (config, contender, str(device)))
            if mb is None:
                return None
            results[f"{contender}_peak_extra_mb"] = mb
    return results


def _peak_extra_mb(config: BenchFilterConfig, contender: str, device_name: str) -> float | None:
    """Run in a fresh process: peak memory of ``warmup + 5`` updates above the memory before them."""
    device = torch.device(device_name)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    hidden = config.memory_hidden
    n = config.memory_particles
    net, observations = _problem(config, hidden, config.warmup + 5, device, seed_everything(config.seed))
    if contender == "ours":
        update = _update(_smcd(net, n, config.noise_std, config, device))
    else:
        update = _naive(net, n, config.noise_std, config, device).update
    with torch.no_grad():
        if device.type == "cuda":
            torch.cuda.synchronize()
            before = torch.cuda.memory_allocated(device)
            torch.cuda.reset_peak_memory_stats(device)
            for x, z in observations:
                update(x, z)
            torch.cuda.synchronize()
            return (torch.cuda.max_memory_allocated(device) - before) / 2**20
        try:
            Path("/proc/self/clear_refs").write_text("5")  # reset the peak resident set (Linux)
            before = _status_kb("VmRSS")
        except OSError:
            return None
        for x, z in observations:
            update(x, z)
        return (_status_kb("VmHWM") - before) / 1024


def _status_kb(field: str) -> int:
    match = re.search(rf"^{field}:\s+(\d+) kB", Path("/proc/self/status").read_text(), re.MULTILINE)
    if match is None:
        raise OSError(f"no {field} in /proc/self/status")
    return int(match.group(1))
