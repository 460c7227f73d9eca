"""The task families of ``smcd-rl regimes``: their networks, training data, tuning episodes and test streams.

Two networks serve three families. The arm network (``q -> ee``) is trained on motor babbling of
many fixed two-link arms, exactly as ``smcd-rl two-link`` trains its M network; the two-link
family tests it on new arms, the telescoping family on arms whose second link changes as the
stream goes on (:func:`smcd_rl.envs.two_link_telescoping.telescoping_length`), which no training
arm did. The pendulum network (observation, action -> next observation) is trained on
random-torque episodes of many pendulums of ``smcd_rl/PendulumFamily-v0``'s mass and length
prior. Both families of the arm network are tuned on the same held-out episodes of fresh fixed
arms: the protocol tunes on the training distribution, never on the test tasks.

A family draws test tasks (:meth:`Family.sample`), noisy observations of a task from stream time
``start`` on (:meth:`Family.observed`) and noise-free points of the task at time ``at`` that the
errors are scored on (:meth:`Family.truth`).

Example:
    >>> import torch
    >>> from smcd_rl.experiments.regimes.config import RegimesConfig
    >>> family = FAMILIES["telescoping"]
    >>> g = torch.Generator().manual_seed(0)
    >>> tasks = family.sample(3, g)
    >>> family.observed(tasks, 4, 0, g, RegimesConfig()).batch_size, family.truth(tasks, 5, 4, g).batch_size
    (torch.Size([3, 4]), torch.Size([3, 5]))
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

import smcd_rl
from smcd_rl.envs.pendulum_family import pendulum_transitions, sample_pendulum_parameters
from smcd_rl.envs.two_link_arm import motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.envs.two_link_telescoping import telescoping_length
from smcd_rl.experiments.regimes.config import RegimesConfig
from smcd_rl.experiments.shared.two_link_family import network as arm_network
from smcd_rl.experiments.shared.two_link_family import reptile_settings, task_fit_settings

__all__ = [
    "Family",
    "FAMILIES",
    "NETWORKS",
    "OTHER_NETWORKS",
    "network_of",
    "method_network",
    "split_method",
    "runs_on",
    "split_network",
    "build_model",
    "other_network",
    "training_data",
    "tuning_episodes",
]

#: family -> the network it uses.
NETWORKS = {"two-link": "arm", "telescoping": "arm", "pendulum": "pendulum"}
#: Seed offsets of the streams of their own: tuning episodes and test tasks never meet the training data.
TUNING_SEED, TEST_SEED = 2_000_003, 1_000_003


#: Method prefix -> the kind of a family's other network: masks trained to identify the task (every
#: family's network), or Reptile (the pendulum's only). The network is named ``<base>-<kind>``.
OTHER_NETWORKS = {"T": "task", "R": "reptile"}


def network_of(family: str) -> str:
    """The network a family's unprefixed methods adapt (``"arm"`` or ``"pendulum"``)."""
    return NETWORKS[family]


def split_method(method: str) -> tuple[str, str]:
    """``(prefix, variant)``: ``("T", "S")`` for ``"T+S"``, ``("", method)`` for a method of a family's own network.

    Only the prefixes of :data:`OTHER_NETWORKS` count, so a budgeted label such as ``"G@1e+06ms"`` is no prefix.

    Example:
        >>> split_method("R+G"), split_method("G@1e+06ms")
        (('R', 'G'), ('', 'G@1e+06ms'))
    """
    prefix, plus, variant = method.partition("+")
    return (prefix, variant) if plus and prefix in OTHER_NETWORKS else ("", method)


def method_network(family: str, method: str) -> tuple[str, str]:
    """``(network, variant)`` of a method of ``family``: ``"T+S"`` is ``S`` on the family's task-mask network.

    Example:
        >>> method_network("pendulum", "T+S"), method_network("telescoping", "T+S"), method_network("two-link", "G")
        (('pendulum-task', 'S'), ('arm-task', 'S'), ('arm', 'G'))
    """
    prefix, variant = split_method(method)
    if not prefix:
        return network_of(family), method
    if not runs_on(family, method):
        raise ValueError(f"{method} runs on the pendulum family only, not on {family}")
    return f"{network_of(family)}-{OTHER_NETWORKS[prefix]}", variant


