"""The training scripts under scripts/ run end to end at tiny scale, write their logs and resume.

Each is a copy-and-edit script, not a library module, so it is run as a user runs it: a
subprocess, ``python scripts/<name>.py --tiny --out <tmp>``. To interrupt a run at a chosen
step, :data:`INTERRUPTED` runs the script the same way after wrapping every env that
``gymnasium.make`` builds so that its ``step`` raises ``KeyboardInterrupt`` (Ctrl-C) after
``stop_after`` steps of all envs together; it prints how many steps the run took.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


INTERRUPTED = """
import atexit, runpy, sys, gymnasium
stop_after, script, *args = sys.argv[1:]
steps, make = 0, gymnasium.make


class Interrupt(gymnasium.Wrapper):
    def step(self, action):
        global steps
        if steps == int(stop_after):
            raise KeyboardInterrupt
        steps += 1
        return self.env.step(action)


gymnasium.make = lambda *a, **k: Interrupt(make(*a, **k))
atexit.register(lambda: print(f"env steps: {steps}"))
sys.argv = [script, *args]
runpy.run_path(script, run_name="__main__")
"""


def run_script(name: str, out: Path, *args: str, stop_after: int | None = None, returncode: int = 0) -> str:
    """stdout and stderr of ``name --tiny --out out *args``; with ``stop_after``, interrupted after that many env steps."""
    script = [str(ROOT / "scripts" / name), "--tiny", "--out", str(out), *args]
    prefix = [] if stop_after is None else ["-c", INTERRUPTED, str(stop_after)]
    result = subprocess.run([sys.executable, *prefix, *script], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == returncode, result.stdout[-2000:] + result.stderr[-4000:]
    return result.stdout + result.stderr


def env_steps(output: str) -> int:
    return int(output.rsplit("env steps: ", 1)[1].split()[0])


def interrupted(name: str, out: Path, stop_after: int) -> None:
    """Run ``name`` until ``stop_after`` env steps, as if Ctrl-C came then: it says how to resume."""
    output = run_script(name, out, stop_after=stop_after, returncode=130)
    assert "interrupted; run the same command again to resume" in output and "Traceback" not in output


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
@pytest.mark.parametrize(
    ("name", "args", "message"),
    [
        ("mbrl_torchrl.py", ["--seed", "-1"], "argument --seed: must be >= 0, got -1"),
        ("mbrl_torchrl.py", ["--top-k", "300"], "argument --top-k: must be at most --num-candidates (200), got 300"),
        ("pets_mbrl_lib.py", ["--seed", "-1"], "argument --seed: must be >= 0, got -1"),
        (
            "pets_mbrl_lib.py",
            ["--elite-ratio", "0.001"],
            "argument --elite-ratio: --population-size 200 x --elite-ratio 0.001 keeps 1 elite, but CEM with "
            "--cem-iterations 5 needs at least 2",
        ),
        ("sb3_context.py", ["--train-steps", "0"], "argument --train-steps: must be >= 1, got 0"),
    ],
)
def test_bad_numbers_are_refused_with_the_usage(name: str, args: list[str], message: str, tmp_path: Path) -> None:
    """Before: ``--seed -1`` printed a traceback from deep inside the run (other numbers ran or failed late)."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / name), "--out", str(tmp_path), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr[-3000:]
    assert result.stderr.startswith("usage:") and f"{name}: error: {message}" in result.stderr
    assert "Traceback" not in result.stderr and not any(tmp_path.iterdir())  # refused before any work


@pytest.mark.slow
def test_mbrl_torchrl_tiny_and_resumed(tmp_path: Path) -> None:
    """Interrupted, rerun: it goes on from the last batch, to the same frames and fits, refusing other options.

    Before: an interrupted run started over. Not bit for bit: the interrupted episode restarts.
    """
    run_script("mbrl_torchrl.py", tmp_path / "whole")
    run = tmp_path / "whole" / "mbrl_Pendulum-v1_seed0"
    scalars = run / "logs" / run.name / "scalars"
    assert (scalars / "fit_loss.csv").read_text().strip() and (scalars / "smcd_ess.csv").read_text().strip()
    assert sorted(p.name for p in (run / "checkpoints").iterdir())[0].startswith("model_")
    whole = json.loads((run / "summary.json").read_text())
    assert whole["frames"] == 40 and whole["fits"] == 3 and not whole["resumed"]

    interrupted("mbrl_torchrl.py", tmp_path / "cut", stop_after=100 + 30)  # random frames, then 1.5 batches
    cut = tmp_path / "cut" / run.name
    refused = run_script("mbrl_torchrl.py", tmp_path / "cut", "--lr", "0.01", returncode=2)
    assert "holds a checkpoint of a run with other options: --lr 0.001 (now 0.01)" in refused
    assert "use another --out, or delete" in refused
    output = run_script("mbrl_torchrl.py", tmp_path / "cut", stop_after=10**6)
    assert "resuming" in output and "after 20 of 40 MPC frames" in output
    assert env_steps(output) == 20  # the random frames and the first batch were not collected again
    resumed = json.loads((cut / "summary.json").read_text())
    assert resumed["frames"] == 40 and resumed["fits"] == 3 and resumed["resumed"]

    def fitted_at(folder: Path) -> list[str]:
        return [
            row.split(",")[0]
            for row in (folder / "logs" / folder.name / "scalars" / "fit_loss.csv").read_text().split()
        ]

    assert fitted_at(cut) == fitted_at(run) == ["100", "120", "140"]  # fitted on the same buffer sizes


