"""MPCAgent: a learned, SMCD-adapted model drives a point mass to its goal; objective semantics; errors.

The task is a point mass on a line, obs ``[x, v]``, force ``a`` in ``[-1, 1]``, ``dt = 0.1``
(semi-implicit Euler), starting at rest at ``x = 0``; success means ``|x - 1| < 0.1`` and
``|v| < 0.2`` after 40 steps. Chance level: uniformly random forces succeed with probability
about 0.9% (measured over 200,000 episodes; :func:`test_chance_level_of_the_goal_is_low`
re-measures it), so an agent that succeeds is not lucky. The dynamics model is a MaskedMLP fitted
on 2,000 random transitions (about a second), and it never sees the true dynamics otherwise.
Over 4 training seeds x 3 planner seeds both ensemble modes ended within ``|x - 1| <= 0.021`` and
``|v| <= 0.053``, far inside the tolerances.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium import spaces
from tensordict import TensorDict
from torch import Tensor

import smcd_rl
from smcd_rl.agents.mpc import MPCAgent, model_reward_objective
from smcd_rl.agents.planners import CEM, RandomShooting
from smcd_rl.integrations.gymnasium import AdaptationWrapper

DT = 0.1
GOAL = 1.0
STEPS = 40


def point_mass_step(x: Any, v: Any, force: Any) -> tuple[Any, Any]:
    """Semi-implicit Euler of x'' = force (force clipped to [-1, 1]); numpy arrays or torch tensors."""
    v_next = v + force.clip(-1.0, 1.0) * DT
    return x + v_next * DT, v_next


def succeeded(x: Any, v: Any) -> Any:
    return (abs(x - GOAL) < 0.1) & (abs(v) < 0.2)


class PointMassEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """The test task as a gymnasium env (reward: minus squared distance to the goal)."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self._state = np.zeros(2)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._state = np.zeros(2)
        return self._state.astype(np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        x, v = point_mass_step(self._state[0], self._state[1], np.asarray(action, np.float64).reshape(-1)[0])
        self._state = np.array([x, v])
        return self._state.astype(np.float32), -float((x - GOAL) ** 2), False, False, {}


def reward_fn(obs: Tensor, action: Tensor, next_obs: Tensor) -> Tensor:
    return -(next_obs[..., 0] - GOAL).square() - 0.1 * next_obs[..., 1].square()


@pytest.fixture(scope="module")
def trained() -> smcd_rl.AdaptiveDynamicsModel:
    """Dynamics model fitted on random transitions around the task's region of the state space."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    n = 2000
    obs = torch.stack([torch.rand(n, generator=g) * 2.5 - 0.5, torch.rand(n, generator=g) * 3 - 1.5], -1)
    action = torch.rand(n, 1, generator=g) * 2 - 1
    x, v = point_mass_step(obs[:, 0], obs[:, 1], action[:, 0])
    data = TensorDict({"observation": obs, "action": action, ("next", "observation"): torch.stack([x, v], -1)}, [n])
    net = smcd_rl.MaskedMLP(2 + 1, 2, hidden=(64, 64), dropout=0.1)
    model = smcd_rl.AdaptiveDynamicsModel(net)
    losses = smcd_rl.fit_dynamics(model, data, epochs=30, batch_size=128, lr=3e-3, progress=False)
    assert losses[-1] < 0.2 * losses[0]
    return model


def smcd_copy(model: smcd_rl.AdaptiveDynamicsModel, seed: int = 0) -> smcd_rl.AdaptiveDynamicsModel:
    adaptation = smcd_rl.SMCD(num_particles=32, noise_std=0.01, generator=torch.Generator().manual_seed(seed))
    copy = model.with_adaptation(adaptation)
    assert isinstance(copy, smcd_rl.AdaptiveDynamicsModel)
    copy.reset()
    return copy


def cem(horizon: int = 10, candidates: int = 48, seed: int = 0) -> CEM:
    return CEM(
        action_low=-1.0,
        action_high=1.0,
        horizon=horizon,
        num_candidates=candidates,
        num_elites=6,
        iterations=3,
        generator=torch.Generator().manual_seed(seed),
    )


def test_chance_level_of_the_goal_is_low() -> None:
    rng = np.random.default_rng(0)
    x, v = np.zeros(100_000), np.zeros(100_000)
    for _ in range(STEPS):
        x, v = point_mass_step(x, v, rng.uniform(-1.0, 1.0, x.shape))
    assert succeeded(x, v).mean() < 0.02  # measured 0.009


@pytest.mark.parametrize("ensemble", ["mmse", "particles"])
def test_mpc_with_learned_model_reaches_the_goal(trained: smcd_rl.AdaptiveDynamicsModel, ensemble: str) -> None:
    model = smcd_copy(trained)
    env = AdaptationWrapper(PointMassEnv(), model)  # the step hook resets and adapts the model
    agent = MPCAgent(model, cem(), reward_fn, ensemble=ensemble)  # type: ignore[arg-type]
    obs, _ = env.reset(seed=0)
    agent.reset()
    for _ in range(STEPS):
        action = agent.act(obs)
        assert action.shape == (1,) and action.dtype == np.float32 and abs(action[0]) <= 1.0
        obs, *_ = env.step(action)
    assert succeeded(obs[0], obs[1]), f"ended at x={obs[0]:.3f}, v={obs[1]:.3f}"
    assert model.summary()["log_evidence"] != 0.0  # the wrapper fed the model every step


def test_particles_mode_gives_candidate_p_the_particle_p_mod_n(
    trained: smcd_rl.AdaptiveDynamicsModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = smcd_copy(trained)
    masks: list[Tensor | None] = []
    step = model.step

    def spy(obs: Tensor, action: Tensor, *, mask: Tensor | None = None) -> Tensor:
        masks.append(mask)
        return step(obs, action, mask=mask)

    monkeypatch.setattr(model, "step", spy)
    objective = model_reward_objective(model, torch.zeros(2), reward_fn, ensemble="particles")
    objective(torch.zeros(80, 3, 1))  # 80 candidates > 32 particles: wraps around
    particles = model.particles
    assert len(masks) == 3 and all(m is masks[0] for m in masks)  # one mask per candidate for the whole horizon
    mask = masks[0]
    assert mask is not None and mask.shape == (80, model.net.mask_dim)
    for p in (0, 5, 31, 32, 79):
        assert torch.equal(mask[p], particles[p % 32])
    assert len({tuple(row.tolist()) for row in mask[:32]}) > 1  # different candidates, different masks

    masks.clear()
    model_reward_objective(model, torch.zeros(2), reward_fn)(torch.zeros(8, 3, 1))
    assert masks == [None, None, None]  # "mmse": the model's adapted prediction


def test_particles_mode_with_one_state_per_env(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    model.reset(batch_shape=(2,))
    agent = MPCAgent(model, cem(horizon=4, candidates=16), reward_fn, ensemble="particles")
    assert agent.act(np.zeros((2, 2), np.float32)).shape == (2, 1)


def test_objective_sums_rewards_and_stops_after_termination(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    ones = lambda obs, action, next_obs: torch.ones(next_obs.shape[:-1])  # noqa: E731
    actions = torch.zeros(5, 4, 1)
    never = model_reward_objective(model, torch.zeros(2), ones)(actions)
    always = model_reward_objective(model, torch.zeros(2), ones, lambda n: torch.ones(n.shape[:-1], dtype=torch.bool))
    # Full force from rest gives v = 0.1, 0.2, 0.3, 0.4: "v > 0.25" ends the rollout at step 3.
    fast = model_reward_objective(model, torch.zeros(2), ones, lambda n: n[..., 1] > 0.25)
    push = torch.cat([torch.ones(3, 4, 1), -torch.ones(2, 4, 1)])  # 3 candidates push, 2 brake
    assert torch.equal(never, torch.full((5,), 4.0))
    assert torch.equal(always(actions), torch.ones(5))  # the terminating step's reward still counts
    assert torch.equal(fast(push), torch.tensor([3.0, 3.0, 3.0, 4.0, 4.0]))


def test_batched_observations_plan_one_problem_per_row(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    obs = np.array([[0.0, 0.0], [2.0, 0.0]], np.float32)  # left of the goal / right of it
    shared = MPCAgent(model, cem(), reward_fn)  # batch_shape=(): one state broadcast over rows
    first = shared.act(obs)
    assert first.shape == (2, 1) and first[0, 0] > 0.5 and first[1, 0] < -0.5
    model.reset(batch_shape=(2,))  # one adaptation state per row
    assert MPCAgent(model, cem(), reward_fn).act(torch.as_tensor(obs)).shape == (2, 1)
    with pytest.raises(ValueError, match=r"batch_shape \[2\]"):
        MPCAgent(model, cem(), reward_fn).act(np.zeros(2, np.float32))


def test_reset_forgets_the_warm_start_only(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    model.observe(
        TensorDict(
            {
                "observation": torch.zeros(2),
                "action": torch.ones(1),
                ("next", "observation"): torch.tensor([0.01, 0.1]),
            },
            [],
        )
    )
    particles = model.particles.clone()
    agent = MPCAgent(model, RandomShooting(action_low=-1.0, action_high=1.0, horizon=3, num_candidates=8), reward_fn)
    agent.act(np.zeros(2, np.float32))
    assert agent.planner.mean is not None
    agent.reset()
    assert agent.planner.mean is None
    assert torch.equal(model.particles, particles)  # the agent never adapts nor resets the model


def test_reward_fn_of_the_wrong_shape_is_named(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    keepdim = lambda obs, action, next_obs: -next_obs[..., :1].abs()  # [*batch, P, 1]  # noqa: E731
    agent = MPCAgent(model, cem(horizon=2, candidates=8), keepdim)
    with pytest.raises(ValueError, match=r"reward_fn.*returned shape \[8, 1\], expected \[\*batch, P\] = \[8\]"):
        agent.act(np.zeros(2, np.float32))
    bad_done = MPCAgent(model, cem(horizon=2, candidates=8), reward_fn, lambda n: n[..., :1] > 0)
    with pytest.raises(ValueError, match=r"termination_fn.*\[8, 1\]"):
        bad_done.act(np.zeros(2, np.float32))


def test_mismatches_with_the_model_are_named(trained: smcd_rl.AdaptiveDynamicsModel) -> None:
    model = smcd_copy(trained)
    agent = MPCAgent(model, cem(), reward_fn)
    with pytest.raises(ValueError, match=r"observation has shape \[3\].*size 2"):
        agent.act(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"planner plans actions of size 2 but the model takes actions of size 1"):
        MPCAgent(model, CEM(action_low=[-1.0, -1.0], action_high=[1.0, 1.0], horizon=3), reward_fn)
    with pytest.raises(ValueError, match=r"ensemble='particles' needs .*NoAdaptation"):
        MPCAgent(trained, cem(), reward_fn, ensemble="particles")
    with pytest.raises(ValueError, match="ensemble must be one of"):
        MPCAgent(model, cem(), reward_fn, ensemble="mean")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="AdaptiveDynamicsModel"):
        MPCAgent(
            smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(3, 2, hidden=(8,)), in_keys=["q"], out_key="y"), cem(), reward_fn
        )  # type: ignore[arg-type]


def test_action_sequences_of_the_wrong_shape_are_named() -> None:
    from smcd_rl.agents.mpc import model_reward_objective

    model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(2 + 1, 2, hidden=(8,)))
    model.fitted = True  # random weights on purpose: only the shape checks are tested
    model.reset()
    objective = model_reward_objective(model, torch.zeros(2), lambda o, a, n: -n.square().sum(-1))
    with pytest.raises(ValueError, match=r"\[\*batch, P, H, A\]"):
        objective(torch.zeros(5, 1))  # no horizon dim
    with pytest.raises(ValueError, match="actions of size 1"):
        objective(torch.zeros(8, 5, 3))  # 3 action dims for a 1-dim action model