def split_network(network: str) -> tuple[str, str]:
    """``(base, kind)`` of a network's name: ``("arm", "task")`` for ``"arm-task"``, ``("arm", "")`` for ``"arm"``.

    Example:
        >>> split_network("pendulum-reptile"), split_network("arm")
        (('pendulum', 'reptile'), ('arm', ''))
    """
    base, _, kind = network.partition("-")
    return base, kind


def runs_on(family: str, method: str) -> bool:
    """Whether ``method`` runs on ``family``: Reptile's network (``R+``) is the pendulum's only.

    Example:
        >>> runs_on("two-link", "T+S"), runs_on("two-link", "R+G"), runs_on("pendulum", "R+G")
        (True, False, True)
    """
    return split_method(method)[0] != "R" or family == "pendulum"


def build_model(
    network: str, config: RegimesConfig, device: torch.device | str, *, mask_groups: int | None = None
) -> smcd_rl.AdaptiveModel:
    """The untrained network ``network`` as an adaptive model (its strategy is set per method)."""
    if network == "arm":
        return smcd_rl.AdaptiveModel(arm_network(config, device, mask_groups=mask_groups), in_keys=["q"], out_key="ee")
    hidden = (config.hidden,) * config.depth
    net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=hidden, dropout=config.dropout, mask_groups=mask_groups, device=device)
    return smcd_rl.AdaptiveDynamicsModel(net)


def other_network(
    network: str, config: RegimesConfig, data: TensorDictBase, device: torch.device | str
) -> tuple[smcd_rl.AdaptiveModel, Any, TensorDictBase, dict[str, Any]]:
    """A network ``<base>-<kind>`` (:data:`OTHER_NETWORKS`), untrained, with its training function, data and settings.

    It trains on its base network's own ``data`` (batch ``[tasks, episodes, steps]``); its
    initial weights come from a seed of its own and the global RNG is left as it was, so adding
    it changes nothing for the other methods. The arm's task-mask network trains every sample
    through its arm's masks (``--arm-task-share``, the masks sweep's choice on held-out arms), the
    pendulum's ``--task-share`` of them.
    """
    base, kind = split_network(network)
    task = kind == "task"
    groups = (config.mask_groups or None) if task else None  # Reptile's network is M's
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed + (29 if task else 17))
        model = build_model(base, config, device, mask_groups=groups)
    if task:
        tasks = torch.arange(data.batch_size[0], device=data.device).view(-1, 1, 1).expand(data.batch_size)
        settings = task_fit_settings(config)
        if base == "arm":
            settings["task_share"] = config.arm_task_share
        return model, smcd_rl.fit, data.clone(recurse=False).set("task", tasks), settings
    return model, smcd_rl.fit_reptile, data, reptile_settings(config)


def training_data(network: str, config: RegimesConfig, generator: torch.Generator) -> TensorDictBase:
    """The network's training data (batch ``[tasks, episodes, steps]``) from the run's generator."""
    if network == "arm":
        data = motor_babbling(
            config.tasks, config.episodes, config.steps, measurement_noise=config.measurement_noise, generator=generator
        )
        return data.select("q", "ee")
    data = pendulum_transitions(
        config.pendulum_tasks,
        config.pendulum_episodes,
        config.pendulum_steps,
        measurement_noise=config.pendulum_noise,
        generator=generator,
    )
    return data.select("observation", "action", ("next", "observation"))


def tuning_episodes(network: str, config: RegimesConfig) -> TensorDictBase:
    """``tuning_episodes`` held-out episodes ``[E, tuning_steps]`` of fresh training-distribution tasks.

    Drawn as the training data is (fixed arms; pendulums of the same prior) from a generator of
    their own, so neither training nor test tasks are among them.
    """
    generator = torch.Generator().manual_seed(config.seed + TUNING_SEED)
    family = FAMILIES["two-link" if network == "arm" else "pendulum"]
    return family.observed(family.sample(config.tuning_episodes, generator), config.tuning_steps, 0, generator, config)


