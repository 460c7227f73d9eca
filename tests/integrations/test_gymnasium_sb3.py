"""The gymnasium step hook, its vector version, and stable-baselines3 through it.

The model here is an untrained dynamics network: the wrapper's contract (when the model resets,
what it observes, what info and the context carry) does not depend on how good the model is.
"""

from __future__ import annotations

import itertools
import warnings
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from stable_baselines3 import PPO
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from tensordict import TensorDictBase

import smcd_rl
from smcd_rl.envs import TASKS
from smcd_rl.integrations.gymnasium import AdaptationVectorWrapper, AdaptationWrapper, collect_transitions

ARM = "smcd_rl/TwoLinkArm-v0"
pytestmark = pytest.mark.filterwarnings("ignore::smcd_rl.UnfittedModelWarning")  # untrained on purpose, see above


def arm_model(seed: int = 0, particles: int = 16) -> smcd_rl.AdaptiveDynamicsModel:
    """Dynamics model of the arm: observation (q1, q2, x, y) + action (u1, u2) -> next observation."""
    torch.manual_seed(seed)
    net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32, 32), dropout=0.5)
    adaptation = smcd_rl.SMCD(num_particles=particles, noise_std=0.1, generator=torch.Generator().manual_seed(seed))
    return smcd_rl.AdaptiveDynamicsModel(net, adaptation)


class CountObserve:
    """Records every TensorDict passed to ``model.observe``."""

    def __init__(self, model: smcd_rl.AdaptiveDynamicsModel, monkeypatch: pytest.MonkeyPatch) -> None:
        self.calls: list[TensorDictBase] = []
        observe = model.observe

        def spy(td: TensorDictBase) -> None:
            self.calls.append(td.clone())
            observe(td)

        monkeypatch.setattr(model, "observe", spy)


class FixedLinks(gymnasium.Wrapper[np.ndarray, np.ndarray, np.ndarray, np.ndarray]):
    """Resets the arm with fixed link lengths, autoresets of a vector env included."""

    def __init__(self, env: gymnasium.Env[np.ndarray, np.ndarray], lengths: tuple[float, float]) -> None:
        super().__init__(env)
        self.lengths = lengths

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        return self.env.reset(seed=seed, options={**(options or {}), "link_lengths": self.lengths})


def two_arms(mode: AutoresetMode) -> SyncVectorEnv:
    """Sub-env 0: short links, episodes of 3 steps; sub-env 1: long links, episodes of 5 steps."""
    return SyncVectorEnv(
        [
            lambda: FixedLinks(gymnasium.make(ARM, max_episode_steps=3), (0.5, 0.5)),
            lambda: FixedLinks(gymnasium.make(ARM, max_episode_steps=5), (1.5, 1.0)),
        ],
        autoreset_mode=mode,
    )


# ---------------------------------------------------------------------------- conformance
def test_wrapped_arm_with_context_passes_both_env_checkers() -> None:
    env = AdaptationWrapper(gymnasium.make(ARM), arm_model(), context=4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advice only: unbounded Box, asymmetric actions, "not unwrapped"
        gymnasium_check_env(env)
        sb3_check_env(env)


@pytest.mark.parametrize("env_id", [task[0] for task in TASKS])
def test_registered_ids_pass_both_env_checkers(env_id: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # The render check opens every declared mode, MuJoCo's "human" included, which needs a display.
        gymnasium_check_env(gymnasium.make(env_id).unwrapped, skip_render_check=True)
        sb3_check_env(gymnasium.make(env_id))


def test_env_spaces_that_do_not_fit_the_model_are_named() -> None:
    three_obs = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 2, 3, hidden=(8,)))
    with pytest.raises(ValueError, match=r"observation space Box\(.*\(4,\).*observations of shape \(3,\)"):
        AdaptationWrapper(gymnasium.make(ARM), three_obs)
    one_action = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4 + 1, 4, hidden=(8,)))
    with pytest.raises(ValueError, match=r"action space Box\(.*\(2,\).*actions of shape \(1,\)"):
        AdaptationWrapper(gymnasium.make(ARM), one_action)
    with pytest.raises(ValueError, match=r"observation space .*\(4,\).*\(3,\)"):
        AdaptationVectorWrapper(gymnasium.make_vec(ARM, num_envs=2), three_obs)
    with pytest.raises(ValueError, match="context must be None or a positive int"):
        AdaptationWrapper(gymnasium.make(ARM), arm_model(), context=0)


