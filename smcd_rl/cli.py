"""The ``smcd-rl`` command: one sub-command per experiment or benchmark, each with ``--help``.

Every sub-command is a config dataclass (its field help is the ``--help`` text), an optional
``--full`` preset (the paper's scale; options given explicitly still win) and a ``run`` function.
A name with a space in :data:`COMMANDS` is a nested command: ``"bench planners"`` runs as
``smcd-rl bench planners``.

The parser is built from the configs alone, which live in torch-free modules (each command's
package has its ``config.py``); a command's ``run`` module, and with it torch, is
imported only once its options have parsed, so ``--help`` and option errors come back at once.

Example:
    >>> config = make_config("bench planners", {"full": True, "repeats": 7})
    >>> config.repeats, config.warmup
    (7, 5)
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import importlib
import sys
import typing
from collections.abc import Sequence
from typing import Any, NamedTuple

from smcd_rl.allocator import keep_freed_memory

__all__ = ["main", "COMMANDS", "Command", "build_parser", "make_config"]


class Command(NamedTuple):
    """One ``smcd-rl`` command: where its config is (a torch-free module) and where its ``run`` is."""

    #: The module of its config class and ``FULL`` preset; it must import no torch, so ``--help`` stays fast.
    config_module: str
    #: The config dataclass: its fields are the command's options.
    config_class: str
    #: The module whose ``run(config)`` runs the command, imported only once the options are parsed.
    run_module: str
    #: The one-line description in ``smcd-rl --help``.
    summary: str


#: sub-command -> its :class:`Command`.
COMMANDS: dict[str, Command] = {
    "two-link": Command(
        "smcd_rl.experiments.two_link.config",
        "TwoLinkConfig",
        "smcd_rl.experiments.two_link.run",
        "two-link arm look-ahead prediction after T burn-in steps (paper Fig. 2)",
    ),
    "panda": Command(
        "smcd_rl.experiments.panda.config",
        "PandaConfig",
        "smcd_rl.experiments.panda.run",
        "7-DOF Panda reaching with an unknown tool, measured every n-th step: FK, M+N, M+G, M+S (paper Fig. 3)",
    ),
    "telescoping": Command(
        "smcd_rl.experiments.telescoping.config",
        "TelescopingConfig",
        "smcd_rl.experiments.telescoping.run",
        "PD tracking of a circling target with a telescoping link, adapted Jacobians (paper appendix A.4, Fig. 8)",
    ),
    "interpret": Command(
        "smcd_rl.experiments.interpret.config",
        "InterpretConfig",
        "smcd_rl.experiments.interpret.run",
        "mask interpretability: link lengths (Fig. 9), drone skill/strategy/phase/success (Figs. 4, 13), drone look-ahead (Fig. 14)",
    ),
    "sweep": Command(
        "smcd_rl.experiments.sweep.config",
        "SweepConfig",
        "smcd_rl.experiments.sweep.run",
        "hyper-parameter ablations on Ray: training loss (Figs. 5, 12) and SMCD look-ahead error (Fig. 6)",
    ),
    "task-masks": Command(
        "smcd_rl.experiments.task_masks.config",
        "TaskMasksConfig",
        "smcd_rl.experiments.task_masks.run",
        "the task-mask network's share and mask groups measured on one family's held-out training tasks",
    ),
    "ant": Command(
        "smcd_rl.experiments.ant.config",
        "AntConfig",
        "smcd_rl.experiments.ant.run",
        "crippled-leg Ant: planners x adaptations, healthy and crippled (paper appendix C, Fig. 15)",
    ),
    "fetch": Command(
        "smcd_rl.experiments.fetch.config",
        "FetchConfig",
        "smcd_rl.experiments.fetch.run",
        "Fetch task families (rotated reach, heavy push): MPC with CEM/MPPI on a learnt model, N/G/S/S(paper)",
    ),
    "regimes": Command(
        "smcd_rl.experiments.regimes.config",
        "RegimesConfig",
        "smcd_rl.experiments.regimes.run",
        "every method tuned by one criterion on two-link, telescoping and pendulum tasks: few and many "
        "observations, a task switch, an outlier, sparse measurements; time per step and a budgeted view",
    ),
    "scoreboard": Command(
        "smcd_rl.experiments.scoreboard.config",
        "ScoreboardConfig",
        "smcd_rl.experiments.scoreboard.run",
        "one table and plot of every task from experiments' run directories: none, GD, SMCD (one-step, paper, "
        "calibrated), the combination; time per observation",
    ),
    "bench planners": Command(
        "smcd_rl.experiments.bench.planners.config",
        "BenchPlannersConfig",
        "smcd_rl.experiments.bench.planners.run",
        "time our CEM against torchrl's CEMPlanner on the same model, with the bare forwards as the floor",
    ),
    "bench filter": Command(
        "smcd_rl.experiments.bench.filter.config",
        "BenchFilterConfig",
        "smcd_rl.experiments.bench.filter.run",
        "time one SMCD update against a dense matmul and a naive update, realistic and worst case; peak memory",
    ),
    "bench control": Command(
        "smcd_rl.experiments.bench.control.config",
        "BenchControlConfig",
        "smcd_rl.experiments.bench.control.run",
        "time the Panda reaching loop (observe + Jacobian + PD) with SMCD against gradient descent and the analytic chain",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``smcd-rl`` and all its commands; it imports their configs only (no torch)."""
    parser = argparse.ArgumentParser(
        prog="smcd-rl",
        description="Sequential Monte Carlo Dropout: experiments and benchmarks. "
        "Experiments write CSV/JSON results and a PNG plot and print their table; benchmarks print their ratios and write CSV/JSON.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    groups: dict[str, Any] = {}  # group name -> its sub-parsers
    for name, (config_module, config_name, _, summary) in COMMANDS.items():
        config_cls = getattr(importlib.import_module(config_module), config_name)
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
    config_module, config_name, _, _ = COMMANDS[command]
    module = importlib.import_module(config_module)
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}
    config = getattr(module, config_name)(**given)
    if getattr(config, "full", False):
        config = dataclasses.replace(config, **{**getattr(module, "FULL", {}), **given})
    return config


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``smcd-rl`` command; returns the exit status.

    Problems the user can fix (bad options, unreadable or unwritable files, a full disk, a missing
    extra) print one line on stderr and return 2; Ctrl-C prints one line saying how to resume and returns 130
    (``128 + SIGINT``, what shells report for an interrupted command).
    """
    name = "smcd-rl"
    try:
        args = build_parser().parse_args(argv)
        name = f"smcd-rl {args._command}"
        given = {k: v for k, v in vars(args).items() if k != "command" and not k.startswith("_")}
        config = make_config(args._command, given)
        keep_freed_memory()  # before the first large tensor: no page faults for every temporary
        module = importlib.import_module(COMMANDS[args._command].run_module)  # torch etc.: only now
        module.run(config)
    except KeyboardInterrupt:
        # Experiments save each finished piece (trained models, caches) as they go, atomically.
        print(f"{name}: interrupted; run the same command again to resume (finished work is kept)", file=sys.stderr)
        return 130
    # ValueError includes smcd_rl.files' unreadable-file and failed-write errors; ImportError: a missing extra.
    except (ValueError, KeyError, FileNotFoundError, ImportError) as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a full disk met by a write that is not the project's own (a library's log, ...)
        if err.errno not in _DISK_FULL:
            raise
        where = f" writing {err.filename}" if err.filename else ""
        print(
            f"{name}: error: {err.strerror or 'no space left on the disk'}{where}; free some space, or give another "
            "--out, and run the same command again to resume",
            file=sys.stderr,
        )
        return 2
    return 0


#: The errors of a full disk (no space left; disk quota exceeded).
_DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
