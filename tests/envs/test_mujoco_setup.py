"""MuJoCo set-up: headless rendering without MUJOCO_GL, and the install hint when an extra is missing.

Each end-to-end case runs in a fresh interpreter: ``tests/conftest.py`` sets ``MUJOCO_GL=egl`` in
this one, and a module that failed to import (or mujoco's GL choice) would leak into other tests.
"""

from __future__ import annotations

import ctypes.util
import json
import os
import subprocess
import sys

import pytest

from smcd_rl.envs.mujoco_setup import headless_mujoco, missing_extra

pytest.importorskip("mujoco")


def _fresh(code: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter without a display or MUJOCO_GL (plus ``env``)."""
    clean = {
        k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")
    }
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env={**clean, **env}, check=False
    )


_RENDER = """
import json, os, gymnasium, smcd_rl
from smcd_rl.integrations.task_family import TaskFamily, Uniform
shapes = {}
ant = gymnasium.make("smcd_rl/CrippledAnt-v0", render_mode="rgb_array", width=48, height=32)
ant.reset(seed=0)
shapes["ant"] = list(ant.render().shape)
hopper = TaskFamily(gymnasium.make("Hopper-v5", render_mode="rgb_array", width=48, height=32),
                    params={"body_mass:torso": Uniform(2.0, 4.0)})
hopper.reset(seed=0)
shapes["hopper"] = list(hopper.render().shape)
print(json.dumps({"shapes": shapes, "MUJOCO_GL": os.environ.get("MUJOCO_GL")}))
"""


@pytest.mark.slow  # about 5-10 s: a fresh interpreter imports torch and mujoco and opens an EGL context
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="headless rendering is chosen on Linux")
@pytest.mark.skipif(ctypes.util.find_library("EGL") is None, reason="needs the EGL library (libegl1)")
def test_mujoco_tasks_render_headless_without_mujoco_gl() -> None:
    done = _fresh(_RENDER)
    assert done.returncode == 0, done.stderr[-2000:]  # before: mujoco.FatalError: an OpenGL platform library ...
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result == {"shapes": {"ant": [32, 48, 3], "hopper": [32, 48, 3]}, "MUJOCO_GL": "egl"}


def test_headless_mujoco_chooses_a_backend_only_without_display_and_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    monkeypatch.delenv("DISPLAY", raising=False)
    assert headless_mujoco() == "osmesa"  # the user's choice stays
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setenv("DISPLAY", ":0")
    assert headless_mujoco() is None and "MUJOCO_GL" not in os.environ  # a display: glfw works
    monkeypatch.delenv("DISPLAY")
    libraries = {"EGL": None, "OSMesa": "libOSMesa.so.8"}  # a machine with OSMesa only
    monkeypatch.setattr(ctypes.util, "find_library", libraries.get)
    assert headless_mujoco() == "osmesa" == os.environ["MUJOCO_GL"]
    monkeypatch.delenv("MUJOCO_GL")
    libraries["OSMesa"] = None
    with pytest.warns(RuntimeWarning, match="set MUJOCO_GL=egl"):
        assert headless_mujoco() is None
    assert "MUJOCO_GL" not in os.environ


_MISSING = """
import sys
sys.modules[{module!r}] = None  # as if the extra were not installed
import gymnasium, smcd_rl
try:
    {statement}
except ModuleNotFoundError as error:
    print(type(error).__name__, error)
"""


@pytest.mark.parametrize(
    ("module", "statement", "extra"),
    [
        ("mujoco", 'gymnasium.make("smcd_rl/CrippledAnt-v0")', "mujoco"),
        ("mujoco", "from smcd_rl.integrations.task_family import TaskFamily", "mujoco"),
        ("gymnasium_robotics", 'gymnasium.make("smcd_rl/FetchPushHeavy-v0")', "robotics"),
        ("gymnasium_robotics", 'gymnasium.make("smcd_rl/FrankaReachTool-v0")', "robotics"),
        ("mujoco", 'gymnasium.make("smcd_rl/FetchReachRotated-v0")', "robotics"),
    ],
)
def test_a_missing_extra_is_named_with_the_command_that_installs_it(module: str, statement: str, extra: str) -> None:
    done = _fresh(_MISSING.format(module=module, statement=statement))
    assert done.returncode == 0, done.stderr[-2000:]
    line = done.stdout.strip().splitlines()[-1]
    assert line.startswith("ModuleNotFoundError ")
    assert f"'{module}' (extra [{extra}])" in line
    assert f'pip install -e ".[{extra}]"' in line and "bash bootstrap.sh" in line


def test_missing_extra_keeps_other_errors() -> None:
    other = ModuleNotFoundError("No module named 'scipy'", name="scipy")
    assert missing_extra(other, "mujoco", "x") is other  # not the extra's module: a real bug, not a hint
    hinted = missing_extra(ModuleNotFoundError(name="gymnasium_robotics.envs"), "robotics", "Fetch")
    assert hinted.name == "gymnasium_robotics.envs" and "[robotics]" in str(hinted)
