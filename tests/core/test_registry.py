"""The registry: every strategy built by name and from its stored settings, in one format everywhere."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.strategies import registry

#: One setting of every registered strategy, SMCD's seeded (its stored form) so that runs repeat.
SMCD_SETTINGS = {"num_particles": 32, "noise_std": 0.2, "flip_prob": 0.02, "seed": 7, "device": "cpu"}
SETTINGS: dict[str, dict[str, Any]] = {
    "none": {},
    "gradient_descent": {"lr": 0.05, "steps": 2, "window": 4, "loss": "huber", "huber_delta": 2.0},
    "smcd": SMCD_SETTINGS,
    "last_layer": {"prior_scale": 0.5, "noise_std": 0.1, "drift": 0.01},
    "smcd_last_layer": {"smcd": SMCD_SETTINGS, "last_layer": {"prior_scale": 0.3}},
    "combination": {
        "members": [
            {"name": "none", "settings": {}},
            {"name": "gradient_descent", "settings": {"lr": 0.1}},
            {"name": "smcd", "settings": SMCD_SETTINGS},
        ],
        "eta": 2.0,
        "share": 0.01,
    },
}


def _model() -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16, 16)), in_keys=["q"], out_key="ee")
    model.fitted = True  # a random network on purpose: the test compares two runs of it
    return model


def _run(model: smcd_rl.AdaptiveModel, strategy: smcd_rl.Adaptation) -> torch.Tensor:
    """The strategy's predictions along one stream of 6 observations, batch [3]."""
    adaptive = model.with_adaptation(strategy)
    adaptive.reset(batch_shape=(3,))
    generator = torch.Generator().manual_seed(1)
    predictions = []
    for _ in range(6):
        q = torch.rand(3, 2, generator=generator)
        td = TensorDict({"q": q, "ee": q.sin() + 0.3}, [3])
        predictions.append(adaptive(td.exclude("ee"))["ee"])
        adaptive.observe(td)
    return torch.stack(predictions)


def test_the_table_names_every_strategy_by_its_own_name() -> None:
    assert sorted(registry.REGISTRY) == sorted(SETTINGS)
    for name in registry.REGISTRY:
        assert registry.strategy_class(name).name == name
    assert registry.strategy_class("gd") is smcd_rl.GradientDescent


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_every_strategy_builds_by_name_and_again_from_its_stored_settings(name: str) -> None:
    """Built from its settings, stored (spec), rebuilt: the same settings and, run for run, the same predictions."""
    model = _model()
    built = registry.build(name, SETTINGS[name])
    assert isinstance(built, registry.strategy_class(name))
    record = registry.spec(built)
    assert record["name"] == name
    rebuilt = registry.from_spec(record)
    assert rebuilt.settings() == built.settings() and type(rebuilt) is type(built)
    assert torch.equal(_run(model, built), _run(model, rebuilt))


def test_a_strategy_saved_with_a_model_loads_with_its_settings(tmp_path: Path) -> None:
    model = _model().with_adaptation(registry.build("combination", SETTINGS["combination"]))
    smcd_rl.save(model, tmp_path / "model.pt")
    loaded = smcd_rl.load(tmp_path / "model.pt")
    assert registry.spec(loaded.adaptation) == registry.spec(model.adaptation)


def test_older_records_that_call_the_settings_config_still_build() -> None:
    """Checkpoints and combinations once stored ``{"name", "config"}`` (without SMCD's seed)."""
    legacy = {
        "name": "combination",
        "config": {"members": [{"name": "smcd", "config": {"num_particles": 8}}], "eta": 1.0, "share": 0.0},
    }
    combination = registry.from_spec(legacy)
    assert isinstance(combination, smcd_rl.Combination)
    (smcd,) = combination.members
    assert isinstance(smcd, smcd_rl.SMCD) and smcd.num_particles == 8 and "seed" not in smcd.settings()


def test_an_unknown_name_or_a_record_without_one_is_refused_clearly() -> None:
    with pytest.raises(ValueError, match=r"unknown adaptation 'magic'; choose one of \['combination'"):
        registry.build("magic", {})
    with pytest.raises(ValueError, match="a strategy spec is a dict"):
        registry.from_spec({"settings": {}})
    with pytest.raises(TypeError, match="must be a dict"):
        registry.build("smcd", [("num_particles", 8)])  # type: ignore[arg-type]


def test_the_old_module_paths_still_import_with_a_deprecation_warning() -> None:
    for old, new, name in (
        ("smcd_rl.adaptation", "smcd_rl.strategies", "SMCD"),
        ("smcd_rl.diagnostics", "smcd_rl.tuning.diagnostics", "trace"),
        ("smcd_rl.task_masks", "smcd_rl.training.task_masks", "TaskEpochs"),
    ):
        sys.modules.pop(old, None)
        with pytest.warns(DeprecationWarning, match=f"{old} moved to {new}"):
            module = importlib.import_module(old)
        assert getattr(module, name) is getattr(importlib.import_module(new), name)


def test_an_unknown_setting_names_the_strategys_settings() -> None:
    """Python's "unexpected keyword argument" named the bad key but not the good ones."""
    with pytest.raises(
        TypeError, match=r"'bogus'; the settings of a 'smcd' strategy are \['num_particles', .*'seed', 'device'"
    ):
        registry.build("smcd", {"bogus": 1})
    with pytest.raises(TypeError, match="seed must be an int, got 'x'"):  # torch's "manual_seed expected a long"
        registry.build("smcd", {"seed": "x"})
