"""The Jacobian PD controller: exact Jacobians of any row-wise kinematics, and it reaches goals."""

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.agents.pd import JacobianPD, batch_jacobian
from smcd_rl.envs.two_link_arm import two_link_fk


def finite_difference_jacobian(kinematics, q: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    columns = []
    for i in range(q.shape[-1]):
        step = torch.zeros(q.shape[-1], dtype=q.dtype)
        step[i] = eps
        columns.append((kinematics(q + step) - kinematics(q - step)) / (2 * eps))
    return torch.stack(columns, -1)


def test_analytic_jacobian_matches_the_closed_form() -> None:
    lengths = torch.tensor([1.2, 0.7])
    q = torch.tensor([[0.3, -1.1], [2.0, 0.4]])
    q1, q12 = q[:, 0], q.sum(-1)
    expected = torch.stack(
        [
            torch.stack([-1.2 * torch.sin(q1) - 0.7 * torch.sin(q12), -0.7 * torch.sin(q12)], -1),
            torch.stack([1.2 * torch.cos(q1) + 0.7 * torch.cos(q12), 0.7 * torch.cos(q12)], -1),
        ],
        -2,
    )
    assert torch.allclose(batch_jacobian(lambda a: two_link_fk(a, lengths), q), expected, atol=1e-6)


@pytest.mark.parametrize(
    "strategy",
    [lambda: smcd_rl.SMCD(num_particles=30), lambda: smcd_rl.GradientDescent(steps=2), smcd_rl.NoAdaptation],
    ids=["smcd", "gd", "none"],
)
def test_network_jacobian_is_per_row_and_matches_finite_differences(strategy) -> None:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(2, 2, hidden=(32, 32), dropout=0.5).double()
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee").double().with_adaptation(strategy())
    model.fitted = True  # random weights on purpose: any network has a Jacobian to check
    model.reset(batch_shape=(3,))
    # Different observations per row give each row its own adapted network (masks or weights).
    model.observe(TensorDict({"q": torch.randn(3, 2), "ee": 3 * torch.randn(3, 2)}, [3]).double())
    q = torch.randn(3, 2, dtype=torch.float64)
    jacobian = batch_jacobian(model.predict, q)
    assert jacobian.shape == (3, 2, 2)
    assert torch.allclose(jacobian, finite_difference_jacobian(model.predict, q), atol=1e-6)


def test_pd_with_true_kinematics_reaches_goals() -> None:
    # 50 random reachable goals for a random arm; a controller that did not follow the Jacobian
    # would not bring all of them within 1 cm (the goals are spread over the whole workspace).
    generator = torch.Generator().manual_seed(0)
    lengths = torch.tensor([1.0, 0.8])
    goals = two_link_fk((torch.rand(50, 2, generator=generator) * 2 - 1) * math.pi, lengths)
    q = torch.full((50, 2), 0.5)
    q_dot = torch.zeros(50, 2)
    pd = JacobianPD(lambda a: two_link_fk(a, lengths), k1=20.0, k2=5.0, damping=0.01)
    for _ in range(200):
        q_dot = q_dot + 0.05 * pd(q, q_dot, goals)
        q = q + 0.05 * q_dot
    distance = (two_link_fk(q, lengths) - goals).norm(dim=-1)
    assert (distance < 0.01).float().mean() >= 0.95


def test_position_overrides_the_model_and_max_command_clips() -> None:
    pd = JacobianPD(lambda q: q, k1=1.0, k2=0.0, max_command=0.5)
    q = torch.zeros(2)
    assert torch.equal(pd(q, q, torch.zeros(2), position=torch.tensor([0.2, -3.0])), torch.tensor([-0.2, 0.5]))


def test_bad_shapes_and_settings_are_named() -> None:
    pd = JacobianPD(lambda q: q[..., :2], k1=1.0, k2=1.0)
    with pytest.raises(ValueError, match="q_dot"):
        pd(torch.zeros(3), torch.zeros(2), torch.zeros(2))
    with pytest.raises(ValueError, match="goal must have shape"):
        pd(torch.zeros(3), torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueError, match="damping"):
        JacobianPD(lambda q: q, k1=1.0, k2=1.0, damping=-1.0)


def test_predict_refuses_delta_models_and_wrong_widths() -> None:
    dynamics = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3, 2, hidden=(8,)))
    dynamics.fitted = True  # random networks on purpose: only the refusals are tested
    dynamics.reset()
    with pytest.raises(ValueError, match="use model.step"):
        dynamics.predict(torch.zeros(3))
    model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    model.fitted = True
    model.reset()
    with pytest.raises(ValueError, match=r"inputs \[\.\.\., 2\]"):
        model.predict(torch.zeros(3))
