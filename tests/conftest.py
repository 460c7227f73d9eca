"""Fixtures shared across test files: a small trained two-link forward-kinematics model."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless MuJoCo rendering for every test; before mujoco is imported
import pytest
import torch

import smcd_rl
from smcd_rl.allocator import keep_freed_memory
from smcd_rl.envs.two_link_arm import motor_babbling

keep_freed_memory()  # as every command does: large temporaries without page faults (no result changes)


@pytest.fixture(scope="session")
def two_link_model() -> smcd_rl.AdaptiveModel:
    """q -> end-effector model trained on 200 arms (~5 s); M+N test RMSE ~0.4 m, SMCD ~0.2 m."""
    torch.manual_seed(0)
    data = motor_babbling(200, 20, 10, generator=torch.Generator().manual_seed(0))
    net = smcd_rl.MaskedMLP(2, 2, hidden=(128, 128), dropout=0.5)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    smcd_rl.fit(model, data, epochs=12, batch_size=128, lr=2e-3, progress=False)
    return model
