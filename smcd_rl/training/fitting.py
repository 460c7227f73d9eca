"""Training with dropout: multi-task (:func:`fit`, samples pooled from many settings) or Reptile meta-learning."""

from __future__ import annotations

import copy
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from tqdm.auto import tqdm

from smcd_rl.checks import check_count, check_key, check_real, check_seed, check_tensordict
from smcd_rl.digests import content_digest
from smcd_rl.feature_readout import FeatureReadout
from smcd_rl.files import CheckpointMismatchError, load_file, save_file
from smcd_rl.filter import SMCDFilter
from smcd_rl.masked_mlp import MaskedMLP, task_mask_groups
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel
from smcd_rl.training.task_masks import TaskEpochs, task_index

__all__ = ["fit", "fit_dynamics", "fit_reptile", "MaskTraining"]

#: How :func:`fit` draws the dropout masks of its gradient steps, see its docstring.
MaskTraining = Literal["random", "task"]

_FORMAT = "smcd_rl.fit/1"
#: Rows per forward pass when measuring the residual scale (bounds its memory, not its result much).
_RESIDUAL_CHUNK = 65536


class _Checkpointable(Protocol):
    """What the training checkpoints need of a model."""

    def checkpoint(self) -> dict[str, Any]: ...

    def load_checkpoint(self, checkpoint: dict[str, Any]) -> None: ...


