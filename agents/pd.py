"""Jacobian PD control of a kinematic chain: ``u = -K1 J^+ (x - x_g) - K2 q_dot`` (paper sec. 4.2, A.4).

``u`` is a joint acceleration: the ``K2 q_dot`` term is damping, which needs ``q_dot`` to be a
state the command changes gradually. (Fed back on a velocity-commanded arm, ``q_dot = u``, the
term becomes ``-K2 u_prev``, which diverges for the paper's ``K2 = 5`` at any step size.)

The controller only sees a kinematics function ``q -> x``: the analytic chain, or an adaptive
network (``model.predict``), whose Jacobian under the current mask comes from ``torch.func``. A
batch of arms is controlled at once; the kinematics must treat batch rows independently (true of
the analytic functions and of every :class:`smcd_rl.AdaptiveModel` strategy, whose adaptation
state is per row), which lets one reverse-mode pass per output give every row's Jacobian.

Example:
    >>> import torch
    >>> from smcd_rl.envs.two_link_arm import two_link_fk
    >>> from smcd_rl.agents.pd import JacobianPD
    >>> pd = JacobianPD(lambda q: two_link_fk(q, torch.tensor([1.0, 1.0])), k1=20.0, k2=5.0)
    >>> q, q_dot, goal = torch.tensor([0.3, 0.8]), torch.zeros(2), torch.tensor([1.0, 1.0])
    >>> for _ in range(200):  # a double integrator: u is the joint acceleration
    ...     q_dot = q_dot + 0.05 * pd(q, q_dot, goal)
    ...     q = q + 0.05 * q_dot
    >>> bool((two_link_fk(q, torch.tensor([1.0, 1.0])) - goal).norm() < 1e-3)
    True
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["JacobianPD", "batch_jacobian"]

Kinematics = Callable[[Tensor], Tensor]


def batch_jacobian(kinematics: Kinematics, q: Tensor) -> Tensor:
    """Jacobians ``dx/dq`` of a row-wise kinematics function at every row of ``q``.

    Args:
        kinematics: ``[*batch, n] -> [*batch, m]``, each output row depending only on its own
            input row.
        q: joint angles ``[*batch, n]``.

    Returns:
        ``[*batch, m, n]``.

    Example:
        >>> import torch
        >>> batch_jacobian(lambda q: torch.stack([q[..., 0] * q[..., 1]], -1), torch.tensor([[2.0, 3.0]]))
        tensor([[[3., 2.]]])
    """
    return _jacobian_and_position(kinematics, q)[0]


def _jacobian_and_position(kinematics: Kinematics, q: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`batch_jacobian` and the kinematics' value at ``q``, from the same forward pass."""
    batch_dims = tuple(range(q.dim() - 1))

    def summed(angles: Tensor) -> tuple[Tensor, Tensor]:
        # Rows are independent, so d(sum over rows of x_row)/dq_row = dx_row/dq_row.
        x = kinematics(angles)
        return (x.sum(dim=batch_dims) if batch_dims else x), x

    with torch.enable_grad():
        jacobian, position = torch.func.jacrev(summed, has_aux=True)(q.detach())
    return jacobian.movedim(0, -2), position.detach()


class JacobianPD:
    """The paper's PD law on end-effector error, through the pseudo-inverse of the kinematics Jacobian.

    Args:
        kinematics: ``q [*batch, n] -> x [*batch, m]`` whose Jacobian steers the arm (the true
            chain, or an adapted network such as ``model.predict``).
        k1: gain on the end-effector error (the paper uses 20 for the two-link arm).
        k2: gain on the joint velocity (the paper uses 5).
        damping: ``0`` gives the Moore-Penrose pseudo-inverse of the paper; ``lambda > 0`` gives
            the damped least-squares inverse ``J^T (J J^T + lambda^2 I)^-1``, bounded near
            singularities.
        max_command: optional bound on every joint-acceleration command (rad/s^2).

    Example:
        >>> import torch
        >>> pd = JacobianPD(lambda q: q * 2.0, k1=1.0, k2=0.0)
        >>> pd(torch.zeros(2), torch.zeros(2), goal=torch.tensor([1.0, -1.0]))
        tensor([ 0.5000, -0.5000])
    """

    def __init__(
        self, kinematics: Kinematics, *, k1: float, k2: float, damping: float = 0.0, max_command: float | None = None
    ) -> None:
        if damping < 0 or (max_command is not None and max_command <= 0):
            raise ValueError(f"need damping >= 0 and max_command > 0, got damping={damping}, max_command={max_command}")
        self.kinematics = kinematics
        self.k1, self.k2, self.damping, self.max_command = k1, k2, damping, max_command

    def __call__(self, q: Tensor, q_dot: Tensor, goal: Tensor, position: Tensor | None = None) -> Tensor:
        """The joint-acceleration command.

        Args:
            q: joint angles ``[*batch, n]``.
            q_dot: current joint velocities ``[*batch, n]``.
            goal: end-effector goal ``[*batch, m]``.
            position: the end-effector position to correct, e.g. a measurement; ``None`` uses the
                kinematics' own prediction (model-reference control between measurements).

        Returns:
            ``u [*batch, n]``.
        """
        if q.shape != q_dot.shape:
            raise ValueError(f"q and q_dot must have the same shape, got {list(q.shape)} and {list(q_dot.shape)}")
        jacobian, predicted = _jacobian_and_position(self.kinematics, q)
        if goal.shape != jacobian.shape[:-1]:
            raise ValueError(
                f"goal must have shape {list(jacobian.shape[:-1])} (batch, end-effector), got {list(goal.shape)}"
            )
        if position is None:
            position = predicted
        elif position.shape != goal.shape:
            raise ValueError(f"position must have the goal's shape {list(goal.shape)}, got {list(position.shape)}")
        error = (position - goal).unsqueeze(-1)
        u = -self.k1 * (self._inverse(jacobian) @ error).squeeze(-1) - self.k2 * q_dot
        return u if self.max_command is None else u.clamp(-self.max_command, self.max_command)

    def jacobian(self, q: Tensor) -> Tensor:
        """``dx/dq`` of the controller's kinematics, ``[*batch, m, n]``."""
        return batch_jacobian(self.kinematics, q)

    def _inverse(self, jacobian: Tensor) -> Tensor:
        if self.damping == 0:
            return torch.linalg.pinv(jacobian)
        jjt = jacobian @ jacobian.transpose(-1, -2)
        eye = torch.eye(jjt.shape[-1], dtype=jjt.dtype, device=jjt.device)
        return jacobian.transpose(-1, -2) @ torch.linalg.inv(jjt + self.damping**2 * eye)
