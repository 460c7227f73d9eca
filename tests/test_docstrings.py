"""Every ``>>>`` example in the package runs and prints what its docstring says."""

import doctest
import importlib
import pkgutil

import pytest

import smcd_rl
import smcd_rl.agents
import smcd_rl.envs

# envs/ and agents/ are mapped into smcd_rl by package-dir, so they are walked separately.
MODULES = sorted(
    name
    for package in (smcd_rl, smcd_rl.envs, smcd_rl.agents)
    for _, name, _ in pkgutil.walk_packages(package.__path__, package.__name__ + ".")
)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0
