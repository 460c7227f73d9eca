"""Every registered smcd_rl task renders ``rgb_array`` frames headless; the frame functions draw their state; GIFs record.

MuJoCo tasks render through EGL: ``tests/conftest.py`` sets ``MUJOCO_GL=egl`` before mujoco is imported.
"""

from __future__ import annotations

import importlib.util
import math
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from PIL import Image

import smcd_rl  # noqa: F401 - registers the tasks
from smcd_rl.envs import ROBOTICS_TASKS, TASKS
from smcd_rl.envs.drone_landing import PLATFORMS, START, DroneLandingEnv, drone_frame
from smcd_rl.envs.panda_reach import READY_POSE, PandaReachEnv, panda_fk, panda_frame, panda_points
from smcd_rl.envs.rendering import BACKGROUND, Canvas
from smcd_rl.envs.two_link_arm import EE_COLOR, GOAL_COLOR, TwoLinkArmEnv, two_link_frame
from smcd_rl.envs.two_link_telescoping import TwoLinkTelescopingEnv, telescoping_frame
from smcd_rl.experiments.shared.video import RecordGif, video_name, write_gif

IDS = sorted({env_id for env_id, _, _ in TASKS} | {i for i in gymnasium.registry if i.startswith("smcd_rl/")})
MUJOCO = {"smcd_rl/CrippledAnt-v0"}
ROBOTICS = {env_id for env_id, _, _ in ROBOTICS_TASKS}
DRAWN = [TwoLinkArmEnv, PandaReachEnv, TwoLinkTelescopingEnv, DroneLandingEnv]
DRAWN_IDS = [
    "smcd_rl/TwoLinkArm-v0",
    "smcd_rl/PandaReach-v0",
    "smcd_rl/TwoLinkTelescoping-v0",
    "smcd_rl/DroneLanding-v0",
]


def _make(env_id: str, **kwargs: object) -> gymnasium.Env:
    if env_id in MUJOCO and importlib.util.find_spec("mujoco") is None:
        pytest.skip("needs the mujoco extra")
    if env_id in ROBOTICS and importlib.util.find_spec("gymnasium_robotics") is None:
        pytest.skip("needs the robotics extra")  # registered anyway: making it says what to install
    return gymnasium.make(env_id, **kwargs)


@pytest.mark.parametrize("env_id", IDS)
def test_every_task_renders_rgb_frames_that_follow_its_state(env_id: str) -> None:
    env = _make(env_id, render_mode="rgb_array")
    assert "rgb_array" in env.metadata["render_modes"] and env.metadata["render_fps"] > 0
    env.reset(seed=0)
    first = env.render()
    assert isinstance(first, np.ndarray) and first.dtype == np.uint8
    assert first.ndim == 3 and first.shape[2] == 3 and first.shape[0] >= 64 and first.shape[1] >= 64
    assert first.std() > 0, "a blank frame"
    again = env.render()
    np.testing.assert_array_equal(first, again)  # the same state draws the same frame
    env.action_space.seed(0)
    for _ in range(5):
        env.step(env.action_space.sample())
    assert (env.render() != first).any(), "the frame did not change after 5 random steps"
    env.reset(seed=1)
    assert (env.render() != first).any(), "two episodes' start frames are the same"
    env.close()


@pytest.mark.parametrize("cls", DRAWN, ids=lambda c: c.__name__)
def test_our_tasks_render_480_square_frames_and_refuse_other_modes(cls: type[gymnasium.Env]) -> None:
    env = cls(render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="reset"):
        env.render()
    env.reset(seed=0)
    assert env.render().shape == (480, 480, 3)
    with pytest.raises(ValueError, match="render_mode"):
        cls(render_mode="human")


