"""torchrl integration: planners on the adaptive world model, the step hook, fitting from a replay buffer.

Planner tolerances were measured over seeds 0-99 of the exact settings below (worst case in
brackets); each test uses a fixed seed, so it is deterministic, and the margin says a regression
must be large to hide:

- CEMPlanner, horizon 2, 10 iterations, 200 candidates, top 20, point mass ``next = obs + action``,
  reward ``-|next - goal|^2``: first action within 0.05 of the goal [worst 0.010].
- MPPIPlanner, same setting, temperature 3 with :class:`RewardToGo`: within 0.1 [worst 0.020].
  By chance alone a uniform action lands within 0.1 of the goal in both dims with probability 0.01.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import gymnasium
import pytest
import torch
from tensordict import TensorDict
from torch import Tensor
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import GymEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import CEMPlanner, MPPIPlanner

import smcd_rl
from smcd_rl.envs.crippled_ant import ant_reward, ant_termination
from smcd_rl.integrations.torchrl import (
    AdaptationTransform,
    AdaptiveWorldModelEnv,
    RewardToGo,
    fit_from_replay_buffer,
    mbrl_loop,
)

ARM = "smcd_rl/TwoLinkArm-v0"
N_PARTICLES = 16
GOAL = torch.tensor([0.5, -0.3])


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny models: threads only add overhead on the shared 2-core machine
    yield
    torch.set_num_threads(threads)


def smcd_model(obs_dim: int, action_dim: int, *, seed: int = 0, fitted: bool = True) -> smcd_rl.AdaptiveDynamicsModel:
    """A random network with SMCD, marked fitted: the tests check plumbing, not predictions.

    ``fitted=False`` for a test that trains it, whose fitting then sets the normalisers from its data.
    """
    torch.manual_seed(seed)
    net = smcd_rl.MaskedMLP(obs_dim + action_dim, obs_dim, hidden=(32, 32))
    generator = torch.Generator().manual_seed(seed)
    model = smcd_rl.AdaptiveDynamicsModel(
        net, smcd_rl.SMCD(num_particles=N_PARTICLES, noise_std=0.5, generator=generator)
    )
    model.fitted = fitted
    return model


def point_mass_model() -> smcd_rl.AdaptiveDynamicsModel:
    """A hand-built network with exactly ``next_obs = obs + action`` in the plane."""
    net = smcd_rl.MaskedMLP(4, 2, hidden=(4,), dropout=0.0)
    with torch.no_grad():
        w1 = torch.zeros(4, 4)
        w1[0, 2], w1[1, 2], w1[2, 3], w1[3, 3] = 1.0, -1.0, 1.0, -1.0  # relu(+-a0), relu(+-a1)
        net.linears[0].weight.copy_(w1)
        net.linears[0].bias.zero_()
        net.linears[1].weight.copy_(torch.tensor([[1.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0]]))
        net.linears[1].bias.zero_()
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.NoAdaptation())
    model.fitted = True  # trained by hand above
    model.reset()
    return model


def reach(goal: Tensor) -> Callable[[Tensor, Tensor, Tensor], Tensor]:
    return lambda obs, action, next_obs: -(next_obs - goal).square().sum(-1)


def arm_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    return -next_obs[..., 2:].square().sum(-1)


def arm_world(model: smcd_rl.AdaptiveDynamicsModel) -> AdaptiveWorldModelEnv:
    return AdaptiveWorldModelEnv.from_gym(model, gymnasium.make(ARM), arm_reward)


def cem(world: AdaptiveWorldModelEnv, **kwargs: int) -> CEMPlanner:
    settings = {"planning_horizon": 2, "optim_steps": 10, "num_candidates": 200, "top_k": 20} | kwargs
    return CEMPlanner(world, **settings)


def mppi(world: AdaptiveWorldModelEnv, **kwargs: int) -> MPPIPlanner:
    settings = {"planning_horizon": 2, "optim_steps": 10, "num_candidates": 200, "top_k": 20} | kwargs
    return MPPIPlanner(world, RewardToGo(), temperature=3.0, **settings)


# ---------------------------------------------------------------------- our ids as torchrl envs
@pytest.mark.parametrize("env_id", [ARM, "smcd_rl/CrippledAnt-v0"])
def test_gym_env_of_our_ids_passes_check_env_specs(env_id: str) -> None:
    env = GymEnv(env_id)
    check_env_specs(env, seed=0)
    assert env.rollout(3)["next", "observation"].shape[0] == 3


# ---------------------------------------------------------------------- planning on the world model
@pytest.mark.parametrize("make_planner", [cem, mppi], ids=["cem", "mppi"])
def test_torchrl_planners_return_in_bounds_actions_of_the_right_shape(make_planner: Callable) -> None:
    model = smcd_model(4, 2)
    model.reset()
    world = arm_world(model)
    planner = make_planner(world, planning_horizon=4, optim_steps=3, num_candidates=32, top_k=4)
    torch.manual_seed(0)
    with torch.no_grad():
        single = planner(world.reset())["action"]
        batch = planner(world.reset(TensorDict({"observation": torch.randn(3, 4)}, [3])))["action"]
    assert single.shape == (2,) and batch.shape == (3, 2)
    for action in (single, batch):
        assert bool(((action >= -3.0) & (action <= 3.0)).all())
        assert world.action_spec.is_in(action)


@pytest.mark.parametrize(("make_planner", "tolerance"), [(cem, 0.05), (mppi, 0.1)], ids=["cem", "mppi"])
def test_torchrl_planner_finds_the_known_optimum(make_planner: Callable, tolerance: float) -> None:
    world = AdaptiveWorldModelEnv(point_mass_model(), reach(GOAL), action_low=-1.0, action_high=1.0)
    torch.manual_seed(0)
    with torch.no_grad():
        action = make_planner(world)(world.reset())["action"]
    # From the origin the goal is one step away and then staying is free: the first action is the goal.
    assert (action - GOAL).abs().max().item() < tolerance


def test_cem_optimum_beyond_the_bounds_is_clipped_to_the_bound() -> None:
    goal = torch.tensor([2.0, -0.3])
    world = AdaptiveWorldModelEnv(point_mass_model(), reach(goal), action_low=-1.0, action_high=1.0)
    torch.manual_seed(0)
    with torch.no_grad():
        action = cem(world)(world.reset())["action"]
    assert action[0].item() <= 1.0 and action[0].item() > 0.95
    assert abs(action[1].item() + 0.3) < 0.05


def test_world_model_predicts_with_the_adapted_mask_of_the_shared_model() -> None:
    model = smcd_model(4, 2)
    model.reset()
    world = arm_world(model)
    td = TensorDict({"observation": torch.randn(5, 4), "action": torch.rand(5, 2)}, [5])
    stepped = world.step(td.clone())["next"]
    expected = model(td.clone())["next", "observation"]
    torch.testing.assert_close(stepped["observation"], expected)
    torch.testing.assert_close(stepped["reward"], arm_reward(td["observation"], td["action"], expected).unsqueeze(-1))
    assert stepped["reward"].shape == (5, 1)

    # Adapting the model moves its MMSE mask, and the env (holding a reference) follows.
    mask_before = model.mask.clone()
    real = TensorDict(
        {"observation": torch.zeros(4), "action": torch.ones(2), ("next", "observation"): torch.ones(4)}, []
    )
    for _ in range(3):
        model.observe(real)
    assert not torch.equal(model.mask, mask_before)
    torch.testing.assert_close(world.step(td.clone())["next", "observation"], model(td.clone())["next", "observation"])


def test_termination_fn_sets_done_and_planners_still_run() -> None:
    model = smcd_model(41, 8)
    model.reset()
    ant = GymEnv("smcd_rl/CrippledAnt-v0")
    world = AdaptiveWorldModelEnv.from_env(model, ant, ant_reward, termination_fn=ant_termination)
    assert world.observation_spec["observation"].dtype == torch.float64
    td = world.reset().set("action", torch.zeros(8))
    # The zero observation has torso height 0 < 0.2: an unhealthy Ant, so the step terminates.
    assert world.step(td)["next", "done"].item() is True
    torch.manual_seed(0)
    with torch.no_grad():
        action = cem(world, planning_horizon=3, optim_steps=2, num_candidates=16, top_k=4)(world.reset())["action"]
    assert action.shape == (8,) and world.action_spec.is_in(action)


def test_world_env_passes_check_env_specs() -> None:
    model = smcd_model(4, 2)
    model.reset()
    check_env_specs(arm_world(model), seed=0)


def test_reward_to_go_is_the_discounted_sum_of_future_rewards() -> None:
    reward = torch.tensor([1.0, 2.0, 4.0]).reshape(1, 3, 1)
    td = RewardToGo(gamma=0.5, subtract_max=False)(TensorDict({("next", "reward"): reward}, [1, 3]))
    torch.testing.assert_close(td["advantage"].flatten(), torch.tensor([1 + 1 + 1.0, 2 + 2.0, 4.0]))


def test_reward_to_go_shifts_the_best_candidate_to_zero_so_mppi_weights_cannot_underflow() -> None:
    reward = torch.tensor([[-300.0, -300.0], [-400.0, -100.0]]).reshape(2, 2, 1)  # [K=2, T=2, 1]
    advantage = RewardToGo()(TensorDict({("next", "reward"): reward}, [2, 2]))["advantage"]
    # Returns -600 and -500: the best candidate's return is subtracted everywhere.
    torch.testing.assert_close(advantage[:, 0, 0], torch.tensor([-100.0, 0.0]))
    torch.testing.assert_close(advantage[:, 1, 0], torch.tensor([200.0, 400.0]))
    # Very poor returns (an untrained model) still give MPPIPlanner finite actions.
    model = smcd_model(4, 2)
    model.reset()
    world = AdaptiveWorldModelEnv.from_gym(model, gymnasium.make(ARM), lambda o, a, n: -1e4 * n.square().sum(-1))
    torch.manual_seed(0)
    with torch.no_grad():
        action = mppi(world, planning_horizon=4, optim_steps=3, num_candidates=32, top_k=4)(world.reset())["action"]
    assert bool(torch.isfinite(action).all())


# ---------------------------------------------------------------------- the step hook
def test_transform_observes_every_real_step_and_writes_the_summary(monkeypatch: pytest.MonkeyPatch) -> None:
    model = smcd_model(4, 2)
    env = TransformedEnv(GymEnv(ARM), AdaptationTransform(model))
    env.set_seed(0)
    calls: list[TensorDict] = []
    observe = model.observe
    monkeypatch.setattr(model, "observe", lambda td: (calls.append(td), observe(td))[1])

    start = env.reset()
    particles = model.particles.clone()
    assert start["smcd_ess"].item() == N_PARTICLES and start["smcd_log_evidence"].item() == 0.0
    td = env.rollout(5, auto_reset=False, tensordict=start)

    assert len(calls) == 5
    for call, step in zip(calls, td, strict=True):
        torch.testing.assert_close(call["observation"], step["observation"])
        torch.testing.assert_close(call["action"], step["action"])
        torch.testing.assert_close(call["next", "observation"], step["next", "observation"])
    assert not torch.equal(model.particles, particles)
    assert td["next", "smcd_ess"].shape == (5, 1) and td["next", "smcd_log_evidence"].shape == (5, 1)
    ess = td["next", "smcd_ess"]
    assert bool(((ess >= 1.0 - 1e-4) & (ess <= N_PARTICLES + 1e-4)).all())
    torch.testing.assert_close(td["next", "smcd_log_evidence"][-1, 0], model.summary()["log_evidence"])
    assert td["next", "smcd_log_evidence"][-1].item() != 0.0

    env.reset()  # a new episode starts the adaptation afresh
    assert model.summary()["log_evidence"].item() == 0.0


def test_transformed_envs_pass_check_env_specs() -> None:
    check_env_specs(TransformedEnv(GymEnv(ARM), AdaptationTransform(smcd_model(4, 2))), seed=0)
    check_env_specs(TransformedEnv(GymEnv("smcd_rl/CrippledAnt-v0"), AdaptationTransform(smcd_model(41, 8))), seed=0)


def test_batched_env_keeps_one_particle_set_per_sub_env() -> None:
    model = smcd_model(4, 2)
    env = TransformedEnv(SerialEnv(2, lambda: GymEnv(ARM)), AdaptationTransform(model))
    env.set_seed(0)
    td = env.rollout(4)
    assert model.batch_shape == (2,)
    assert model.particles.shape[:2] == (2, N_PARTICLES)
    assert td["next", "smcd_ess"].shape == (2, 4, 1)
    evidence = td["next", "smcd_log_evidence"][:, -1, 0]
    assert evidence[0].item() != evidence[1].item()  # different arms, different evidence

    # A partial reset restarts only the sub-env that resets.
    kept = model.particles[1].clone()
    reset = env.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, [2]))
    assert model.summary()["log_evidence"][0].item() == 0.0
    torch.testing.assert_close(model.summary()["log_evidence"][1], evidence[1])
    assert torch.equal(model.particles[1], kept)
    assert reset["smcd_log_evidence"][0].item() == 0.0
    env.close()


def test_transform_needs_an_adaptive_model() -> None:
    with pytest.raises(TypeError, match="AdaptiveModel"):
        AdaptationTransform(torch.nn.Linear(2, 2))  # type: ignore[arg-type]


# ---------------------------------------------------------------------- fitting and the loop
def test_fit_from_replay_buffer_reduces_the_loss_on_collected_data() -> None:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32, 32), dropout=0.1)
    model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.SMCD(num_particles=N_PARTICLES))
    env = TransformedEnv(SerialEnv(2, lambda: GymEnv(ARM)), AdaptationTransform(model))
    env.set_seed(0)
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000))
    with warnings.catch_warnings():
        # The first data is collected before the model is fitted on it: adapting the untrained network is expected.
        warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)
        collector = Collector(env, None, frames_per_batch=256, total_frames=256)
        for batch in collector:
            assert batch.shape == (2, 128) and "smcd_ess" in batch["next"].keys()
            buffer.extend(batch.reshape(-1))
        collector.shutdown()
    losses = fit_from_replay_buffer(model, buffer, epochs=20, batch_size=32, lr=3e-3)
    # Targets are standardised, so a net that learns nothing stays near 1 (the first epoch is ~1.0);
    # on this data 20 epochs end at 0.45-0.51 of the first epoch's loss (seeds 0-4).
    assert len(losses) == 20 and losses[-1] < 0.7 * losses[0]


def test_fit_from_replay_buffer_rejects_empty_or_unsuitable_buffers() -> None:
    model = smcd_model(4, 2)
    buffer = ReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="empty"):
        fit_from_replay_buffer(model, buffer)
    buffer.extend(TensorDict({"observation": torch.zeros(4, 4), "action": torch.zeros(4, 2)}, [4]))
    with pytest.raises(KeyError, match="next"):
        fit_from_replay_buffer(model, buffer)


@pytest.mark.parametrize("planner", ["cem", "mppi"])
def test_mbrl_loop_runs_collect_fit_plan_adapt(planner: str) -> None:
    def pendulum_reward(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
        angle = torch.atan2(obs[..., 1], obs[..., 0])
        return -(angle**2 + 0.1 * obs[..., 2] ** 2 + 0.001 * action[..., 0] ** 2)

    model = smcd_model(3, 1, fitted=False)  # the loop fits it
    env = GymEnv("Pendulum-v1")
    returns = mbrl_loop(
        env,
        model,
        pendulum_reward,
        iterations=2,
        initial_frames=64,
        episode_steps=5,
        fit_epochs=2,
        planner=planner,
        planning_horizon=3,
        optim_steps=2,
        num_candidates=16,
        top_k=4,  # type: ignore[arg-type]
    )
    assert len(returns) == 2 and all(torch.isfinite(torch.tensor(returns)))
    assert all(r <= 0.0 for r in returns)  # Pendulum's rewards are never positive
    assert model.batch_shape == () and not env.is_closed


# ---------------------------------------------------------------------- bad input
def test_space_size_mismatch_names_the_mismatch() -> None:
    arm = gymnasium.make(ARM)
    with pytest.raises(ValueError, match=r"observation space has shape \(4,\) but the model expects 3"):
        AdaptiveWorldModelEnv.from_gym(smcd_model(3, 3), arm, arm_reward)
    with pytest.raises(ValueError, match=r"action space has shape \(2,\) but the model expects 1"):
        AdaptiveWorldModelEnv.from_gym(smcd_model(4, 1), arm, arm_reward)
    with pytest.raises(ValueError, match=r"observation spec has shape \(4,\) but the model expects 3"):
        AdaptiveWorldModelEnv.from_env(smcd_model(3, 3), GymEnv(ARM), arm_reward)
    with pytest.raises(ValueError, match=r"action_low has shape \[3\] but the model has 2"):
        AdaptiveWorldModelEnv(smcd_model(4, 2), arm_reward, action_low=torch.zeros(3), action_high=1.0)
    with pytest.raises(ValueError, match="Box"):
        AdaptiveWorldModelEnv.from_gym(smcd_model(4, 2), gymnasium.make("CartPole-v1"), arm_reward)


@pytest.mark.parametrize(
    "reward_fn",
    [
        lambda obs, action, next_obs: next_obs.sum(),  # one number for the whole batch
        lambda obs, action, next_obs: next_obs,  # one per observation dim
    ],
    ids=["scalar", "per-dim"],
)
def test_reward_fn_of_the_wrong_shape_is_a_clear_error(reward_fn: Callable) -> None:
    with pytest.raises(ValueError, match="reward_fn returned shape"):
        AdaptiveWorldModelEnv(smcd_model(4, 2), reward_fn, action_low=-1.0, action_high=1.0)


def test_model_that_is_not_a_dynamics_model_is_rejected() -> None:
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    with pytest.raises(TypeError, match="AdaptiveDynamicsModel"):
        AdaptiveWorldModelEnv(model, arm_reward, action_low=-1.0, action_high=1.0)  # type: ignore[arg-type]
