"""The ``smcd-rl`` command line: every ``--help`` renders, whatever the help texts contain, and without torch."""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
from dataclasses import dataclass

import pytest

from smcd_rl import cli
from smcd_rl.experiments.shared.harness import ExperimentConfig, setting


@dataclass
class PercentConfig(ExperimentConfig):
    keep: float = setting(0.5, "fraction of units kept (50% is the paper's)", low=0.0, high=1.0)
    label: str = setting("top 10%", "a name shown in the plot")


def test_a_percent_sign_in_a_help_text_or_default_renders_in_help(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="smcd-rl percent")
    cli._add_config_arguments(parser, PercentConfig)
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(["--help"])
    assert exit_info.value.code == 0
    printed = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "(50% is the paper's)" in printed and "(default: top 10%)" in printed
    assert vars(parser.parse_args(["--keep", "0.25"])) == {"keep": 0.25}  # the options still parse


@pytest.mark.parametrize("command", ["", *cli.COMMANDS])
def test_help_of_smcd_rl_and_of_every_command_exits_0(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*command.split(), "--help"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: smcd-rl {command}".rstrip())


#: Modules the help paths must not import: torch and what builds on it, and the optional extras.
HEAVY = ("torch", "tensordict", "torchrl", "ray", "stable_baselines3", "mujoco", "matplotlib")

# Runs every --help in one fresh interpreter and prints, per command, the heavy modules loaded by then.
_HELP_SCRIPT = """
import contextlib, io, json, sys
from smcd_rl import cli
heavy = set(sys.argv[1].split(","))
loaded = {}
for command in ["", "bench", *cli.COMMANDS]:
    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):
        cli.main([*command.split(), "--help"])
    assert out.getvalue().startswith("usage: smcd-rl"), out.getvalue()
    loaded[command] = sorted({m.split(".")[0] for m in sys.modules} & heavy)
print(json.dumps(loaded))
"""


def test_help_of_smcd_rl_and_of_every_command_imports_no_torch() -> None:
    """``--help`` builds the parser from the torch-free configs: it must not wait seconds for torch."""
    done = subprocess.run(
        [sys.executable, "-c", _HELP_SCRIPT, ",".join(HEAVY)], capture_output=True, text=True, check=True
    )
    loaded = json.loads(done.stdout)
    assert set(loaded) == {"", "bench", *cli.COMMANDS}
    assert {command: modules for command, modules in loaded.items() if modules} == {}


def test_the_smcd_rl_module_entry_point_imports_no_torch_for_help() -> None:
    """The real entry (``python -m smcd_rl.cli``, as the ``smcd-rl`` script): no torch in its import log."""
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "smcd_rl.cli", "two-link", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert done.stdout.startswith("usage: smcd-rl two-link")
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time:")}
    assert "gymnasium" in imported  # the log is what it seems (it names what import statements import)
    assert {name.split(".")[0] for name in imported} & set(HEAVY) == set()


@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_every_command_runs_the_config_that_its_help_describes(command: str) -> None:
    """The run module exports the config module's class and ``FULL`` (the same objects), and a ``run``."""
    entry = cli.COMMANDS[command]
    config_module = importlib.import_module(entry.config_module)
    run_module = importlib.import_module(entry.run_module)
    assert getattr(run_module, entry.config_class) is getattr(config_module, entry.config_class)
    assert getattr(run_module, "FULL", None) is getattr(config_module, "FULL", None)
    assert callable(run_module.run)
    assert entry.config_class in run_module.__all__


def test_env_constants_repeated_in_the_torch_free_configs_agree_with_the_envs() -> None:
    from smcd_rl.envs import panda_reach, two_link_telescoping
    from smcd_rl.experiments.panda import config as panda
    from smcd_rl.experiments.telescoping import config as telescoping

    for name in ("TELESCOPING_DT", "TARGET_ANGULAR_SPEED"):
        assert getattr(telescoping, name) == getattr(two_link_telescoping, name), name
    for name in ("DEFAULT_DT", "GOAL_TOLERANCE", "MAX_EPISODE_STEPS", "TOOL_RANGE"):
        assert getattr(panda, name) == getattr(panda_reach, name), name


def test_a_full_disk_under_any_write_is_one_error_line(
    tmp_path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A write that is not the project's own (a library's log) meeting a full disk was a traceback."""
    import errno

    from smcd_rl.experiments.scoreboard import run as scoreboard

    def full(config, **kwargs):  # type: ignore[no-untyped-def]
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "ray.log"))

    monkeypatch.setattr(scoreboard, "run", full)
    assert cli.main(["scoreboard", str(tmp_path), "--out", str(tmp_path / "board")]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"smcd-rl scoreboard: error: No space left on device writing {tmp_path / 'ray.log'}; free some space, "
        "or give another --out, and run the same command again to resume\n"
    )
    monkeypatch.setattr(scoreboard, "run", lambda config, **kwargs: (_ for _ in ()).throw(OSError(errno.EIO, "I/O")))
    with pytest.raises(OSError, match="I/O"):  # anything else is not the user's to fix: its traceback stays
        cli.main(["scoreboard", str(tmp_path), "--out", str(tmp_path / "board")])
