"""The config of ``smcd-rl two-link`` (:mod:`smcd_rl.experiments.two_link.run`): its settings, ``--full`` preset and methods.

Example:
    >>> TwoLinkConfig().burn_in, FULL["tasks"], "R+S" in DEFAULT_METHODS, "R+S" in FULL["methods"]
    ((1, 5, 10), 1000, False, True)
    >>> [m for m in DEFAULT_METHODS if m.startswith("T+")]
    ['T+N', 'T+G', 'T+S', 'T+L', 'T+SL']
"""

from __future__ import annotations

from dataclasses import dataclass

from smcd_rl.experiments.shared.adaptation_config import TASK_VARIANTS, VARIANTS
from smcd_rl.experiments.shared.config import setting
from smcd_rl.experiments.shared.two_link_family_config import FAMILY_FULL, TwoLinkFamilyConfig

__all__ = ["TwoLinkConfig", "FULL", "METHODS", "DEFAULT_METHODS", "REPTILE_METHODS"]

#: Method labels that this command runs: Fig. 2's, with S SMCD tuned by look-ahead error, S(evidence)
#: SMCD calibrated by its evidence, S(paper) SMCD at the paper's settings, C the combination, L the
#: Bayesian last layer and SL SMCD with a Bayesian readout, and the network T trained for mask
#: adaptation (``fit(mask_training="task")``).
METHODS = (
    "O+P",
    *(f"{network}+{variant}" for network in ("M", "R") for variant in VARIANTS),
    *(f"T+{variant}" for variant in TASK_VARIANTS),
    "LV+N",
)
#: The Reptile network's methods (``--full`` runs them; R+S(paper) only on request).
REPTILE_METHODS = ("R+N", "R+G", "R+S", "R+S(evidence)", "R+C", "R+L", "R+SL")
#: What runs by default: the multi-task network's methods, the baselines, the task-trained network's
#: methods (SMCD with a Bayesian readout on T too) and Reptile's gradient descent (the method T+S
#: is to be compared with). Reptile's other methods run with ``--full`` or on request
#: (``--methods ... R+N R+S``).
DEFAULT_METHODS = (
    "O+P",
    "M+N",
    "M+G",
    "M+S",
    "M+S(evidence)",
    "M+S(paper)",
    "M+C",
    "M+L",
    "M+SL",
    "R+G",
    "T+N",
    "T+G",
    "T+S",
    "T+L",
    "T+SL",
    "LV+N",
)


@dataclass
class TwoLinkConfig(TwoLinkFamilyConfig):
    """Settings of ``smcd-rl two-link``; the defaults are the quick start's main job (minutes on 2 CPU cores)."""

    out: str = setting("runs/two-link", "output directory (results, plot, report, trained models)")
    trials: int = setting(200, "held-out arms to evaluate on", low=2)
    chunk: int = setting(100, "trials evaluated at once (bounds memory: chunk x particles x hidden)", low=1)
    # T = 20 (the paper's longest) doubles the filtering time of every method and of the tuning
    # episodes: --burn-in 1 5 10 20 adds it; the default keeps the quick start within minutes.
    burn_in: tuple[int, ...] = setting((1, 5, 10), "burn-in (adaptation) steps T", low=1)
    horizons: tuple[int, ...] = setting((1, 5, 10, 20), "look-ahead horizons H", low=1)
    methods: tuple[str, ...] = setting(
        DEFAULT_METHODS,
        "methods to run: O+P (oracle PF); M (multi-task) or R (Reptile) + N, G (tuned GD), S (SMCD tuned by "
        "the tuning criterion), S(evidence) (SMCD calibrated by its evidence), S(paper), C (combination of the "
        "tuned ones), L (Bayesian last layer) or SL (SMCD with a Bayesian readout); T (masks trained to "
        "identify the arm) + N, G, S, L or SL; LV+N (VRNN)",
        choices=METHODS,
    )
    # The table scores look-ahead errors: every method is tuned by its 10-step look-ahead error,
    # so the tuning arms babble max(burn_in) + tuning_horizon steps; half as many arms as the
    # other commands' 32 keep the tuning's cost (episodes x steps) as it was.
    tuning_horizon: int = setting(
        10,
        "look-ahead H every method is tuned by (open loop after each step of the tuning episodes; 1: one-step)",
        low=1,
    )
    tuning_episodes: int = setting(
        16, "held-out babbling episodes of fresh training-distribution arms every method is tuned on", low=2
    )
    tuning_options: bool = setting(
        False,
        "also trace the calibrated SMCD with 5x particles, the predictive mean and a Student-t likelihood on "
        "the tuning episodes (diagnosis only; adds about a minute per network)",
    )
    lv_epochs: int = setting(20, "training epochs of the latent-variable (VRNN) model", low=1)
    lv_width: int = setting(128, "width of the VRNN's layers (its recurrent state h has 8 dims)", low=1)
    lv_batch_size: int = setting(256, "VRNN batch size (two-step windows)", low=1)
    lv_lr: float = setting(1e-3, "VRNN Adam learning rate", above=0.0)
    full: bool = setting(
        False,
        "the paper's scale: 1000 tasks x 150 episodes, hidden 1024, 1000 trials, the Reptile network's methods "
        "(Reptile 1000 and LV 200 epochs), T = 20 and the tuning options",
    )

    NON_EMPTY = ("burn_in", "horizons", "methods")
    SELECTION = ("methods",)  # each method's errors are its own: a rerun with more methods reuses the others


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    **FAMILY_FULL,
    "trials": 1000,
    "chunk": 25,
    "burn_in": (1, 5, 10, 20),
    "methods": tuple(dict.fromkeys((*DEFAULT_METHODS[:-1], *REPTILE_METHODS, DEFAULT_METHODS[-1]))),
    "tuning_options": True,
    "lv_epochs": 200,
    "lv_batch_size": 64,
}