# ---------------------------------------------------------------------------- the step hook
def test_reset_restarts_the_model_and_each_step_observes_once(monkeypatch: pytest.MonkeyPatch) -> None:
    model = arm_model()
    spy = CountObserve(model, monkeypatch)
    env = AdaptationWrapper(gymnasium.make(ARM), model, context=4)
    obs, info = env.reset(seed=0)
    env.action_space.seed(0)
    assert spy.calls == [] and info["smcd"] == {"ess": 16.0, "log_evidence": 0.0}
    previous, evidence = obs, 0.0
    for step in range(1, 6):
        particles = model.particles.clone()
        action = env.action_space.sample()
        obs, _, _, _, info = env.step(action)
        assert len(spy.calls) == step
        td = spy.calls[-1]  # the ORIGINAL observations, without the context
        np.testing.assert_array_equal(td["observation"].numpy(), previous[:4])
        np.testing.assert_array_equal(td["action"].numpy(), action)
        np.testing.assert_array_equal(td["next", "observation"].numpy(), obs[:4])
        assert not torch.equal(model.particles, particles)
        # A log density, so either sign is possible; each observation must add to it.
        assert isinstance(info["smcd"]["log_evidence"], float) and np.isfinite(info["smcd"]["log_evidence"])
        assert info["smcd"]["log_evidence"] != evidence
        assert info["smcd"]["log_evidence"] == pytest.approx(float(model.summary()["log_evidence"]))
        previous, evidence = obs, info["smcd"]["log_evidence"]
    obs, info = env.reset()
    assert len(spy.calls) == 5 and info["smcd"]["log_evidence"] == 0.0  # a new adaptation episode


def test_seeded_episodes_repeat_exactly_context_included() -> None:
    env = AdaptationWrapper(gymnasium.make(ARM), arm_model(), context=4)
    runs = []
    for _ in range(2):
        env.action_space.seed(1)
        obs = [env.reset(seed=3)[0]] + [env.step(env.action_space.sample())[0] for _ in range(4)]
        obs.append(env.reset()[0])  # the unseeded reset after a seeded one, too
        runs.append(np.stack(obs))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_context_is_a_fixed_projection_of_the_mmse_mask_and_moves_as_the_model_adapts() -> None:
    model = arm_model(particles=64)
    env = AdaptationWrapper(gymnasium.make(ARM), model, context=6, context_seed=7)
    assert env.observation_space.shape == (4 + 6 + 1,) and env.context_dim == 7
    obs, _ = env.reset(seed=0)
    contexts = [obs[4:]]
    for _ in range(10):
        obs, *_ = env.step(env.action_space.sample())
        assert obs in env.observation_space
        contexts.append(obs[4:])
    # Recompute the documented formula: W @ (m - p) / sqrt(p (1 - p)), then ESS / N.
    p = model.net.keep_prob
    weights = torch.randn(6, model.net.mask_dim, generator=torch.Generator().manual_seed(7)) / model.net.mask_dim**0.5
    torch.testing.assert_close(env.context_projection, weights)
    expected = weights @ ((model.mask - p) / (p * (1 - p)) ** 0.5)
    np.testing.assert_allclose(contexts[-1][:6], expected.numpy(), rtol=1e-5, atol=1e-6)
    assert contexts[-1][6] == pytest.approx(float(model.summary()["ess"]) / 64)
    # The prior's MMSE mask is near its mean, so the projection starts near 0 and moves away
    # as the filter concentrates on a few masks.
    norms = [float(np.linalg.norm(c[:6])) for c in contexts]
    assert norms[0] < 0.5 < norms[-1]
    assert all(not np.array_equal(a[:6], b[:6]) for a, b in itertools.pairwise(contexts))


