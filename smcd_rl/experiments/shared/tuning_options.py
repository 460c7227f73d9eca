"""Options of the tuned SMCD, measured on the tuning episodes only (diagnosis: no method uses them).

Each option changes one setting of the tuned SMCD (:data:`OPTIONS`); :data:`STUDENT` swaps its
Gaussian likelihood for a Student-t one, whose noise is calibrated by its own evidence, since a
likelihood of its own needs a noise of its own. Every option's one-step error goes into the
experiment's tuning table beside the tuned SMCD's.

Example:
    >>> import smcd_rl
    >>> OPTIONS["5x particles"](smcd_rl.SMCD(num_particles=100))
    {'num_particles': 500}
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.strategies.registry import build
from smcd_rl.tuning import describe_settings
from smcd_rl.tuning.calibration import calibrate
from smcd_rl.tuning.diagnostics import trace

__all__ = ["OPTIONS", "STUDENT", "trace_options"]

#: Option -> the settings it changes, from the tuned SMCD's.
OPTIONS: dict[str, Callable[[smcd_rl.SMCD], dict[str, Any]]] = {
    "5x particles": lambda smcd: {"num_particles": 5 * smcd.num_particles},
    "predictive mean": lambda smcd: {"prediction": "predictive"},
}
#: The option of a Student-t likelihood (4 degrees of freedom), calibrated by its own evidence.
STUDENT = "Student-t likelihood"


def trace_options(
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    settings: dict[str, Any],
    *,
    seed: int,
    device: str,
    progress: bool,
) -> tuple[dict[str, dict[str, Any]], dict[str, float]]:
    """The tuned SMCD's trace with each option changed, and with a Student-t likelihood of its own calibration.

    Args:
        model: the trained model; its own calibration is kept.
        episodes: the tuning episodes ``[E, T]``.
        config: the experiment's config (``particles``, ``calibrate_flips``).
        settings: the tuned SMCD's settings.
        seed: every filter's generator seed.
        device: where the filters' generators live (the model's device).
        progress: show the calibration's progress bar.

    Returns:
        option -> trace (as a dict, with a ``"settings"`` description), and the wall seconds of the
        ``"options"`` and ``"student-t"`` stages.
    """
    started = time.perf_counter()
    options = {}
    tuned = build("smcd", {**settings, "seed": seed, "device": device})
    assert isinstance(tuned, smcd_rl.SMCD)
    for option, changed in OPTIONS.items():
        generator = torch.Generator(device=device).manual_seed(seed)
        other = smcd_rl.SMCD(**{**tuned.config(), **changed(tuned)}, generator=generator)
        options[option] = {**trace(model, episodes, other).to_dict(), "settings": "as S"}
    seconds = {"options": time.perf_counter() - started}
    started = time.perf_counter()
    chosen = model.calibration
    student = calibrate(
        model,
        episodes,
        base=smcd_rl.SMCD(num_particles=config.particles, likelihood="student-t"),
        flip_probs=config.calibrate_flips,
        criterion="evidence",
        seed=seed,
        progress=progress,
    )
    model.calibration = chosen  # the model keeps its own calibration
    generator = torch.Generator(device=device).manual_seed(seed)
    strategy = smcd_rl.SMCD(**student.strategy.config(), generator=generator)
    options[STUDENT] = {
        **trace(model, episodes, strategy).to_dict(),
        "settings": describe_settings({"noise_std": student.noise_std, "flip_prob": student.flip_prob}),
    }
    seconds["student-t"] = time.perf_counter() - started
    return options, seconds
