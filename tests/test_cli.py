"""The ``smcd-rl`` command line: every ``--help`` renders, whatever the help texts contain."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import pytest

from smcd_rl import cli
from smcd_rl.experiments.harness import ExperimentConfig, setting


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
