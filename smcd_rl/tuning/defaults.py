"""Every default of the tuning in one table: the kinds and their order, each kind's grid, the flip
probabilities, the race, and which kinds a strategy built from others needs.

:func:`smcd_rl.tune`, :func:`smcd_rl.calibrate` and the experiments read them from here.

Example:
    >>> from smcd_rl.tuning.defaults import GD_GRID, kinds_needed
    >>> kinds_needed(["combination"])  # a combination mixes no adaptation, gradient descent and SMCD
    ['none', 'gradient_descent', 'smcd', 'combination']
    >>> kinds_needed(["smcd_last_layer"])
    ['smcd', 'last_layer', 'smcd_last_layer']
    >>> {**GD_GRID, "loss": ("huber",)}  # a gd_grid for smcd_rl.tune that tries the Huber loss only
    {'lr': (0.001, 0.01, 0.1), 'steps': (1, 5), 'window': (1, 10), 'loss': ('huber',)}
    >>> [form for form, _ in ROBUST_FORMS["gradient_descent"]]  # the strongest protection first
    ["Tukey's biweight loss", 'Huber loss']
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    "KINDS",
    "ADAPTING",
    "MASKED_KINDS",
    "NEEDS",
    "kinds_needed",
    "GD_GRID",
    "ROBUST_SCALE_FACTOR",
    "ROBUST_FORMS",
    "MAX_EXTENSIONS",
    "EXTENSIBLE",
    "COMBINATION_GRID",
    "LAST_LAYER_GRID",
    "SMCD_LAST_LAYER_SCALES",
    "SMCD_LAST_LAYER_QUIET_SHARE",
    "FLIP_PROBS",
    "PREDICTIONS",
    "WEIGHINGS",
    "CALIBRATION_REFINE",
    "SEARCH_PARTICLE_SHARE",
    "FINALISTS",
    "SMCD_LAST_LAYER_FINALISTS",
    "MIN_SEARCH_PARTICLES",
    "MIN_PARTICLES",
    "RACE_SHARE",
    "RACE_MARGIN",
    "ROBUST_MARGIN",
    "SEARCHED",
]

#: The strategies :func:`smcd_rl.tune` knows (names of :data:`smcd_rl.strategies.registry.REGISTRY`),
#: in the order it tunes them: SMCD with a Bayesian readout starts from the tuned SMCD and last
#: layer; a combination mixes the others.
KINDS = ("none", "gradient_descent", "smcd", "last_layer", "smcd_last_layer", "combination")
#: The kinds that filter over dropout masks: a network without dropout runs none of them.
MASKED_KINDS = ("smcd", "smcd_last_layer")
#: The kinds that adapt: what a combination mixes, with no adaptation.
ADAPTING = ("gradient_descent", "smcd", "last_layer", "smcd_last_layer")
#: What each kind built from others tunes first: a combination mixes no adaptation, gradient
#: descent and SMCD (and every other kind that adapts and was tuned); SMCD with a Bayesian readout
#: starts from the tuned SMCD and last layer.
NEEDS: dict[str, tuple[str, ...]] = {
    "combination": ("none", "gradient_descent", "smcd"),
    "smcd_last_layer": ("smcd", "last_layer"),
}


def kinds_needed(strategies: Iterable[str]) -> list[str]:
    """The kinds :func:`smcd_rl.tune` runs for ``strategies``: each one asked for and what it is built
    from (:data:`NEEDS`), in :data:`KINDS`' order."""
    needed = set(strategies)
    for kind in KINDS[::-1]:  # a kind needs only kinds before it
        if kind in needed:
            needed |= set(NEEDS.get(kind, ()))
    return [kind for kind in KINDS if kind in needed]


