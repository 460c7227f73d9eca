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


# ---------------------------------------------------------------- bad input, refused before any work
@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ({"planning_horizon": 0}, r"planning_horizon must be an int >= 1, got 0"),
        ({"num_iterations": 0}, r"num_iterations must be an int >= 1, got 0 \(with 0, mbrl-lib's CEM never samples"),
        ({"population_size": 0}, r"population_size must be an int >= 1, got 0"),
        ({"num_particles": 0}, r"num_particles must be an int >= 1, got 0"),
        ({"replan_freq": 0}, r"replan_freq must be an int >= 1, got 0"),
        ({"replan_freq": 16}, r"replan_freq must be in \[1, planning_horizon=15\]"),
        ({"planning_horizon": 2.5}, r"planning_horizon must be an int >= 1, got 2.5"),
        ({"num_particles": True}, r"num_particles must be an int >= 1, got True"),
        ({"elite_ratio": 0}, r"elite_ratio must be in \(0, 1\], got 0"),
        ({"elite_ratio": 2.0}, r"elite_ratio must be in \(0, 1\], got 2.0"),
        ({"elite_ratio": float("nan")}, r"elite_ratio must be in \(0, 1\], got nan"),
        ({"alpha": -1.0}, r"alpha must be in \[0, 1\) \(with 1 the CEM mean never moves from action 0\), got -1.0"),
        ({"alpha": 1.0}, r"alpha must be in \[0, 1\)"),
        (
            {"population_size": 10, "elite_ratio": 0.1},
            r"keeps 1 elite, but CEM with num_iterations=5 needs at least 2 .*population_size >= 11, elite_ratio > 0.1,"
            r" or num_iterations=1",
        ),
    ],
)
def test_make_cem_agent_refuses_settings_out_of_range(setting: dict[str, float], message: str) -> None:
    """Before: mbrl-lib failed deep inside (horizon 0, elite_ratio 2, ...) or planned NaN or action 0."""
    with pytest.raises(ValueError, match=message):
        make_cem_agent(object(), **setting)  # refused before the model env is looked at


def test_make_cem_agent_accepts_one_elite_with_one_iteration() -> None:
    from smcd_rl.integrations.mbrl_lib import _check_cem_settings

    _check_cem_settings(
        planning_horizon=1,
        num_iterations=1,
        population_size=1,
        elite_ratio=1.0,
        alpha=0.0,
        num_particles=1,
        replan_freq=1,
    )


class CountingEnv(gymnasium.Wrapper):
    """Counts resets and steps; raises KeyboardInterrupt at step ``stop_at`` (an interrupted run)."""

    def __init__(self, env: gymnasium.Env, stop_at: int | None = None) -> None:
        super().__init__(env)
        self.resets, self.steps, self.stop_at = 0, 0, stop_at

    def reset(self, **kwargs):  # type: ignore[no-untyped-def]
        self.resets += 1
        return self.env.reset(**kwargs)

    def step(self, action):  # type: ignore[no-untyped-def]
        if self.steps == self.stop_at:
            raise KeyboardInterrupt
        self.steps += 1
        return self.env.step(action)


def pets_model() -> smcd_rl.AdaptiveDynamicsModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(4 + 1, 4, hidden=(32,), dropout=0.1)
    smcd = smcd_rl.SMCD(num_particles=10, noise_std=0.05, flip_prob=0.001, generator=torch.Generator().manual_seed(0))
    return smcd_rl.AdaptiveDynamicsModel(net, smcd)


TINY_PETS = {"num_steps": 30, "initial_steps": 100, "freq_train_model": 10, "fit_epochs": 2, "planning_horizon": 3,
             "num_iterations": 2, "population_size": 16, "num_particles": 2}  # fmt: skip


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ({"planning_horizon": 0}, r"planning_horizon must be an int >= 1, got 0"),
        ({"elite_ratio": 2.0}, r"elite_ratio must be in \(0, 1\], got 2.0"),
        ({"population_size": 0}, r"population_size must be an int >= 1"),
        ({"num_particles": 0}, r"num_particles must be an int >= 1"),
        ({"num_iterations": 0}, r"num_iterations must be an int >= 1"),
        ({"alpha": -1.0}, r"alpha must be in \[0, 1\)"),
        ({"num_steps": 0}, r"num_steps must be an int >= 1, got 0"),
        ({"fit_epochs": 0}, r"fit_epochs must be an int >= 1, got 0"),
        ({"fit_batch_size": 0}, r"fit_batch_size must be an int >= 1, got 0"),
        ({"lr": 0.0}, r"lr must be a finite number > 0, got 0.0"),
        ({"seed": -1}, r"seed must be an int >= 0, got -1"),
    ],
)
def test_pets_loop_refuses_bad_settings_before_any_step(setting: dict[str, float], message: str) -> None:
    """Before: the CEM settings failed only after the random rollouts and the first fit."""
    env = CountingEnv(gymnasium.make("InvertedPendulum-v5"))
    with pytest.raises(ValueError, match=message):
        pets_loop(env, pets_model(), pendulum_reward, pendulum_termination, **{**TINY_PETS, **setting})
    assert env.resets == env.steps == 0


