"""mbrl-lib integration: the adapter under mbrl-lib's own ModelEnv and TrajectoryOptimizerAgent.

The adapter's own tests need only torch; the rest run mbrl-lib 0.2.0 itself (installed by
``scripts/install_mbrl_lib.sh``, which CI runs) and skip, saying so, where it is not importable.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import gymnasium
import numpy as np
import pytest
import torch
from torch import Tensor

import smcd_rl
from smcd_rl.integrations.gymnasium import AdaptationWrapper, collect_transitions
from smcd_rl.integrations.mbrl_lib import (
    MbrlLibModel,
    make_cem_agent,
    make_model_env,
    pets_loop,
    replay_buffer_to_tensordict,
    termination_for_mbrl,
)

try:
    import mbrl.models
    import mbrl.util
except Exception as err:  # any failure to import (hydra-core 1.0.3 raises ValueError) means: not usable here
    MBRL_MISSING: str | None = f"mbrl-lib is not importable ({err}); install it with bash scripts/install_mbrl_lib.sh"
else:
    MBRL_MISSING = None

needs_mbrl = pytest.mark.skipif(MBRL_MISSING is not None, reason=MBRL_MISSING or "")


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small models: threads only add overhead on the shared 2-core machine
    yield
    torch.set_num_threads(threads)


def toy_model(*, adaptation: smcd_rl.Adaptation | None = None) -> smcd_rl.AdaptiveDynamicsModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=(16,))
    if adaptation is None:
        adaptation = smcd_rl.SMCD(num_particles=8, generator=torch.Generator().manual_seed(0))
    model = smcd_rl.AdaptiveDynamicsModel(net, adaptation)
    model.fitted = True  # a random stand-in: these tests check which masks predict, not how well
    model.reset()
    return model


def pendulum_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    """InvertedPendulum-v5's reward: 1 while the pole angle is within 0.2 rad."""
    return (next_obs[..., 1].abs() <= 0.2).to(torch.float32)


def pendulum_termination(next_obs: Tensor) -> Tensor:
    return ~(torch.isfinite(next_obs).all(-1) & (next_obs[..., 1].abs() <= 0.2))


# ---------------------------------------------------------------- the adapter, without mbrl-lib
def test_fixed_model_keeps_one_posterior_mask_per_row_for_the_horizon() -> None:
    model = toy_model()
    adapter = MbrlLibModel(model, propagation="fixed_model")
    rng = torch.Generator().manual_seed(1)
    state = adapter.reset(np.zeros((32, 3), dtype=np.float32), rng=rng)
    masks = state["masks"]
    particles = model.particles.to(masks.dtype)
    # Every row's mask is one of the particles.
    assert bool((masks.unsqueeze(1) == particles.unsqueeze(0)).all(-1).any(-1).all())
    obs = state["obs"]
    for _ in range(3):
        action = torch.randn(32, 1)
        next_obs, reward, terminals, state = adapter.sample(action, state, rng=rng)
        torch.testing.assert_close(next_obs, model.step(obs, action, mask=masks))
        assert reward is None and terminals is None and state["masks"] is masks
        obs = next_obs


def test_random_model_draws_new_masks_and_expectation_uses_the_adapted_model() -> None:
    model = toy_model()
    obs, action = torch.randn(64, 3), torch.randn(64, 1)
    rng = torch.Generator().manual_seed(0)
    random_model = MbrlLibModel(model, propagation="random_model")
    state = random_model.reset(obs, rng=rng)
    first = random_model.sample(action, state, rng=rng)[0]
    second = random_model.sample(action, state, rng=rng)[0]
    assert not torch.equal(first, second)  # the same inputs, other masks
    expectation = MbrlLibModel(model, propagation="expectation", reward_fn=pendulum_reward)
    next_obs, reward, _, _ = expectation.sample(action, expectation.reset(obs), rng=rng)
    torch.testing.assert_close(next_obs, model.step(obs, action))
    assert reward is not None and reward.shape == (64, 1)
    torch.testing.assert_close(reward[:, 0], pendulum_reward(obs, action, next_obs))


def test_refuses_what_it_cannot_do() -> None:
    with pytest.raises(ValueError, match="propagation must be one of"):
        MbrlLibModel(toy_model(), propagation=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="keeps no particles"):
        MbrlLibModel(toy_model(adaptation=smcd_rl.NoAdaptation()), propagation="fixed_model")
    MbrlLibModel(toy_model(adaptation=smcd_rl.NoAdaptation()), propagation="expectation")
    batched = toy_model()
    batched.reset(batch_shape=(2,))
    with pytest.raises(ValueError, match="batch_shape"):
        MbrlLibModel(batched).reset(np.zeros((4, 3), dtype=np.float32))
    done = termination_for_mbrl(lambda next_obs: next_obs.sum(-1, keepdim=True).unsqueeze(0) > 0)
    with pytest.raises(ValueError, match="termination_fn returned shape"):
        done(torch.zeros(3, 1), torch.zeros(3, 3))