def fit(
    model: AdaptiveModel,
    data: TensorDictBase,
    *,
    epochs: int = 100,
    batch_size: int = 64,
    lr: float = 1e-4,
    weight_decay: float = 0.0,
    seed: int = 0,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool = True,
    callback: Callable[[int, float], None] | None = None,
    validation: TensorDictBase | None = None,
    mask_training: MaskTraining = "random",
    task_key: NestedKey = "task",
    task_share: float = 1.0,
    mask_particles: int = 100,
    mask_observations: int = 16,
    mask_flip_prob: float = 0.01,
    mask_noise_scale: float = 1.0,
    mask_callback: Callable[[int, dict[str, Tensor]], None] | None = None,
    group_masks: bool = True,
) -> list[float]:
    """Train ``model.net`` with dropout on ``data`` (multi-task training: samples drawn at random).

    Inputs and targets are standardised with statistics computed from ``data`` the first time a
    model is fitted; they are stored in the model. Each step draws one Bernoulli(``keep_prob``)
    mask per sample from the run's own generator, so a run is repeatable from ``seed``.

    ``mask_training`` chooses those masks:

    * ``"random"`` (default): every mask is an independent Bernoulli(``keep_prob``) draw, the
      paper's multi-task training. Nothing ties a mask to a task.
    * ``"task"``: masks that carry the task. ``data[task_key]`` holds an integer task id per
      sample (any integers; they are mapped to ``0 .. K-1``). Every epoch after the first
      starts by inferring each task's mask posterior with the SMCD filter itself
      (:class:`smcd_rl.SMCD` on the current weights, all tasks as one batch of independent
      filters): ``mask_particles`` particles, moved by ``mask_flip_prob`` bit flips, observe
      ``mask_observations`` random samples of their task one after the other, under a Gaussian
      likelihood whose noise is ``mask_noise_scale`` times the RMS residual, per output, of the
      network with dropout off on those samples (normalised units, at least 1e-3). In that
      epoch's gradient steps each sample then takes, with probability ``task_share``, a particle
      of its task's posterior (drawn by weight), else a Bernoulli(``keep_prob``) mask, so the
      ensemble of all masks stays trained. The first epoch of a run (epoch 0), before any
      posterior exists, is plain random dropout, exactly as with ``"random"``. Posteriors are
      inferred afresh every epoch from the current weights and the epoch's seed, so they need no
      checkpoint and a resumed run still equals an uninterrupted one. The inference costs about
      ``K * mask_observations * mask_particles`` forward passes (no backward) per epoch, against
      about three per sample for the epoch's gradient steps, and holds ``K * mask_particles *
      mask_dim`` bytes of masks. ``task_share=0`` trains as ``"random"`` does (with another
      random stream) but still reports the posteriors to ``mask_callback``: what the filter
      finds in a randomly trained network.

      The defaults are the settings ``smcd-rl task-masks`` measured best across its families
      (the task-mask settings page): every sample through its task's posterior
      (``task_share=1``; at least as good as half the samples on every family), and masks
      over blocks of units: a network with one bit per unit is given the grouping
      :func:`smcd_rl.masked_mlp.task_mask_groups` chooses, the divisor of its masked widths
      nearest 16 (:meth:`smcd_rl.MaskedMLP.group_masks`; 16 was best or level with the best on
      five of six families, and 20 of the Ant's 200 units on the sixth), before any epoch; its
      strategy is attached again. Blocks make the filters' masks short, so inferring them costs
      a fraction of one bit per unit, and the identified task more often holds. A network built
      with ``mask_groups`` keeps its own; ``group_masks=False`` keeps one bit per unit.

    With ``checkpoint``, the model, optimiser and loss history are saved after every epoch, and a
    later call with the same path resumes after the last finished epoch: the result is identical
    to an uninterrupted run, because each epoch's shuffling and masks depend on (seed, epoch) only.
    The same holds for a call with more ``epochs`` than the checkpoint has finished: it trains on
    from there, as the longer run would have. A call with fewer epochs, other settings or other
    data raises :class:`smcd_rl.CheckpointMismatchError`, which says how to go on.

    After training, the network with dropout off is run once over ``validation`` (else over
    ``data``) to record :attr:`smcd_rl.AdaptiveModel.residual_scale`, the RMS residual per output,
    where :func:`smcd_rl.calibrate` starts its noise search; measured on ``data`` it is optimistic
    (the network has seen those samples). This pass draws no random numbers, so the weights and
    losses are those of a run without it. A previous :attr:`~smcd_rl.AdaptiveModel.calibration`,
    :attr:`~smcd_rl.AdaptiveModel.tuning` and residual scale are cleared before the first step:
    they belonged to the old weights, also when the run stops midway.

    Args:
        model: the model whose network is trained (its strategy is irrelevant here).
        data: transitions with the model's input and target keys; any batch shape.
        epochs: passes over the data.
        batch_size: samples per gradient step.
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        seed: seed of shuffling and dropout masks.
        checkpoint: file to save to after each epoch and to resume from.
        progress: show a progress bar.
        callback: called as ``callback(epoch, mean_loss)`` after each epoch.
        validation: held-out transitions (the model's keys, any batch shape) for the residual
            scale; never trained on.
        mask_training: ``"random"`` or ``"task"``, see above.
        task_key: key of the integer task ids in ``data`` (``"task"``: what
            :func:`smcd_rl.envs.two_link_arm.motor_babbling` writes), shape ``data.batch_size``
            or ``[*data.batch_size, 1]``; read with ``mask_training="task"`` only.
        task_share: probability, in ``[0, 1]``, that a sample of a ``"task"`` epoch trains
            through a mask of its task's posterior rather than a random one (default 1).
        mask_particles: particles per task of the posterior inference.
        mask_observations: samples of a task each of its filters observes, one per filter
            step (a task with fewer samples repeats them).
        mask_flip_prob: per-bit flip probability of the inference filters' ``"keep_rate"``
            transition (see :class:`smcd_rl.SMCDFilter`).
        mask_noise_scale: factor on the inference likelihood's noise (positive): below 1 the
            posteriors concentrate on fewer masks, above 1 they stay closer to the prior.
        mask_callback: with ``"task"``, called as ``mask_callback(epoch, posteriors)`` after each
            epoch's inference (every epoch but the first), before its gradient steps.
            ``posteriors`` holds CPU tensors, one row per task in the order of ``"tasks"``:
            ``"tasks"`` the task ids ``[K]``; ``"mean_masks"`` the MMSE masks ``[K, mask_dim]``;
            ``"ess_share"`` the ESS of the last update over ``mask_particles`` ``[K]`` (1: the
            last observation told the particles nothing apart, ``1 / N``: one particle took all
            weight); ``"distinct_share"`` the share of distinct particles after the last
            resampling ``[K]``; ``"log_likelihood"`` the log evidence per observation ``[K]``;
            ``"shuffled_log_likelihood"`` the same for the same samples dealt to the tasks at
            random ``[K]`` (the gap measures how much the masks stand for the tasks: near 0
            when they do not); ``"noise"`` the likelihood noise ``[out_features]``.
        group_masks: with ``"task"``, give a network with one bit per unit the grouping
            :func:`~smcd_rl.masked_mlp.task_mask_groups` chooses (see above); ``False`` keeps one
            bit per unit.

    Returns:
        Mean training loss (MSE in normalised units) of every epoch, resumed ones included.

    Raises:
        ValueError: a setting out of range; with ``"task"``, task ids of the wrong shape or a
            single task. Raised before any training: the model is unchanged.
        TypeError: with ``"task"``, task ids that are not integers.
        KeyError: with ``"task"``, ``data`` has no ``task_key``.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> q = torch.rand(256, 2)
        >>> data = TensorDict({"q": q, "ee": torch.cos(q)}, [256])
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(32,)), in_keys=["q"], out_key="ee")
        >>> losses = smcd_rl.fit(model, data, epochs=2, batch_size=32, lr=1e-3, progress=False)
        >>> len(losses)
        2

        Task-tied masks, with the posteriors' spread reported every epoch:

        >>> data["task"] = torch.arange(256) % 4  # four tasks
        >>> seen = []
        >>> losses = smcd_rl.fit(model, data, epochs=3, batch_size=32, lr=1e-3, progress=False,
        ...                      mask_training="task", mask_particles=20, mask_observations=4,
        ...                      mask_callback=lambda epoch, posteriors: seen.append(epoch))
        >>> seen  # epoch 0 has no posteriors yet
        [1, 2]
    """
    _check_model_and_data(model, data, "fit")
    epochs, batch_size = check_count(epochs, "epochs", minimum=0), check_count(batch_size, "batch_size")
    lr = _checked_rate(lr, "lr")
    weight_decay = check_real(weight_decay, "weight_decay", low=0.0, high=_LARGEST)
    loop = _Loop("fit", epochs, seed, checkpoint, progress, callback)
    _require_samples(data, "fit")
    _check_validation(validation, model, "fit")
    net = model.net
    _require_own_network(net, "fit")
    if mask_training not in ("random", "task"):
        raise ValueError(f"mask_training must be 'random' or 'task', got {mask_training!r}")
    # Every setting is checked whatever mask_training is: a typo fails now, not when it is switched.
    check_key(task_key, "task_key")
    task_share = check_real(task_share, "task_share", low=0.0, high=1.0)
    mask_particles = check_count(mask_particles, "mask_particles")
    mask_observations = check_count(mask_observations, "mask_observations")
    mask_flip_prob = check_real(mask_flip_prob, "mask_flip_prob", low=0.0, high=1.0)
    mask_noise_scale = check_real(mask_noise_scale, "mask_noise_scale", low=0.0, high=1e6, open_low=True)
    # The filter's own check of the flip probability against keep_prob (its own generator: the
    # check must not draw from torch's global one).
    SMCDFilter(net.mask_dim, 1, mask_flip_prob, net.keep_prob, generator=torch.Generator())
    if mask_callback is not None and mask_training != "task":
        raise ValueError(
            "mask_callback reports the task posteriors of mask_training='task'; random training infers none: "
            "pass mask_training='task' (task_share=0 keeps the training random) or drop mask_callback"
        )
    device = next(net.parameters()).device
    # Read before the normalisation is fitted below: bad task ids leave the model untouched.
    tasks = task_index(data, task_key, device) if mask_training == "task" else None
    if not isinstance(group_masks, bool):
        raise TypeError(f"group_masks must be True or False, got {group_masks!r} ({type(group_masks).__name__})")
    x, y = _normalised_pairs(model, data.reshape(-1), device)
    if tasks is not None and group_masks and net.mask_groups is None:
        # Task masks identify a task far better, and train faster, on blocks of units than on
        # single units (the task-mask settings page): the network takes the measured grouping.
        net.group_masks(task_mask_groups(net))
        model._bind(model.adaptation)  # its strategy's masks change size with the grouping
    optimizer = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=weight_decay)
    settings: dict[str, Any] = {"batch_size": batch_size, "lr": lr, "weight_decay": weight_decay, "seed": seed}
    n = x.shape[0]

    def one_epoch(generator: torch.Generator) -> float:
        def batch_loss(idx: Tensor) -> Tensor:
            mask = torch.rand(idx.shape[0], net.mask_dim, generator=generator, device=device) < net.keep_prob
            return (net(x[idx], mask=mask) - y[idx]).square().mean()

        return _shuffled_epoch(n, batch_size, optimizer, generator, batch_loss)

    train_epoch, before_epoch = one_epoch, None
    if tasks is not None:
        # Only a "task" run records its mask settings: a "random" run records the four settings
        # above and nothing else, so its checkpoints match those of every random run.
        settings.update(
            mask_training=mask_training,
            task_key=task_key,
            task_share=task_share,
            mask_particles=mask_particles,
            mask_observations=mask_observations,
            mask_flip_prob=mask_flip_prob,
            mask_noise_scale=mask_noise_scale,
        )
        task_epoch = TaskEpochs(
            net,
            x,
            y,
            tasks,
            run_epoch=lambda generator, batch_loss: _shuffled_epoch(n, batch_size, optimizer, generator, batch_loss),
            task_share=task_share,
            particles=mask_particles,
            observations=mask_observations,
            flip_prob=mask_flip_prob,
            noise_scale=mask_noise_scale,
            random_epoch=one_epoch,
            report=mask_callback,
        )
        train_epoch, before_epoch = task_epoch, task_epoch.start

    _forget_fitted_records(model)
    history = _train(
        model, train_epoch, data, loop, trained=net, settings=settings, optimizer=optimizer, before_epoch=before_epoch
    )
    _record_residual_scale(model, (x, y) if validation is None else validation)
    return history


