"""The training scripts' command line: a typed config as options with ranges, and resuming a run.

Each script in ``scripts/`` declares its options as a dataclass whose fields carry ``"help"`` and,
for numbers, ``"valid"`` (the range, ``"[1, inf)"`` or ``"(0, 1]"``) in their metadata. This module
turns such a config into argparse options, checks every range (after ``--tiny``), and refuses to
resume a run directory whose checkpoint other options wrote: usage and exit 2, before any work.

Example:
    >>> from dataclasses import dataclass, field
    >>> from smcd_rl.integrations.script_options import parse_config
    >>> @dataclass(frozen=True)
    ... class Config:
    ...     out: str = field(default="runs", metadata={"help": "output directory"})
    ...     steps: int = field(default=10, metadata={"help": "steps", "valid": "[1, inf)"})
    ...     tiny: bool = field(default=False, metadata={"help": "a run of seconds"})
    >>> parse_config(Config, ["--tiny"], tiny={"steps": 2}, run_dir=lambda c: Path(c.out) / "run")
    Config(out='runs', steps=2, tiny=True)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from smcd_rl.files import write_text

__all__ = ["RESUMABLE_WITH_OTHER", "describe", "parse_config", "save_options", "within"]

#: Options a run may be resumed with other values of: where it is, and speed alone.
RESUMABLE_WITH_OTHER = ("out", "threads")

C = TypeVar("C")


def within(value: float, interval: str) -> bool:
    """Whether ``value`` lies in ``interval``, written ``"[1, inf)"`` or ``"(0, 1]"``; NaN never does.

    Example:
        >>> within(0.5, "(0, 1]"), within(0, "(0, 1]"), within(float("nan"), "[0, inf)")
        (True, False, False)
    """
    low, high = (float(end) for end in interval[1:-1].split(","))
    above = low < value if interval[0] == "(" else low <= value
    below = value < high if interval[-1] == ")" else value <= high
    return above and below


def describe(interval: str) -> str:
    """``interval`` in words for a message: ``"[1, inf)"`` -> ``">= 1"``, ``"(0, 1]"`` -> ``"in (0, 1]"``."""
    low, high = interval[1:-1].split(", ")
    return f"{'>' if interval[0] == '(' else '>='} {low}" if high == "inf" else f"in {interval}"


def parse_config(
    config_type: type[C],
    argv: Sequence[str] | None = None,
    *,
    run_dir: Callable[[C], Path],
    tiny: Mapping[str, Any],
    description: str | None = None,
    choices: Mapping[str, Sequence[str]] | None = None,
    checkpoints: Sequence[str] = ("checkpoint.pt",),
    check: Callable[[C], str | None] | None = None,
) -> C:
    """The config of ``argv`` (the command line by default), checked before any work.

    Args:
        config_type: A dataclass of the options (bool fields are flags; a ``tiny`` flag applies
            ``tiny``'s values).
        run_dir: Where a config's run writes; a checkpoint there is resumed only by the same options.
        tiny: The values ``--tiny`` sets.
        description: The ``--help`` text's first line.
        choices: The valid values of a string option, by field name.
        checkpoints: The files in ``run_dir`` whose presence means a run to resume.
        check: A further check of the whole config: the message of what is wrong, or ``None``.

    Stops with the usage and exit 2 on a value outside its range, a failed ``check``, or a
    checkpoint that a run with other options wrote (each differing option named).
    """
    parser = argparse.ArgumentParser(description=description)
    for f in dataclasses.fields(config_type):  # type: ignore[arg-type]
        flag = "--" + f.name.replace("_", "-")
        if f.type in (bool, "bool"):
            parser.add_argument(flag, action="store_true", help=f.metadata["help"])
        else:
            kind = {"int": int, "float": float, "str": str}[str(f.type)]
            valid = f"; {describe(f.metadata['valid'])}" if "valid" in f.metadata else ""
            parser.add_argument(
                flag, type=kind, default=f.default, choices=(choices or {}).get(f.name),
                help=f"{f.metadata['help']} (default: {f.default}{valid})",
            )  # fmt: skip
    config = config_type(**vars(parser.parse_args(argv)))
    config = dataclasses.replace(config, **tiny) if getattr(config, "tiny", False) else config  # type: ignore[type-var]
    for f in dataclasses.fields(config_type):  # type: ignore[arg-type]
        value = getattr(config, f.name)
        if "valid" in f.metadata and not within(value, f.metadata["valid"]):
            parser.error(f"argument --{f.name.replace('_', '-')}: must be {describe(f.metadata['valid'])}, got {value}")
    problem = check(config) if check is not None else None
    if problem is not None:
        parser.error(problem)
    _check_resume(parser, config, run_dir(config), checkpoints)
    return config


def _options(config: Any) -> dict[str, Any]:
    return {k: v for k, v in dataclasses.asdict(config).items() if k not in RESUMABLE_WITH_OTHER}


def _check_resume(parser: argparse.ArgumentParser, config: Any, run: Path, checkpoints: Sequence[str]) -> None:
    """Refuse to resume a checkpoint that a run with other options wrote."""
    if not any((run / name).is_file() for name in checkpoints):
        return
    fix = f"use another --out, or delete {' and '.join(str(run / name) for name in checkpoints)} to start afresh"
    if not (run / "options.json").is_file():
        parser.error(f"{run} holds a checkpoint but no options.json saying which options wrote it; {fix}")
    saved = json.loads((run / "options.json").read_text())
    now = _options(config)
    differ = [
        f"--{k.replace('_', '-')} {saved.get(k)} (now {now.get(k)})"
        for k in sorted(set(saved) | set(now))
        if saved.get(k) != now.get(k)
    ]
    if differ:
        parser.error(
            f"{run} holds a checkpoint of a run with other options: {', '.join(differ)}; rerun with those to "
            f"resume it, or {fix}"
        )


def save_options(config: Any, run: Path) -> None:
    """Write ``run/options.json``, the options a resumed run must repeat (all but :data:`RESUMABLE_WITH_OTHER`)."""
    write_text(run / "options.json", json.dumps(_options(config), indent=2) + "\n", what="options")
