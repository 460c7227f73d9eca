"""One trial of ``smcd-rl sweep``: train a grid point's model and score it, from its configuration alone.

These functions run on Ray workers: each takes a grid point (a plain dict from
:func:`~smcd_rl.experiments.sweep.grid.trial_configs`), seeds itself and sets its own threads, so a
grid point computed on Ray equals the same call in-process, bit for bit.

Example:
    >>> from smcd_rl.experiments.sweep.config import SweepConfig
    >>> from smcd_rl.experiments.sweep.grid import trial_configs
    >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=1"), tasks=4, episodes=2))[0]
    >>> list(trial(point))
    ['train_loss']
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.allocator import keep_freed_memory
from smcd_rl.experiments.shared.runtime import seed_everything, torch_threads
from smcd_rl.experiments.shared.two_link_family import TUNING_ARMS_SEED
from smcd_rl.experiments.shared.two_link_lookahead import TEST_ARMS_SEED, lookahead_errors, test_arms
from smcd_rl.experiments.sweep.config import FILTER_STUDIES
from smcd_rl.experiments.sweep.posteriors import held_out_posteriors, training_posteriors
from smcd_rl.experiments.two_link.config import TwoLinkConfig

__all__ = ["REFERENCES", "trial", "train", "evaluate", "evaluate_arms", "arm_means", "timed_evaluate", "training_data"]

#: The smcd study's reference methods, run once per trained model on the same held-out arms:
#: the network without adaptation and with online gradient descent.
REFERENCES = ("M+N", "M+G")


def trial(config: Mapping[str, Any]) -> dict[str, float]:
    """Metrics of one grid point, from its configuration alone (it seeds itself).

    Training and drone studies: ``train_loss``, the mean training loss (MSE in normalised units,
    dropout on, as the paper plots) of the last epoch. smcd study: ``mse_T{t}_H{h}``, the mean
    squared end-effector error (m^2) over held-out arms and the first ``h`` look-ahead steps after
    ``t`` burn-in steps.
    """
    return evaluate(config, train(config))


def train(config: Mapping[str, Any]) -> dict[str, Any]:
    """Train the grid point's model: ``{"losses", "seconds", "checkpoint", "posteriors"}``.

    The filter studies keep the checkpoint; the masks study trains with
    ``fit(mask_training="task")`` and records its training posteriors per epoch
    (:func:`~smcd_rl.experiments.sweep.posteriors.training_posteriors`), an empty list elsewhere.

    Example:
        >>> from smcd_rl.experiments.sweep.config import SweepConfig
        >>> from smcd_rl.experiments.sweep.grid import trial_configs
        >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=2"), tasks=4, episodes=2))[0]
        >>> len(train(point)["losses"])
        2
    """
    keep_freed_memory()  # a Ray worker is a process of its own
    with torch_threads(int(config["threads"])):
        generator = seed_everything(int(config["seed"]))
        data = training_data(config, generator)
        model = _model(config, data)
        started = time.perf_counter()
        posteriors: list[dict[str, float]] = []
        masks: dict[str, Any] = {}
        if config["study"] == "masks":  # masks tied to the arm, and how concentrated each epoch's posteriors are
            masks = {
                "mask_training": "task",
                "task_share": float(config["task_share"]),
                "group_masks": False,  # the grid's network keeps one bit per unit
                "mask_callback": lambda epoch, found: posteriors.append(
                    training_posteriors(epoch, found, model.net.keep_prob)
                ),
            }
        losses = smcd_rl.fit(
            model,
            data.to(config["device"]),
            epochs=int(config["epochs"]),
            batch_size=int(config["batch_size"]),
            lr=float(config["lr"]),
            seed=int(config["seed"]),
            progress=False,
            **masks,
        )
        seconds = time.perf_counter() - started
    checkpoint = model.checkpoint() if config["study"] in FILTER_STUDIES else None
    return {"losses": losses, "seconds": seconds, "checkpoint": checkpoint, "posteriors": posteriors}


def evaluate(config: Mapping[str, Any], trained: Mapping[str, Any]) -> dict[str, float]:
    """The grid point's metrics from a model trained by :func:`train` (with at least its epochs).

    smcd study: the mean over arms of :func:`evaluate_arms`.

    Example:
        >>> from smcd_rl.experiments.sweep.config import SweepConfig
        >>> from smcd_rl.experiments.sweep.grid import trial_configs
        >>> point = trial_configs(SweepConfig(grid=("hidden=8", "epochs=1"), tasks=4, episodes=2))[0]
        >>> evaluate(point, {"losses": [0.5, 0.25]})
        {'train_loss': 0.5}
    """
    if config["study"] not in FILTER_STUDIES:
        epochs = int(config["epochs"])
        if len(trained["losses"]) < epochs:
            raise ValueError(f"the trained model ran {len(trained['losses'])} epochs; this grid point needs {epochs}")
        return {"train_loss": float(trained["losses"][epochs - 1])}
    return arm_means(evaluate_arms(config, trained))


def arm_means(arms: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """Each metric's mean over the arms (in float64, as the confidence intervals take it)."""
    return {name: float(values.double().mean()) for name, values in arms.items()}