def _require_own_network(net: MaskedMLP, what: str) -> None:
    """Refuse a network trained elsewhere: smcd_rl's training makes a MaskedMLP, it does not retrain a user's."""
    if isinstance(net, FeatureReadout):
        raise TypeError(
            f"{what} trains smcd_rl's own MaskedMLP; a FeatureReadout network was trained by your own code and is "
            "adapted as it is (adaptive_model_from declares it trained): train the module with your own loop, "
            "then wrap it again"
        )


def fit_dynamics(model: AdaptiveDynamicsModel, data: TensorDictBase, **kwargs: Any) -> list[float]:
    """:func:`fit` for a dynamics model; ``data`` holds observation, action and ("next", "observation").

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> obs, act = torch.randn(128, 3), torch.randn(128, 1)
        >>> data = TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + 0.1 * act}, [128])
        >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4, 3, hidden=(32,)))
        >>> len(smcd_rl.fit_dynamics(model, data, epochs=1, progress=False))
        1
    """
    if not isinstance(model, AdaptiveDynamicsModel):
        raise TypeError(f"fit_dynamics takes an AdaptiveDynamicsModel, got {type(model).__name__}; use smcd_rl.fit")
    return fit(model, data, **kwargs)


def fit_reptile(
    model: AdaptiveModel,
    data: TensorDictBase,
    *,
    epochs: int = 100,
    batch_size: int = 64,
    lr: float = 0.1,
    inner_lr: float = 0.02,
    inner_epochs: int = 1,
    tasks_per_batch: int = 1,
    seed: int = 0,
    checkpoint: str | os.PathLike[str] | None = None,
    progress: bool = True,
    callback: Callable[[int, float], None] | None = None,
    validation: TensorDictBase | None = None,
) -> list[float]:
    """Train ``model.net`` with Reptile (first-order meta-learning, Nichol et al. 2018) and dropout.

    ``data``'s first batch dim indexes tasks (e.g. ``motor_babbling`` gives ``[tasks, episodes,
    steps]``); everything after it is that task's samples. An epoch visits every task once, in
    random order, ``tasks_per_batch`` tasks per meta step. For each task of a meta step the
    weights are copied and trained by plain SGD (``inner_lr``) for ``inner_epochs`` passes over
    the task's samples in mini-batches of ``batch_size``, with one Bernoulli(``keep_prob``)
    dropout mask per sample as in :func:`fit`, so the result works with :class:`smcd_rl.SMCD`.
    The meta weights then move toward the adapted ones:

        theta <- theta + lr * mean_over_tasks(theta_task - theta)

    ``lr`` is this outer (meta) step size, the fraction of the way to the tasks' mean adapted
    weights: 1 replaces ``theta`` by that mean, small values move it gently. The defaults (0.1,
    one task per meta step) are those of Reptile's reference sine-wave regression, whose inner
    settings (SGD at 0.02, one inner epoch) are the ones the paper kept fixed. Unlike there the
    step is not annealed, so a run does not depend on its planned number of epochs. Progress
    per epoch grows with ``lr / tasks_per_batch`` and with the inner steps per task
    (samples / ``batch_size``).

    Normalisation, repeatability from ``seed``, checkpoint/resume and the residual scale
    recorded after training (on ``validation`` if given) behave exactly as in :func:`fit`. (The tasks of a meta step are trained one after the other: on CPU a
    ``torch.func.vmap`` over them measured no faster.)

    Args:
        model: the model whose network is trained.
        data: ``[tasks, *samples]`` with the model's input and target keys; every task has the
            same number of samples (a dense TensorDict).
        epochs: passes over all tasks.
        batch_size: samples per inner SGD step.
        lr: outer (meta) step size, see above.
        inner_lr: SGD learning rate of the inner loop (normalised units).
        inner_epochs: passes over a task's samples in its inner loop.
        tasks_per_batch: tasks adapted per meta step (the last step of an epoch may have fewer).
        seed: seed of task order, shuffling and dropout masks.
        checkpoint: file to save to after each epoch and to resume from.
        progress: show a progress bar.
        callback: called as ``callback(epoch, mean_loss)`` after each epoch.
        validation: held-out transitions for the residual scale, as in :func:`fit`.

    Returns:
        Mean inner-loop training loss (MSE in normalised units, before each SGD step) of every
        epoch, resumed ones included.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> q = torch.rand(8, 32, 2)  # 8 tasks of 32 samples
        >>> data = TensorDict({"q": q, "ee": torch.cos(q) * torch.rand(8, 1, 2)}, [8, 32])
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(32,)), in_keys=["q"], out_key="ee")
        >>> losses = smcd_rl.fit_reptile(model, data, epochs=2, batch_size=16, tasks_per_batch=4, progress=False)
        >>> len(losses)
        2
    """
    _check_model_and_data(model, data, "fit_reptile")
    epochs, batch_size = check_count(epochs, "epochs", minimum=0), check_count(batch_size, "batch_size")
    lr, inner_lr = _checked_rate(lr, "lr"), _checked_rate(inner_lr, "inner_lr")
    inner_epochs, tasks_per_batch = (
        check_count(inner_epochs, "inner_epochs"),
        check_count(tasks_per_batch, "tasks_per_batch"),
    )
    if data.batch_dims < 2:
        raise ValueError(
            f"fit_reptile needs data whose first batch dim indexes tasks, [tasks, *samples], got batch "
            f"{list(data.batch_size)}; e.g. data.reshape(num_tasks, -1), or smcd_rl.fit for pooled multi-task training"
        )
    loop = _Loop("fit_reptile", epochs, seed, checkpoint, progress, callback)
    _require_samples(data, "fit_reptile")
    _check_validation(validation, model, "fit_reptile")
    _require_own_network(model.net, "fit_reptile")
    num_tasks = data.batch_size[0]
    if tasks_per_batch > num_tasks:
        raise ValueError(
            f"tasks_per_batch={tasks_per_batch} exceeds the {num_tasks} tasks in data; pass at most {num_tasks}"
        )
    net = model.net
    device = next(net.parameters()).device
    x, y = _normalised_pairs(model, data.reshape(num_tasks, -1), device)  # [tasks, n, features]
    n = x.shape[1]
    settings = {
        "trainer": "reptile",
        "batch_size": batch_size,
        "lr": lr,
        "inner_lr": inner_lr,
        "inner_epochs": inner_epochs,
        "tasks_per_batch": tasks_per_batch,
        "seed": seed,
    }

    params = list(net.parameters())
    # The inner loops run on a copy of the network, so the meta weights stay put until the meta step.
    worker = copy.deepcopy(net)
    worker_params = list(worker.parameters())

    def one_epoch(generator: torch.Generator) -> float:
        tasks = torch.randperm(num_tasks, generator=generator, device=device)
        total = 0.0
        for first in range(0, num_tasks, tasks_per_batch):
            chosen = tasks[first : first + tasks_per_batch].tolist()
            summed = [torch.zeros_like(p) for p in params]
            for task in chosen:
                with torch.no_grad():
                    for w, p in zip(worker_params, params, strict=True):
                        w.copy_(p)
                for _ in range(inner_epochs):
                    order = torch.randperm(n, generator=generator, device=device)
                    for begin in range(0, n, batch_size):
                        idx = order[begin : begin + batch_size]
                        draw = torch.rand(idx.shape[0], net.mask_dim, generator=generator, device=device)
                        mask = draw < net.keep_prob
                        loss = (worker(x[task, idx], mask=mask) - y[task, idx]).square().mean()
                        grads = torch.autograd.grad(loss, worker_params)
                        with torch.no_grad():
                            for w, g in zip(worker_params, grads, strict=True):
                                w.add_(g, alpha=-inner_lr)
                        total += float(loss.detach()) * idx.shape[0]
                with torch.no_grad():
                    for total_w, w in zip(summed, worker_params, strict=True):
                        total_w.add_(w)
            with torch.no_grad():
                for p, s in zip(params, summed, strict=True):
                    p.add_(s / len(chosen) - p, alpha=lr)
        return total / (num_tasks * n * inner_epochs)

    _forget_fitted_records(model)
    history = _train(model, one_epoch, data, loop, trained=net, settings=settings, optimizer=None)
    _record_residual_scale(
        model, (x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1])) if validation is None else validation
    )
    return history


