"""``--video N``: tiny panda and telescoping runs write each method's first N episodes as GIFs, and change no number."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
from PIL import Image

from smcd_rl import cli
from smcd_rl.cli import make_config
from smcd_rl.envs.two_link_telescoping import circle_target, telescoping_frame
from smcd_rl.experiments.shared.outputs import settings_fingerprint
from smcd_rl.experiments.telescoping.tracking import sample_episodes

# The tiny settings of tests/experiments/test_panda_experiment.py and test_telescoping_experiment.py.
PANDA = (
    "--samples 2000 --hidden 32 --depth 2 --epochs 2 --tasks 4 --seeds 2 --intervals 2 5 --steps 25 "
    "--particles 20 --gd-steps 1 --gd-window 3 --tuning-episodes 4 --tuning-steps 5"
).split()
TELESCOPING = (
    "--tasks 20 --episodes 5 --hidden 32 --epochs 2 --reptile-epochs 1 --trials 6 --horizon 12 --report-steps 5 12 "
    "--particles 50 --oracle-particles 50 --gd-steps 1"
).split()
# ... and of tests/experiments/test_ant_experiment.py.
ANT = (
    "--transitions 400 --data-episode-steps 100 --hidden 16 --mask-groups 4 --epochs 2 --episodes 2 --episode-steps 4 --horizon 3 "
    "--candidates 12 --elites 3 --iterations 2 --particles 8 --threads 1 --tuning-episodes 4 --tuning-steps 6 "
    "--prediction-episodes 6 --prediction-steps 8 --prediction-horizon 3 --gd-lr 0.01 0.1 --gd-steps 1 --gd-window 5"
).split()


def _frames(path, tick: int) -> list[np.ndarray]:
    """The GIF's frames, one per step of ``tick`` ms: Pillow stores a run of identical frames once, for their total time."""
    with Image.open(path) as gif:
        frames = []
        for k in range(gif.n_frames):
            gif.seek(k)
            frames += [np.asarray(gif.convert("RGB"))] * round(gif.info["duration"] / tick)
        return frames


def test_video_is_output_only_so_fingerprints_and_caches_stay() -> None:
    for command in ("panda", "telescoping", "ant"):
        plain, filmed = make_config(command, {}), make_config(command, {"video": 2})
        assert filmed.video == 2 and "video" not in filmed.settings()
        assert settings_fingerprint(plain.settings()) == settings_fingerprint(filmed.settings())


def test_panda_video_writes_each_methods_first_arms_until_they_reach(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    # 5 videos per method from 4 tasks a seed: seed 0's four arms, then seed 1's first.
    assert cli.main(["panda", "--out", str(out), *PANDA, "--video", "5"]) == 0
    capsys.readouterr()
    methods = {
        "FK": "FK",
        "M+N": "M+N",
        "M+G": "M+G",
        "M+S": "M+S",
        "M+S(evidence)": "M+S-evidence",
        "M+S(paper)": "M+S-paper",
        "M+C": "M+C",
        "M+L": "M+L",
        "M+SL": "M+SL",
        "T+N": "T+N",
        "T+G": "T+G",
        "T+S": "T+S",
        "T+L": "T+L",
        "T+SL": "T+SL",
    }
    names = [f"videos/{safe}-{k}.gif" for safe in methods.values() for k in range(5)]
    assert [f for f in json.loads((out / "results.json").read_text())["files"] if f.startswith("videos/")] == names
    trials = {
        (r["method"], int(r["seed"]), int(r["task"])): r
        for r in csv.DictReader(open(out / "trials.csv"))
        if r["interval"] == "5"  # the largest interval: the tiny run has no n = 20
    }
    for method, safe in methods.items():
        for k, (seed, task) in enumerate([(0, 0), (0, 1), (0, 2), (0, 3), (1, 0)]):
            frames = _frames(out / f"videos/{safe}-{k}.gif", 50)  # dt = 0.05 s
            # An episode ends at the first arrival (or after --steps 25): the start frame and one a step.
            assert len(frames) == min(int(trials[(method, seed, task)]["steps"]), 25) + 1
            assert frames[0].shape == (480, 480, 3) and (frames[-1] != frames[0]).any()

    # The same run without videos: the very same numbers, and the same settings fingerprint in the report.
    plain = tmp_path / "plain"
    assert cli.main(["panda", "--out", str(plain), *PANDA]) == 0
    capsys.readouterr()
    assert (plain / "trials.csv").read_text() == (out / "trials.csv").read_text()
    assert not (plain / "videos").exists()
    fingerprint = [line for line in (out / "report.md").read_text().splitlines() if "fingerprint" in line]
    assert fingerprint == [line for line in (plain / "report.md").read_text().splitlines() if "fingerprint" in line]


def test_telescoping_video_draws_the_recorded_episodes(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert cli.main(["telescoping", "--out", str(out), *TELESCOPING, "--video", "1", "--methods", "true", "M+S"]) == 0
    capsys.readouterr()
    files = json.loads((out / "results.json").read_text())["files"]
    assert [f for f in files if f.startswith("videos/")] == ["videos/true-0.gif", "videos/M+S-0.gif"]
    true, adapted = (_frames(out / f"videos/{name}-0.gif", 100) for name in ("true", "M+S"))  # dt = 0.1 s
    assert len(true) == len(adapted) == 13  # k = 0 .. --horizon 12
    assert (true[0] == adapted[0]).all()  # the same episode, from the same start
    assert any((a != b).any() for a, b in zip(true, adapted, strict=True))  # driven by other kinematics
    # The first frame is the episode's start state drawn by the frame function.
    config = make_config("telescoping", {"trials": 6, "horizon": 12})
    episodes, _ = sample_episodes(config, torch.device("cpu"))
    target = circle_target(0, episodes["radius"][0], episodes["start_angle"][0], step_angle=0.0)
    start = telescoping_frame(
        episodes["q"][0].numpy(), float(episodes["l1"][0]), 0, target.numpy(), float(episodes["radius"][0])
    )
    np.testing.assert_array_equal(true[0], start)


def test_ant_video_redraws_the_recorded_mujoco_episode(tmp_path, capsys) -> None:
    pytest.importorskip("mujoco")
    out = tmp_path / "run"
    options = ["--planners", "rs", "--adaptations", "N", "--conditions", "crippled", "--video", "1"]
    assert cli.main(["ant", "--out", str(out), *ANT, *options]) == 0
    capsys.readouterr()
    files = json.loads((out / "results.json").read_text())["files"]
    assert [f for f in files if f.startswith("videos/")] == ["videos/RS-M+N-crippled-0.gif"]
    frames = _frames(out / "videos/RS-M+N-crippled-0.gif", 50)  # the Ant's dt = 0.05 s
    assert len(frames) == 5 and frames[0].shape == (480, 480, 3)  # the reset state and --episode-steps 4
    assert (frames[-1] != frames[0]).any()
