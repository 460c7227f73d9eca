"""A method's strategy and time from its network's tuning: ``"M+G"`` is ``G`` of the tuned network ``M``.

Example:
    >>> method_variant("M+S(paper)")
    ('M', 'S(paper)')
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import torch

import smcd_rl

if TYPE_CHECKING:
    from smcd_rl.experiments.shared.tuning import Tuning

__all__ = ["method_variant", "tuned_variants", "strategy_for", "ms_column"]


def method_variant(name: str) -> tuple[str, str]:
    """``"M+S(paper)"`` -> ``("M", "S(paper)")``."""
    model, _, variant = name.partition("+")
    return model, variant


def tuned_variants(network: str, methods: Sequence[str]) -> list[str]:
    """The variants of ``network``'s methods among ``methods`` that need its tuning (``N`` needs none).

    Example:
        >>> tuned_variants("T", ["M+S", "T+N", "T+G", "true"]), tuned_variants("R", ["R+N"])
        (['G'], [])
    """
    return [method_variant(m)[1] for m in methods if m.startswith(network + "+") and not m.endswith("+N")]


def strategy_for(
    name: str, tunings: Mapping[str, Tuning], *, seed: int, device: torch.device | str = "cpu"
) -> smcd_rl.Adaptation:
    """The strategy of method ``name`` (``"M+G"``, ``"R+S(paper)"``...) from its network's tuning.

    ``N`` needs none (an experiment runs no tuning when only unadapted methods run).
    """
    network, variant = method_variant(name)
    if variant == "N":
        return smcd_rl.NoAdaptation()
    if network not in tunings:
        raise ValueError(f"{name} adapts with tuned settings, but {network} was not tuned")
    return tunings[network].strategy(variant, seed=seed, device=device)


def ms_column(methods: Sequence[str], tunings: Mapping[str, Tuning]) -> dict[str, float]:
    """Method name -> its median ms per observation, for the methods whose network was tuned."""
    found = {}
    for name in methods:
        network, variant = method_variant(name)
        if network in tunings and variant in tunings[network].ms:
            found[name] = tunings[network].ms[variant]
    return found