class Family:
    """A task family: test tasks, their noisy observations and the noise-free points errors are scored on."""

    name = ""
    #: The key of what the network predicts.
    target: Any = ""
    #: The unit of the error.
    unit = ""

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        """``[count, 2]`` task parameters."""
        raise NotImplementedError

    def observed(
        self, tasks: Tensor, steps: int, start: int, generator: torch.Generator, config: RegimesConfig
    ) -> TensorDictBase:
        """``[count, steps]`` noisy observations of each task, stream times ``start`` to ``start + steps - 1``."""
        raise NotImplementedError

    def truth(self, tasks: Tensor, points: int, at: int, generator: torch.Generator) -> TensorDictBase:
        """``[count, points]`` noise-free points of each task as it is at stream time ``at``."""
        raise NotImplementedError


class TwoLinkFamily(Family):
    """Arms of unknown link lengths ~ N(1, 0.3) m, observed and scored at random joint configurations.

    Every observation is the end effector at a fresh joint configuration ~ U(-pi, pi)^2, so that
    what a method learns from the observations is what it is scored on: the arm over its whole
    workspace (observations along a short babbling path would reward fitting that neighbourhood).
    """

    name, target, unit = "two-link", "ee", "m"

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        return sample_link_lengths((count,), generator=generator)

    def lengths(self, tasks: Tensor, times: Tensor) -> Tensor:
        """``[count, len(times), 2]`` link lengths at the stream times (fixed for this family)."""
        return tasks.unsqueeze(1).expand(-1, times.numel(), -1)

    def observed(
        self, tasks: Tensor, steps: int, start: int, generator: torch.Generator, config: RegimesConfig
    ) -> TensorDictBase:
        count = tasks.shape[0]
        joints = (torch.rand(count, steps, 2, generator=generator) * 2 - 1) * math.pi
        ee = two_link_fk(joints, self.lengths(tasks, torch.arange(start, start + steps)))
        ee = ee + config.measurement_noise * torch.randn(ee.shape, generator=generator)
        return TensorDict({"q": joints, "ee": ee}, [count, steps])

    def truth(self, tasks: Tensor, points: int, at: int, generator: torch.Generator) -> TensorDictBase:
        count = tasks.shape[0]
        q = (torch.rand(count, points, 2, generator=generator) * 2 - 1) * math.pi
        lengths = self.lengths(tasks, torch.tensor([at])).expand(-1, points, -1)
        return TensorDict({"q": q, "ee": two_link_fk(q, lengths)}, [count, points])


class TelescopingFamily(TwoLinkFamily):
    """Arms whose second link telescopes, ``1 + 0.25 sin(pi (k + phase) / 20)`` m at stream step ``k``.

    The first link ~ N(1, 0.3) m and the phase ~ U(0, 40) steps are the task; the arm network
    never saw a link change within an episode.
    """

    name = "telescoping"

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        first = sample_link_lengths((count,), generator=generator)[:, 0]
        return torch.stack((first, 40 * torch.rand(count, generator=generator)), -1)

    def lengths(self, tasks: Tensor, times: Tensor) -> Tensor:
        second = telescoping_length(times.unsqueeze(0) + tasks[:, 1:])
        return torch.stack((tasks[:, :1].expand_as(second), second), -1)


class PendulumFamily(Family):
    """Pendulums of mass ~ U(0.5, 2) and length ~ U(0.5, 1.5) under random torques (Pendulum-v1's physics)."""

    name, target, unit = "pendulum", ("next", "observation"), "observation units"

    def sample(self, count: int, generator: torch.Generator) -> Tensor:
        return sample_pendulum_parameters((count,), generator=generator)

    def observed(
        self, tasks: Tensor, steps: int, start: int, generator: torch.Generator, config: RegimesConfig
    ) -> TensorDictBase:
        data = pendulum_transitions(
            tasks.shape[0], 1, steps, parameters=tasks, measurement_noise=config.pendulum_noise, generator=generator
        )
        return data.select("observation", "action", ("next", "observation"))[:, 0]

    def truth(self, tasks: Tensor, points: int, at: int, generator: torch.Generator) -> TensorDictBase:
        # One random-torque transition from each of `points` fresh initial states: the states a
        # planner asks about, away from the observed trajectory.
        data = pendulum_transitions(tasks.shape[0], points, 1, parameters=tasks, generator=generator)
        return data.select("observation", "action", ("next", "observation"))[:, :, 0]


#: name -> family.
FAMILIES: dict[str, Family] = {f.name: f for f in (TwoLinkFamily(), TelescopingFamily(), PendulumFamily())}
