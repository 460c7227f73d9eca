"""torchrl integration: plan on an adaptive world model, adapt on every real step, fit from a replay buffer.

* :class:`AdaptiveWorldModelEnv` turns an :class:`~smcd_rl.AdaptiveDynamicsModel` and a pure batched
  reward function into a torchrl model-based env, so torchrl's own ``CEMPlanner`` and
  ``MPPIPlanner`` plan on the adapted model unchanged. :class:`RewardToGo` is the advantage
  module ``MPPIPlanner`` needs.
* :class:`AdaptationTransform` is the environment-step hook: appended to a ``TransformedEnv`` it
  calls ``model.observe`` on every real transition and writes the filter's summary (ESS, log
  evidence) into the step's tensordict.
* :func:`fit_from_replay_buffer` fits the model on a torchrl ``ReplayBuffer``; :func:`mbrl_loop`
  is the whole recipe: collect, fit, plan, adapt.

The model is shared: the transform adapts it from real steps and the world-model env predicts
with its adapted (MMSE) mask, so the planner always sees the latest posterior. Call planners under
``torch.no_grad()`` (torchrl 0.14 does not disable gradients; the env never builds autograd graphs
itself). ``torch.inference_mode()`` works too, but its tensors cannot be updated in place outside
it: a replay buffer whose lazy storage is first filled under it fails on the next ``extend``.

Import everything from this package; its modules, by job: ``envs`` (the world-model env),
``modules`` (the TensorDict modules the planners run, and the function types), ``transforms``
(the step hook), ``mbrl`` (fitting from a replay buffer and the loop).

Example:
    >>> import torch, smcd_rl
    >>> from torchrl.modules import CEMPlanner
    >>> from smcd_rl.integrations.torchrl import AdaptiveWorldModelEnv
    >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
    <torch._C.Generator object at ...>
    >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3, 2, hidden=(32,)), smcd_rl.SMCD(num_particles=10))
    >>> model.fitted = True  # a random stand-in for a trained network
    >>> model.reset()
    >>> world = AdaptiveWorldModelEnv(
    ...     model, lambda obs, act, next_obs: -next_obs.square().sum(-1), action_low=-1.0, action_high=1.0)
    >>> planner = CEMPlanner(world, planning_horizon=5, optim_steps=3, num_candidates=20, top_k=5)
    >>> with torch.no_grad():
    ...     td = planner(world.reset())
    >>> td["action"].shape
    torch.Size([1])
"""

from __future__ import annotations

from smcd_rl.integrations.torchrl.envs import AdaptiveWorldModelEnv
from smcd_rl.integrations.torchrl.mbrl import fit_from_replay_buffer, mbrl_loop
from smcd_rl.integrations.torchrl.modules import RewardFn, RewardToGo, TerminationFn
from smcd_rl.integrations.torchrl.transforms import AdaptationTransform

__all__ = [
    "RewardFn",
    "TerminationFn",
    "AdaptiveWorldModelEnv",
    "RewardToGo",
    "AdaptationTransform",
    "fit_from_replay_buffer",
    "mbrl_loop",
]
