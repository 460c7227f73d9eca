"""mbrl-lib's own trained ``GaussianMLP`` ensemble, wrapped, adapted and planned with.

The ensemble is trained by mbrl-lib's ``ModelTrainer`` on the pendulum family's transitions, as a
PETS user trains it; these tests need mbrl-lib 0.2.0 (``scripts/install_mbrl_lib.sh``, which CI
runs) and skip, saying so, where it is not importable.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch

import smcd_rl
from smcd_rl.envs.pendulum_family import pendulum_reward, pendulum_transitions
from smcd_rl.integrations.mbrl_lib import MbrlLibModel, make_cem_agent, make_model_env
from smcd_rl.integrations.mbrl_models import dynamics_models_from_mbrl, members_from_gaussian_mlp
from tests.integrations.test_mbrl_lib import MBRL_MISSING

if MBRL_MISSING is None:  # mbrl-lib imports here (the adapter's tests checked it)
    import mbrl.models
    import mbrl.util.common

pytestmark = pytest.mark.skipif(MBRL_MISSING is not None, reason=MBRL_MISSING or "")

MEMBERS = 3


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def trained() -> object:
    """A 3-member GaussianMLP (2 x 64) in mbrl-lib's wrapper, trained by its ModelTrainer on 60 poles."""
    generator = torch.Generator().manual_seed(0)
    data = pendulum_transitions(60, 1, 50, measurement_noise=0.01, generator=generator).reshape(-1)
    rows = data.shape[0]
    buffer = mbrl.util.ReplayBuffer(rows, (3,), (1,), rng=np.random.default_rng(0))
    none = np.zeros(rows, dtype=bool)
    buffer.add_batch(
        data["observation"].numpy(),
        data["action"].numpy(),
        data["next", "observation"].numpy(),
        np.zeros(rows, dtype=np.float32),
        none,
        none,
    )
    torch.manual_seed(0)
    gaussian = mbrl.models.GaussianMLP(4, 3, "cpu", num_layers=2, ensemble_size=MEMBERS, hid_size=64)
    wrapper = mbrl.models.OneDTransitionRewardModel(
        gaussian, target_is_delta=True, normalize=True, learned_rewards=False
    )
    wrapper.update_normalizer(buffer.get_all())
    train, val = mbrl.util.common.get_basic_buffer_iterators(buffer, 64, 0.1, ensemble_size=MEMBERS)
    mbrl.models.ModelTrainer(wrapper, optim_lr=1e-3).train(train, val, num_epochs=20, silent=True)
    return wrapper


def _poles(count: int, steps: int, seed: int):
    return pendulum_transitions(count, 1, steps, measurement_noise=0.01, generator=torch.Generator().manual_seed(seed))[
        :, 0
    ]


def test_each_member_predicts_exactly_what_mbrl_libs_model_predicts(trained) -> None:
    """The wrapped members' next observations are the wrapper's: normalised input, member's mean, plus obs."""
    poles = _poles(4, 5, seed=1)
    obs, action = poles["observation"].reshape(-1, 3), poles["action"].reshape(-1, 1)
    with torch.no_grad():
        model_in = trained._get_model_input(obs, action)
        mean, _ = trained.model(model_in.expand(MEMBERS, *model_in.shape))
    models = dynamics_models_from_mbrl(trained)
    assert len(models) == MEMBERS
    for i, member in enumerate(models):
        member.reset()
        with torch.no_grad():
            torch.testing.assert_close(member.step(obs, action), mean[i] + obs, rtol=1e-5, atol=1e-5)


def test_a_silu_gaussian_mlp_with_learned_rewards_is_read_without_its_reward_column() -> None:
    torch.manual_seed(0)
    gaussian = mbrl.models.GaussianMLP(
        5, 4, "cpu", num_layers=3, ensemble_size=2, hid_size=16, activation_fn_cfg={"_target_": "torch.nn.SiLU"}
    )
    nets = members_from_gaussian_mlp(gaussian, outputs=3)
    assert [net.activation for net in nets] == ["silu", "silu"] and nets[0].hidden == (16, 16, 16)
    x = torch.rand(7, 5)
    with torch.no_grad():
        mean, _ = gaussian(x.expand(2, 7, 5))
        for i, net in enumerate(nets):
            torch.testing.assert_close(net(x), mean[i, :, :3], rtol=1e-5, atol=1e-6)
    wrapper = mbrl.models.OneDTransitionRewardModel(gaussian, learned_rewards=True)
    (model, *_) = dynamics_models_from_mbrl(wrapper, members=[1])
    assert model.observation_dim == 3 and model.action_dim == 2  # 5 inputs: 3 observations, 2 actions


