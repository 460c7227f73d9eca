"""The TensorDict modules the planners run: the world model behind :class:`AdaptiveWorldModelEnv` and
:class:`RewardToGo`, the advantage module of ``MPPIPlanner``; and the reward / termination function types."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from smcd_rl.integrations.gymnasium import GoalReward
from smcd_rl.model import AdaptiveDynamicsModel

__all__ = ["RewardFn", "TerminationFn", "RewardToGo"]

#: ``reward_fn(obs, action, next_obs) -> reward``: pure and batched, ``[..., O], [..., A], [..., O] -> [...]``
#: (``[..., 1]`` is accepted too).
RewardFn = Callable[[Tensor, Tensor, Tensor], Tensor]
#: ``termination_fn(next_obs) -> terminated``: pure and batched, ``[..., O] -> bool [...]`` (or ``[..., 1]``).
TerminationFn = Callable[[Tensor], Tensor]


class _WorldModel(TensorDictModuleBase):
    """(observation, action) -> (observation, reward[, terminated, done]) through the adapted model.

    ``ModelBasedEnvBase._step`` keeps only the observation, reward and done keys of what this
    module writes, so the next observation overwrites the observation key itself. With a
    :class:`GoalReward` the reward is the env's ``compute_reward`` towards the tensordict's
    desired goal, which is carried over unchanged, and the achieved goal of the predicted
    observation is written to ``achieved_goal_key``.
    """

    def __init__(
        self,
        model: AdaptiveDynamicsModel,
        reward_fn: RewardFn | GoalReward,
        termination_fn: TerminationFn | None,
        *,
        observation_key: str,
        observation_dtype: torch.dtype,
        achieved_goal_key: str = "achieved_goal",
    ) -> None:
        super().__init__()
        self.model = model
        self.reward_fn = reward_fn
        self.termination_fn = termination_fn
        self.observation_key = observation_key
        self.observation_dtype = observation_dtype
        self.goal = reward_fn if isinstance(reward_fn, GoalReward) else None
        self.achieved_goal_key = achieved_goal_key
        goal_in = [] if self.goal is None else [self.goal.desired_goal_key]
        goal_out = [] if self.goal is None else [achieved_goal_key, self.goal.desired_goal_key]
        self.in_keys = [observation_key, "action", *goal_in]
        self.out_keys = [observation_key, *goal_out, "reward"] + (["terminated", "done"] if termination_fn else [])

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        key = self.observation_key
        obs = td.get(key).to(self.observation_dtype)
        action = td.get("action")
        # Planning never needs gradients through the model, and graphs over thousands of
        # candidates cost memory and time.
        with torch.no_grad():
            query = TensorDict({key: obs, "action": action}, batch_size=td.batch_size, device=td.device)
            next_obs = self.model(query).get(("next", key)).to(self.observation_dtype)
            if self.goal is not None:
                desired = td.get(self.goal.desired_goal_key)
                reward = _checked_reward(self.goal(next_obs, desired), obs)
                td.set(self.achieved_goal_key, self.goal.achieved_goal(next_obs).to(desired.dtype))
            else:
                assert not isinstance(self.reward_fn, GoalReward)
                reward = _checked_reward(self.reward_fn(obs, action, next_obs), obs)
            td.set(key, next_obs)
            td.set("reward", reward.to(torch.float32).unsqueeze(-1))
            if self.termination_fn is not None:
                terminated = _checked_termination(self.termination_fn(next_obs), obs).unsqueeze(-1)
                td.set("terminated", terminated)
                td.set("done", terminated)
        return td


def _checked_reward(reward: Tensor, obs: Tensor) -> Tensor:
    return _one_per_transition(reward, obs, function="reward_fn", each="reward")


def _checked_termination(terminated: Tensor, obs: Tensor) -> Tensor:
    return _one_per_transition(terminated, obs, function="termination_fn", each="flag").to(torch.bool)


def _one_per_transition(value: Tensor, obs: Tensor, *, function: str, each: str) -> Tensor:
    """``value`` of shape ``obs.shape[:-1]`` (a trailing dim of 1 is dropped), else an error naming ``function``.

    Reward and termination functions are checked alike: both return one number per transition.
    """
    batch = obs.shape[:-1]
    if not isinstance(value, Tensor):
        raise TypeError(f"{function} must return a Tensor, got {type(value).__name__}")
    if value.shape == (*batch, 1):
        value = value.squeeze(-1)
    if value.shape != batch:
        raise ValueError(
            f"{function} returned shape {list(value.shape)} for observations of shape {list(obs.shape)}; "
            f"it must return one {each} per transition, shape {list(batch)} (or {[*batch, 1]})"
        )
    return value


class RewardToGo(TensorDictModuleBase):
    """Discounted reward-to-go along a rollout's time dim, the advantage module ``MPPIPlanner`` needs.

    Writes ``advantage[..., t, :] = sum_{k >= t} gamma ** (k - t) * reward[..., k, :]``, minus (with
    ``subtract_max``) the best return among the candidates. torchrl's ``MPPIPlanner`` ranks
    candidates by the advantage at t = 0, the discounted return of the whole planned sequence,
    after zeroing rewards that follow a ``done``. It weights the top candidates by
    ``exp(temperature * advantage)`` without subtracting the maximum (torchrl 0.14.1), so returns of
    a few hundred underflow every weight to 0 and the plan becomes NaN; the update is invariant to
    a shift of all candidates' advantages, so ``subtract_max`` shifts the best to 0.

    Args:
        gamma: discount factor in ``(0, 1]``.
        reward_key: where the rewards are, ``[..., K, T, 1]`` in a planner's rollout.
        advantage_key: where the reward-to-go is written (same shape).
        time_dim: the (negative) time dim of the reward tensor; candidates are the dim before it.
        subtract_max: subtract, per planning problem, the largest t = 0 return over the candidates.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from smcd_rl.integrations.torchrl import RewardToGo
        >>> td = TensorDict({("next", "reward"): torch.ones(2, 3, 1)}, [2, 3])
        >>> RewardToGo(gamma=0.5, subtract_max=False)(td)["advantage"][0, :, 0]
        tensor([1.7500, 1.5000, 1.0000])
        >>> RewardToGo(gamma=0.5)(td)["advantage"][0, :, 0]
        tensor([ 0.0000, -0.2500, -0.7500])
    """

    def __init__(
        self,
        gamma: float = 1.0,
        *,
        reward_key: NestedKey = ("next", "reward"),
        advantage_key: NestedKey = "advantage",
        time_dim: int = -2,
        subtract_max: bool = True,
    ) -> None:
        super().__init__()
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        if time_dim >= 0:
            raise ValueError(f"time_dim must be negative (counted from the last dim), got {time_dim}")
        self.gamma = float(gamma)
        self.time_dim = int(time_dim)
        self.subtract_max = bool(subtract_max)
        self.in_keys = [reward_key]
        self.out_keys = [advantage_key]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        reward = td.get(self.in_keys[0])
        r = reward.movedim(self.time_dim, -1)  # [..., T]
        steps = torch.arange(r.shape[-1], device=r.device)
        lag = steps.unsqueeze(0) - steps.unsqueeze(1)  # lag[t, k] = k - t
        discount = torch.where(lag >= 0, self.gamma ** lag.clamp(min=0).to(r.dtype), torch.zeros((), dtype=r.dtype))
        advantage = (r @ discount.T).movedim(-1, self.time_dim)
        candidate_dim = self.time_dim - 1
        if self.subtract_max and advantage.dim() >= -candidate_dim:
            best = advantage.narrow(self.time_dim, 0, 1).amax(dim=candidate_dim, keepdim=True)
            advantage = advantage - best
        td.set(self.out_keys[0], advantage)
        return td