def _shuffled_epoch(
    n: int,
    batch_size: int,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    batch_loss: Callable[[Tensor], Tensor],
) -> float:
    """One pass over ``n`` samples in shuffled mini-batches; returns the mean of ``batch_loss(indices)``.

    The shuffle is drawn first and ``batch_loss`` may draw from ``generator`` after it, so an
    epoch is a function of the generator's seed alone.
    """
    order = torch.randperm(n, generator=generator, device=generator.device)
    total = 0.0
    for begin in range(0, n, batch_size):
        idx = order[begin : begin + batch_size]
        loss = batch_loss(idx)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        total += float(loss.detach()) * idx.shape[0]
    return total / n


def _check_model_and_data(model: Any, data: Any, what: str) -> None:
    """Refuse a bare network or anything but a TensorDict of transitions, with the fix."""
    if not isinstance(model, AdaptiveModel):
        hint = (
            "; wrap it: smcd_rl.AdaptiveModel(net, in_keys=[...], out_key=...)" if isinstance(model, MaskedMLP) else ""
        )
        raise TypeError(f"{what} trains an smcd_rl.AdaptiveModel, got {type(model).__name__}{hint}")
    check_tensordict(data, what)


def _require_samples(data: TensorDictBase, what: str) -> None:
    if math.prod(data.batch_size) == 0:  # TensorDict.numel() reports 1 for batch [0]
        raise ValueError(f"{what} got an empty dataset (no transitions); collect data before training")


