"""Strategies from their settings: what a tuning result records and how it rebuilds each strategy.

A tuned setting is a plain dict (JSON types only, so that ``model.tuning`` can hold it): a
strategy's ``config()``, plus for SMCD the ``seed`` and ``device`` of its random generator, for
SMCD with a Bayesian readout its two parts' settings, and for a combination its members by name. :func:`build_strategy` turns it back into a strategy,
:func:`describe_settings` into a few words for a table.

Example:
    >>> build_strategy("smcd", {"num_particles": 50, "noise_std": 0.1, "seed": 3}).num_particles
    50
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch

from smcd_rl.adaptation import SMCD, Adaptation, GradientDescent, NoAdaptation
from smcd_rl.combination import Combination
from smcd_rl.last_layer import BayesianLastLayer
from smcd_rl.smcd_last_layer import SMCDLastLayer

__all__ = ["KINDS", "build_strategy", "describe_settings", "on_device", "with_generators"]

#: The strategies :func:`smcd_rl.tune` knows, in the order it tunes them (SMCD with a Bayesian
#: readout starts from the tuned SMCD and last layer; a combination needs the others).
KINDS = ("none", "gradient_descent", "smcd", "last_layer", "smcd_last_layer", "combination")


def build_strategy(kind: str, settings: dict[str, Any]) -> Adaptation:
    """A fresh strategy of ``kind`` (one of :data:`KINDS`) with a candidate's ``settings``.

    SMCD's ``seed`` becomes its generator, so the strategy repeats the tuned run's filter.

    Example:
        >>> build_strategy("gradient_descent", {"lr": 0.1, "steps": 2, "window": 5}).config()["lr"]
        0.1
    """
    if kind not in KINDS:
        raise ValueError(f"unknown strategy kind {kind!r}; choose one of {list(KINDS)}")
    builders: dict[str, Callable[..., Adaptation]] = {
        "none": NoAdaptation,
        "gradient_descent": GradientDescent,
        "smcd": _smcd,
        "last_layer": BayesianLastLayer,
        "smcd_last_layer": _smcd_last_layer,
        "combination": _combination,
    }
    return builders[kind](**settings)


def _smcd(seed: int = 0, device: str = "cpu", **settings: Any) -> SMCD:
    kind = torch.device(device).type
    if kind != "cpu" and not getattr(torch, kind).is_available():
        raise ValueError(
            f"this SMCD was tuned on {device}, which this machine does not have; rebuild it for the model's "
            f"device, e.g. result.strategy('smcd', device='cpu')"
        )
    return SMCD(**settings, generator=torch.Generator(device=device).manual_seed(seed))


def _smcd_last_layer(smcd: dict[str, Any], last_layer: dict[str, Any]) -> SMCDLastLayer:
    return SMCDLastLayer(_smcd(**smcd), BayesianLastLayer(**last_layer))


def on_device(kind: str, settings: dict[str, Any], device: str) -> dict[str, Any]:
    """``settings`` with every SMCD's generator on ``device`` (a combination's members too)."""
    return with_generators(kind, settings, device=device)


def with_generators(kind: str, settings: dict[str, Any], **generator: Any) -> dict[str, Any]:
    """``settings`` with every SMCD's generator settings (``seed``, ``device``) replaced by ``generator``:
    SMCD's own, the filter's of SMCD with a Bayesian readout, and a combination's members'.

    Example:
        >>> with_generators("smcd_last_layer", {"smcd": {"seed": 0}, "last_layer": {}}, seed=3)["smcd"]
        {'seed': 3}
    """
    if kind == "smcd":
        return {**settings, **generator}
    if kind == "smcd_last_layer":
        return {**settings, "smcd": with_generators("smcd", settings["smcd"], **generator)}
    if kind == "combination":
        members = [
            {**m, "settings": with_generators(m["name"], m["settings"], **generator)} for m in settings["members"]
        ]
        return {**settings, "members": members}
    return settings


def _combination(members: list[dict[str, Any]], eta: float, share: float) -> Combination:
    return Combination([build_strategy(m["name"], m["settings"]) for m in members], eta=eta, share=share)


def describe_settings(settings: dict[str, Any]) -> str:
    """A candidate's settings in a few words, as :meth:`TuneResult.table` shows them.

    What :func:`tune` searches is always shown (SMCD's particles, flip probability and noise;
    gradient descent's learning rate, steps and window); any other setting only where it differs
    from its default, so a row says what was chosen, not the strategy's whole config.

    Example:
        >>> describe_settings({"lr": 0.1, "steps": 5, "window": 10, "loss": "mse", "huber_delta": 1.0})
        'lr 0.1, steps 5, window 10'
        >>> describe_settings({**SMCD(num_particles=500, noise_std=[0.0134, 0.01325]).config(), "seed": 3})
        'num_particles 500, flip_prob 0.01, noise_std [0.0134, 0.0132]'
        >>> describe_settings(BayesianLastLayer(prior_scale=0.3, drift=0.01).config())
        'prior_scale 0.3, noise_std 0.1, drift 0.01, likelihood gaussian'
    """
    if "members" in settings:
        return f"{' + '.join(m['name'] for m in settings['members'])}, eta {settings['eta']:g}, share {settings['share']:g}"
    if "last_layer" in settings:
        return f"{describe_settings(settings['smcd'])}; readout {describe_settings(settings['last_layer'])}"
    kind = "smcd" if "num_particles" in settings else "last_layer" if "prior_scale" in settings else "gradient_descent"
    searched, defaults = _SEARCHED[kind], _DEFAULTS[kind]
    shown = {
        k: v
        for k, v in settings.items()
        if k not in ("seed", "device") and (k in searched or defaults.get(k, _UNSET) != v)
    }
    if shown.get("loss", "mse") == "mse":  # the squared error's Huber delta is unused
        shown.pop("huber_delta", None)
    parts = []
    for k, v in shown.items():
        if isinstance(v, (list, tuple)) and len(v) > 3:
            v = f"rms {math.sqrt(sum(float(u) ** 2 for u in v) / len(v)):.3g} ({len(v)} dims)"
        elif isinstance(v, (list, tuple)):
            v = "[" + ", ".join(f"{float(u):.3g}" for u in v) + "]"
        parts.append(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}")
    return ", ".join(parts) or "-"


#: What :func:`smcd_rl.tune` searches of each kind: :func:`describe_settings` always shows it.
_SEARCHED = {
    "smcd": ("num_particles", "flip_prob", "noise_std"),
    "gradient_descent": ("lr", "steps", "window"),
    "last_layer": ("prior_scale", "noise_std", "drift", "likelihood"),
}
#: Each kind's default settings: :func:`describe_settings` leaves out what equals them.
_DEFAULTS: dict[str, dict[str, Any]] = {
    "smcd": SMCD().config(),
    "gradient_descent": GradientDescent().config(),
    "last_layer": BayesianLastLayer().config(),
}
_UNSET = object()
