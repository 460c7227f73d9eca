"""Multi-task dropout training: fit a masked network on transitions pooled from many settings."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel, CheckpointMismatchError

__all__ = ["fit", "fit_dynamics"]

_FORMAT = "smcd_rl.fit/1"


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
) -> list[float]:
    """Train ``model.net`` with dropout on ``data`` (multi-task training: samples drawn at random).

    Inputs and targets are standardised with statistics computed from ``data`` the first time a
    model is fitted; they are stored in the model. Each step draws one Bernoulli(``keep_prob``)
    mask per sample from the run's own generator, so a run is repeatable from ``seed``.

    With ``checkpoint``, the model, optimiser and loss history are saved after every epoch, and a
    later call with the same path resumes after the last finished epoch: the result is identical
    to an uninterrupted run, because each epoch's shuffling and masks depend on (seed, epoch) only.

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

    Returns:
        Mean training loss (MSE in normalised units) of every epoch, resumed ones included.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> q = torch.rand(256, 2)
        >>> data = TensorDict({"q": q, "ee": torch.cos(q)}, [256])
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(32,)), in_keys=["q"], out_key="ee")
        >>> losses = smcd_rl.fit(model, data, epochs=2, batch_size=32, lr=1e-3, progress=False)
        >>> len(losses)
        2
    """
    if epochs < 0 or batch_size < 1 or lr <= 0:
        raise ValueError(f"need epochs >= 0, batch_size >= 1 and lr > 0, got {epochs}, {batch_size}, {lr}")
    if math.prod(data.batch_size) == 0:  # TensorDict.numel() reports 1 for batch [0]
        raise ValueError("fit got an empty dataset (no transitions); collect data before training")
    flat = data.reshape(-1)
    net = model.net
    device = next(net.parameters()).device
    x, y = model.training_pairs(flat.to(device))
    if not bool(model.input_norm.fitted):
        model.input_norm.fit(x)
        model.output_norm.fit(y)
    x, y = model.input_norm(x), model.output_norm(y)

    optimizer = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=weight_decay)
    settings = {"batch_size": batch_size, "lr": lr, "weight_decay": weight_decay, "seed": seed}
    history: list[float] = []
    start = 0
    path = Path(checkpoint) if checkpoint is not None else None
    if path is not None and path.is_file():
        start, history = _resume(path, model, optimizer, settings)

    generator = torch.Generator(device=device)
    n = x.shape[0]
    bar = tqdm(range(start, epochs), desc="fit", unit="epoch", disable=not progress, initial=start, total=epochs)
    for epoch in bar:
        net.train()
        generator.manual_seed(seed * 1_000_003 + epoch)
        order = torch.randperm(n, generator=generator, device=device)
        total = 0.0
        for begin in range(0, n, batch_size):
            idx = order[begin : begin + batch_size]
            mask = torch.rand(idx.shape[0], net.mask_dim, generator=generator, device=device) < net.keep_prob
            loss = (net(x[idx], mask=mask) - y[idx]).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * idx.shape[0]
        history.append(total / n)
        bar.set_postfix(loss=f"{history[-1]:.4g}")
        if path is not None:
            _save(path, model, optimizer, epoch + 1, history, settings)
        if callback is not None:
            callback(epoch, history[-1])
    net.eval()
    return history


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


def _save(
    path: Path, model: AdaptiveModel, optimizer: torch.optim.Optimizer, epoch: int, history: list[float], settings: dict
) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    state = {
        "format": _FORMAT,
        "model": model.checkpoint(),
        "optimizer": optimizer.state_dict(),
        "epoch": epoch,
        "history": history,
        "settings": settings,
    }
    torch.save(state, tmp)
    os.replace(tmp, path)  # atomic: an interruption never leaves a half-written checkpoint


def _resume(
    path: Path, model: AdaptiveModel, optimizer: torch.optim.Optimizer, settings: dict
) -> tuple[int, list[float]]:
    state = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise CheckpointMismatchError(f"{path} is not an smcd_rl training checkpoint; delete it or pick another path")
    if state["settings"] != settings:
        raise CheckpointMismatchError(
            f"{path} was written with training settings {state['settings']}, not {settings}; "
            "resume with the same settings or use a new checkpoint path"
        )
    model.load_checkpoint(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    return int(state["epoch"]), list(state["history"])
