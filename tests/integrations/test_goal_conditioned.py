"""Goal-conditioned envs (Dict observations and ``compute_reward``) end to end.

First on :class:`PointGoal`, a pure-python point mass defined here (fast), then on
gymnasium-robotics' ``FetchReach-v4`` (real MuJoCo). The dynamics model learns the ``observation``
entry; the achieved goal is a slice of it (``achieved_goal_fn``, derived for Fetch) and the
planning reward is the env's own batched ``compute_reward``.
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from stable_baselines3 import SAC, HerReplayBuffer
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from tensordict import TensorDictBase
from torchrl.envs.utils import check_env_specs
from torchrl.modules import CEMPlanner

import smcd_rl
from smcd_rl.agents.mpc import MPCAgent
from smcd_rl.agents.planners import CEM
from smcd_rl.integrations.gymnasium import (
    CONTEXT_KEY,
    AdaptationVectorWrapper,
    AdaptationWrapper,
    GoalReward,
    collect_transitions,
    fetch_achieved_goal,
)
from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv


class PointGoal(gymnasium.Env[dict[str, np.ndarray], np.ndarray]):
    """A point in the plane pushed towards a goal: the smallest goal-conditioned env.

    * observation: ``(x, y, vx, vy)``, the position and the last displacement;
      achieved_goal: ``(x, y)``; desired_goal: ``(gx, gy)`` uniform in ``[-0.8, 0.8]^2``.
    * action ``a`` in ``[-1, 1]^2``: ``x' = clip(x + 0.1 * gain * a, -1, 1)``, ``v' = x' - x``.
    * reward: ``-|x' - g|`` (``"dense"``) or ``-(|x' - g| > 0.05)`` (``"sparse"``), batched in
      :meth:`compute_reward`; episodes truncate after ``max_steps`` steps, never terminate.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, gain: float = 1.0, reward_type: str = "dense", max_steps: int = 20) -> None:
        goal = spaces.Box(-1.0, 1.0, (2,), np.float64)
        self.observation_space = spaces.Dict(
            observation=spaces.Box(-2.0, 2.0, (4,), np.float64), achieved_goal=goal, desired_goal=goal
        )
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.gain, self.reward_type, self.max_steps = gain, reward_type, max_steps
        self.pos, self.vel, self.goal, self.t = np.zeros(2), np.zeros(2), np.zeros(2), 0

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        d = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
        return -(d > 0.05).astype(np.float64) if self.reward_type == "sparse" else -d

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            "observation": np.concatenate([self.pos, self.vel]),
            "achieved_goal": self.pos.copy(),
            "desired_goal": self.goal.copy(),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        self.pos, self.vel, self.t = np.zeros(2), np.zeros(2), 0
        self.goal = self.np_random.uniform(-0.8, 0.8, size=2)
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        new = np.clip(self.pos + 0.1 * self.gain * a, -1.0, 1.0)
        self.vel, self.pos, self.t = new - self.pos, new, self.t + 1
        obs = self._obs()
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], {}))
        return obs, reward, False, self.t >= self.max_steps, {"is_success": float(reward > -0.05)}


POINT_GOAL = slice(0, 2)  # the achieved goal is the observation's first two columns
pytestmark = pytest.mark.filterwarnings("ignore::smcd_rl.UnfittedModelWarning")  # untrained models where noted


def point_model(particles: int = 16, seed: int = 0) -> smcd_rl.AdaptiveDynamicsModel:
    """An untrained model of the point's observation: the wrappers' contract does not need a good one."""
    torch.manual_seed(seed)
    net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32, 32), dropout=0.5)
    adaptation = smcd_rl.SMCD(num_particles=particles, noise_std=0.1, generator=torch.Generator().manual_seed(seed))
    return smcd_rl.AdaptiveDynamicsModel(net, adaptation)


@pytest.fixture(scope="module")
def trained_point_model() -> smcd_rl.AdaptiveDynamicsModel:
    """The point's dynamics learnt from 3000 random transitions (~3 s)."""
    torch.manual_seed(0)
    data = collect_transitions(PointGoal(), steps=3000, seed=0)
    net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(64, 64), dropout=0.1)
    adaptation = smcd_rl.SMCD(num_particles=50, noise_std=0.02, generator=torch.Generator().manual_seed(0))
    model = smcd_rl.AdaptiveDynamicsModel(net, adaptation)
    smcd_rl.fit_dynamics(model, data, epochs=15, batch_size=64, lr=2e-3, progress=False)
    return model


