"""Tuning: every strategy's settings chosen on held-out training-task episodes, by one criterion.

One module per concept:

* :mod:`~smcd_rl.tuning.protocol`: :func:`tune`, the fair protocol as one call;
* :mod:`~smcd_rl.tuning.calibration`: :func:`calibrate`, SMCD's noise and flip probability;
* :mod:`~smcd_rl.tuning.criteria`: what a setting is scored by (one-step, look-ahead, your own);
* :mod:`~smcd_rl.tuning.held_out`: the episodes as every tuning function takes them, checked once;
* :mod:`~smcd_rl.tuning.episode_windows`: :func:`episodes`, fixed-length episodes cut from collected transitions;
* :mod:`~smcd_rl.tuning.diagnostics`: a strategy's run over the episodes, step by step;
* :mod:`~smcd_rl.tuning.scoring`: the runs and scores :func:`tune` and :func:`calibrate` share;
* :mod:`~smcd_rl.tuning.search`: the candidates, their runs and times, and the race;
* :mod:`~smcd_rl.tuning.kinds`: how each kind of strategy is searched;
* :mod:`~smcd_rl.tuning.defaults`: every grid and default in one table;
* :mod:`~smcd_rl.tuning.result`: :class:`TuneResult`, what was chosen and from what;
* :mod:`~smcd_rl.tuning.advice`: what to use, in the result's closing lines.

Example:
    >>> import smcd_rl
    >>> result = smcd_rl.tune(model, episodes)  # doctest: +SKIP
    >>> adaptive = model.with_adaptation(result.best)  # doctest: +SKIP
    >>> smcd_rl.calibrate(model, episodes, criterion="lookahead", horizon=10)  # doctest: +SKIP
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from smcd_rl.tuning.calibration import Calibration, Candidate, calibrate, evidence
    from smcd_rl.tuning.defaults import (
        COMBINATION_GRID,
        EXTENSIBLE,
        FLIP_PROBS,
        GD_GRID,
        KINDS,
        LAST_LAYER_GRID,
        MAX_EXTENSIONS,
        MIN_PARTICLES,
    )
    from smcd_rl.tuning.episode_windows import episodes
    from smcd_rl.tuning.protocol import ms_per_observation, tune
    from smcd_rl.tuning.result import TuneResult, describe_settings
    from smcd_rl.tuning.search import TuneCandidate

#: Where each name is defined. The package imports them on first use, so that a torch-free module
#: (an experiment's config) can read :mod:`smcd_rl.tuning.defaults` without importing torch.
_SOURCES: dict[str, str] = {
    **dict.fromkeys(["Calibration", "Candidate", "calibrate", "evidence"], "calibration"),
    **dict.fromkeys(
        [
            "COMBINATION_GRID",
            "EXTENSIBLE",
            "FLIP_PROBS",
            "GD_GRID",
            "KINDS",
            "LAST_LAYER_GRID",
            "MAX_EXTENSIONS",
            "MIN_PARTICLES",
        ],
        "defaults",
    ),
    "episodes": "episode_windows",
    **dict.fromkeys(["ms_per_observation", "tune"], "protocol"),
    **dict.fromkeys(["TuneResult", "describe_settings"], "result"),
    "TuneCandidate": "search",
}

__all__ = [
    "tune",
    "TuneResult",
    "TuneCandidate",
    "calibrate",
    "Calibration",
    "Candidate",
    "evidence",
    "episodes",
    "ms_per_observation",
    "describe_settings",
    "KINDS",
    "GD_GRID",
    "MAX_EXTENSIONS",
    "EXTENSIBLE",
    "COMBINATION_GRID",
    "LAST_LAYER_GRID",
    "MIN_PARTICLES",
    "FLIP_PROBS",
]


def _load(name: str) -> Any:
    if name not in _SOURCES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_SOURCES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if not TYPE_CHECKING:
    __getattr__ = _load
