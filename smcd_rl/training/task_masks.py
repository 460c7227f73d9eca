"""The machinery of ``smcd_rl.fit(..., mask_training="task")``: tie dropout masks to training tasks.

Each epoch after the first infers every training task's mask posterior with the model's own SMCD
filter (all tasks as one batch of filters) and trains each sample through a particle of its
task's posterior with probability ``task_share``, the rest through a random mask
(the concepts page "Mask training"). :func:`smcd_rl.fit` builds a :class:`TaskEpochs` from its
arguments; nothing here is public API.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from smcd_rl.checks import check_real_tensor
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies import SMCD

__all__ = ["TaskIndex", "TaskEpochs", "task_index", "TASK_PARTICLES", "MIN_MASK_NOISE"]

#: Particles (over all tasks) per filter batch of ``mask_training="task"``: the tasks' filters run
#: in batches of ``max(1, TASK_PARTICLES // mask_particles)`` tasks, which bounds the memory of a
#: particle forward pass. Fixed, so a run repeats; changing it changes the random stream.
TASK_PARTICLES = 32768
#: The smallest likelihood noise of the task inference, in normalised units: a network that fits
#: its samples exactly would otherwise give every particle but the best zero weight.
MIN_MASK_NOISE = 1e-3


class TaskIndex:
    """Task ids of a flattened dataset: ``ids [K]`` (sorted), ``index [n]`` in ``0 .. K-1``, and
    per task its sample ``counts [K]`` and the ``starts [K]`` of its block once samples are sorted
    by task."""

    def __init__(self, ids: Tensor, index: Tensor) -> None:
        self.ids, self.index = ids, index
        self.counts = torch.bincount(index, minlength=ids.numel())
        self.starts = self.counts.cumsum(0) - self.counts


def task_index(data: TensorDictBase, task_key: NestedKey, device: torch.device) -> TaskIndex:
    """The checked task ids of ``data`` (one per sample, in ``data.reshape(-1)``'s order)."""
    what = "fit(mask_training='task')"
    value = data.get(task_key, None)
    if value is None:
        raise KeyError(
            f"{what} needs an integer task id per sample under task_key={task_key!r}, but the data has no such "
            f"key; it has {sorted(map(str, data.keys(True, True)))}: pass the key that holds the ids as task_key"
        )
    value = check_real_tensor(value, f"{what}: {task_key!r}")
    batch = tuple(data.batch_size)
    if tuple(value.shape) not in (batch, (*batch, 1)):
        raise ValueError(
            f"{what}: {task_key!r} must hold one task id per sample, shape {list(batch)} (the data's batch) "
            f"or {[*batch, 1]}, got {list(value.shape)}"
        )
    if value.is_floating_point() or value.dtype == torch.bool:
        nan = " (some are NaN)" if value.is_floating_point() and bool(torch.isnan(value).any()) else ""
        raise TypeError(
            f"{what}: task ids are labels and must be an integer tensor, got {value.dtype}{nan}; "
            f"store whole-number ids as integers (e.g. data[{task_key!r}] = ids.long())"
        )
    ids, index = torch.unique(value.reshape(-1).to(device=device, dtype=torch.long), sorted=True, return_inverse=True)
    if ids.numel() < 2:
        raise ValueError(
            f"{what}: {task_key!r} holds a single task (id {int(ids[0])}); tying masks to tasks needs at least "
            "two of them: train single-task data with mask_training='random'"
        )
    return TaskIndex(ids, index)


class TaskEpochs:
    """The epochs of ``fit(mask_training="task")``: infer every task's mask posterior, then train.

    ``start(epoch)`` is told the epoch before each call; epoch 0 runs ``random_epoch`` (no
    posterior exists yet), every later one infers the posteriors from the current weights and
    trains through them, one shuffled pass of ``run_epoch(generator, batch_loss)`` (see
    :func:`smcd_rl.fit`). Everything is drawn from the epoch's generator.
    """

    def __init__(
        self,
        net: MaskedMLP,
        x: Tensor,
        y: Tensor,
        tasks: TaskIndex,
        *,
        run_epoch: Callable[[torch.Generator, Callable[[Tensor], Tensor]], float],
        task_share: float,
        particles: int,
        observations: int,
        flip_prob: float,
        noise_scale: float,
        random_epoch: Callable[[torch.Generator], float],
        report: Callable[[int, dict[str, Tensor]], None] | None,
    ) -> None:
        self.net, self.x, self.y, self.tasks = net, x, y, tasks
        self.run_epoch, self.task_share = run_epoch, task_share
        self.particles, self.observations, self.flip_prob = particles, observations, flip_prob
        self.noise_scale = noise_scale
        self.random_epoch, self.report = random_epoch, report
        self.epoch = 0

    def start(self, epoch: int) -> None:
        self.epoch = epoch

    def __call__(self, generator: torch.Generator) -> float:
        if self.epoch == 0:
            return self.random_epoch(generator)
        net, x, y, device = self.net, self.x, self.y, self.x.device
        particles, weights, posteriors = self.infer(generator)
        if self.report is not None:
            self.report(self.epoch, posteriors)
        task_of = self.tasks.index

        def batch_loss(idx: Tensor) -> Tensor:
            mask = torch.rand(idx.shape[0], net.mask_dim, generator=generator, device=device) < net.keep_prob
            # Which samples train through their task's posterior; the rest keep the random mask,
            # so every sub-network of the ensemble stays trained.
            chosen = (torch.rand(idx.shape[0], generator=generator, device=device) < self.task_share).nonzero()
            chosen = chosen.squeeze(-1)
            if chosen.numel() > 0:
                task = task_of[idx[chosen]]
                pick = torch.multinomial(weights[task], 1, generator=generator).squeeze(-1)  # a particle by weight
                mask[chosen] = particles[task, pick]
            return (net(x[idx], mask=mask) - y[idx]).square().mean()

        return self.run_epoch(generator, batch_loss)

    def infer(self, generator: torch.Generator) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """Every task's posterior on the current weights: particles ``[K, N, D]``, weights ``[K, N]``, diagnostics."""
        net, tasks, steps = self.net, self.tasks, self.observations
        x, y, device = self.x, self.y, self.x.device
        n = x.shape[0]
        # A random order within each task: sort by task id plus a uniform key in [0, 1). Each
        # task's filters observe the first `steps` samples of its block, cycling if it is shorter.
        keys = torch.rand(n, generator=generator, device=device, dtype=torch.float64)
        order = torch.argsort(tasks.index.to(torch.float64) + keys)
        offsets = torch.arange(steps, device=device)
        chosen = order[tasks.starts.unsqueeze(-1) + offsets % tasks.counts.unsqueeze(-1)]  # [K, steps]
        with torch.no_grad():
            xs, ys = x[chosen], y[chosen]
            mean_mask = torch.full((net.mask_dim,), net.keep_prob, dtype=x.dtype, device=device)
            # The likelihood noise: how far the network with dropout off is from these samples (times
            # the scale), so the likelihood sharpens as the network's fit improves.
            noise = (net(xs, mask=mean_mask) - ys).square().mean(dim=(0, 1)).sqrt()
            if not bool(torch.isfinite(noise).all()):
                raise ValueError(
                    f"fit(mask_training='task'): at epoch {self.epoch} the network predicts inf or NaN (training "
                    "diverged); lower lr"
                )
            noise = (noise * self.noise_scale).clamp_min(MIN_MASK_NOISE)
            found = self._filters(xs, ys, noise, generator)
            posteriors = {
                "tasks": tasks.ids.cpu(),
                "mean_masks": found["mean_masks"].cpu(),
                "ess_share": (found["ess"] / self.particles).cpu(),
                "distinct_share": (found["distinct"] / self.particles).cpu(),
                "log_likelihood": (found["evidence"] / steps).cpu(),
                "noise": noise.cpu(),
            }
            if self.report is not None:
                # The same filters on the same samples dealt to the tasks at random: what the log
                # likelihood is when a filter's observations do not share a task. From a generator
                # of its own, so that reporting never changes the training's random stream.
                seed = (generator.initial_seed() * 1_000_003 + self.epoch) % 2**63
                other = torch.Generator(device=device).manual_seed(seed)
                deal = torch.randperm(xs.shape[0] * steps, generator=other, device=device)
                mixed_x, mixed_y = (v.reshape(-1, v.shape[-1])[deal].reshape(v.shape) for v in (xs, ys))
                shuffled = self._filters(mixed_x, mixed_y, noise, other)["evidence"]
                posteriors["shuffled_log_likelihood"] = (shuffled / steps).cpu()
        return found["particles"], found["weights"], posteriors

    def _filters(self, xs: Tensor, ys: Tensor, noise: Tensor, generator: torch.Generator) -> dict[str, Tensor]:
        """One SMCD filter per row of ``xs [K, steps, in]`` observing its samples in order, in batches of tasks."""
        net, num_tasks, steps, device = self.net, xs.shape[0], xs.shape[1], xs.device
        per_batch = max(1, TASK_PARTICLES // self.particles)
        names = ("particles", "weights", "mean_masks", "ess", "evidence", "distinct")
        parts: dict[str, list[Tensor]] = {name: [] for name in names}
        for first in range(0, num_tasks, per_batch):
            rows = slice(first, min(first + per_batch, num_tasks))
            smcd = SMCD(
                num_particles=self.particles,
                flip_prob=self.flip_prob,
                noise_std=noise.tolist(),
                generator=generator,
            )
            smcd.bind(net, torch.ones_like(noise))  # the noise is already in normalised units
            smcd.reset((rows.stop - rows.start,))
            for step in range(steps):
                smcd.observe(xs[rows, step], ys[rows, step])
            filt = smcd.filter
            assert filt is not None and filt.particles is not None
            assert filt.log_evidence is not None and filt.last_ess is not None  # set by reset()
            parts["particles"].append(filt.particles)
            parts["weights"].append(filt.weights)
            parts["mean_masks"].append(filt.mean_mask)
            parts["ess"].append(filt.last_ess)
            parts["evidence"].append(filt.log_evidence)
            ancestors = filt.ancestors
            if ancestors is None:  # no resampling at the last update: every particle its own
                distinct = torch.full(filt.log_evidence.shape, float(self.particles), device=device)
            else:  # resampling returns sorted ancestors: count the changes along each row
                distinct = 1.0 + (ancestors[..., 1:] != ancestors[..., :-1]).sum(-1).to(torch.float32)
            parts["distinct"].append(distinct)
        return {name: torch.cat(values) for name, values in parts.items()}