def distance(obs: dict[str, np.ndarray]) -> float:
    return float(np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]))


# ---------------------------------------------------------------------------- data
def test_collect_transitions_records_each_dict_entry_in_the_layout_fit_dynamics_takes() -> None:
    data = collect_transitions(PointGoal(max_steps=5), steps=12, seed=0)
    assert data.batch_size == torch.Size([12])
    for prefix in ((), ("next",)):
        assert data[(*prefix, "observation")].shape == (12, 4)
        assert data[(*prefix, "achieved_goal")].shape == (12, 2)
        assert data[(*prefix, "desired_goal")].shape == (12, 2)
    # Within an episode the next step starts where this one ended; the goal is constant.
    same = ~data["next", "done"][:-1, 0]
    assert torch.equal(data["next", "observation"][:-1][same], data["observation"][1:][same])
    assert torch.equal(data["desired_goal"][:5], data["desired_goal"][:1].expand(5, 2))
    assert torch.allclose(data["next", "achieved_goal"], data["next", "observation"][:, :2])
    assert data["next", "done"].sum() == 2  # episodes of 5 steps: 12 steps end two of them
    model = point_model()
    losses = smcd_rl.fit_dynamics(model, data, epochs=2, batch_size=4, lr=1e-3, progress=False)
    assert len(losses) == 2 and all(np.isfinite(losses))


def test_collect_transitions_through_the_wrapper_drops_the_context_entry() -> None:
    env = AdaptationWrapper(PointGoal(max_steps=5), point_model(), context=3)
    seen: list[Any] = []

    def policy(obs: dict[str, np.ndarray]) -> np.ndarray:
        seen.append(obs)
        return np.zeros(2, dtype=np.float32)

    data = collect_transitions(env, policy, steps=6, seed=0)
    assert all(CONTEXT_KEY in obs for obs in seen)  # the policy sees the context ...
    assert CONTEXT_KEY not in data.keys() and CONTEXT_KEY not in data["next"].keys()  # ... the data does not
    assert sorted(data.keys()) == ["achieved_goal", "action", "desired_goal", "next", "observation"]


# ---------------------------------------------------------------------------- the step hook
def test_wrapper_adds_the_context_as_a_dict_entry_and_passes_the_env_checker() -> None:
    base = PointGoal()
    env = AdaptationWrapper(base, point_model(), context=3)
    space = env.observation_space
    assert isinstance(space, spaces.Dict)
    assert sorted(space.keys()) == sorted(["achieved_goal", "desired_goal", "observation", CONTEXT_KEY])
    assert space[CONTEXT_KEY].shape == (4,) and space["observation"] == base.observation_space["observation"]
    obs, info = env.reset(seed=0)
    assert space.contains(obs) and set(info["smcd"]) == {"ess", "log_evidence"}
    obs, *_ = env.step(np.ones(2, dtype=np.float32))
    assert space.contains(obs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advice only ("not unwrapped", float64 spaces)
        gymnasium_check_env(env, skip_render_check=True)
        sb3_check_env(env)
    # The wrapper is a goal env like the one it wraps (SB3's checker and HER call compute_reward on it).
    goals = np.zeros((3, 2)), np.ones((3, 2))
    assert np.array_equal(env.compute_reward(*goals, {}), base.compute_reward(*goals, {}))
    arm = AdaptationWrapper(
        gymnasium.make("smcd_rl/TwoLinkArm-v0"), smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(6, 4))
    )
    with pytest.raises(AttributeError, match="compute_reward"):
        arm.compute_reward(*goals, {})
    # Without a context the observations pass through untouched.
    plain = AdaptationWrapper(PointGoal(), point_model())
    assert plain.observation_space == base.observation_space