def _check_validation(validation: Any, model: AdaptiveModel, what: str) -> None:
    """Refuse validation data the end of the run could not read (a missing key, a wrong width, NaN)
    now: the run would otherwise train in full, then fail with the new weights in place."""
    if validation is None:
        return
    check_tensordict(validation, f"{what}(validation=...)")
    _require_samples(validation, f"{what}(validation=...)")
    try:
        model.training_pairs(validation.reshape(-1))
    except (KeyError, ValueError, TypeError) as err:
        message = str(err.args[0]) if err.args else str(err)
        raise type(err)(f"{what}(validation=...): {message.removeprefix('fit: ')}") from err


#: The largest finite float: a rate or decay of inf passes a check for "> 0" and trains to NaN.
_LARGEST = sys.float_info.max


def _checked_rate(value: Any, name: str) -> float:
    """A learning rate: a finite real number > 0 (inf would train to NaN, a run that fails only at its end)."""
    return check_real(value, name, low=0.0, high=_LARGEST, open_low=True)


def _forget_fitted_records(model: AdaptiveModel) -> None:
    """Drop what belonged to the weights before training, as the weights are about to change.

    Cleared before the first step, not after the last: a run stopped in between (Ctrl-C, an
    exception in a callback) leaves new weights, and a calibration or tuning of the old ones
    would mislead ``SMCD(noise_std="auto")`` and :func:`smcd_rl.calibrate`. The end of a run
    records a fresh residual scale.
    """
    model.residual_scale = None
    model.calibration = None
    model.tuning = None


