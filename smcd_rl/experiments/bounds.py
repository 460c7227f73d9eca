"""Upper bounds on experiment settings, which :func:`~smcd_rl.experiments.harness.setting` cannot declare.

``setting(low=, above=)`` bounds a value from below only, but probabilities are bounded from above
too (a dropout p below 1, a bit-flip probability at most 1). :func:`bounded` declares a config field
with both, and :func:`check_upper_bounds`, called from a config's ``validate()`` after
``super().validate()``, refuses a value above its bound with a message in the harness's style.
Both are meant to fold into the harness as ``setting(high=, below=)``.

Example:
    >>> from dataclasses import dataclass
    >>> from smcd_rl.experiments.harness import ExperimentConfig
    >>> @dataclass
    ... class C(ExperimentConfig):
    ...     dropout: float = bounded(0.5, "dropout probability", low=0.0, below=1.0)
    ...
    ...     def validate(self) -> None:
    ...         super().validate()
    ...         check_upper_bounds(self)
    >>> C(dropout=1.0).validate()
    Traceback (most recent call last):
    ...
    ValueError: --dropout must be < 1.0, got 1.0
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

from smcd_rl.experiments.harness import setting

__all__ = ["bounded", "check_upper_bounds"]


def bounded(
    default: Any,
    help: str,  # noqa: A002 - mirrors argparse's name
    *,
    low: float | None = None,
    above: float | None = None,
    high: float | None = None,
    below: float | None = None,
    choices: Sequence[Any] | None = None,
) -> Any:
    """A :func:`~smcd_rl.experiments.harness.setting` with an upper bound: at most ``high``, or under ``below``."""
    field = setting(default, help, low=low, above=above, choices=choices)
    return dataclasses.field(
        default=field.default,
        default_factory=field.default_factory,
        metadata={**field.metadata, "high": high, "below": below},
    )


def check_upper_bounds(config: Any) -> None:
    """Raise ``ValueError`` naming the option if a field (or an item of a tuple field) exceeds its upper bound."""
    for field in dataclasses.fields(config):
        high, below = field.metadata.get("high"), field.metadata.get("below")
        if high is None and below is None:
            continue
        value, flag = getattr(config, field.name), "--" + field.name.replace("_", "-")
        for item in value if isinstance(value, tuple) else (value,):
            if high is not None and item > high:
                raise ValueError(f"{flag} must be <= {high}, got {item}")
            if below is not None and item >= below:
                raise ValueError(f"{flag} must be < {below}, got {item}")