def test_wrapper_feeds_the_model_the_observation_entry(monkeypatch: pytest.MonkeyPatch) -> None:
    model = point_model()
    calls: list[TensorDictBase] = []
    observe = model.observe
    monkeypatch.setattr(model, "observe", lambda td: (calls.append(td.clone()), observe(td))[1])
    env = AdaptationWrapper(PointGoal(), model, context=2)
    obs0, _ = env.reset(seed=1)
    action = np.array([0.5, -1.0], dtype=np.float32)
    obs1, *_ = env.step(action)
    (td,) = calls
    assert torch.allclose(td["observation"], torch.as_tensor(obs0["observation"], dtype=torch.float32))
    assert torch.allclose(td["next", "observation"], torch.as_tensor(obs1["observation"], dtype=torch.float32))
    assert torch.allclose(td["action"], torch.as_tensor(action))
    # The context is the filter's: ess / N is its last entry.
    assert obs1[CONTEXT_KEY][-1] == pytest.approx(float(model.summary()["ess"]) / 16, rel=1e-5)


def test_dict_spaces_that_do_not_fit_the_model_are_named() -> None:
    other_key = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(6, 4, hidden=(8,)), observation_key="state")
    with pytest.raises(
        ValueError,
        match=r"Dict with entries \['observation', 'achieved_goal', 'desired_goal'\], but the model reads 'state'",
    ):
        AdaptationWrapper(PointGoal(), other_key)
    wrong_size = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(5 + 2, 5, hidden=(8,)))
    with pytest.raises(ValueError, match=r"entry 'observation'.*shape \(5,\)"):
        AdaptationWrapper(PointGoal(), wrong_size)
    with pytest.raises(ValueError, match="context_key"):
        AdaptationWrapper(PointGoal(), point_model(), context=2, context_key="desired_goal")


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_vector_wrapper_adds_a_batched_context_entry(mode: AutoresetMode, monkeypatch: pytest.MonkeyPatch) -> None:
    model = point_model()
    calls: list[TensorDictBase] = []
    observe = model.observe
    monkeypatch.setattr(model, "observe", lambda td: (calls.append(td.clone()), observe(td))[1])
    vec = SyncVectorEnv([lambda: PointGoal(max_steps=3), lambda: PointGoal(max_steps=4)], autoreset_mode=mode)
    envs = AdaptationVectorWrapper(vec, model, context=3)
    assert envs.single_observation_space[CONTEXT_KEY].shape == (4,)
    obs, _ = envs.reset(seed=0)
    assert obs[CONTEXT_KEY].shape == (2, 4) and obs["observation"].shape == (2, 4)
    assert envs.observation_space.contains(obs)
    previous = obs
    for _ in range(5):
        obs, *_, info = envs.step(np.ones((2, 2), dtype=np.float32))
        assert envs.observation_space.contains(obs)
    td = calls[0]
    assert td.batch_size == torch.Size([2])
    assert torch.allclose(td["observation"], torch.as_tensor(previous["observation"], dtype=torch.float32))
    assert model.particles.shape[0] == 2 and info["smcd"]["ess"].shape == (2,)


# ---------------------------------------------------------------------------- the env's reward
def test_goal_reward_is_the_envs_batched_compute_reward() -> None:
    env = PointGoal()
    reward = GoalReward(env, achieved_goal_fn=POINT_GOAL)
    obs = torch.randn(3, 5, 4, dtype=torch.float64)
    goal = torch.randn(3, 1, 2, dtype=torch.float64)
    expected = env.compute_reward(obs[..., :2].numpy(), goal.expand(3, 5, 2).numpy(), {})
    assert reward(obs, goal).shape == (3, 5)
    assert np.allclose(reward(obs, goal).numpy(), expected)
    # towards: a RewardFn for planning, with the goal of each problem held fixed over its candidates.
    fn = reward.towards(goal[:, 0])
    assert np.allclose(fn(None, None, obs).numpy(), expected)
    sparse = GoalReward(PointGoal(reward_type="sparse"), achieved_goal_fn=lambda o: o[..., :2])
    assert set(sparse(obs, goal).unique().tolist()) <= {-1.0, 0.0}