def test_the_tuned_last_layer_adapts_the_trained_ensemble_to_new_poles(trained) -> None:
    """``smcd_rl.tune`` on 20 held-out poles (member 0), then every member with its choice: after 10
    observations of each of 16 fresh poles, the ensemble's mean one-step prediction of the next 20.

    Measured: the tuned last layer's error is 0.67x the unadapted ensemble's (0.164 against 0.223),
    lower on 14 of 16 poles, its paired difference 3.3 standard errors below zero. The test asks for
    0.8x and 2 standard errors: a readout that did not move (1x) or moved at random cannot pass."""
    held_out, poles = _poles(20, 30, seed=5), _poles(16, 30, seed=2)
    result = smcd_rl.tune(
        dynamics_models_from_mbrl(trained)[0], held_out, strategies=["none", "last_layer"], progress=False
    )

    def error(adaptation: smcd_rl.Adaptation) -> torch.Tensor:
        models = dynamics_models_from_mbrl(trained, adaptation=adaptation)
        for model in models:
            model.reset(batch_shape=(16,))
            for t in range(10):
                model.observe(poles[:, t])
        with torch.no_grad():
            predicted = torch.stack(
                [
                    torch.stack([m.step(poles["observation"][:, t], poles["action"][:, t]) for t in range(10, 30)], 1)
                    for m in models
                ]
            ).mean(0)
        return (predicted - poles["next", "observation"][:, 10:]).square().sum(-1).mean(-1).sqrt()

    unadapted, adapted = error(result.strategy("none")), error(result.strategy("last_layer"))
    difference = adapted - unadapted
    assert adapted.mean() < 0.8 * unadapted.mean(), (adapted.mean(), unadapted.mean())
    assert difference.mean() < -2 * difference.std() / 4, difference


def test_mbrl_libs_planner_plans_with_the_adapted_ensemble_each_row_on_one_member(trained) -> None:
    models = dynamics_models_from_mbrl(trained, adaptation=smcd_rl.BayesianLastLayer(prior_scale=1.0, noise_std=0.05))
    poles = _poles(1, 10, seed=3)
    for model in models:
        model.reset()
        for t in range(10):
            model.observe(poles[0, t])
    adapter = MbrlLibModel(models, propagation="fixed_model")
    rng = torch.Generator().manual_seed(0)
    state = adapter.reset(np.zeros((12, 3), dtype=np.float32), rng=rng)
    assert sorted(state["members"].tolist()) == [i % MEMBERS for i in sorted(range(12), key=lambda i: i % MEMBERS)]
    action = torch.linspace(-2, 2, 12).unsqueeze(-1)
    first, _, _, state = adapter.sample(action, state, rng=rng)
    second, *_ = adapter.sample(action, state, rng=rng)
    with torch.no_grad():
        for row, member in enumerate(state["members"].tolist()):  # each row follows its member for the horizon
            expected = models[member].step(torch.zeros(1, 3), action[row : row + 1])
            torch.testing.assert_close(first[row : row + 1], expected)
            torch.testing.assert_close(second[row : row + 1], models[member].step(expected, action[row : row + 1]))
        mean = MbrlLibModel(models, propagation="expectation").sample(action, {"obs": torch.zeros(12, 3)})[0]
        torch.testing.assert_close(mean, torch.stack([m.step(torch.zeros(12, 3), action) for m in models]).mean(0))

    env = gymnasium.make("Pendulum-v1")
    model_env = make_model_env(env, models, pendulum_reward, seed=0)
    agent = make_cem_agent(model_env, planning_horizon=5, num_iterations=2, population_size=20, num_particles=3)
    agent.reset()
    chosen = agent.act(np.array([1.0, 0.0, 0.0], dtype=np.float32))
    assert chosen.shape == (1,) and abs(float(chosen[0])) <= 2.0


def test_refusals_name_the_problem(trained) -> None:
    with pytest.raises(ValueError, match="GaussianMLP has no dropout"):
        dynamics_models_from_mbrl(trained, adaptation=smcd_rl.SMCD(num_particles=8))
    with pytest.raises(TypeError, match="OneDTransitionRewardModel"):
        dynamics_models_from_mbrl(trained.model)
    with pytest.raises(TypeError, match="GaussianMLP"):
        members_from_gaussian_mlp(torch.nn.Sequential(torch.nn.Linear(2, 2)))
    with pytest.raises(ValueError, match=r"members must be indices in \[0, 3\)"):
        members_from_gaussian_mlp(trained.model, members=[3])
    with pytest.raises(ValueError, match="no_delta_list"):
        dynamics_models_from_mbrl(mbrl.models.OneDTransitionRewardModel(trained.model, no_delta_list=[0]))
    with pytest.raises(ValueError, match="obs_process_fn"):
        dynamics_models_from_mbrl(mbrl.models.OneDTransitionRewardModel(trained.model, obs_process_fn=np.tanh))
    models = dynamics_models_from_mbrl(trained)
    adapter = MbrlLibModel(models)
    for model in models:
        model.reset()
    with pytest.raises(ValueError, match=r"members must be a long tensor \[4\]"):
        adapter.sample(torch.zeros(4, 1), {"obs": torch.zeros(4, 3), "members": torch.full((4,), 3)})


def test_a_wrapped_member_saves_and_loads_with_its_weights_and_normaliser(trained, tmp_path) -> None:
    (model, *_) = dynamics_models_from_mbrl(
        trained, adaptation=smcd_rl.BayesianLastLayer(prior_scale=1.0, noise_std=0.05)
    )
    poles = _poles(1, 6, seed=4)
    smcd_rl.save(model, tmp_path / "member.pt")
    loaded = smcd_rl.load(tmp_path / "member.pt")
    for m in (model, loaded):
        m.reset()
        for t in range(5):
            m.observe(poles[0, t])
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.step(poles["observation"][0, 5:], poles["action"][0, 5:]),
            model.step(poles["observation"][0, 5:], poles["action"][0, 5:]),
        )