def evaluate_arms(config: Mapping[str, Any], trained: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """Filter studies: each held-out arm's look-ahead MSE, ``mse_T{t}_H{h} -> [arms]``, of one method.

    The method is SMCD with the point's filter settings, or ``config["method"]`` (one of
    :data:`REFERENCES`) on the same trained model and arms. The smcd study's arms and their
    evaluation are two-link's own, so its numbers are comparable to Fig. 2's. The masks study
    evaluates the same way on arms drawn from the seed of the two-link experiments' tuning arms
    (their link lengths), never on the test arms, since its result may choose the experiments'
    T setting, as the fair protocol's tuning does. In the masks study SMCD also
    reports how its posterior on each arm concentrates
    (:func:`~smcd_rl.experiments.sweep.posteriors.held_out_posteriors`).
    """
    device = torch.device(config["device"])
    with torch_threads(int(config["threads"])):
        model = _model(config, None)
        model.load_checkpoint(trained["checkpoint"])
        lookahead = TwoLinkConfig(
            seed=int(config["seed"]),
            trials=int(config["arms"]),
            chunk=int(config["chunk"]),
            burn_in=tuple(config["burn_in"]),
            horizons=tuple(config["horizons"]),
            measurement_noise=float(config["measurement_noise"]),
            device=str(device),
        )
        offset = TEST_ARMS_SEED if config["study"] == "smcd" else TUNING_ARMS_SEED
        q, ee, ee_true, _ = test_arms(lookahead, device, count=lookahead.trials, seed=lookahead.seed + offset)
        method = model.with_adaptation(_adaptation(config, device))
        errors = lookahead_errors(method, q, ee, ee_true, lookahead, desc="smcd", progress=False)
        scores = {
            f"mse_T{t}_H{h}": errors[:, i, :h].mean(-1)
            for i, t in enumerate(lookahead.burn_in)
            for h in lookahead.horizons
        }
        if config["study"] == "masks" and config.get("method", "M+S") == "M+S":
            scores |= held_out_posteriors(method, q, ee, ee_true, steps=max(lookahead.burn_in), chunk=lookahead.chunk)
    return scores


def timed_evaluate(config: Mapping[str, Any], trained: Mapping[str, Any]) -> tuple[dict[str, torch.Tensor], float]:
    """:func:`evaluate_arms` and its wall seconds (what a Ray task returns)."""
    keep_freed_memory()  # a Ray worker is a process of its own
    started = time.perf_counter()
    return evaluate_arms(config, trained), time.perf_counter() - started


def _adaptation(config: Mapping[str, Any], device: torch.device) -> smcd_rl.Adaptation:
    method = config.get("method", "M+S")
    if method == "M+N":
        return smcd_rl.NoAdaptation()
    if method == "M+G":
        return smcd_rl.GradientDescent(
            lr=float(config["gd_lr"]), steps=int(config["gd_steps"]), window=int(config["gd_window"])
        )
    return smcd_rl.SMCD(
        num_particles=int(config["particles"]),
        flip_prob=float(config["flip_prob"]),
        noise_std=float(config["noise_std"]),
        generator=torch.Generator(device=device).manual_seed(int(config["seed"]) + 11),
    )


def training_data(config: Mapping[str, Any], generator: torch.Generator) -> TensorDict:
    """The grid point's training data: two-link motor babbling, or the drone trajectories used."""
    if config["study"] == "drone":
        state, action = _drone_data(
            str(config["dataset"]),
            str(config.get("dataset_digest", "")),
            int(config["operators"]),
            int(config["trajectories_per_operator"]),
            int(config["subset"]),
            int(config["seed"]),
        )
        return TensorDict({"state": state, "action": action}, [state.shape[0]])
    from smcd_rl.envs.two_link_arm import motor_babbling

    return motor_babbling(
        int(config["tasks"]),
        int(config["episodes"]),
        int(config["steps"]),
        measurement_noise=float(config["measurement_noise"]),
        generator=generator,
    )


@functools.lru_cache(maxsize=2)  # a Ray worker runs many trials on the same data; simulating takes seconds
def _drone_data(
    dataset: str, digest: str, operators: int, per_operator: int, subset: int, seed: int
) -> tuple[torch.Tensor, ...]:
    """States and actions of the training trajectories used: the paper's split, then ``subset`` at random.

    ``digest`` (the dataset file's) is part of the cache's key, so a rewritten file is read again.
    """
    import numpy as np

    from smcd_rl.envs import drone_operators

    if dataset:
        data = drone_operators.load_dataset(dataset)
    else:
        data = drone_operators.simulate_operators(operators, per_operator, seed=seed)
    train_ids = drone_operators.split_dataset(data, seed=seed)["train"]
    if subset > len(train_ids):
        raise ValueError(
            f"subset = {subset} but the dataset has only {len(train_ids)} training trajectories; lower --subset"
        )
    if subset:
        train_ids = np.sort(np.random.default_rng(seed).choice(train_ids, size=subset, replace=False))
    chosen = data.select(train_ids)
    return torch.from_numpy(chosen.state), torch.from_numpy(chosen.action)


def _model(config: Mapping[str, Any], data: TensorDict | None) -> smcd_rl.AdaptiveModel:
    hidden = (int(config["hidden"]),) * int(config["depth"])
    device = config["device"]
    if config["study"] == "drone":
        assert data is not None
        net = smcd_rl.MaskedMLP(
            data["state"].shape[-1],
            data["action"].shape[-1],
            hidden=hidden,
            dropout=float(config["dropout"]),
            device=device,
        )
        return smcd_rl.AdaptiveModel(net, in_keys=["state"], out_key="action")
    groups = (int(config["mask_groups"]) or None) if config["study"] == "masks" else None
    net = smcd_rl.MaskedMLP(2, 2, hidden=hidden, dropout=float(config["dropout"]), mask_groups=groups, device=device)
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