@pytest.mark.parametrize(
    "env_id", [i for i in IDS if i.split("/")[1].split("-")[0] in {c.__name__[:-3] for c in DRAWN}]
)
def test_check_env_passes_with_its_render_checks(env_id: str) -> None:
    # Made by id, so that the checker can also make the env in every other declared render mode.
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # a failed render check is only a warning
        warnings.filterwarnings("ignore", "(?s).*(infinity|symmetric and normalized)")  # the spaces' own design
        check_env(gymnasium.make(env_id, render_mode="rgb_array").unwrapped)


@pytest.mark.parametrize("cls", DRAWN, ids=lambda c: c.__name__)
def test_render_without_a_mode_warns_and_returns_none(cls: type[gymnasium.Env]) -> None:
    env = cls()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None


@pytest.mark.parametrize("cls", DRAWN, ids=lambda c: c.__name__)
def test_rendering_changes_no_number(cls: type[gymnasium.Env]) -> None:
    """An episode with a frame drawn after every step has the observations of one without."""
    runs = []
    for mode in (None, "rgb_array"):
        env = cls(render_mode=mode)
        env.action_space.seed(3)
        observations = [env.reset(seed=3)[0]]
        for _ in range(5):
            observations.append(env.step(env.action_space.sample())[0])
            if mode is not None:
                env.render()
        runs.append(np.stack(observations))
    np.testing.assert_array_equal(*runs)


def _pixel(canvas_extent: float, point: tuple[float, float], size: int = 480) -> tuple[int, int]:
    column, row = Canvas(extent=canvas_extent, height=size, width=size).to_pixels(point)
    return int(row), int(column)


def test_two_link_frame_draws_the_end_effector_and_goal_where_they_are() -> None:
    # q = 0 stretches the arm along x: the end effector at (l1 + l2, 0); the default extent is 1.15 (l1 + l2).
    frame = two_link_frame((0.0, 0.0), (1.0, 1.0), goal=(0.0, 1.5))
    assert frame[_pixel(2.3, (2.0, 0.0))].tolist() == list(EE_COLOR)
    assert frame[_pixel(2.3, (0.0, 1.5))].tolist() == list(GOAL_COLOR)
    up = two_link_frame((math.pi / 2, 0.0), (1.0, 1.0), goal=(0.0, 1.5))
    assert up[_pixel(2.3, (0.0, 2.0))].tolist() == list(EE_COLOR)
    assert up[_pixel(2.3, (2.0, 0.0))].tolist() == list(BACKGROUND)


def test_telescoping_frame_keeps_its_scale_while_the_link_telescopes() -> None:
    # Same angles, second link 1.0 (k = 0) then 1.25 (k = 10): the base stays put, the end effector moves out.
    short, long = (telescoping_frame((0.0, 0.0), 1.0, k, (0.0, 1.0), 1.0) for k in (0, 10))
    extent = 1.15 * 2.25
    assert short[_pixel(extent, (2.0, 0.0))].tolist() == list(EE_COLOR)
    assert long[_pixel(extent, (2.25, 0.0))].tolist() == list(EE_COLOR)
    assert long[_pixel(extent, (2.0, 0.0))].tolist() != list(EE_COLOR)


def test_panda_points_end_at_the_forward_kinematics() -> None:
    q = torch.rand(4, 7, dtype=torch.float64)
    tools = torch.tensor([-0.3, 0.0, 0.2, 0.5], dtype=torch.float64)
    points = panda_points(q, tools)
    assert points.shape == (4, 9, 3)
    torch.testing.assert_close(points[:, -1], panda_fk(q, tools))
    torch.testing.assert_close(points[:, 0], torch.zeros(4, 3, dtype=torch.float64))


def test_panda_frame_shows_tool_goal_and_measurement() -> None:
    base = panda_frame(READY_POSE, 0.0, goal=(0.5, 0.2, 0.4))
    assert (panda_frame(READY_POSE, 0.4, goal=(0.5, 0.2, 0.4)) != base).any()  # a longer tool
    assert (panda_frame(READY_POSE, 0.0, goal=(0.3, -0.2, 0.6)) != base).any()  # another goal
    assert (panda_frame(READY_POSE, 0.0, goal=(0.5, 0.2, 0.4), measured=True) != base).any()