@needs_mbrl
def test_model_env_refuses_an_env_of_other_sizes_before_any_step() -> None:
    """Before: a 4-observation model was accepted for Pendulum's 3 observations."""
    env = CountingEnv(gymnasium.make("Pendulum-v1"))
    with pytest.raises(ValueError, match=r"observation space is Box.*\(3,\).*observations have size 4.*size 3"):
        make_model_env(env, pets_model(), pendulum_reward)
    with pytest.raises(ValueError, match=r"observations have size 4"):
        pets_loop(env, pets_model(), pendulum_reward, **TINY_PETS)
    assert env.resets == env.steps == 0
    wide = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 2, 3, hidden=(8,)), smcd_rl.SMCD(num_particles=4))
    with pytest.raises(ValueError, match=r"action space is Box.*actions have size 2.*action size 1"):
        make_model_env(env, wide, pendulum_reward)


def test_sample_refuses_a_state_it_did_not_make() -> None:
    """Before: a bare ``KeyError: 'masks'``, and masks of any values were used as they were."""
    model = toy_model()
    fixed = MbrlLibModel(model, propagation="fixed_model")
    action = torch.zeros(4, 1)
    foreign = MbrlLibModel(model, propagation="expectation").reset(np.zeros((4, 3), dtype=np.float32))
    with pytest.raises(ValueError, match=r"not from this model's reset: it needs the keys \['obs', 'masks'\]"):
        fixed.sample(action, foreign)
    with pytest.raises(ValueError, match=r"not from this model's reset"):
        fixed.sample(action, {"obs": torch.zeros(4, 3), "masks": torch.ones(4, 5)})
    state = fixed.reset(np.zeros((4, 3), dtype=np.float32), rng=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"masks must hold only 0 and 1 .*got 0.5"):
        fixed.sample(action, {**state, "masks": torch.full_like(state["masks"], 0.5)})
    with pytest.raises(ValueError, match=r"obs must be a tensor \[B, 3\], got \[4, 2\]"):
        MbrlLibModel(model, propagation="expectation").sample(action, {"obs": torch.zeros(4, 2)})
    fixed.sample(action, state)  # its own state is fine


# ---------------------------------------------------------------- resuming a PETS run
def run_pets(
    checkpoint: object, stop_at: int | None = None
) -> tuple[list[float], list[tuple], smcd_rl.AdaptiveDynamicsModel, CountingEnv]:
    env = CountingEnv(gymnasium.make("InvertedPendulum-v5"), stop_at=stop_at)
    model, episodes = pets_model(), []
    returns = pets_loop(
        env,
        model,
        pendulum_reward,
        pendulum_termination,
        **TINY_PETS,
        on_episode=lambda *row: episodes.append(row),
        checkpoint=checkpoint,  # type: ignore[arg-type]
    )
    return returns, episodes, model, env


@needs_mbrl
def test_pets_loop_resumes_an_interrupted_run_bit_for_bit(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Killed mid-episode, then rerun: it resumes after the last finished episode, not from the start.

    Before: ``pets_loop`` had no checkpoint, so an interrupted run started over.
    """
    returns, episodes, model, _ = run_pets(None)
    path = tmp_path / "pets.pt"
    with pytest.raises(KeyboardInterrupt):
        run_pets(path, stop_at=100 + 17)  # the 100 random steps, then 17 planned ones
    resumed, resumed_episodes, resumed_model, env = run_pets(path)
    assert env.steps < 30 - 5  # neither the random steps nor the finished episodes were run again
    assert resumed == returns and resumed_episodes == episodes and episodes[-1][0] == 30
    for key, value in model.state_dict().items():
        assert torch.equal(value, resumed_model.state_dict()[key]), key
    for key, value in model.adaptation.state_dict().items():
        other = resumed_model.adaptation.state_dict()[key]
        assert value is other is None or torch.equal(value, other), key
    # A finished run's checkpoint gives its results at once.
    again, again_episodes, _, env = run_pets(path)
    assert again == returns and again_episodes == episodes and env.steps == 0


@needs_mbrl
def test_pets_loop_refuses_a_checkpoint_of_other_settings(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "pets.pt"
    with pytest.raises(KeyboardInterrupt):
        run_pets(path, stop_at=100)
    env = CountingEnv(gymnasium.make("InvertedPendulum-v5"))
    with pytest.raises(
        smcd_rl.CheckpointMismatchError, match=r"other settings: lr=0.001 \(this call: 0.01\).*another checkpoint path"
    ):
        pets_loop(env, pets_model(), pendulum_reward, pendulum_termination, **TINY_PETS, lr=0.01, checkpoint=path)
    assert env.steps == 0
