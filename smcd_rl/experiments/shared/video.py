"""Frames to GIF files: the experiments' ``--video N`` and a recorder for any ``rgb_array`` env.

gymnasium's ``RecordVideo`` writes MP4 through moviepy, which this project does not depend on;
:func:`write_gif` writes animated GIFs with Pillow instead, and :class:`RecordGif` is the
wrapper that records an env's episodes with it. Frames drawn by the tasks' own frame functions
(``two_link_frame``, ``panda_frame``, ...) use a handful of flat colours, which the GIF holds
exactly in one shared palette; frames with more colours (MuJoCo's) are quantised by Pillow.

Example:
    >>> import tempfile
    >>> from pathlib import Path
    >>> from smcd_rl.envs.two_link_arm import two_link_frame
    >>> frames = [two_link_frame((0.1 * k, 0.5), (1.0, 0.8)) for k in range(10)]
    >>> path = write_gif(frames, Path(tempfile.mkdtemp()) / "arm.gif", fps=5)
    >>> from PIL import Image
    >>> with Image.open(path) as gif:
    ...     gif.n_frames, gif.size
    (10, (480, 480))
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
from PIL import Image

from smcd_rl.envs.mujoco_setup import headless_mujoco  # re-exported: the experiments' import
from smcd_rl.files import write_atomic

__all__ = ["RecordGif", "headless_mujoco", "video_name", "write_gif"]


def video_name(method: str, k: int) -> str:
    """The file name of method ``method``'s ``k``-th episode: ``videos/<method>-<k>.gif``, file-safe.

    Characters other than letters, digits, ``+``, ``.``, ``_`` and ``-`` become ``-``.

    Example:
        >>> video_name("M+S(paper)", 0), video_name("cem/S/crippled", 2)
        ('videos/M+S-paper-0.gif', 'videos/cem-S-crippled-2.gif')
    """
    safe = re.sub(r"[^A-Za-z0-9+._-]+", "-", method).strip("-")
    return f"videos/{safe}-{k}.gif"


def write_gif(frames: Iterable[np.ndarray], path: str | os.PathLike[str], *, fps: float) -> Path:
    """Write ``uint8 [H, W, 3]`` frames as an animated GIF that loops, ``fps`` frames a second (atomically).

    Args:
        frames: at least one frame, all of one size.
        path: the file (its directory is created).
        fps: frames per second (GIF timing is in hundredths of a second, so it is rounded).

    Returns:
        ``path``.

    Raises:
        ValueError: no frames, frames of different sizes or not ``uint8 [H, W, 3]``, or ``fps <= 0``.
    """
    stack = [np.asarray(frame) for frame in frames]
    if not stack:
        raise ValueError(f"no frames to write to {path}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    shape = stack[0].shape
    if any(f.shape != shape or f.dtype != np.uint8 for f in stack) or len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"frames must all be uint8 [H, W, 3] of one size, got {sorted({f.shape for f in stack})}")
    images = _palette_images(stack)
    duration = max(20, round(100 / fps) * 10)  # ms, in the GIF's 10 ms ticks; browsers slow < 20 ms down

    def save(handle: Any) -> None:
        images[0].save(handle, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)

    write_atomic(path, save, what="video")
    return Path(path)


def _palette_images(frames: Sequence[np.ndarray]) -> list[Image.Image]:
    """Palette images: one exact shared palette when the frames use at most 256 colours, else Pillow's quantiser."""
    packed = [(f[..., 0].astype(np.uint32) << 16) | (f[..., 1].astype(np.uint32) << 8) | f[..., 2] for f in frames]
    colours = np.unique(np.concatenate([np.unique(p) for p in packed]))
    if len(colours) > 256:
        first = Image.fromarray(frames[0]).quantize(256, dither=Image.Dither.NONE)
        return [first, *(Image.fromarray(f).quantize(palette=first, dither=Image.Dither.NONE) for f in frames[1:])]
    palette = np.stack([(colours >> 16) & 255, (colours >> 8) & 255, colours & 255], axis=1).astype(np.uint8)
    images = []
    for p in packed:
        image = Image.fromarray(np.searchsorted(colours, p).astype(np.uint8), mode="P")
        image.putpalette(palette.reshape(-1).tolist())
        images.append(image)
    return images


class RecordGif(gymnasium.Wrapper[Any, Any, Any, Any]):
    """Record episodes of an ``rgb_array`` env as GIFs: ``<folder>/<name_prefix>-episode-<k>.gif``.

    A small stand-in for ``gymnasium.wrappers.RecordVideo``, which needs moviepy: the frame after
    ``reset`` and after every step are kept, and the episode's GIF is written when it terminates
    or is truncated (or on ``close``, for an episode cut short), at the env's
    ``metadata["render_fps"]``.

    Args:
        env: an env made with ``render_mode="rgb_array"``.
        video_folder: where the GIFs go (created).
        episode_trigger: which episodes (0, 1, ...) to record; all by default.
        name_prefix: the files' prefix.

    Example:
        >>> import tempfile, gymnasium, smcd_rl
        >>> folder = tempfile.mkdtemp()
        >>> env = RecordGif(gymnasium.make("smcd_rl/TwoLinkArm-v0", render_mode="rgb_array", max_episode_steps=5), folder)
        >>> _ = env.reset(seed=0)
        >>> while not any(env.step(env.action_space.sample())[2:4]):
        ...     pass
        >>> env.close()
        >>> [path.name for path in env.written]
        ['rl-video-episode-0.gif']
    """

    def __init__(
        self,
        env: gymnasium.Env[Any, Any],
        video_folder: str | os.PathLike[str],
        *,
        episode_trigger: Callable[[int], bool] | None = None,
        name_prefix: str = "rl-video",
    ) -> None:
        super().__init__(env)
        if env.render_mode != "rgb_array":
            raise ValueError(f"RecordGif needs an env made with render_mode='rgb_array', got {env.render_mode!r}")
        self.video_folder = Path(video_folder)
        self.episode_trigger = episode_trigger or (lambda _: True)
        self.name_prefix = name_prefix
        self.episode = -1
        self.written: list[Path] = []
        self._frames: list[np.ndarray] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        self._flush()
        obs, info = self.env.reset(seed=seed, options=options)
        self.episode += 1
        if self.episode_trigger(self.episode):
            self._capture()
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._frames:
            self._capture()
            if terminated or truncated:
                self._flush()
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        self._flush()
        super().close()

    def _capture(self) -> None:
        frame = self.env.render()
        assert isinstance(frame, np.ndarray), "an rgb_array env renders one frame"
        self._frames.append(frame)

    def _flush(self) -> None:
        if not self._frames:
            return
        path = self.video_folder / f"{self.name_prefix}-episode-{self.episode}.gif"
        fps = float(self.env.metadata.get("render_fps") or 30)
        self.written.append(write_gif(self._frames, path, fps=fps))
        self._frames = []