def test_goal_reward_names_what_the_env_lacks() -> None:
    class NoReward(PointGoal):
        compute_reward = None  # type: ignore[assignment]

    with pytest.raises(ValueError, match=r"no compute_reward\(achieved_goal, desired_goal, info\)"):
        GoalReward(NoReward(), achieved_goal_fn=POINT_GOAL)
    with pytest.raises(ValueError, match="achieved_goal_fn is needed"):
        GoalReward(PointGoal())
    with pytest.raises(ValueError, match="Dict observations with entries"):
        GoalReward(gymnasium.make("Pendulum-v1"), achieved_goal_fn=POINT_GOAL)
    with pytest.raises(ValueError, match=r"expected \[2, 2\]"):
        GoalReward(PointGoal(), achieved_goal_fn=slice(0, 3))

    class Unbatched(PointGoal):
        def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
            return np.asarray(-float(np.linalg.norm(achieved_goal - desired_goal)))

    with pytest.raises(ValueError, match="batched compute_reward"):
        GoalReward(Unbatched(), achieved_goal_fn=POINT_GOAL)
    with pytest.raises(TypeError, match="single goal-conditioned env"):
        GoalReward(SyncVectorEnv([PointGoal]), achieved_goal_fn=POINT_GOAL)
    assert fetch_achieved_goal(PointGoal()) is None


# ---------------------------------------------------------------------------- planning
def run_episode(env: gymnasium.Env, act: Any, seed: int) -> float:
    obs, _ = env.reset(seed=seed)
    done = False
    while not done:
        obs, _, terminated, truncated, _ = env.step(act(obs))
        done = terminated or truncated
    return distance(obs)


def test_mpc_with_the_envs_reward_reaches_the_point_goal(trained_point_model: smcd_rl.AdaptiveDynamicsModel) -> None:
    """Planning with compute_reward ends within 0.1 of the goal; random actions end far from it.

    Not by chance: goals are ~0.6 away on average and a random walk of 20 steps of at most 0.14
    ends ~0.5 from its goal; ending within 0.1 on average over 4 episodes needs steering.
    """
    model = trained_point_model
    env = AdaptationWrapper(PointGoal(), model, context=2)  # model.observe on every step
    planner = CEM(
        action_low=[-1.0, -1.0],
        action_high=[1.0, 1.0],
        horizon=5,
        num_candidates=64,
        num_elites=8,
        iterations=3,
        generator=torch.Generator().manual_seed(0),
    )
    agent = MPCAgent.from_goal_env(model, planner, env, achieved_goal_fn=POINT_GOAL)
    planned = [run_episode(env, agent.act, seed) for seed in range(4)]
    rng = np.random.default_rng(0)
    random = [run_episode(env, lambda _: rng.uniform(-1, 1, 2).astype(np.float32), seed) for seed in range(4)]
    assert np.mean(planned) < 0.1, planned
    assert np.mean(planned) < 0.3 * np.mean(random), (planned, random)


