"""Time ``fit(mask_training="task")`` at its defaults against the same fit with random masks.

On the two families of ``smcd-rl regimes`` (the two-link arms and the pendulums, at that
command's default data and network), each network is trained twice from the same initial
weights, side by side in one run: with random dropout masks (``fit``'s default) and with task
masks at ``fit``'s defaults (every sample through its task's posterior, the network's masks
grouped as ``smcd_rl.masked_mlp.task_mask_groups`` chooses). Printed: the machine and thread
count, each training's wall time and their ratio.

    python scripts/bench_task_masks.py
    python scripts/bench_task_masks.py --epochs 10 --threads 1
"""

from __future__ import annotations

import argparse
import time

import torch

import smcd_rl
from smcd_rl.experiments.regimes.config import RegimesConfig
from smcd_rl.experiments.regimes.families import build_model, training_data
from smcd_rl.experiments.shared.runtime import machine_info


def seconds_to_fit(network: str, config: RegimesConfig, masks: str, epochs: int) -> tuple[float, int | None]:
    """Wall seconds of one fit of ``network`` with ``masks`` ("random" or "task"), and the grouping it trained."""
    data = training_data(network, config, torch.Generator().manual_seed(config.seed))
    data.set("task", torch.arange(data.batch_size[0]).view(-1, 1, 1).expand(data.batch_size))
    torch.manual_seed(config.seed)
    model = build_model(network, config, "cpu")
    started = time.perf_counter()
    smcd_rl.fit(
        model,
        data if masks == "task" else data.exclude("task"),
        epochs=epochs,
        batch_size=config.batch_size,
        lr=config.lr,
        seed=config.seed,
        mask_training=masks,  # type: ignore[arg-type]
        progress=False,
    )
    return time.perf_counter() - started, model.net.mask_groups


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--epochs", type=int, default=None, help="epochs of each fit (default: the command's)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    smcd_rl.keep_freed_memory()
    print({k: v for k, v in machine_info().items() if k in ("processor", "cpus", "torch_threads", "torch")})
    config = RegimesConfig()
    epochs = args.epochs or config.epochs
    for network, family in (("arm", "two-link arms"), ("pendulum", "pendulums")):
        random, _ = seconds_to_fit(network, config, "random", epochs)
        task, groups = seconds_to_fit(network, config, "task", epochs)
        print(
            f"{family}: random masks {random:.1f} s, task masks at fit's defaults ({groups} mask groups) "
            f"{task:.1f} s, ratio {task / random:.2f} ({epochs} epochs, hidden {config.hidden})"
        )


if __name__ == "__main__":
    main()