def test_drone_frame_marks_the_target_platform() -> None:
    frames = [drone_frame(START, target=i) for i in range(len(PLATFORMS))]
    orange = [np.nonzero((f == (235, 150, 40)).all(-1)) for f in frames]  # (rows, columns) of the target
    assert all(len(columns) > 100 for _, columns in orange)
    # The platforms lie at x = 3, 5, ..., 11 (x to the right): the orange one moves right with the target.
    centres = [float(columns.mean()) for _, columns in orange]
    assert centres == sorted(centres) and len(set(centres)) == len(PLATFORMS)
    assert (drone_frame((3.0, -1.5, 1.5), target=0) != frames[0]).any()


def test_record_gif_writes_one_gif_per_episode(tmp_path) -> None:
    env = RecordGif(
        gymnasium.make("smcd_rl/DroneLanding-v0", render_mode="rgb_array", max_episode_steps=6), tmp_path / "v"
    )
    for seed in (0, 1):
        env.reset(seed=seed)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(np.array([1.0, 0.0, 0.0], dtype=np.float32))
            done = terminated or truncated
    env.close()
    assert [p.name for p in env.written] == ["rl-video-episode-0.gif", "rl-video-episode-1.gif"]
    with Image.open(env.written[0]) as gif:
        assert gif.n_frames == 7 and gif.size == (480, 480)  # the reset frame and six steps
        assert gif.info["duration"] == 200  # 5 frames a second, the env's render_fps


def test_record_gif_needs_an_rgb_array_env(tmp_path) -> None:
    with pytest.raises(ValueError, match="rgb_array"):
        RecordGif(gymnasium.make("smcd_rl/TwoLinkArm-v0"), tmp_path)


def test_gymnasium_record_video_needs_moviepy_which_we_replace(tmp_path) -> None:
    """gymnasium 1.x's RecordVideo writes MP4 through moviepy (not a dependency); RecordGif stands in."""
    env = gymnasium.make("smcd_rl/TwoLinkArm-v0", render_mode="rgb_array", max_episode_steps=3)
    if importlib.util.find_spec("moviepy") is None:
        with pytest.raises(gymnasium.error.DependencyNotInstalled, match="moviepy"):
            gymnasium.wrappers.RecordVideo(env, str(tmp_path))
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        recorder = gymnasium.wrappers.RecordVideo(env, str(tmp_path))
        recorder.reset(seed=0)
        for _ in range(3):
            recorder.step(recorder.action_space.sample())
        recorder.close()
    assert list(tmp_path.glob("*.mp4"))


def test_write_gif_keeps_flat_colours_exactly_and_checks_its_frames(tmp_path) -> None:
    frames = [two_link_frame((0.2 * k, 0.4), (1.0, 0.7), goal=(0.5, 1.0)) for k in range(4)]
    path = write_gif(frames, tmp_path / "a" / "arm.gif", fps=10)
    with Image.open(path) as gif:
        for k, frame in enumerate(frames):
            gif.seek(k)
            np.testing.assert_array_equal(np.asarray(gif.convert("RGB")), frame)
    noisy = [np.random.default_rng(k).integers(0, 256, (32, 32, 3), dtype=np.uint8) for k in range(2)]
    with Image.open(write_gif(noisy, tmp_path / "noisy.gif", fps=10)) as gif:  # > 256 colours: quantised
        assert gif.n_frames == 2
    with pytest.raises(ValueError, match="no frames"):
        write_gif([], tmp_path / "none.gif", fps=10)
    with pytest.raises(ValueError, match="one size"):
        write_gif([frames[0], frames[0][:10]], tmp_path / "mixed.gif", fps=10)
    assert video_name("M+S(N=10)", 3) == "videos/M+S-N-10-3.gif"