def test_goal_agent_refuses_the_wrong_kind_of_observation(trained_point_model: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = trained_point_model
    model.reset()
    planner = CEM(
        action_low=[-1.0, -1.0], action_high=[1.0, 1.0], horizon=3, num_candidates=16, num_elites=4, iterations=1
    )
    goal_agent = MPCAgent.from_goal_env(model, planner, PointGoal(), achieved_goal_fn=POINT_GOAL)
    obs, _ = PointGoal().reset(seed=0)
    assert goal_agent.act(obs).shape == (2,)
    batched = {k: np.stack([v, v]) for k, v in obs.items()}
    assert goal_agent.act(batched).shape == (2, 2)  # two problems, one per goal
    with pytest.raises(ValueError, match="pass the env's Dict observation"):
        goal_agent.act(obs["observation"])
    with pytest.raises(ValueError, match=r"has no \['desired_goal'\]"):
        goal_agent.act({"observation": obs["observation"]})
    plain = MPCAgent(model, planner, lambda o, a, n: -n.square().sum(-1))
    with pytest.raises(ValueError, match="from_goal_env"):
        plain.act(obs)
    assert "GoalReward" in repr(goal_agent)


def test_torchrl_world_model_of_a_goal_env_plans_with_its_reward(
    trained_point_model: smcd_rl.AdaptiveDynamicsModel,
) -> None:
    model = trained_point_model
    model.reset()
    env = PointGoal()
    world = AdaptiveWorldModelEnv.from_goal_env(model, env, achieved_goal_fn=POINT_GOAL)
    check_env_specs(world)
    assert sorted(world.observation_spec.keys()) == ["achieved_goal", "desired_goal", "observation"]
    obs, _ = env.reset(seed=3)
    td = world.reset()
    for key in ("observation", "achieved_goal", "desired_goal"):
        td[key] = torch.as_tensor(obs[key])
    td["action"] = torch.tensor([1.0, 0.0])
    out = world.step(td)["next"]
    predicted = model.step(td["observation"].float(), td["action"]).detach()
    expected = env.compute_reward(predicted[:2].double().numpy(), obs["desired_goal"], {})
    assert out["reward"].item() == pytest.approx(float(expected), abs=1e-5)
    assert torch.equal(out["desired_goal"], td["desired_goal"])  # the goal is a constant of the plan
    assert torch.allclose(out["achieved_goal"], out["observation"][:2])
    with torch.no_grad():
        action = CEMPlanner(world, planning_horizon=5, optim_steps=3, num_candidates=64, top_k=8)(td.clone())["action"]
    direction = obs["desired_goal"] - obs["achieved_goal"]
    assert float(np.dot(action.numpy(), direction)) > 0  # the first planned move heads for the goal
    with pytest.raises(ValueError, match="from_goal_env"):
        AdaptiveWorldModelEnv.from_gym(model, env, lambda o, a, n: -n.sum(-1))


@pytest.mark.slow
def test_sac_with_her_trains_through_the_wrapper_on_the_point_goal() -> None:
    env = AdaptationWrapper(PointGoal(reward_type="sparse"), point_model(), context=3)
    agent = SAC(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=60,
        batch_size=32,
        policy_kwargs={"net_arch": [32, 32]},
        seed=0,
    )
    agent.learn(120)
    assert agent._n_updates >= 60  # it learnt: one gradient step per env step after learning_starts
    stored = agent.replay_buffer.observations
    assert CONTEXT_KEY in stored and stored[CONTEXT_KEY].shape[-1] == 4
    filled = stored[CONTEXT_KEY][: agent.replay_buffer.pos, 0]
    assert np.ptp(filled[:, 0]) > 0  # the stored context moves as the model adapts


# ---------------------------------------------------------------------------- FetchReach (MuJoCo)
@pytest.fixture(scope="module")
def fetch() -> Any:
    """``make(id, **kwargs)`` for gymnasium-robotics envs, with the mujoco >= 3.12 fix applied."""
    pytest.importorskip("gymnasium_robotics")
    from smcd_rl.integrations.robotics import fix_mujoco_joint_types

    fix_mujoco_joint_types()
    import gymnasium_robotics

    gymnasium.register_envs(gymnasium_robotics)
    return gymnasium.make


@pytest.fixture(scope="module")
def fetch_model(fetch: Any) -> smcd_rl.AdaptiveDynamicsModel:
    """FetchReach's dynamics learnt from 4000 random transitions (80 episodes; ~10 s)."""
    torch.manual_seed(0)
    data = collect_transitions(fetch("FetchReach-v4"), steps=4000, seed=0)
    net = smcd_rl.MaskedMLP(10 + 4, 10, hidden=(128, 128), dropout=0.1)
    adaptation = smcd_rl.SMCD(num_particles=50, noise_std=0.05, generator=torch.Generator().manual_seed(0))
    model = smcd_rl.AdaptiveDynamicsModel(net, adaptation)
    smcd_rl.fit_dynamics(model, data, epochs=10, batch_size=64, lr=2e-3, progress=False)
    return model


def test_fetch_achieved_goal_is_derived_from_the_observation(fetch: Any) -> None:
    for env_id, columns in [
        ("FetchReach-v4", slice(0, 3)),
        ("FetchPush-v4", slice(3, 6)),
        ("smcd_rl/FetchReachRotated-v0", slice(0, 3)),  # the families subclass Fetch's envs
        ("smcd_rl/FetchPushHeavy-v0", slice(3, 6)),
    ]:
        env = fetch(env_id)
        obs, _ = env.reset(seed=0)
        obs, *_ = env.step(env.action_space.sample())
        fn = fetch_achieved_goal(env)
        assert fn is not None and repr(fn) == f"observation[..., {columns.start}:{columns.stop}]"
        assert np.array_equal(fn(torch.as_tensor(obs["observation"])).numpy(), obs["achieved_goal"])
        reward = GoalReward(env)  # derived: no achieved_goal_fn needed
        assert reward(torch.as_tensor(obs["observation"]), torch.as_tensor(obs["desired_goal"])).item() == (
            pytest.approx(float(env.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], {})))
        )


