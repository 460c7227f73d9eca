"""Adaptation strategies: how a trained network responds to real observations, one module each.

* :mod:`~smcd_rl.strategies.base`: :class:`Adaptation`, the contract every strategy keeps;
* :mod:`~smcd_rl.strategies.none`: :class:`NoAdaptation`, the trained network as it is;
* :mod:`~smcd_rl.strategies.gradient_descent`: :class:`GradientDescent`, online SGD on recent
  transitions (its per-stream weights in :mod:`~smcd_rl.strategies.stream_weights`);
* :mod:`~smcd_rl.strategies.smcd`: :class:`SMCD`, the particle filter over dropout masks (its
  batched particle passes in :mod:`~smcd_rl.strategies.particle_forward`);
* :mod:`~smcd_rl.strategies.last_layer`: :class:`BayesianLastLayer`, exact Bayesian regression
  on the readout;
* :mod:`~smcd_rl.strategies.smcd_last_layer`: :class:`SMCDLastLayer`, the mask filter with a
  Bayesian readout;
* :mod:`~smcd_rl.strategies.combination`: :class:`Combination`, several strategies weighed by
  their errors;
* :mod:`~smcd_rl.strategies.registry`: the one table from names to strategies, and the one
  settings format every strategy is stored in.

Example:
    >>> from smcd_rl.strategies import make_adaptation
    >>> make_adaptation("smcd", num_particles=10)
    SMCD(num_particles=10, flip_prob=0.01, noise_std=0.05, resampling='systematic', ess_threshold=1.0, transition='keep_rate', forward_path='auto', prediction='mask', likelihood='gaussian', dof=4.0)
"""

from __future__ import annotations

from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.combination import Combination
from smcd_rl.strategies.gradient_descent import GradientDescent
from smcd_rl.strategies.last_layer import BayesianLastLayer
from smcd_rl.strategies.none import NoAdaptation
from smcd_rl.strategies.registry import make_adaptation
from smcd_rl.strategies.smcd import SMCD
from smcd_rl.strategies.smcd_last_layer import SMCDLastLayer

__all__ = [
    "Adaptation",
    "NoAdaptation",
    "GradientDescent",
    "SMCD",
    "BayesianLastLayer",
    "SMCDLastLayer",
    "Combination",
    "make_adaptation",
]