@pytest.mark.slow
@pytest.mark.skipif(
    importlib.util.find_spec("mbrl") is None, reason="mbrl-lib is not installed (bash scripts/install_mbrl_lib.sh)"
)
def test_pets_mbrl_lib_tiny_and_resumed(tmp_path: Path) -> None:
    """Interrupted mid-episode, rerun: the same results, bit for bit, without the random steps again.

    Before: an interrupted run started over.
    """
    run_script("pets_mbrl_lib.py", tmp_path / "whole")
    run = tmp_path / "whole" / "pets_InvertedPendulum-v5_seed0"
    results = rows(run / "results.csv")
    assert results and float(results[-1]["env_step"]) == 40
    summary = json.loads((run / "summary.json").read_text())
    assert len(summary["episode_returns"]) == len(results) >= 2
    assert (run / "model.pt").is_file()

    last_episode_start = int(float(results[-2]["env_step"]))
    assert 40 - last_episode_start >= 2  # an episode of at least 2 steps to interrupt in its middle
    interrupted("pets_mbrl_lib.py", tmp_path / "cut", stop_after=100 + (last_episode_start + 40) // 2)
    output = run_script("pets_mbrl_lib.py", tmp_path / "cut", stop_after=10**6)
    assert "resuming" in output
    cut = tmp_path / "cut" / run.name
    resumed = json.loads((cut / "summary.json").read_text())
    # The random steps and the finished episodes are not run again: the last episode and the baseline's.
    baseline_steps = env_steps(output) - (40 - last_episode_start)
    assert 0 < baseline_steps < 100
    assert resumed["episode_returns"] == summary["episode_returns"] and resumed["resumed"]
    assert rows(cut / "results.csv") == results  # the resumed log is complete
    whole_model, cut_model = (torch.load(f / "model.pt", weights_only=False)["state_dict"] for f in (run, cut))
    assert all(torch.equal(whole_model[k], cut_model[k]) for k in whole_model)


@pytest.mark.slow
def test_sb3_context_tiny_and_resumed(tmp_path: Path) -> None:
    """Interrupted in the second agent, rerun: the finished agent is kept, the evaluation is that of one run.

    Before: an interrupted run started over.
    """
    stdout = run_script("sb3_context.py", tmp_path / "whole")
    run = tmp_path / "whole" / "sb3_context_k4"
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

    # 400 random transitions for the model, then 250 training and 2 x 200 evaluation steps per agent.
    interrupted("sb3_context.py", tmp_path / "cut", stop_after=400 + 650 + 100)
    output = run_script("sb3_context.py", tmp_path / "cut", stop_after=10**6)
    assert "resuming" in output and "1 agents finished" in output
    assert "seed 0 context" not in output and "seed 0 plain" in output  # the first agent was not trained again
    assert env_steps(output) == 400 + 3 * 650  # the model's data again (fit.pt checks it), then 3 agents
    cut = tmp_path / "cut" / "sb3_context_k4"
    assert rows(cut / "eval.csv") == evaluation
    assert json.loads((cut / "summary.json").read_text())["resumed"]


def test_publish_report_replaces_a_reruns_scoreboard_rows_and_redraws_the_board(tmp_path) -> None:
    """A rerun of one experiment updates its rows of the committed scoreboard, the others kept as they were."""
    import json
    import shutil
    import subprocess
    import sys

    committed = ROOT / "docs" / "experiments" / "scoreboard" / "scoreboard.json"
    board = tmp_path / "board" / "scoreboard.json"
    board.parent.mkdir()
    shutil.copyfile(committed, board)
    entries = json.loads(committed.read_text())["entries"]
    rerun = json.loads(json.dumps(entries[0]["entry"]))  # the two-link entry, with another mean
    rerun["estimates"]["GD"].update(mean=0.0123, low=0.01, high=0.015)
    run = tmp_path / "rerun"
    run.mkdir()
    (run / "results.json").write_text(json.dumps({"experiment": "two-link", "scoreboard": rerun}))
    (run / "report.md").write_text("# a report\n")
    page = tmp_path / "page"
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "publish_report.py"), str(run), str(page), "--scoreboard", str(board)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    after = json.loads(board.read_text())["entries"]
    assert after[0]["entry"]["estimates"]["GD"]["mean"] == 0.0123
    assert [e["entry"] for e in after[1:]] == [e["entry"] for e in entries[1:]]
    assert "0.012" in (board.parent / "report.md").read_text() and (page / "report.md").is_file()


@pytest.mark.slow  # trains a torchrl MLP and tunes it: seconds
def test_adapt_own_network_tiny_writes_every_strategys_paired_error(tmp_path: Path) -> None:
    """A torchrl MLP trained by its own loop and an mbrl-lib ensemble trained by mbrl-lib's trainer,
    wrapped and tuned: every strategy has a row, each but no adaptation with its paired difference
    from it (the ensemble has no dropout: no SMCD rows there)."""
    out = tmp_path / "own-network.md"
    printed = run_script("adapt_own_network.py", out)
    report = out.read_text()
    assert report.startswith("Measured by `python scripts/adapt_own_network.py` on ")
    for label in ("no adaptation", "gradient descent", "SMCD", "Bayesian last layer", "combination"):
        assert f"| {label} | " in report and f"| {label} | " in printed
    intervals = [line for line in report.splitlines() if line.endswith("] |") and ", " in line]
    try:
        import mbrl.models  # noqa: F401
    except Exception:
        assert len(intervals) == 5 and "The mbrl-lib part was skipped" in report
    else:
        assert len(intervals) == 5 + 3 and "`GaussianMLP` ensemble trained by mbrl-lib's `ModelTrainer`" in report