#: Gradient descent's starting grid: learning rate x steps per observation x window x loss
#: (:class:`smcd_rl.GradientDescent`'s ``loss``; this dimension is never extended).
GD_GRID: dict[str, tuple[Any, ...]] = {
    "lr": (1e-3, 1e-2, 1e-1),
    "steps": (1, 5),
    "window": (1, 10),
    "loss": ("mse", "huber", "tukey"),
}
#: Gradient descent's robust losses are tuned at this multiple of the unadapted network's
#: root-mean-square residual on the episodes (normalised units): where the Huber loss turns linear,
#: and Tukey's biweight is flat beyond ``TUKEY_CUT`` (4.685) times it. A reading far beyond what the
#: network gets wrong across training tasks is then a corrupted one.
ROBUST_SCALE_FACTOR = 1.0
#: At most this many extensions past each edge of the GD grid (and the last layer's prior scale).
MAX_EXTENSIONS = 3
#: The dimensions of the GD grid that extend past their edges.
EXTENSIBLE = ("lr", "steps", "window")
#: The combination's grid: the weights' learning rate and the fixed share.
COMBINATION_GRID: dict[str, tuple[float, ...]] = {"eta": (0.1, 1.0, 10.0, 100.0), "share": (0.0, 0.02)}
#: The Bayesian last layer's grid: prior scale x drift x likelihood; a robust form (Tukey's
#: biweight; Student-t where named) also tries its noise at these multiples of the unadapted
#: network's residual, since its down-weighting of a reading depends on it (the Gaussian form's
#: posterior mean does not: it takes the residual itself, for its predictive variance). Tukey's
#: biweight at one residual ignores a reading more than 4.685 residuals off. The prior scale
#: extends past an edge as gradient descent's learning rate does.
LAST_LAYER_GRID: dict[str, tuple[Any, ...]] = {
    "prior_scale": (0.1, 0.3, 1.0, 3.0),
    "drift": (0.0, 0.01),
    "likelihood": ("gaussian", "tukey"),
    "noise_factor": (1.0,),
}
#: SMCD with a Bayesian readout: the tuned last layer's prior scale times each of these (and a
#: third of the smallest, while the best is there). A tight readout leaves the masks to explain the
#: task (SL is then SMCD); a wide one lets each particle's readout take a shift no mask expresses.
#: Where the quiet scale (:data:`SMCD_LAST_LAYER_QUIET_SHARE`) lies below the smallest, the grid's
#: low end moves down to it, its steps geometric, as many as here.
SMCD_LAST_LAYER_SCALES = (1.0, 1 / 100, 1 / 30, 1 / 10, 1 / 3, 3.0)
#: The quiet readout scale: the prior scale at which the readout's predictive variance at the
#: network's typical features is this share of the filter's noise variance, where SL weighs the
#: masks as SMCD does. A network with large features makes even a hundredth of the last layer's
#: scale swamp the filter's likelihood, so SL's grid must reach down to SMCD.
SMCD_LAST_LAYER_QUIET_SHARE = 0.1
#: With tune's shortcuts, SMCD with a Bayesian readout confirms at most this many scales at full size.
SMCD_LAST_LAYER_FINALISTS = 2
#: The flip probabilities SMCD's calibration tries.
FLIP_PROBS = (0.001, 0.003, 0.01, 0.03)
#: How SMCD may predict, what :func:`smcd_rl.tune` tries at its best setting: with the MMSE mask's
#: prediction, and with the posterior predictive mean (one forward pass per particle at every
#: prediction). A planner that scores many candidates per step pays that for each: pass
#: ``predictions=("mask",)`` there.
PREDICTIONS = ("mask", "predictive")
#: How SMCD with a Bayesian readout may weigh its particles, what :func:`smcd_rl.tune` tries at its
#: best setting (:data:`smcd_rl.strategies.smcd_last_layer.WEIGHINGS`): by the readout's
#: predictive, and by each particle's readout mean under the filter's noise alone. A copy: this
#: module imports nothing, so ``--help`` never loads torch (a test keeps the two equal).
WEIGHINGS = ("predictive", "mean")
#: Golden-section runs at the end of SMCD's calibration (:func:`smcd_rl.calibrate`'s ``refine``).
CALIBRATION_REFINE = 5
#: With tune's shortcuts, SMCD's calibration searches with this share of the particles, then
#: confirms its best :data:`FINALISTS` settings at full size (at least :data:`MIN_SEARCH_PARTICLES`
#: particles in the search, else it searches at full size).
SEARCH_PARTICLE_SHARE = 0.25
#: ... the settings confirmed at full size.
FINALISTS = 5
#: ... the fewest particles a reduced search runs with.
MIN_SEARCH_PARTICLES = 64
#: SMCD never halves its particles below this to meet a budget.
MIN_PARTICLES = 8
#: The share of the episodes a raced setting runs on first (at least 2 episodes).
RACE_SHARE = 0.25
#: A raced setting runs on only if its score on the first episodes is at most ``1 + RACE_MARGIN``
#: times the best's there: 10 % is well beyond the spread of two settings that tie on all episodes
#: (paired, on the same episodes), and far below what a learning rate or step count off by a grid
#: step costs.
RACE_MARGIN = 0.1
#: A robust form (:data:`ROBUST_FORMS`) is kept where its score on the tuning
#: episodes is within this share of the plain form's, or within their paired noise: clean
#: episodes cannot show what it is for, a corrupted reading (:meth:`~smcd_rl.tuning.search.Search.prefer_robust`).
ROBUST_MARGIN = 0.05
#: Each kind's robust forms, the strongest protection against one corrupted reading first: Tukey's
#: biweight ignores a reading far off, a Huber loss bounds its pull (which still adds up over
#: gradient steps), a Student-t likelihood down-weights it (SMCD: its heavy tails keep the particles
#: from collapsing onto the masks that explain the reading; the last layer: against the predictive
#: variance, which a wide prior makes large). Each is a name and which settings have that form.
ROBUST_FORMS: dict[str, tuple[tuple[str, Callable[[dict[str, Any]], bool]], ...]] = {
    "gradient_descent": (
        ("Tukey's biweight loss", lambda s: s.get("loss") == "tukey"),
        ("Huber loss", lambda s: s.get("loss") == "huber"),
    ),
    "smcd": (("Student-t likelihood", lambda s: s.get("likelihood") == "student-t"),),
    "last_layer": (
        ("Tukey's biweight", lambda s: s.get("likelihood") == "tukey"),
        ("Student-t likelihood", lambda s: s.get("likelihood") == "student-t"),
    ),
}
#: What :func:`smcd_rl.tune` searches of each kind: a tuning table always shows it.
SEARCHED: dict[str, tuple[str, ...]] = {
    "smcd": ("num_particles", "flip_prob", "noise_std"),
    "gradient_descent": ("lr", "steps", "window"),
    "last_layer": ("prior_scale", "noise_std", "drift", "likelihood"),
}
