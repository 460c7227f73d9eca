"""The stage plan of ``smcd-rl two-link``: each stage's expected cost, for the progress line's time left.

Example:
    >>> from smcd_rl.experiments.two_link.config import TwoLinkConfig
    >>> costs = stage_costs(TwoLinkConfig())
    >>> costs["tune M"] > costs["tune T"] > 0
    True
"""

from __future__ import annotations

from smcd_rl.experiments.shared.tuned_methods import tuned_variants
from smcd_rl.experiments.two_link.config import TwoLinkConfig

__all__ = ["stage_costs"]


#: Seconds of each stage at the defaults, each process on one thread beside another on a 2-core
#: Intel Xeon (two workers): the overall progress line scales these by the settings and by this
#: run's measured speed of each kind of stage to say how long is left, and the workers take the
#: costliest stages first, so that a long one does not start last and run alone.
_REFERENCE_SECONDS = {
    "train": 62.0,
    "train reptile": 64.0,
    "train task": 64.0,  # M's training and, from the second epoch, each arm's mask posterior
    "train latent": 71.0,
    # A network's tuning, at twice the default tuning episodes and burn-in (see the factor below).
    "tune G": 37.0,  # the raced grid of gradient descent and its extensions, on one network
    "tune S": 108.0,  # SMCD's calibration (the noise's factor, shape and flip), 1000 particles of 2 x 512
    "tune S grouped": 180.0,  # the same on the task-mask network, whose arm posteriors each forward samples
    "tune references": 125.0,  # S(evidence)'s calibration, S(paper)'s score and the diagnosis
    "tune L": 6.0,  # the last layer's raced grid
    "tune SL": 40.0,  # the readout's scales and weighings, each a run of the filter with the readout
    "evaluate G": 24.0,  # per method over 200 arms at T = 1, 5, 10
    "evaluate S": 15.0,
    "evaluate S grouped": 22.0,
    "evaluate S(evidence)": 24.0,  # broader posteriors: more distinct particles per step
    "evaluate S(paper)": 17.0,
    "evaluate L": 1.6,  # one forward and a readout update per observation
    "evaluate SL": 39.0,  # SMCD's filter with a readout per particle
    "evaluate SL grouped": 62.0,
    "evaluate C": 39.0,  # its members G and S, run again
    "evaluate C derived": 0.5,  # from its members' runs, where M+N, M+G and M+S run too
    "evaluate O+P": 0.4,
    "evaluate N": 0.1,
}


def stage_costs(config: TwoLinkConfig) -> dict[str, float]:
    """Each stage's expected relative cost at ``config``, in the order the stages run.

    Example:
        >>> costs = stage_costs(TwoLinkConfig())
        >>> list(costs)[:5], costs["evaluate M+S"] > costs["evaluate M+N"]
        (['train', 'train reptile', 'train task', 'train latent', 'tune M'], True)
    """
    ref = _REFERENCE_SECONDS
    data = config.tasks * config.episodes * config.steps / 100_000 * (config.hidden / 512) ** 2 * config.depth / 2
    filtering = config.trials / 200 * sum(config.burn_in) / 16
    particles = config.particles / 1000 * (config.hidden / 512) ** 2
    costs = {"train": ref["train"] * config.epochs / 20 * data}
    if any(m.startswith("R+") for m in config.methods):
        costs["train reptile"] = ref["train reptile"] * config.reptile_epochs / 20 * data
    if any(m.startswith("T+") for m in config.methods):
        costs["train task"] = ref["train task"] * config.epochs / 20 * data
    if "LV+N" in config.methods:
        costs["train latent"] = ref["train latent"] * config.lv_epochs / 20 * config.tasks * config.episodes / 10_000
    tuning = config.tuning_episodes / 32 * max(config.burn_in) / 10 * (2 if config.tuning_options else 1)
    for name in ("M", "R", "T"):
        variants = tuned_variants(name, config.methods)
        if not variants:
            continue
        smcd = "tune S grouped" if name == "T" else "tune S"
        cost = ref["tune G"] * (any(v in ("G", "C") for v in variants))
        cost += ref[smcd] * particles * (any(v in ("S", "C") for v in variants))
        cost += ref["tune references"] * particles * ("S(evidence)" in variants)
        cost += ref["tune L"] * (any(v in ("L", "SL") for v in variants))
        cost += ref["tune SL"] * particles * ("SL" in variants) * (0.3 if name == "T" else 1.0)
        costs[f"tune {name}"] = cost * tuning
    for name in config.methods:
        variant = "O+P" if name == "O+P" else "N" if name.endswith("+N") else name.split("+")[1]
        variant = variant if variant in ("O+P", "S(evidence)", "S(paper)", "SL") else variant[0]
        grouped = " grouped" if name in ("T+S", "T+SL") else ""
        if variant == "C" and all(name.replace("+C", f"+{v}") in config.methods for v in "NGS"):
            grouped = " derived"
        scale = {"O+P": config.oracle_particles / 1000, "S": particles}.get(variant[0], 1.0)
        costs[f"evaluate {name}"] = ref[f"evaluate {variant}{grouped}"] * filtering * scale
    return costs
