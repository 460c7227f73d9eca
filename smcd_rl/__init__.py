"""smcd-rl: Sequential Monte Carlo Dropout for online adaptation of frozen neural models.

A network trained with dropout is an ensemble of sub-networks, one per dropout mask. At run time
:class:`SMCDFilter` keeps a particle filter over masks, updated from each real observation, and
:class:`AdaptiveModel` predicts with the adapted (MMSE) mask. Importing the package registers the
gymnasium tasks ``smcd_rl/...``.

Example:
    >>> import smcd_rl
    >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(64, 64), dropout=0.5)
    >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee", adaptation=smcd_rl.SMCD(num_particles=100))
"""

from __future__ import annotations

from smcd_rl.adaptation import SMCD, Adaptation, GradientDescent, NoAdaptation, make_adaptation
from smcd_rl.calibration import Calibration, calibrate
from smcd_rl.envs import register_all as _register_envs
from smcd_rl.files import FileWriteError, UnreadableFileError
from smcd_rl.filter import ParticleFilter, SMCDFilter
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel, CheckpointMismatchError, UnfittedModelWarning, load
from smcd_rl.training import fit, fit_dynamics, fit_reptile

_register_envs()

__version__ = "0.1.0"

__all__ = [
    "MaskedMLP",
    "SMCDFilter",
    "ParticleFilter",
    "Adaptation",
    "SMCD",
    "GradientDescent",
    "NoAdaptation",
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
    "load",
    "calibrate",
    "Calibration",
]
