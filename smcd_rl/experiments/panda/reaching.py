"""The reaching loop of ``smcd-rl panda``: a batch of Panda arms under Jacobian PD control, measured every n-th step.

:func:`sample_tasks` draws one seed's tools and goals, :func:`method_kinematics` turns a method
label (``FK``, ``M+N``, ``M+G``, ``M+S``, ``M+S(evidence)``, ``M+S(paper)``, ``M+C``) into the
controller's kinematics and what a measurement updates, and :func:`reach` drives the arms and
reports who got there.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

import smcd_rl
from smcd_rl.agents.pd import JacobianPD
from smcd_rl.envs.panda_reach import (
    READY_POSE,
    integrate_panda,
    panda_fk,
    sample_goals,
    sample_tool_lengths,
)
from smcd_rl.experiments.shared.tuned_methods import strategy_for
from smcd_rl.experiments.shared.tuning import Tuning

if TYPE_CHECKING:
    from smcd_rl.experiments.panda.config import PandaConfig

__all__ = ["Kinematics", "Observe", "TUNING_SEED", "sample_tasks", "tuning_episodes", "method_kinematics", "reach"]

#: Offset of the tuning episodes' generator seed from ``--seed``: a stream of its own, apart from the
#: training data's (the run's generator) and the test tasks' (``seed * 1_000_003 + 7919 (s + 1)``).
TUNING_SEED = 2_000_003


def sample_tasks(config: PandaConfig, seed: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """One seed's tools ``[tasks]`` and goals ``[tasks, 3]``, disjoint from the training data's draws."""
    generator = torch.Generator().manual_seed(config.seed * 1_000_003 + 7919 * (seed + 1))
    tools = sample_tool_lengths(config.tasks, tool_range=config.tool_range, generator=generator)
    goals = sample_goals(tools, generator=generator)
    return tools.to(device), goals.to(device)


def tuning_episodes(config: PandaConfig, device: torch.device | str) -> TensorDictBase:
    """The fair protocol's held-out episodes: ``[tuning_episodes, tuning_steps]`` in the model's keys.

    Each episode is a reach of a fresh arm: a tool drawn from the training distribution
    (``U(-tool_range, tool_range)``) and a goal drawn as the test goals are, driven from the ready
    pose by the PD law on the tool-less kinematics measured every step (so it knows nothing learned
    and nothing of the test tasks). The episode holds the joints and the measured end effector at
    ``tuning_steps`` evenly spaced steps of the ``config.steps``-step reach: the states the test
    reaches pass through, where the training data's uniform random poses are mostly far away. The
    generator has a seed of its own (``config.seed + TUNING_SEED``), so neither the training samples
    nor the test tasks are among them.

    Example:
        >>> from smcd_rl.experiments.panda.config import PandaConfig
        >>> episodes = tuning_episodes(PandaConfig(tuning_episodes=3, tuning_steps=4, steps=40), "cpu")
        >>> episodes.batch_size, episodes["q"].shape, episodes["ee"].shape
        (torch.Size([3, 4]), torch.Size([3, 4, 7]), torch.Size([3, 4, 3]))
    """
    generator = torch.Generator().manual_seed(config.seed + TUNING_SEED)
    episodes, steps = config.tuning_episodes, config.tuning_steps
    tools = sample_tool_lengths(episodes, tool_range=config.tool_range, generator=generator)
    goals = sample_goals(tools, generator=generator)
    pd = JacobianPD(lambda q: panda_fk(q, 0.0), k1=config.k1, k2=config.k2)
    q = torch.tensor(READY_POSE, dtype=tools.dtype).expand(episodes, -1).clone()
    q_dot = torch.zeros_like(q)
    every = max(1, config.steps // steps)
    joints, measured = [], []
    for t in range(every * steps):
        position = panda_fk(q, tools)
        if config.measurement_noise > 0:
            position = position + config.measurement_noise * torch.randn(position.shape, generator=generator)
        if t % every == 0:
            joints.append(q)
            measured.append(position)
        with torch.no_grad():
            q, q_dot = integrate_panda(q, q_dot, pd(q, q_dot, goals, position), config.dt)
    data = {"q": torch.stack(joints, 1), "ee": torch.stack(measured, 1)}
    return TensorDict(data, batch_size=[episodes, steps]).to(device)


Kinematics = Callable[[Tensor], Tensor]
Observe = Callable[[Tensor, Tensor], None]


def method_kinematics(
    label: str,
    models: dict[str, smcd_rl.AdaptiveModel],
    tools: Tensor,
    tunings: dict[str, Tuning],
    config: PandaConfig,
    seed: int,
    device: torch.device,
) -> tuple[Kinematics, Observe | None]:
    """The controller's kinematics and, for adaptive models, what a measurement updates.

    Every method but ``FK`` and ``M+N`` adapts its network (``models[network]``: ``M``, or ``T``
    whose masks were trained to identify the tool) with the strategy its network's tuning holds
    for it: ``G`` tuned GD, ``S`` SMCD tuned by one-step error, ``S(evidence)`` SMCD calibrated by
    its evidence, ``C`` the combination, ``L``/``SL`` the last layers, ``S(paper)`` SMCD at
    ``--noise-std`` and ``--flip-prob``; ``M+N`` does not adapt.
    """
    if label == "FK":
        return (lambda q: panda_fk(q, 0.0)), None  # the tool is unknown: assume none
    model = models[label.partition("+")[0]]
    adapted = model.with_adaptation(strategy_for(label, tunings, seed=config.seed * 1_000_003 + seed, device=device))
    adapted.reset(batch_shape=(tools.shape[0],))

    def observe(q: Tensor, measured: Tensor) -> None:
        adapted.observe(TensorDict({"q": q, "ee": measured}, [q.shape[0]]))

    return adapted.predict, observe


def reach(
    kinematics: Kinematics,
    observe: Observe | None,
    tools: Tensor,
    goals: Tensor,
    *,
    interval: int,
    config: PandaConfig,
    generator: torch.Generator | None = None,
    record: int = 0,
) -> dict[str, Tensor]:
    """Drive a batch of arms from the ready pose towards their goals with Jacobian PD control.

    At steps ``0, interval, 2 interval, ...`` the true end effector is measured: ``observe(q, x)``
    adapts the model (if any) and the controller corrects the measured error; at other steps it
    corrects its kinematics' own prediction (model-reference control).

    Args:
        kinematics: the controller's ``q [B, 7] -> x [B, 3]`` (row-wise).
        observe: called with ``(q, measured x)`` at every measurement, or ``None``.
        tools: the true tool of each arm ``[B]``.
        goals: ``[B, 3]``.
        interval: a measurement every ``interval``-th step.
        config: gains, step, tolerance, step count and measurement noise.
        generator: random source of the measurement noise.
        record: keep the joint angles of the first ``record`` arms at every step (for videos);
            recording changes no number.

    Returns:
        ``reached`` (bool ``[B]``: within ``config.tolerance`` at some step), ``steps`` (the first
        such step, ``config.steps + 1`` if never) and ``final_distance`` (m) after the last step
        (``config.steps``, or earlier once every arm has reached its goal); with ``record``, also
        ``trajectory``, the first arms' joint angles ``[record, config.steps + 1, 7]`` from the
        start (after an early stop the last angles repeat).

    Example:
        >>> import torch
        >>> from smcd_rl.experiments.panda.run import PandaConfig, reach
        >>> from smcd_rl.envs.panda_reach import panda_fk, sample_goals
        >>> tools = torch.tensor([0.3, -0.2])
        >>> goals = sample_goals(tools, generator=torch.Generator().manual_seed(0))
        >>> result = reach(lambda q: panda_fk(q, tools), None, tools, goals, interval=1, config=PandaConfig())
        >>> result["reached"]  # the true kinematics, measured every step
        tensor([True, True])
    """
    batch = tools.shape[0]
    pd = JacobianPD(kinematics, k1=config.k1, k2=config.k2)
    q = torch.tensor(READY_POSE, device=tools.device, dtype=tools.dtype).expand(batch, -1).clone()
    q_dot = torch.zeros_like(q)
    reached = torch.zeros(batch, dtype=torch.bool, device=tools.device)
    first = torch.full((batch,), config.steps + 1, device=tools.device)
    trajectory = [q[:record].cpu()] if record else []  # (a copy to the CPU syncs a GPU: only when recording)
    for t in range(config.steps):
        position = None
        if t % interval == 0:
            position = panda_fk(q, tools)
            if config.measurement_noise > 0:
                noise = torch.randn(position.shape, generator=generator, device=position.device)
                position = position + config.measurement_noise * noise
            if observe is not None:
                observe(q, position)
        with torch.no_grad():
            try:
                u = pd(q, q_dot, goals, position)
            except torch.linalg.LinAlgError as err:  # the pseudo-inverse of a NaN Jacobian
                raise ValueError(
                    f"the controller's kinematics became non-finite at step {t} (a diverged adaptation, e.g. "
                    "gradient descent with too high a learning rate: lower --gd-lr)"
                ) from err
            q, q_dot = integrate_panda(q, q_dot, u, config.dt)
            close = (panda_fk(q, tools) - goals).norm(dim=-1) < config.tolerance
        first = torch.where(close & ~reached, torch.full_like(first, t + 1), first)
        reached |= close
        if record:
            trajectory.append(q[:record].cpu())
        if bool(reached.all()):  # success is decided at the first arrival: nothing left to learn
            break
    final = (panda_fk(q, tools) - goals).norm(dim=-1)
    result = {"reached": reached, "steps": first, "final_distance": final}
    if record:
        trajectory += trajectory[-1:] * (config.steps + 1 - len(trajectory))
        result["trajectory"] = torch.stack(trajectory, dim=1)
    return result
