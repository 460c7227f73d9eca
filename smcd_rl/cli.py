"""The ``smcd-rl`` command: one sub-command per experiment or benchmark, each with ``--help``.

Every sub-command is a config dataclass (its field help is the ``--help`` text), an optional
``--full`` preset (the paper's scale; options given explicitly still win) and a ``run`` function.
A name with a space in :data:`COMMANDS` is a nested command: ``"bench planners"`` runs as
``smcd-rl bench planners``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
import typing
from collections.abc import Sequence
from typing import Any

__all__ = ["main", "COMMANDS"]

#: sub-command -> (module, config class, one-line description)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "two-link": (
        "smcd_rl.experiments.two_link",
        "TwoLinkConfig",
        "two-link arm look-ahead prediction after T burn-in steps (paper Fig. 2)",
    ),
    "panda": (
        "smcd_rl.experiments.panda",
        "PandaConfig",
        "7-DOF Panda reaching with an unknown tool, measured every n-th step: FK, M+N, M+G, M+S (paper Fig. 3)",
    ),
    "telescoping": (
        "smcd_rl.experiments.telescoping",
        "TelescopingConfig",
        "PD tracking of a circling target with a telescoping link, adapted Jacobians (paper appendix A.4, Fig. 8)",
    ),
    "interpret": (
        "smcd_rl.experiments.interpret",
        "InterpretConfig",
        "mask interpretability: link lengths (Fig. 9), drone skill/strategy/phase/success (Figs. 4, 13), drone look-ahead (Fig. 14)",
    ),
    "sweep": (
        "smcd_rl.experiments.sweep",
        "SweepConfig",
        "hyper-parameter ablations on Ray: training loss (Figs. 5, 12) and SMCD look-ahead error (Fig. 6)",
    ),
    "ant": (
        "smcd_rl.experiments.ant",
        "AntConfig",
        "crippled-leg Ant: planners x adaptations, healthy and crippled (paper appendix C, Fig. 15)",
    ),
    "scoreboard": (
        "smcd_rl.experiments.scoreboard",
        "ScoreboardConfig",
        "one table and plot of every task from experiments' run directories: none, GD, SMCD (paper), SMCD (calibrated)",
    ),
    "bench planners": (
        "smcd_rl.experiments.bench_planners",
        "BenchPlannersConfig",
        "time our CEM against torchrl's CEMPlanner on the same model, with the bare forwards as the floor",
    ),
    "bench filter": (
        "smcd_rl.experiments.bench_filter",
        "BenchFilterConfig",
        "time one SMCD update against a dense matmul and a naive update, realistic and worst case; peak memory",
    ),
    "bench control": (
        "smcd_rl.experiments.bench_control",
        "BenchControlConfig",
        "time the Panda reaching loop (observe + Jacobian + PD) with SMCD against gradient descent and the analytic chain",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smcd-rl",
        description="Sequential Monte Carlo Dropout: experiments and benchmarks. "
        "Experiments write CSV/JSON results and a PNG plot and print their table; benchmarks print their ratios and write CSV/JSON.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups: dict[str, Any] = {}  # group name -> its sub-parsers
    for name, (module, config_name, summary) in COMMANDS.items():
        config_cls = getattr(importlib.import_module(module), config_name)
        group, _, leaf = name.rpartition(" ")
        if group and group not in groups:  # "bench planners": a "bench" command with its own sub-commands
            parent = commands.add_parser(group, help=f"{group} commands", description=f"{group} commands.")
            groups[group] = parent.add_subparsers(dest="_" + group, required=True, metavar="COMMAND")
        sub = (groups[group] if group else commands).add_parser(
            leaf, help=_escape_percent(summary), description=summary + "."
        )
        _add_config_arguments(sub, config_cls)
        sub.set_defaults(_command=name)
    return parser


def _add_config_arguments(parser: argparse.ArgumentParser, config_cls: type) -> None:
    hints = typing.get_type_hints(config_cls)
    defaults = config_cls()
    for field in dataclasses.fields(config_cls):
        flag = "--" + field.name.replace("_", "-")
        kind = hints[field.name]
        default = getattr(defaults, field.name)
        help_text = _escape_percent(f"{field.metadata.get('help', '')} (default: {default})")
        # SUPPRESS: only options the user typed reach the config, so --full can fill the rest.
        if field.metadata.get("positional"):
            item = typing.get_args(kind)[0]
            help_text = _escape_percent(field.metadata.get("help", ""))
            parser.add_argument(field.name, type=item, nargs="+", metavar=field.name.upper(), help=help_text)
        elif kind is bool:
            parser.add_argument(flag, action="store_true", default=argparse.SUPPRESS, help=help_text)
        elif typing.get_origin(kind) is tuple:
            item = typing.get_args(kind)[0]
            parser.add_argument(flag, type=item, nargs="+", default=argparse.SUPPRESS, help=help_text)
        else:
            parser.add_argument(flag, type=kind, default=argparse.SUPPRESS, help=help_text)


def _escape_percent(text: str) -> str:
    """``text`` as argparse help: it %-formats help strings, so a bare ``%`` ("50% of ...") would crash ``--help``."""
    return text.replace("%", "%%")


def make_config(command: str, given: dict[str, Any]) -> Any:
    """The config of ``command`` from explicitly given options, with ``--full`` applied under them."""
    module_name, config_name, _ = COMMANDS[command]
    module = importlib.import_module(module_name)
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}
    config = getattr(module, config_name)(**given)
    if getattr(config, "full", False):
        config = dataclasses.replace(config, **{**getattr(module, "FULL", {}), **given})
    return config


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``smcd-rl`` command; returns the exit status.

    Problems the user can fix (bad options, unreadable or unwritable files, a missing extra) print
    one line on stderr and return 2; Ctrl-C prints one line saying how to resume and returns 130
    (``128 + SIGINT``, what shells report for an interrupted command).
    """
    name = "smcd-rl"
    try:
        args = build_parser().parse_args(argv)
        name = f"smcd-rl {args._command}"
        given = {k: v for k, v in vars(args).items() if k != "command" and not k.startswith("_")}
        config = make_config(args._command, given)
        module = importlib.import_module(COMMANDS[args._command][0])
        module.run(config)
    except KeyboardInterrupt:
        # Experiments save each finished piece (trained models, caches) as they go, atomically.
        print(f"{name}: interrupted; run the same command again to resume (finished work is kept)", file=sys.stderr)
        return 130
    # ValueError includes smcd_rl.files' unreadable-file and failed-write errors; ImportError: a missing extra.
    except (ValueError, KeyError, FileNotFoundError, ImportError) as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