# ---------------------------------------------------------------------------- vector envs
def evidence(info: dict[str, Any]) -> np.ndarray:
    return info["smcd"]["log_evidence"]


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED])
def test_vector_env_keeps_one_particle_set_per_sub_env(mode: AutoresetMode, monkeypatch: pytest.MonkeyPatch) -> None:
    model = arm_model()
    spy = CountObserve(model, monkeypatch)
    envs = AdaptationVectorWrapper(two_arms(mode), model, context=4)
    assert envs.single_observation_space.shape == (9,) and envs.observation_space.shape == (2, 9)
    envs.action_space.seed(0)
    obs, info = envs.reset(seed=0)
    assert model.batch_shape == (2,) and model.particles.shape[:2] == (2, 16)
    np.testing.assert_array_equal(info["link_lengths"], [[0.5, 0.5], [1.5, 1.0]])
    np.testing.assert_array_equal(evidence(info), [0.0, 0.0])
    assert info["_smcd"].all() and info["smcd"]["_ess"].all()  # gymnasium's vector-info masks

    history = []
    for step in range(1, 4):
        obs, _, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert len(spy.calls) == step and spy.calls[-1].batch_size == (2,)
        history.append(evidence(info).copy())
        assert obs.shape == (2, 9)
    assert (truncated == [True, False]).all()  # sub-env 0 ends after 3 steps, sub-env 1 runs on
    assert (np.diff(np.stack(history)[:, 1]) != 0).all()  # each step adds evidence to sub-env 1
    assert not torch.equal(model.particles[0], model.particles[1])  # separate particle sets

    if mode == AutoresetMode.NEXT_STEP:
        assert (evidence(info) != 0).all()  # a log density: nonzero once adapting, either sign
        long_arm = model.particles[1].clone()
        _, _, _, _, info = envs.step(envs.action_space.sample())  # sub-env 0's reset step
        assert evidence(info)[0] == 0.0  # no transition observed, fresh state
        assert evidence(info)[1] != history[-1][1]  # sub-env 1 observed its transition as usual
        assert not torch.equal(model.particles[1], long_arm)
        _, _, _, _, info = envs.step(envs.action_space.sample())
        assert evidence(info)[0] != 0.0  # sub-env 0 adapts again in its new episode
    elif mode == AutoresetMode.SAME_STEP:
        final = info["final_obs"][0]
        np.testing.assert_array_equal(spy.calls[-1]["next", "observation"][0].numpy(), final)  # into the end state
        assert evidence(info)[0] == 0.0 and evidence(info)[1] != 0.0  # then sub-env 0 starts afresh
        assert not np.array_equal(obs[0, :4], final)  # the observation is already the reset one
    else:
        long_arm = model.particles[1].clone()
        obs, info = envs.reset(options={"reset_mask": np.array([True, False])})
        assert len(spy.calls) == 3  # a reset is never a transition
        assert model.summary()["log_evidence"][0] == 0.0
        assert model.summary()["log_evidence"][1] == pytest.approx(float(history[-1][1]))
        assert torch.equal(model.particles[1], long_arm)  # sub-env 1 untouched by sub-env 0's reset
        _, _, _, _, info = envs.step(envs.action_space.sample())
        assert (evidence(info) != 0).all()


def test_a_sub_envs_reset_leaves_the_other_sub_envs_mask_bit_identical() -> None:
    """Its particles were always kept; its MMSE mask moved in the last bits (by up to 7e-7),
    recomputed over a batch whose copies the other sub-env's fresh particles had changed."""
    # 50 particles: weights of 1/50 are inexact in binary, so the order of the mask's sum shows.
    model = arm_model(particles=50)
    envs = AdaptationVectorWrapper(two_arms(AutoresetMode.DISABLED), model, context=4)
    envs.action_space.seed(0)
    envs.reset(seed=0)
    for _ in range(3):
        envs.step(envs.action_space.sample())
        mask, particles = model.mask[1].clone(), model.particles[1].clone()
        envs.reset(options={"reset_mask": np.array([True, False])})
        assert model.summary()["log_evidence"][0] == 0.0  # sub-env 0 starts afresh
        assert torch.equal(model.particles[1], particles)
        assert torch.equal(model.mask[1], mask), (model.mask[1] - mask).abs().max()


