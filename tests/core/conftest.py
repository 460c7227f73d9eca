"""Fixtures of the core tests: a small fitted sine model and one torch thread for tiny networks."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch
from tensordict import TensorDict

import smcd_rl


@pytest.fixture(scope="module")
def sine_model() -> smcd_rl.AdaptiveModel:
    """A small network fitted to ``sin(q)`` (under a second); its targets' std is about 0.53 per output."""
    torch.manual_seed(0)
    q = torch.rand(400, 2) * 2 - 1
    m = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(32,), dropout=0.2), in_keys=["q"], out_key="ee")
    smcd_rl.fit(m, TensorDict({"q": q, "ee": torch.sin(q)}, [400]), epochs=20, lr=1e-2, progress=False)
    return m


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Tiny networks: on a shared 2-core machine a second thread only waits for the first, and
    under load the waits made such tests 20 to 35 times slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
