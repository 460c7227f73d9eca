"""The two SMCD references every experiment reports beside the tuned methods: ``S(evidence)`` and ``S(paper)``.

``S(evidence)`` is SMCD calibrated by the filter's evidence (:func:`smcd_rl.calibrate`), as the
paper calibrates, in the likelihood's form (Gaussian or Student-t) that :func:`smcd_rl.tune` kept
for SMCD on the same episodes by its robust-form rule; ``S(paper)`` is SMCD at the paper's noise
and flip probability, untuned.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.tuning import calibrate
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.result import TuneResult

__all__ = ["reference_specs"]


def reference_specs(
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: Any,
    free: TuneResult,
    *,
    variants: Sequence[str],
    paper_noise: float | tuple[float, ...] | list[float],
    seed: int,
    device: str,
    progress: bool,
) -> tuple[dict[str, dict[str, Any]], dict[str, Trace]]:
    """The specs of the references among ``variants``, and their runs on ``episodes`` where calibration made them.

    ``free`` is the unbudgeted :func:`smcd_rl.tune` result on the same episodes: its SMCD search's
    runs are reused, and its SMCD's likelihood form is the references' by the robust-form rule.
    """
    specs: dict[str, dict[str, Any]] = {}
    runs: dict[str, Trace] = {}
    if "S(evidence)" in variants:
        searched = free.calibrations.get("search")  # its runs at these particles are not run again
        evidence = calibrate(
            model,
            episodes,
            base=smcd_rl.SMCD(num_particles=config.particles),
            flip_probs=config.calibrate_flips,
            criterion="evidence",
            seed=seed,
            progress=progress,
            reuse=searched if searched and searched.num_particles == config.particles else None,
        )
        settings = {**evidence.strategy.config(), "seed": seed, "device": device}
        # The likelihood's form follows tune's robust-form rule for SMCD on the same episodes: the
        # evidence chooses the noise of the Gaussian it scores, and the clean episodes cannot show
        # what a Student-t form is for, a corrupted reading.
        likelihood = free.best_of["smcd"].settings.get("likelihood", "gaussian") if "smcd" in free.best_of else None
        if likelihood is not None and likelihood != settings["likelihood"]:
            settings["likelihood"] = likelihood
        elif evidence.best.trace is not None:
            runs["S(evidence)"] = evidence.best.trace
        specs["S(evidence)"] = {"name": "smcd", "settings": settings}
    if "S(paper)" in variants:
        noise = list(paper_noise) if isinstance(paper_noise, (tuple, list)) else float(paper_noise)
        paper = {"num_particles": config.particles, "noise_std": noise, "flip_prob": config.flip_prob}
        specs["S(paper)"] = {"name": "smcd", "settings": {**paper, "seed": seed, "device": device}}
    return specs, runs