def _record_residual_scale(model: AdaptiveModel, data: TensorDictBase | tuple[Tensor, Tensor]) -> None:
    """Set ``model.residual_scale`` from the network with dropout off.

    ``data`` is a TensorDict of transitions or the normalised ``(inputs, targets)`` already
    computed for training. Draws no random numbers and changes no weights.
    """
    net = model.net
    if isinstance(data, TensorDictBase):
        device = next(net.parameters()).device
        x, y = model.training_pairs(data.reshape(-1).to(device))
        x, y = model.input_norm(x), model.output_norm(y)
    else:
        x, y = data
    was_training = net.training
    net.eval()
    squared = torch.zeros(net.out_features, dtype=torch.float64, device=y.device)
    with torch.no_grad():
        for begin in range(0, x.shape[0], _RESIDUAL_CHUNK):
            residual = net(x[begin : begin + _RESIDUAL_CHUNK]) - y[begin : begin + _RESIDUAL_CHUNK]
            squared += residual.to(torch.float64).square().sum(0)
    net.train(was_training)
    rms = (squared / x.shape[0]).sqrt() * model.output_norm.std.to(torch.float64)
    # A dimension the network fits exactly (a constant target) gets a small positive scale, not 0.
    floor = 1e-6 * model.output_norm.std.to(torch.float64)
    model.residual_scale = torch.maximum(rms, floor).to(torch.float32).cpu()


