"""The base of every ``smcd-rl`` command's config, importable without torch: what ``--help`` is built from.

This module holds :func:`setting` and :class:`ExperimentConfig`. Each command's package has a
``config.py`` with its config dataclass (deriving :class:`ExperimentConfig`), its ``FULL`` preset
and the constants its fields use. None of them imports torch, tensordict or any optional extra,
so that ``smcd-rl --help`` and ``smcd-rl COMMAND --help`` start as fast as Python does; a
command's ``run`` module imports its config from there and still exports it under its own name.

Example:
    >>> from dataclasses import dataclass
    >>> @dataclass
    ... class C(ExperimentConfig):
    ...     widths: tuple[int, ...] = setting((64, 64), "hidden widths", low=1, repeats=True)
    >>> C().settings()
    {'seed': 0, 'threads': 1, 'device': 'cpu', 'widths': [64, 64]}
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

__all__ = ["ExperimentConfig", "EvaluationConfig", "setting", "config_dict", "OUTPUT_ONLY"]

#: Settings that change where or how fast a run goes, never its numbers.
OUTPUT_ONLY = ("out", "full", "video", "workers")


def config_dict(config: Any) -> dict[str, Any]:
    """A JSON-ready dict of a config dataclass (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=list))


def setting(
    default: Any,
    help: str,  # noqa: A002 - mirrors argparse's name
    *,
    low: float | None = None,
    above: float | None = None,
    high: float | None = None,
    below: float | None = None,
    choices: Sequence[Any] | None = None,
    repeats: bool = False,
    positional: bool = False,
) -> Any:
    """A config field: ``help`` becomes its ``--help`` text; the bounds are checked before any work.

    Args:
        default: the default value (a list or tuple becomes a tuple field).
        help: the ``--help`` text.
        low: the smallest allowed value (inclusive), for a number or each item of a tuple.
        above: values must be strictly greater than this.
        high: the largest allowed value (inclusive).
        below: values must be strictly smaller than this.
        choices: the allowed values (of each item, for a tuple).
        repeats: whether a tuple may hold a value twice (layer widths may; methods, horizons and
            the like may not: each would be run, tabled and compared twice).
        positional: a tuple field given as the command's positional arguments instead of an option.

    Example:
        >>> from dataclasses import dataclass
        >>> @dataclass
        ... class C(ExperimentConfig):
        ...     particles: int = setting(100, "SMCD particles", low=1)
        >>> C(particles=0).validate()
        Traceback (most recent call last):
        ...
        ValueError: --particles must be >= 1, got 0
    """
    metadata = {
        "help": help,
        "low": low,
        "above": above,
        "high": high,
        "below": below,
        "choices": None if choices is None else tuple(choices),
        "repeats": repeats,
        "positional": positional,
    }
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return dataclasses.field(default_factory=lambda: value, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass
class ExperimentConfig:
    """The settings every experiment command shares; a command's config derives from this.

    A derived config redeclares a field to change its default (e.g. ``out``) and adds its own.
    """

    out: str = setting("runs/experiment", "output directory (results, plot, report, trained models)")
    # Experiments derive further seeds from this one (e.g. seed * 1_000_003 + k): 2^31 keeps them in torch's range.
    seed: int = setting(0, "seed of data, training, trials and filters", low=0, high=2**31 - 1)
    threads: int = setting(
        1, "torch CPU threads (0: torch's default); results repeat bit for bit per thread count", low=0, high=256
    )
    device: str = setting("cpu", "torch device: cpu, cuda, cuda:1 or auto")
    full: bool = setting(False, "the paper's scale (options given explicitly still win)")
    video: int = setting(0, "episodes per method to write as GIFs in out/videos (0: none)", low=0)

    #: Fields whose values must be non-empty when given as tuples (e.g. methods, horizons); a
    #: subclass's list adds to those of the classes it derives from.
    NON_EMPTY: ClassVar[tuple[str, ...]] = ()
    #: Fields the method cache leaves out: those that choose which methods or cells run (not what
    #: any of them computes), so a rerun with more methods reuses the finished ones, and paths of
    #: inputs whose content the cache is keyed by instead.
    SELECTION: ClassVar[tuple[str, ...]] = ()

    def validate(self) -> None:
        """Check every field against its declared type and bounds; raise ValueError naming the option."""
        hints = typing.get_type_hints(type(self))
        non_empty = {name for cls in type(self).__mro__ for name in vars(cls).get("NON_EMPTY", ())}
        for field in dataclasses.fields(self):
            value, flag = getattr(self, field.name), "--" + field.name.replace("_", "-")
            items = value if isinstance(value, tuple) else (value,)
            if isinstance(value, tuple) and not value and field.name in non_empty:
                raise ValueError(f"{flag} needs at least one value")
            repeated = sorted({item for item in items if items.count(item) > 1}, key=repr)
            if isinstance(value, tuple) and repeated and not field.metadata.get("repeats"):
                raise ValueError(f"{flag} repeats {repeated}; give each value once")
            kind = hints[field.name]
            item_kind = typing.get_args(kind)[0] if typing.get_origin(kind) is tuple else kind
            for item in items:
                _check_item(flag, item, item_kind, field.metadata)
        if not self.out.strip():
            raise ValueError("--out must name a directory (it is empty)")
        from smcd_rl.experiments.shared.runtime import resolve_device

        resolve_device(self.device)

    def settings(self, *, exclude: Sequence[str] = ()) -> dict[str, Any]:
        """The JSON-ready settings that determine the results (output-only fields left out)."""
        return {k: v for k, v in config_dict(self).items() if k not in (*OUTPUT_ONLY, *exclude)}


@dataclass
class EvaluationConfig(ExperimentConfig):
    """The settings of a command that evaluates independent methods: how many processes run them."""

    workers: int = setting(
        0,
        "worker processes that evaluate independent methods side by side, each with --threads torch threads "
        "(0: one per free core when the evaluation is long enough to repay starting them; 1: none); "
        "the results are the same for any number",
        low=0,
        high=256,
    )


def _check_item(flag: str, value: Any, kind: Any, metadata: Mapping[str, Any]) -> None:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind in (int, float, str, bool) and not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"{flag} must be a {kind.__name__}, got {value!r}")
    if kind is float and not math.isfinite(value):
        raise ValueError(f"{flag} must be a finite number, got {value}")
    low, above, choices = metadata.get("low"), metadata.get("above"), metadata.get("choices")
    high, below = metadata.get("high"), metadata.get("below")
    if low is not None and value < low:
        raise ValueError(f"{flag} must be >= {low}, got {value}")
    if above is not None and value <= above:
        raise ValueError(f"{flag} must be > {above}, got {value}")
    if high is not None and value > high:
        raise ValueError(f"{flag} must be <= {high}, got {value}")
    if below is not None and value >= below:
        raise ValueError(f"{flag} must be < {below}, got {value}")
    if choices is not None and value not in choices:
        raise ValueError(f"{flag}: unknown value {value!r}; choose from {list(choices)}")
