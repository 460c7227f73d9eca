"""Every method's settings from :func:`smcd_rl.tune` on one network's held-out training-task episodes.

One call of :func:`smcd_rl.tune` per network chooses gradient descent (its grid, its robust
losses), SMCD (noise and flips by one-step error) and their combination by the same criterion;
a second call under ``--budget-ms`` per observation, reusing the first call's scores, gives the
budgeted view; SMCD calibrated by
evidence and SMCD at the paper's settings are the two references every other experiment reports.
Each method's median time per observation (one stream, the run's threads) is measured here, in
the main process, while no worker runs. The result is cached in the run's store, keyed by the
model, the episodes and the settings.

Example:
    >>> spec = {"name": "smcd", "settings": {"num_particles": 10, "noise_std": 0.1, "flip_prob": 0.01, "seed": 0}}
    >>> type(strategy_of(spec)).__name__
    'SMCD'
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.regimes.config import BUDGETED, RegimesConfig
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.tuning import VARIANTS, tuned_specs
from smcd_rl.strategies.registry import build

__all__ = ["tune_network", "strategy_of", "residual_of", "budgeted_label"]


def budgeted_label(method: str, config: RegimesConfig) -> str:
    """The label of ``method`` tuned under the per-observation budget, e.g. ``"G@10ms"``."""
    return f"{method}@{config.budget_ms:g}ms"


def strategy_of(spec: dict[str, Any]) -> smcd_rl.Adaptation:
    """A fresh strategy from ``{"name": ..., "settings": ...}`` (a strategy spec, :func:`smcd_rl.strategies.registry.spec`) (what :func:`tune_network` returns per method)."""
    return build(spec["name"], spec["settings"])


def residual_of(model: smcd_rl.AdaptiveModel, episodes: TensorDictBase) -> torch.Tensor:
    """Per output dimension, the RMS error of the unadapted model on the episodes (target units)."""
    plain = model.with_adaptation(smcd_rl.NoAdaptation())
    plain.reset(batch_shape=tuple(episodes.batch_size[:1]))
    with torch.no_grad():
        predicted = plain(episodes.exclude(model.target_key))[model.target_key]
    return (predicted - episodes.get(model.target_key)).square().mean((0, 1)).sqrt().cpu()


def tune_network(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: RegimesConfig,
    *,
    name: str,
    methods: Sequence[str],
    variants: Sequence[str] = VARIANTS,
    budgeted: Sequence[str] = BUDGETED,
) -> dict[str, Any]:
    """Each method's spec, time per observation and the tuning tables of one network (or a rerun's).

    ``variants`` (default all of :data:`VARIANTS`) are the kinds of method to tune (``"G"``, ``"S"``...: only what
    they need runs) and ``budgeted`` those tuned again under the budget; ``methods`` selects the
    specs returned.

    Returns:
        ``{"specs": method -> {"name", "settings"}, "ms": method -> ms per observation,
        "tables": caption -> Markdown, "residual": [per dimension], "seconds": float}``.
    """
    key = {
        "model": model_digest(model),
        "episodes": content_digest(episodes),
        "settings": config.settings(exclude=("methods", "families", "trials")),
        "variants": sorted(variants),
        "budgeted": sorted(budgeted),
    }
    with ex.stage(f"tune {name}"):
        found = ex.store.get(f"tuning-{name}", key)
        if found is None:
            found = _tune(ex, model, episodes, config, name=name, variants=variants, budgeted=budgeted)
            ex.store.put(f"tuning-{name}", key, found)
    ex.timings[f"tune {name}"] = found["seconds"]
    wanted = {*methods, *(budgeted_label(m, config) for m in budgeted if m in methods)}
    return {**found, "specs": {m: s for m, s in found["specs"].items() if m in wanted}}


def _tune(
    ex: Experiment,
    model: smcd_rl.AdaptiveModel,
    episodes: TensorDictBase,
    config: RegimesConfig,
    *,
    name: str,
    variants: Sequence[str],
    budgeted: Sequence[str],
) -> dict[str, Any]:
    found = tuned_specs(
        model,
        episodes,
        config,
        name=name,
        paper_noise=config.noise_std,
        budgeted=budgeted,
        variants=variants,
        device=str(ex.device),
        progress=ex.progress,
    )
    return {**found, "residual": residual_of(model, episodes).tolist()}
