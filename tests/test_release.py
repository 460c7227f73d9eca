"""The release files agree: one version in pyproject, the package, CITATION.cff and the changelog."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import tomllib

import smcd_rl

ROOT = Path(__file__).resolve().parents[1]


def test_one_version_everywhere() -> None:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    citation = re.search(r"^version:\s*(\S+)", (ROOT / "CITATION.cff").read_text(), re.M)
    newest = re.search(r"^## (\d+\.\d+\.\d+) \(", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert citation and newest
    assert pyproject == smcd_rl.__version__ == citation[1] == newest[1]


def test_the_licence_is_the_one_the_package_declares() -> None:
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"]["text"]
    assert declared == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_bootstrap_has_help_and_refuses_an_unknown_option() -> None:
    shown = subprocess.run(["bash", str(ROOT / "bootstrap.sh"), "--help"], capture_output=True, text=True)
    assert shown.returncode == 0 and "--mbrl-lib" in shown.stdout
    refused = subprocess.run(["bash", str(ROOT / "bootstrap.sh"), "--no-such"], capture_output=True, text=True)
    assert refused.returncode == 2 and "unknown option --no-such" in refused.stderr