def _normalised_pairs(model: Any, data: TensorDictBase, device: torch.device) -> tuple[Tensor, Tensor]:
    """Normalised inputs and targets ``[*batch, features]`` from ``model.training_pairs``, on ``device``.

    ``model.input_norm`` and ``model.output_norm`` are fitted on ``data`` the first time a model
    is trained, then kept.
    """
    x, y = model.training_pairs(data.to(device))
    if not bool(model.input_norm.fitted):
        model.input_norm.fit(x)
        model.output_norm.fit(y)
    return model.input_norm(x), model.output_norm(y)


@dataclass(frozen=True)
class _Loop:
    """A trainer's own name and the options of its epoch loop, which every trainer takes from its caller as they are."""

    name: str  # the progress bar's label
    epochs: int
    seed: int
    checkpoint: str | os.PathLike[str] | None
    progress: bool
    callback: Callable[[int, float], None] | None

    def __post_init__(self) -> None:
        """Refuse a bad option now, before the trainer changes the model: a bad seed or checkpoint
        path otherwise failed once the normalisation was fitted, and a bad callback after a whole epoch."""
        object.__setattr__(self, "seed", check_seed(self.seed))
        if self.checkpoint is not None:
            if not isinstance(self.checkpoint, (str, os.PathLike)):
                raise TypeError(
                    f"{self.name}: checkpoint must be a file path (str or pathlib.Path), got "
                    f"{type(self.checkpoint).__name__}"
                )
            if Path(self.checkpoint).is_dir():
                raise ValueError(
                    f"{self.name}: checkpoint {str(self.checkpoint)!r} is a directory; pass a file path in it"
                )
        if self.callback is not None and not callable(self.callback):
            raise TypeError(
                f"{self.name}: callback must be callable as callback(epoch, mean_loss), got {type(self.callback).__name__}"
            )


