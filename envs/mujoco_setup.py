"""Setting MuJoCo up for the tasks: a headless rendering backend, and a clear error when an extra is missing.

MuJoCo renders through an OpenGL backend named by the ``MUJOCO_GL`` environment variable; without
it gymnasium tries GLFW, which needs a display, and rendering fails with ``mujoco.FatalError: an
OpenGL platform library has not been loaded into this process``. :func:`headless_mujoco` chooses
EGL (or OSMesa where only that is installed) when there is no display and ``MUJOCO_GL`` is unset;
the MuJoCo tasks and :class:`~smcd_rl.integrations.task_family.TaskFamily` call it when they are
made with a ``render_mode``, which is before their first frame (gymnasium reads the variable
when it makes the renderer).

:func:`missing_extra` turns the ``ModuleNotFoundError`` of an optional dependency into one that
names the extra and the command that installs it from a checkout.

Example:
    >>> import os
    >>> backend = headless_mujoco()
    >>> backend == os.environ.get("MUJOCO_GL")
    True
    >>> error = missing_extra(ModuleNotFoundError("No module named 'mujoco'", name="mujoco"), "mujoco", "CrippledAnt")
    >>> print(error)
    CrippledAnt needs the optional dependency 'mujoco' (extra [mujoco]): run pip install -e ".[mujoco]" in the smcd-rl checkout, or bash bootstrap.sh
"""

from __future__ import annotations

import ctypes.util
import os
import sys
import warnings

__all__ = ["EXTRA_MODULES", "headless_mujoco", "missing_extra"]

#: The top-level modules each extra provides (what ``missing_extra`` recognises).
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "mujoco": ("mujoco", "glfw"),
    "robotics": ("gymnasium_robotics", "mujoco", "glfw"),
}
# Backends to try without a display, with the shared library each needs.
_HEADLESS_BACKENDS = (("egl", "EGL"), ("osmesa", "OSMesa"))


def headless_mujoco() -> str | None:
    """Choose a headless MuJoCo rendering backend when there is no display and ``MUJOCO_GL`` is unset.

    Sets ``MUJOCO_GL`` to ``"egl"`` if the EGL library is found, else to ``"osmesa"`` if OSMesa
    is, and warns (saying what to install and set) if neither is. Does nothing on a machine with
    a display (``DISPLAY`` or ``WAYLAND_DISPLAY``), outside Linux, or when ``MUJOCO_GL`` is
    already set. Must run before the first ``render()``.

    Returns:
        The value of ``MUJOCO_GL`` afterwards (``None`` if unset).
    """
    chosen = os.environ.get("MUJOCO_GL")
    if chosen or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or not sys.platform.startswith("linux"):
        return chosen or None
    for backend, library in _HEADLESS_BACKENDS:
        if ctypes.util.find_library(library):
            os.environ["MUJOCO_GL"] = backend
            return backend
    warnings.warn(
        "No display and no EGL or OSMesa library found: MuJoCo cannot render here. Install one "
        "(Debian: apt-get install libegl1, or libosmesa6) and set MUJOCO_GL=egl (or osmesa).",
        RuntimeWarning,
        stacklevel=2,
    )
    return None


def missing_extra(error: ModuleNotFoundError, extra: str, what: str) -> ModuleNotFoundError:
    """A ``ModuleNotFoundError`` naming the extra that provides the missing module, and how to install it.

    Args:
        error: The error of the failed import.
        extra: The extra that provides it (``"mujoco"``, ``"robotics"``).
        what: What needs it, for the message (a module or task name).

    Returns:
        The new error (raise it ``from error``), or ``error`` itself when the missing module is
        not one of the extra's (a genuine bug, not a missing install).
    """
    missing = (error.name or "").split(".")[0]
    if missing not in EXTRA_MODULES[extra]:
        return error
    return ModuleNotFoundError(
        f"{what} needs the optional dependency {missing!r} (extra [{extra}]): run "
        f'pip install -e ".[{extra}]" in the smcd-rl checkout, or bash bootstrap.sh',
        name=error.name,
    )
