"""smcd-rl: Sequential Monte Carlo Dropout for online adaptation of frozen neural models.

A network trained with dropout is an ensemble of sub-networks, one per dropout mask. At run time
:class:`SMCDFilter` keeps a particle filter over masks, updated from each real observation, and
:class:`AdaptiveModel` predicts with the adapted (MMSE) mask. Importing the package registers the
gymnasium tasks ``smcd_rl/...``.

The public names are loaded when first used (:pep:`562`): ``import smcd_rl`` itself imports
gymnasium but not torch or tensordict, so the ``smcd-rl`` command's ``--help`` starts at once;
the first use of ``smcd_rl.SMCD``, ``from smcd_rl import fit`` and the like imports what it needs.

Example:
    >>> import smcd_rl
    >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(64, 64), dropout=0.5)
    >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(num_particles=100))
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from typing import TYPE_CHECKING, Any

from smcd_rl.envs import register_all as _register_envs

if TYPE_CHECKING:
    from smcd_rl.allocator import keep_freed_memory
    from smcd_rl.feature_readout import FeatureReadout
    from smcd_rl.files import FileWriteError, UnreadableFileError
    from smcd_rl.filter import ParticleFilter, SMCDFilter
    from smcd_rl.masked_mlp import MaskedMLP
    from smcd_rl.model import (
        AdaptiveDynamicsModel,
        AdaptiveModel,
        CheckpointMismatchError,
        UnfittedModelWarning,
        load,
        save,
    )
    from smcd_rl.strategies import (
        SMCD,
        Adaptation,
        BayesianLastLayer,
        Combination,
        GradientDescent,
        NoAdaptation,
        SMCDLastLayer,
        make_adaptation,
    )
    from smcd_rl.training import fit, fit_dynamics, fit_reptile
    from smcd_rl.tuning import Calibration, TuneResult, calibrate, episodes, tune
    from smcd_rl.wrapping import adaptive_model_from, masked_mlp_from

_register_envs()

__version__ = "0.2.0"

__all__ = [
    "MaskedMLP",
    "FeatureReadout",
    "SMCDFilter",
    "ParticleFilter",
    "Adaptation",
    "SMCD",
    "GradientDescent",
    "NoAdaptation",
    "Combination",
    "BayesianLastLayer",
    "SMCDLastLayer",
    "make_adaptation",
    "AdaptiveModel",
    "AdaptiveDynamicsModel",
    "CheckpointMismatchError",
    "UnreadableFileError",
    "FileWriteError",
    "UnfittedModelWarning",
    "fit",
    "fit_dynamics",
    "fit_reptile",
    "save",
    "load",
    "calibrate",
    "Calibration",
    "episodes",
    "tune",
    "TuneResult",
    "keep_freed_memory",
    "masked_mlp_from",
    "adaptive_model_from",
]

#: Where each public name is defined: its module is imported on the name's first use.
_SOURCES: dict[str, str] = {
    **dict.fromkeys(
        [
            "SMCD",
            "Adaptation",
            "GradientDescent",
            "NoAdaptation",
            "Combination",
            "BayesianLastLayer",
            "SMCDLastLayer",
            "make_adaptation",
        ],
        "strategies",
    ),
    **dict.fromkeys(["Calibration", "calibrate", "episodes", "tune", "TuneResult"], "tuning"),
    "keep_freed_memory": "allocator",
    **dict.fromkeys(["FileWriteError", "UnreadableFileError"], "files"),
    **dict.fromkeys(["ParticleFilter", "SMCDFilter"], "filter"),
    "MaskedMLP": "masked_mlp",
    "FeatureReadout": "feature_readout",
    **dict.fromkeys(
        ["AdaptiveDynamicsModel", "AdaptiveModel", "CheckpointMismatchError", "UnfittedModelWarning", "load", "save"],
        "model",
    ),
    **dict.fromkeys(["fit", "fit_dynamics", "fit_reptile"], "training"),
    **dict.fromkeys(["masked_mlp_from", "adaptive_model_from"], "wrapping"),
}

#: Modules that moved into the ``strategies``, ``tuning`` and ``training`` packages: the old path
#: still imports, as the new module, with a DeprecationWarning (until the next release).
_MOVED: dict[str, str] = {
    "adaptation": "strategies",
    "combination": "strategies.combination",
    "last_layer": "strategies.last_layer",
    "smcd_last_layer": "strategies.smcd_last_layer",
    "stream_weights": "strategies.stream_weights",
    "particle_forward": "strategies.particle_forward",
    "strategy_specs": "strategies.registry",
    "calibration": "tuning.calibration",
    "criteria": "tuning.criteria",
    "diagnostics": "tuning.diagnostics",
    "held_out": "tuning.held_out",
    "scoring": "tuning.scoring",
    "tuning_advice": "tuning.advice",
    "tuning_kinds": "tuning.kinds",
    "tuning_search": "tuning.search",
    "episode_windows": "tuning.episode_windows",
    "task_masks": "training.task_masks",
    "script_options": "integrations.script_options",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``smcd_rl.<old>`` for a module of :data:`_MOVED` and gives the module at its new path."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        package, _, old = fullname.rpartition(".")
        if package != __name__ or old not in _MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> Any:
        new = f"{__name__}.{_MOVED[spec.name.rpartition('.')[2]]}"
        warnings.warn(f"{spec.name} moved to {new}; import it from there", DeprecationWarning, stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module: Any) -> None:
        pass  # the new module ran when it was imported


sys.meta_path.append(_MovedModules())


def _load(name: str) -> Any:
    """A public name, imported from its module on first use; or a submodule (``smcd_rl.model``), imported."""
    if name in _SOURCES:
        value = getattr(importlib.import_module(f"{__name__}.{_SOURCES[name]}"), name)
        globals()[name] = value  # later uses find it without this function
        return value
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")  # as when the package imported them all
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if not TYPE_CHECKING:  # for mypy the names are the imports above: a misspelt one stays an error, not Any
    __getattr__ = _load