def _train(
    model: _Checkpointable,
    one_epoch: Callable[[torch.Generator], float],
    data: TensorDictBase,
    loop: _Loop,
    *,
    trained: nn.Module,
    settings: dict[str, Any],
    optimizer: torch.optim.Optimizer | None,
    before_epoch: Callable[[int], None] | None = None,
) -> list[float]:
    """The epoch loop shared by the trainers: resume, seeding, progress bar, checkpoints, callback.

    ``loop`` holds the caller's epochs, seed, checkpoint path, progress flag and callback.
    ``one_epoch(generator)`` trains one epoch and returns its mean loss; the generator is
    reseeded from (seed, epoch) before each epoch, which is what makes a resumed run identical
    to an uninterrupted one. ``before_epoch(epoch)``, if given, is told each epoch's number
    right before its ``one_epoch`` call (for an epoch that trains differently by its number).
    ``trained`` is the module put in train mode meanwhile (and in eval mode after); ``model`` is
    what the checkpoint saves and restores. The checkpoint records a digest of ``data``, so that a
    run on other data never resumes it, and its finished epochs: a run of more epochs trains on
    from there (no setting depends on the planned number of epochs), one of fewer is refused,
    since the checkpoint's model is trained further than asked.
    """
    net = trained
    device = next(net.parameters()).device
    history: list[float] = []
    start, epochs = 0, loop.epochs
    path = Path(loop.checkpoint) if loop.checkpoint is not None else None
    digest = content_digest(data) if path is not None else ""
    if path is not None and path.is_file():
        start, history = _resume(path, model, optimizer, settings, digest, epochs)
    generator = torch.Generator(device=device)
    bar = tqdm(
        range(start, epochs), desc=loop.name, unit="epoch", disable=not loop.progress, initial=start, total=epochs
    )
    for epoch in bar:
        net.train()
        generator.manual_seed(loop.seed * 1_000_003 + epoch)
        if before_epoch is not None:
            before_epoch(epoch)
        history.append(one_epoch(generator))
        bar.set_postfix(loss=f"{history[-1]:.4g}")
        if path is not None:
            _save(path, model, optimizer, epoch + 1, history, settings, digest)
        if loop.callback is not None:
            loop.callback(epoch, history[-1])
    net.eval()
    return history


def _save(
    path: Path,
    model: _Checkpointable,
    optimizer: torch.optim.Optimizer | None,
    epoch: int,
    history: list[float],
    settings: dict,
    digest: str,
) -> None:
    state = {
        "format": _FORMAT,
        "model": model.checkpoint(),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "epoch": epoch,
        "history": history,
        "settings": settings,
        "data": digest,
    }
    save_file(state, path, what="training checkpoint")  # atomic: an interruption never leaves half a checkpoint


def _resume(
    path: Path,
    model: _Checkpointable,
    optimizer: torch.optim.Optimizer | None,
    settings: dict,
    digest: str,
    epochs: int,
) -> tuple[int, list[float]]:
    state = load_file(
        path,
        what="smcd_rl training checkpoint",
        expect_format=_FORMAT,
        expect_keys=("model", "optimizer", "epoch", "history", "settings"),
        fix="delete it to train afresh, or pass another checkpoint path",
    )
    if state["settings"] != settings:
        raise CheckpointMismatchError(
            f"{path} was written with training settings {state['settings']}, not {settings}; "
            "resume with the same settings or use a new checkpoint path"
        )
    if state.get("data") != digest:
        raise CheckpointMismatchError(
            f"{path} was trained on other data (or written before checkpoints recorded their data); "
            "resume with the same data, delete it to train afresh, or use another checkpoint path"
        )
    finished = int(state["epoch"])
    if finished > epochs:
        raise CheckpointMismatchError(
            f"{path} holds a model trained for {finished} epochs, more than the epochs={epochs} asked for; "
            f"pass epochs >= {finished} to use it (epochs={finished} loads it as it is), or delete it or use "
            f"another checkpoint path to train {epochs} epochs afresh"
        )
    model.load_checkpoint(state["model"])
    if optimizer is not None:
        optimizer.load_state_dict(state["optimizer"])
    return finished, list(state["history"])