@pytest.mark.slow
def test_mpc_on_the_adapted_model_gets_closer_to_the_fetch_goal_than_random_actions(
    fetch: Any, fetch_model: smcd_rl.AdaptiveDynamicsModel
) -> None:
    """CEM with FetchReach's own (dense) compute_reward ends near the goal; random actions do not.

    Not by chance: the goal lies up to 15 cm from the gripper along each axis and random
    mocap displacements wander off it; ending within the env's 5 cm success radius, on average
    over three seeded episodes of 15 steps, and at under half random's distance needs steering.
    The dense reward (``reward_type="dense"``) is used because a sparse one gives CEM nothing to
    rank until a candidate already reaches the goal.
    """
    model = fetch_model
    env = AdaptationWrapper(fetch("FetchReach-v4", reward_type="dense", max_episode_steps=15), model)
    planner = CEM(
        action_low=env.action_space.low,
        action_high=env.action_space.high,
        horizon=5,
        num_candidates=100,
        num_elites=10,
        iterations=3,
        generator=torch.Generator().manual_seed(0),
    )
    agent = MPCAgent.from_goal_env(model, planner, env)  # achieved goal derived: observation[..., 0:3]

    def episode(act: Any, seed: int) -> float:
        agent.reset()
        return run_episode(env, act, seed)

    planned = [episode(agent.act, seed) for seed in range(3)]
    env.action_space.seed(0)
    random = [episode(lambda _: env.action_space.sample(), seed) for seed in range(3)]
    assert np.mean(planned) < 0.05, planned
    assert np.mean(planned) < 0.5 * np.mean(random), (planned, random)


@pytest.mark.slow
def test_sac_with_her_trains_through_the_wrapper_on_fetch_reach(
    fetch: Any, fetch_model: smcd_rl.AdaptiveDynamicsModel
) -> None:
    model = fetch_model.with_adaptation(smcd_rl.SMCD(num_particles=20, noise_std=0.05))
    env = AdaptationWrapper(fetch("FetchReach-v4"), model, context=4)
    agent = SAC(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"n_sampled_goal": 4, "goal_selection_strategy": "future"},
        learning_starts=100,
        batch_size=64,
        policy_kwargs={"net_arch": [64, 64]},
        seed=0,
    )
    agent.learn(200)
    buffer = agent.replay_buffer
    assert CONTEXT_KEY in buffer.observations and buffer.observations[CONTEXT_KEY].shape[-1] == 5
    stored = buffer.observations[CONTEXT_KEY][: buffer.pos, 0]
    assert np.isfinite(stored).all() and np.ptp(stored[:, 0]) > 0
    sample = buffer.sample(16)  # HER relabels goals with compute_reward through the wrapper
    assert sample.observations[CONTEXT_KEY].shape == (16, 5)
    assert agent._n_updates >= 100  # one gradient step per env step after learning_starts


def test_torchrl_world_model_of_fetch_reach_passes_check_env_specs_and_plans_from_gymenv(fetch: Any) -> None:
    from torchrl.envs import GymEnv, TransformedEnv

    from smcd_rl.integrations.torchrl import AdaptationTransform

    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(10 + 4, 10, hidden=(32,)), smcd_rl.SMCD(num_particles=8))
    model.fitted = True  # a random stand-in: specs and keys do not depend on training
    model.reset()
    world = AdaptiveWorldModelEnv.from_goal_env(model, fetch("FetchReach-v4"))
    check_env_specs(world)
    real = GymEnv("FetchReach-v4")
    td = real.reset()
    assert set(world.observation_spec.keys()) <= set(td.keys())  # the same nested keys as torchrl's GymEnv
    with torch.no_grad():
        planned = CEMPlanner(world, planning_horizon=3, optim_steps=2, num_candidates=32, top_k=4)(td.clone())
    assert planned["action"].shape == (4,) and bool(real.action_spec.is_in(planned["action"].to(torch.float32)))
    # The torchrl step hook adapts the same model from GymEnv's nested Dict keys.
    rollout = TransformedEnv(GymEnv("FetchReach-v4"), AdaptationTransform(model)).rollout(3)
    assert rollout["next", "smcd_log_evidence"][-1].item() != 0.0