def test_without_mbrl_lib_the_builders_say_how_to_install_it() -> None:
    code = textwrap.dedent(
        """
        import sys
        sys.modules["mbrl"] = None  # as if mbrl-lib were not installed
        import gymnasium
        import smcd_rl.integrations.mbrl_lib as m  # importing works without it
        try:
            m.make_model_env(gymnasium.make("Pendulum-v1"), None, None)
        except ImportError as err:
            print(err)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert "bash scripts/install_mbrl_lib.sh" in result.stdout
    assert "pip install --no-deps mbrl==0.2.0" in result.stdout


# ---------------------------------------------------------------- with mbrl-lib itself
@needs_mbrl
def test_model_env_scores_sequences_with_the_adapted_model_and_stops_at_termination() -> None:
    """mbrl-lib's ``evaluate_action_sequences`` equals a rollout of ``model.step`` by hand."""
    model = toy_model()
    env = gymnasium.make("Pendulum-v1")  # only its spaces are read: 3 observations, 1 action

    def reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
        return obs[:, 0] + next_obs[:, 1]  # uses the state before the step too

    def done(next_obs: Tensor) -> Tensor:
        return next_obs[:, 2] > 0.0

    model_env = make_model_env(env, model, reward, done, propagation="expectation")
    start = np.array([0.1, -0.2, 0.3], dtype=np.float32)
    sequences = torch.randn(4, 5, 1)  # 4 candidates, horizon 5
    scores = model_env.evaluate_action_sequences(sequences, start, num_particles=2)
    expected = torch.zeros(4)
    obs, alive = torch.as_tensor(start).expand(4, 3), torch.ones(4, dtype=torch.bool)
    for t in range(5):
        next_obs = model.step(obs, sequences[:, t])
        expected += torch.where(alive, reward(obs, sequences[:, t], next_obs), torch.zeros(4))
        alive &= ~done(next_obs)
        obs = next_obs
    torch.testing.assert_close(scores, expected)


@needs_mbrl
def test_replay_buffer_to_tensordict_keeps_every_transition() -> None:
    buffer = mbrl.util.ReplayBuffer(10, (3,), (1,), rng=np.random.default_rng(0))
    for i in range(4):
        buffer.add(np.full(3, i, np.float32), np.ones(1, np.float32), np.full(3, i + 1, np.float32), 0.5, i == 3, False)
    data = replay_buffer_to_tensordict(buffer)
    assert data.batch_size == (4,)
    assert data["next", "observation"][2].tolist() == [3.0, 3.0, 3.0]
    assert data["next", "done"][:, 0].tolist() == [False, False, False, True]


@needs_mbrl
def test_mbrl_lib_cem_agent_balances_inverted_pendulum() -> None:
    """mbrl-lib's own ``TrajectoryOptimizerAgent`` (CEM) through the adapter keeps the pole up.

    An SMCD model fitted on 1000 random transitions plans with ``propagation="fixed_model"``
    (5 posterior masks per candidate) and adapts on every real step (``AdaptationWrapper``).
    Why 30 of 50 steps cannot be reached by chance: with uniform random actions an
    InvertedPendulum-v5 episode lasted 6.0 steps on average over 1000 seeded episodes, the longest
    34, and only 2 in 1000 reached 30. Seeds 0-5 of this setting balanced 40-50 steps (seed 0: 50).
    """
    torch.manual_seed(0)
    env = gymnasium.make("InvertedPendulum-v5")
    data = collect_transitions(env, None, 1000, seed=0)
    net = smcd_rl.MaskedMLP(4 + 1, 4, hidden=(128, 128), dropout=0.1)
    smcd = smcd_rl.SMCD(num_particles=50, noise_std=0.05, flip_prob=0.001, generator=torch.Generator().manual_seed(0))
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd)
    smcd_rl.fit_dynamics(model, data, epochs=30, batch_size=64, lr=1e-3, seed=0, progress=False)
    adaptive_env = AdaptationWrapper(env, model)  # model.reset() on reset, model.observe on every step
    model_env = make_model_env(env, model, pendulum_reward, pendulum_termination, seed=0)
    assert isinstance(model_env, mbrl.models.ModelEnv)
    agent = make_cem_agent(model_env, planning_horizon=10, num_iterations=3, population_size=100, num_particles=5)
    obs, _ = adaptive_env.reset(seed=1000)
    agent.reset()
    steps = 0
    for _ in range(50):
        obs, _, terminated, truncated, info = adaptive_env.step(agent.act(obs))
        steps += 1
        if terminated or truncated:
            break
    assert steps >= 30, f"the pole fell after {steps} steps"
    assert info["smcd"]["log_evidence"] != 0.0  # the model adapted on the real steps


@needs_mbrl
def test_pets_loop_runs_and_adapts_every_step() -> None:
    env = gymnasium.make("InvertedPendulum-v5")
    net = smcd_rl.MaskedMLP(4 + 1, 4, hidden=(32,), dropout=0.1)
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.SMCD(num_particles=10, noise_std=0.05, flip_prob=0.001))
    episodes: list[tuple[int, float, int]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the model is fitted before it first adapts: no UnfittedModelWarning
        returns = pets_loop(
            env,
            model,
            pendulum_reward,
            pendulum_termination,
            num_steps=30,
            initial_steps=100,
            freq_train_model=10,
            fit_epochs=2,
            planning_horizon=3,
            num_iterations=2,
            population_size=16,
            num_particles=2,
            on_episode=lambda *row: episodes.append(row),
        )
    assert len(returns) == len(episodes) >= 1
    assert sum(length for _, _, length in episodes) == 30 and episodes[-1][0] == 30
    assert model.summary()["log_evidence"].item() != 0.0


def test_no_installed_package_shadows_the_projects_tests() -> None:
    """mbrl 0.2.0's wheel ships a top-level ``tests`` package; scripts/install_mbrl_lib.sh removes it.

    Left in place, ``tests.core...`` imports resolve into site-packages and test collection fails.
    """
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec("tests")
    root = Path(__file__).resolve().parents[1]
    assert spec is not None and [Path(p).resolve() for p in spec.submodule_search_locations] == [root]