# ---------------------------------------------------------------------------- stable-baselines3
def test_ppo_trains_through_the_wrapper_and_its_policy_collects_fitting_data(monkeypatch: pytest.MonkeyPatch) -> None:
    model = arm_model()
    spy = CountObserve(model, monkeypatch)
    env = AdaptationWrapper(gymnasium.make(ARM, max_episode_steps=50), model, context=4)
    agent = PPO(
        "MlpPolicy",
        env,
        n_steps=64,
        batch_size=32,
        n_epochs=2,
        seed=0,
        device="cpu",
        policy_kwargs={"net_arch": [32, 32]},
    )
    agent.learn(256)
    assert len(spy.calls) >= 256  # the hook saw every step PPO took

    data = collect_transitions(env, agent, 200, seed=0)
    assert data.batch_size == (200,)
    assert data["observation"].shape == (200, 4)  # the context columns are dropped
    assert data["next", "done"].sum() == 4  # 200 steps of 50-step episodes
    continuing = ~data["next", "done"][:-1, 0]
    torch.testing.assert_close(data["observation"][1:][continuing], data["next", "observation"][:-1][continuing])

    fresh = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(4 + 2, 4, hidden=(64, 64), dropout=0.1))
    losses = smcd_rl.fit_dynamics(fresh, data, epochs=40, batch_size=50, lr=3e-3, progress=False)
    assert losses[-1] < 0.5 * losses[0]


def test_collect_transitions_with_random_or_callable_policies() -> None:
    random = collect_transitions(gymnasium.make(ARM), None, 20, seed=0)
    again = collect_transitions(gymnasium.make(ARM), None, 20, seed=0)
    assert (random == again).all()  # seeded: identical data
    assert random["action"].abs().max() <= 3.0
    constant = collect_transitions(gymnasium.make(ARM), lambda obs: np.array([9.0, -9.0]), 5, seed=0)
    np.testing.assert_array_equal(constant["action"].numpy(), np.tile([3.0, -3.0], (5, 1)))  # clipped to the box
    with pytest.raises(TypeError, match="single gymnasium.Env"):
        collect_transitions(gymnasium.make_vec(ARM, num_envs=2), None, 5)  # type: ignore[arg-type]


# Every smcd_rl id, those of the optional extras included (skipped where the extra is not installed).
_EXTRA_MODULE = {"smcd_rl/CrippledAnt-v0": "mujoco", "smcd_rl/FetchReachRotated-v0": "gymnasium_robotics"}
_EXTRA_MODULE |= {"smcd_rl/FetchPushHeavy-v0": "gymnasium_robotics", "smcd_rl/FrankaReachTool-v0": "gymnasium_robotics"}
_ALL_IDS = sorted(i for i in gymnasium.registry if i.startswith("smcd_rl/"))


@pytest.mark.parametrize("env_id", _ALL_IDS)
def test_every_registered_id_passes_sb3_check_env_with_python_float_rewards(env_id: str) -> None:
    if env_id in _EXTRA_MODULE:
        pytest.importorskip(_EXTRA_MODULE[env_id])
    env = gymnasium.make(env_id)
    # A goal env is checked unwrapped: SB3 calls env.compute_reward, which gymnasium's wrappers do not forward.
    checked = env.unwrapped if hasattr(env.unwrapped, "compute_reward") else env
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sb3_check_env(checked, skip_render_check=True)
    for layer in (env, env.unwrapped):
        layer.reset(seed=0)
        layer.action_space.seed(0)
        reward = layer.step(layer.action_space.sample())[1]
        assert type(reward) is float, f"{env_id}: {type(layer).__name__}.step returned a {type(reward).__name__} reward"
