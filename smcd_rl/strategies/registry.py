"""The one registry of strategies: a name or stored settings become a strategy here, and only here.

Every strategy smcd_rl knows is one row of :data:`REGISTRY`, as Gymnasium's ``register`` calls
name an environment's entry point: the name a config file, a checkpoint, :func:`smcd_rl.tune`'s
record or an experiment's letter uses, and the class it builds. A strategy is stored in one
format everywhere: its **settings**, the class's :meth:`~smcd_rl.Adaptation.settings` (its
constructor arguments, plus the seed and device of an SMCD's random generator where it was built
from one), and a **spec** ``{"name": ..., "settings": ...}`` where the name must travel with
them (a checkpoint's strategy, a combination's members).

Example:
    >>> from smcd_rl.strategies import registry
    >>> smcd = registry.build("smcd", {"num_particles": 50, "noise_std": 0.1, "seed": 3})
    >>> smcd.num_particles, registry.spec(smcd)["settings"]["seed"]
    (50, 3)
    >>> registry.from_spec(registry.spec(smcd)).config() == smcd.config()
    True
    >>> registry.make_adaptation("gd", lr=0.1)
    GradientDescent(lr=0.1, steps=1, window=10, loss='mse', huber_delta=1.0)
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable, Mapping
from typing import Any

from smcd_rl.strategies.base import Adaptation

__all__ = [
    "REGISTRY",
    "ALIASES",
    "strategy_class",
    "make_adaptation",
    "build",
    "spec",
    "from_spec",
    "with_generators",
    "on_device",
    "settings_of",
]

#: Every strategy by name: the module and class that implement it (imported on first use, so
#: that a strategy built from others, such as a combination, can build its members here).
REGISTRY: dict[str, str] = {
    "none": "smcd_rl.strategies.none:NoAdaptation",
    "gradient_descent": "smcd_rl.strategies.gradient_descent:GradientDescent",
    "smcd": "smcd_rl.strategies.smcd:SMCD",
    "last_layer": "smcd_rl.strategies.last_layer:BayesianLastLayer",
    "smcd_last_layer": "smcd_rl.strategies.smcd_last_layer:SMCDLastLayer",
    "combination": "smcd_rl.strategies.combination:Combination",
}
#: Other names a user may write for a strategy.
ALIASES = {"gd": "gradient_descent"}


def strategy_class(name: str) -> type[Adaptation]:
    """The class registered as ``name`` (or one of :data:`ALIASES`).

    Raises:
        ValueError: no strategy has that name.
    """
    key = ALIASES.get(name, name) if isinstance(name, str) else name
    if key not in REGISTRY:
        raise ValueError(f"unknown adaptation {name!r}; choose one of {sorted(REGISTRY)} (or 'gd')")
    module, cls = REGISTRY[key].split(":")
    found: type[Adaptation] = getattr(importlib.import_module(module), cls)
    return found


def make_adaptation(name: str, **arguments: Any) -> Adaptation:
    """A strategy from its name (or an alias such as ``"gd"``) and constructor arguments (a ``generator`` object, say).

    Example:
        >>> make_adaptation("smcd", num_particles=10).num_particles
        10
    """
    return strategy_class(name)(**arguments)


def build(name: str, settings: Mapping[str, Any]) -> Adaptation:
    """A fresh strategy from its stored settings (see the module doc): the class's ``from_settings``."""
    if not isinstance(settings, Mapping):
        raise TypeError(f"the settings of a {name!r} strategy must be a dict, got {type(settings).__name__}")
    cls = strategy_class(name)
    try:
        return cls.from_settings(settings)
    except TypeError as err:
        if "unexpected keyword argument" not in str(err):
            raise
        known = [p for p in inspect.signature(cls).parameters if p not in ("args", "kwargs")]
        if "generator" in known:  # stored as the generator's seed and device
            known[known.index("generator") : known.index("generator") + 1] = ["seed", "device"]
        raise TypeError(f"{err}; the settings of a {name!r} strategy are {known}") from err


def spec(strategy: Adaptation) -> dict[str, Any]:
    """``{"name": ..., "settings": ...}``: what :func:`from_spec` rebuilds ``strategy`` from (unadapted)."""
    return {"name": strategy.name, "settings": strategy.settings()}


def from_spec(record: Mapping[str, Any]) -> Adaptation:
    """A strategy from a :func:`spec` record (older files call the settings ``"config"``).

    Raises:
        ValueError: the record names no strategy or holds no settings.
    """
    if not isinstance(record, Mapping) or not isinstance(record.get("name"), str):
        raise ValueError(f"a strategy spec is a dict {{'name': ..., 'settings': {{...}}}}, got {record!r}")
    return build(record["name"], settings_of(record))


def with_generators(name: str, settings: Mapping[str, Any], **generator: Any) -> dict[str, Any]:
    """``settings`` with every SMCD's generator settings (``seed``, ``device``) replaced by ``generator``:
    SMCD's own, the filter's of SMCD with a Bayesian readout, and a combination's members'.

    Example:
        >>> with_generators("smcd_last_layer", {"smcd": {"seed": 0}, "last_layer": {}}, seed=3)["smcd"]
        {'seed': 3}
    """
    return _each_smcd(name, settings, lambda smcd: {**smcd, **generator})


def on_device(name: str, settings: Mapping[str, Any], device: str) -> dict[str, Any]:
    """``settings`` with every SMCD generator they store on ``device`` (an SMCD stored without one keeps none).

    Example:
        >>> on_device("smcd", {"num_particles": 10, "seed": 3, "device": "cuda"}, "cpu")["device"]
        'cpu'
    """
    return _each_smcd(name, settings, lambda smcd: {**smcd, "device": device} if "seed" in smcd else dict(smcd))


def _each_smcd(
    name: str, settings: Mapping[str, Any], change: Callable[[Mapping[str, Any]], dict[str, Any]]
) -> dict[str, Any]:
    """``settings`` with ``change`` applied to the settings of every SMCD in them."""
    name = ALIASES.get(name, name)
    if name == "smcd":
        return dict(change(settings))
    if name == "smcd_last_layer":
        return {**settings, "smcd": _each_smcd("smcd", settings["smcd"], change)}
    if name == "combination":
        members = [
            {"name": m["name"], "settings": _each_smcd(m["name"], settings_of(m), change)} for m in settings["members"]
        ]
        return {**settings, "members": members}
    return dict(settings)


def settings_of(member: Mapping[str, Any]) -> Mapping[str, Any]:
    """A spec's settings (older records call them ``"config"``)."""
    return member["settings"] if "settings" in member else member.get("config", {})
