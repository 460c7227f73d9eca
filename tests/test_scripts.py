"""The training scripts under scripts/ run end to end at tiny scale and write their logs.

Each is a copy-and-edit script, not a library module, so it is run as a user runs it: a
subprocess, ``python scripts/<name>.py --tiny --out <tmp>``.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_script(name: str, out: Path, *args: str) -> str:
    result = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), "--tiny", "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
    return result.stdout


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as file:
        return list(csv.DictReader(file))


@pytest.mark.slow  # each imports torch, torchrl or SB3: seconds
@pytest.mark.parametrize("name", ["mbrl_torchrl.py", "pets_mbrl_lib.py", "sb3_context.py"])
def test_help_lists_the_config(name: str) -> None:
    result = subprocess.run([sys.executable, str(ROOT / "scripts" / name), "--help"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "--tiny" in result.stdout and "--out" in result.stdout and "(default:" in result.stdout


@pytest.mark.slow
def test_mbrl_torchrl_tiny(tmp_path: Path) -> None:
    run_script("mbrl_torchrl.py", tmp_path)
    run = tmp_path / "mbrl_Pendulum-v1_seed0"
    scalars = run / "logs" / run.name / "scalars"
    assert (scalars / "fit_loss.csv").read_text().strip() and (scalars / "smcd_ess.csv").read_text().strip()
    assert sorted(p.name for p in (run / "checkpoints").iterdir())[0].startswith("model_")
    assert json.loads((run / "summary.json").read_text())["frames"] == 40


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("mbrl") is None, reason="mbrl-lib is not installed (bash scripts/install_mbrl_lib.sh)"
)
def test_pets_mbrl_lib_tiny(tmp_path: Path) -> None:
    run_script("pets_mbrl_lib.py", tmp_path)
    run = tmp_path / "pets_InvertedPendulum-v5_seed0"
    results = rows(run / "results.csv")
    assert results and float(results[-1]["env_step"]) == 40
    summary = json.loads((run / "summary.json").read_text())
    assert len(summary["episode_returns"]) == len(results)
    assert (run / "model.pt").is_file()


@pytest.mark.slow
def test_sb3_context_tiny(tmp_path: Path) -> None:
    stdout = run_script("sb3_context.py", tmp_path)
    run = tmp_path / "sb3_context_k4"
    evaluation = rows(run / "eval.csv")
    assert len(evaluation) == 2 * 2 * 2  # 2 arms x 2 seeds x 2 episodes
    # Both arms meet the same evaluation pendulums, in the same order.
    tasks = {
        arm: [(r["seed"], r["mass"], r["length"]) for r in evaluation if r["arm"] == arm]
        for arm in ("context", "plain")
    }
    assert tasks["context"] == tasks["plain"]
    assert (run / "context_seed0" / "progress.csv").read_text().strip()
    assert "context - plain" in stdout
