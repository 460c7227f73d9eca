"""A small raster drawing kit for the tasks' ``rgb_array`` frames: lines, discs, rings and boxes on numpy.

Each task draws its frame with a pure function of its state (``two_link_frame``,
``panda_frame``, ...) on a :class:`Canvas`: a ``uint8 [H, W, 3]`` image with a linear map from
world coordinates (metres) to pixels. Shapes are filled by testing pixel centres inside a
bounding box, with no anti-aliasing, so a frame is exactly the same for the same state on every
machine, and a 480 x 480 frame of a few dozen shapes takes about a millisecond.

Example:
    >>> canvas = Canvas(center=(0.0, 0.0), extent=1.0, height=64, width=64)
    >>> canvas.line((-0.5, 0.0), (0.5, 0.0), color=(255, 0, 0), width=0.1)
    >>> canvas.disc((0.0, 0.5), 0.1, color=(0, 0, 255))
    >>> frame = canvas.image
    >>> frame.shape, frame.dtype, frame[32, 32].tolist(), frame[16, 32].tolist()
    ((64, 64, 3), dtype('uint8'), [255, 0, 0], [0, 0, 255])
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TypeVar

import gymnasium
import numpy as np
from numpy.typing import ArrayLike

State = TypeVar("State")

__all__ = [
    "render_state",
    "BACKGROUND",
    "Canvas",
    "Color",
    "FRAME_SIZE",
    "RENDER_MODES",
    "check_render_mode",
]

#: An RGB colour, each channel 0..255.
Color = tuple[int, int, int]
#: The default frame size in pixels (height, width).
FRAME_SIZE: tuple[int, int] = (480, 480)
#: The background every task draws on.
BACKGROUND: Color = (245, 245, 240)
#: The render modes every smcd_rl task declares in its ``metadata``.
RENDER_MODES: tuple[str, ...] = ("rgb_array",)


def check_render_mode(render_mode: str | None) -> None:
    """Raise ValueError unless ``render_mode`` is ``None`` or one of :data:`RENDER_MODES`.

    Example:
        >>> check_render_mode("human")
        Traceback (most recent call last):
        ...
        ValueError: render_mode must be None or one of ['rgb_array'], got 'human'.
    """
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}, got {render_mode!r}.")


class Canvas:
    """An RGB image with a world-to-pixel map: x to the right, y up, ``extent`` metres from centre to the nearer edge.

    Args:
        center: the world point at the image's centre.
        extent: half the world span of the image's shorter side (m), ``> 0``.
        height: image height in pixels.
        width: image width in pixels.
        background: the fill colour, or an image ``uint8 [height, width, 3]`` to start from (copied),
            e.g. a static scene drawn once.

    Example:
        >>> canvas = Canvas(center=(1.0, 0.0), extent=2.0, height=100, width=100)
        >>> canvas.to_pixels([[1.0, 0.0], [3.0, 2.0]])  # the centre, then the top-right corner
        array([[ 50.,  50.],
               [100.,   0.]])
    """

    def __init__(
        self,
        *,
        center: Sequence[float] = (0.0, 0.0),
        extent: float = 1.0,
        height: int = FRAME_SIZE[0],
        width: int = FRAME_SIZE[1],
        background: Color | np.ndarray = BACKGROUND,
    ) -> None:
        if not (math.isfinite(extent) and extent > 0):
            raise ValueError(f"extent must be finite and > 0, got {extent!r}")
        if height < 1 or width < 1:
            raise ValueError(f"height and width must be >= 1, got {height} x {width}")
        self.image = np.empty((height, width, 3), dtype=np.uint8)
        self.image[:] = background  # a colour broadcasts; an image of another size raises here
        self.center = (float(center[0]), float(center[1]))
        self.scale = min(height, width) / (2.0 * extent)  # pixels per metre

    def to_pixels(self, points: ArrayLike) -> np.ndarray:
        """World points ``[..., 2]`` to pixel coordinates ``[..., 2]`` (column, row), as floats."""
        p = np.asarray(points, dtype=np.float64)
        height, width = self.image.shape[:2]
        column = width / 2 + (p[..., 0] - self.center[0]) * self.scale
        row = height / 2 - (p[..., 1] - self.center[1]) * self.scale
        return np.stack((column, row), axis=-1)

    def _window(self, low: np.ndarray, high: np.ndarray) -> tuple[slice, slice, np.ndarray, np.ndarray] | None:
        """The pixel rows and columns whose centres may lie in the pixel-space box, and those centres."""
        height, width = self.image.shape[:2]
        c0, r0 = max(int(math.floor(low[0])), 0), max(int(math.floor(low[1])), 0)
        c1, r1 = min(int(math.ceil(high[0])) + 1, width), min(int(math.ceil(high[1])) + 1, height)
        if c0 >= c1 or r0 >= r1:
            return None
        columns = np.arange(c0, c1, dtype=np.float64)[None, :] + 0.5
        rows = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5
        return slice(r0, r1), slice(c0, c1), columns, rows

    def line(self, start: ArrayLike, end: ArrayLike, *, color: Color, width: float = 0.02) -> None:
        """A segment with round caps, ``width`` metres wide (at least one pixel)."""
        a, b = self.to_pixels(start), self.to_pixels(end)
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            return
        half = max(width * self.scale, 1.0) / 2
        window = self._window(np.minimum(a, b) - half, np.maximum(a, b) + half)
        if window is None:
            return
        rows, columns, x, y = window
        d = b - a
        length2 = float(d @ d)
        t = np.zeros_like(x * y) if length2 == 0 else np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / length2, 0, 1)
        inside = (x - a[0] - t * d[0]) ** 2 + (y - a[1] - t * d[1]) ** 2 <= half * half
        self.image[rows, columns][inside] = color  # two slices: a view, so this writes the image

    def polyline(self, points: ArrayLike, *, color: Color, width: float = 0.02) -> None:
        """Segments through consecutive points ``[n, 2]``."""
        p = np.asarray(points, dtype=np.float64)
        for start, end in zip(p[:-1], p[1:], strict=True):
            self.line(start, end, color=color, width=width)

    def disc(self, center: ArrayLike, radius: float, *, color: Color) -> None:
        """A filled circle of ``radius`` metres (at least one pixel across)."""
        self.ring(center, radius, color=color, width=None)

    def ring(self, center: ArrayLike, radius: float, *, color: Color, width: float | None = 0.02) -> None:
        """A circle's outline ``width`` metres wide (``None``: filled)."""
        c = self.to_pixels(center)
        if not np.isfinite(c).all():
            return
        outer = max(radius * self.scale, 0.5)
        window = self._window(c - outer, c + outer)
        if window is None:
            return
        rows, columns, x, y = window
        r2 = (x - c[0]) ** 2 + (y - c[1]) ** 2
        inside = r2 <= outer * outer
        if width is not None:
            inner = max(outer - max(width * self.scale, 1.0), 0.0)
            inside &= r2 >= inner * inner
        self.image[rows, columns][inside] = color

    def box(self, low: ArrayLike, high: ArrayLike, *, color: Color, width: float | None = None) -> None:
        """An axis-aligned rectangle from corner ``low`` to ``high`` (world), filled or outlined ``width`` m wide."""
        (x0, y0), (x1, y1) = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        if width is not None:
            corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
            self.polyline(corners, color=color, width=width)
            return
        p = self.to_pixels([[min(x0, x1), max(y0, y1)], [max(x0, x1), min(y0, y1)]])
        height, width_px = self.image.shape[:2]
        c0, r0 = max(int(round(p[0, 0])), 0), max(int(round(p[0, 1])), 0)
        c1, r1 = min(int(round(p[1, 0])), width_px), min(int(round(p[1, 1])), height)
        if c0 < c1 and r0 < r1:
            self.image[r0:r1, c0:c1] = color


def render_state(
    render_mode: str | None, state: State | None, draw: Callable[[State], np.ndarray]
) -> np.ndarray | None:
    """What an env's ``render()`` returns: ``draw(state)`` in ``"rgb_array"`` mode.

    Without a render mode it warns and returns None, as gymnasium's own envs do; before the first
    ``reset()`` (``state`` is None) it raises.

    Example:
        >>> render_state("rgb_array", 3, lambda n: np.zeros((n, n, 3), np.uint8)).shape
        (3, 3, 3)
    """
    if render_mode is None:
        gymnasium.logger.warn(
            "You are calling render method without specifying any render mode; "
            'pass render_mode="rgb_array" at initialization.'
        )
        return None
    if state is None:
        raise RuntimeError("call reset() before render().")
    return draw(state)
