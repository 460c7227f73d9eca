"""Every package directory is declared, so a regular (non-editable) install ships all modules; the package imports lightly."""

import json
import subprocess
import sys
from pathlib import Path

import tomllib

import smcd_rl

ROOT = Path(__file__).resolve().parents[1]

#: What ``import smcd_rl`` must not import: torch and what builds on it (loaded on first use of a
#: name that needs them), and the optional extras (imported only where they are used).
HEAVY = ("torch", "tensordict", "torchrl", "ray", "stable_baselines3", "mujoco", "matplotlib", "gymnasium_robotics")


def _fresh(code: str) -> dict:
    """Run ``code`` in a fresh interpreter; it prints one JSON value, returned."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout)


def test_every_package_directory_is_listed_in_pyproject() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    declared = set(config["packages"])
    mapping = config["package-dir"]
    found = set()
    for package, directory in mapping.items():
        for init in (ROOT / directory).rglob("__init__.py"):
            relative = init.parent.relative_to(ROOT / directory)
            found.add(".".join([package, *relative.parts]) if relative.parts else package)
    assert found == declared, f"declare {sorted(found - declared)}; remove {sorted(declared - found)}"


def test_import_smcd_rl_loads_no_torch_until_a_name_needs_it() -> None:
    """``import smcd_rl`` registers the tasks but imports none of HEAVY; ``smcd_rl.SMCD`` then loads torch and works."""
    result = _fresh(
        f"""
import json, sys
import gymnasium, smcd_rl
heavy = set({list(HEAVY)!r})
before = sorted({{m.split(".")[0] for m in sys.modules}} & heavy)
registered = "smcd_rl/TwoLinkArm-v0" in gymnasium.registry
smcd = smcd_rl.SMCD(num_particles=3)
print(json.dumps({{"before": before, "registered": registered, "torch after": "torch" in sys.modules,
                   "type": type(smcd).__module__ + "." + type(smcd).__name__}}))
"""
    )
    assert result == {"before": [], "registered": True, "torch after": True, "type": "smcd_rl.strategies.smcd.SMCD"}


def test_every_public_name_resolves_and_is_listed() -> None:
    for name in smcd_rl.__all__:
        assert getattr(smcd_rl, name).__name__ == name
    assert set(smcd_rl.__all__) <= set(dir(smcd_rl))
    namespace: dict = {}
    exec("from smcd_rl import *", namespace)
    assert set(smcd_rl.__all__) <= set(namespace)
    assert smcd_rl.model.load is smcd_rl.load  # submodules stay reachable as attributes
    assert not hasattr(smcd_rl, "no_such_name")


def test_a_task_id_with_the_module_prefix_makes_the_env_without_importing_smcd_rl_first() -> None:
    """``gymnasium.make("smcd_rl:smcd_rl/TwoLinkArm-v0")`` imports the package, which registers its tasks."""
    result = _fresh(
        """
import json, sys
import gymnasium
before = "smcd_rl" in sys.modules
env = gymnasium.make("smcd_rl:smcd_rl/TwoLinkArm-v0")
obs, info = env.reset(seed=0)
print(json.dumps({"before": before, "id": env.spec.id, "obs": list(obs.shape)}))
"""
    )
    assert result == {"before": False, "id": "smcd_rl/TwoLinkArm-v0", "obs": [4]}
