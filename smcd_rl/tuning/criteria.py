"""What :func:`smcd_rl.tune` and :func:`smcd_rl.calibrate` score a setting by: the error you are judged by.

A strategy runs over held-out episodes. At every start ``t = 1..T-H`` of an episode, after
observing steps ``< t``, its state is frozen and it predicts steps ``t..t+H-1``, **open loop**:

* a model such as ``q -> ee`` predicts each of those steps from that step's recorded inputs
  (what the look-ahead tables of the two-link and drone experiments score);
* an :class:`smcd_rl.AdaptiveDynamicsModel` rolls its own predictions forward from the recorded
  observation at ``t`` on the recorded actions (what a planner's rollout does).

The criteria score those predictions:

* ``"one-step"`` (the default): ``H = 1``, the RMSE of each step predicted from the steps before it;
* ``"lookahead"`` with ``horizon=H``: the RMSE pooled over the ``H`` steps and every start;
* a callable ``score(predicted, observed) -> float``, lower is better: your own score.
  ``predicted`` and ``observed`` are ``[E, S, H, out]`` tensors (``E`` episodes, ``S = T - H``
  starts, ``H`` steps ahead) of the model's target (for a dynamics model, the next observation)
  in its own units. It is called on every episode and, when settings are raced, on the first
  quarter of them, so it must be a score of any subset of episodes (a mean over them, say);
  ``inf`` marks a setting that cannot be used.

Where the score is a control outcome (tracking error, success), a look-ahead over the horizon the
controller plans is its proxy: a filter tuned for one step ahead may be noisy or slow over ten.

Example:
    >>> import torch
    >>> criterion = checked_criterion("lookahead", 10)
    >>> criterion.label, criterion.horizon
    ('10-step look-ahead RMSE', 10)
    >>> def worst_final_step(predicted, observed):  # a score of your own: [E, S, H, out] each
    ...     return float((predicted[:, :, -1] - observed[:, :, -1]).norm(dim=-1).max())
    >>> mine = checked_criterion(worst_final_step, 3)
    >>> mine.label, mine.score(torch.zeros(2, 4, 3, 1), torch.ones(2, 4, 3, 1))
    ('worst_final_step (3 steps ahead)', 1.0)
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torch import Tensor

from smcd_rl.checks import check_count
from smcd_rl.model import AdaptiveDynamicsModel, AdaptiveModel
from smcd_rl.strategies.base import Adaptation

__all__ = ["Criterion", "Score", "Lookahead", "checked_criterion", "CRITERIA"]

#: A score of your own: ``score(predicted, observed) -> float``, both ``[E, S, H, out]``, lower is better.
Score = Callable[[Tensor, Tensor], float]
#: The criteria named by a string (``"evidence"``: :func:`smcd_rl.calibrate`'s filter evidence).
CRITERIA = ("one-step", "evidence", "lookahead")


@dataclass(frozen=True)
class Criterion:
    """A checked criterion: its name, how many steps ahead it looks, and the score of your own."""

    #: ``"one-step"``, ``"evidence"``, ``"lookahead"`` or ``"custom"``.
    name: str
    #: Steps predicted open loop from each start (1 for one-step and evidence).
    horizon: int = 1
    #: The callable of a ``"custom"`` criterion.
    fn: Score | None = field(default=None, compare=False)

    @property
    def looks_ahead(self) -> bool:
        """Whether runs must record their open-loop predictions (a look-ahead or a score of your own)."""
        return self.name in ("lookahead", "custom")

    @property
    def key(self) -> str:
        """What a reused result must have been tuned by: the name, horizon and, for a callable, its name."""
        if self.name == "custom":
            qualified = getattr(self.fn, "__qualname__", _name(self.fn))
            return f"custom:{getattr(self.fn, '__module__', '')}.{qualified}:{self.horizon}"
        return self.name if self.horizon == 1 else f"{self.name}:{self.horizon}"

    @property
    def label(self) -> str:
        """The score's name in tables."""
        if self.name == "lookahead":
            return f"{self.horizon}-step look-ahead RMSE"
        if self.name == "custom":
            return f"{_name(self.fn)} ({self.horizon} step{'s' if self.horizon > 1 else ''} ahead)"
        return "log evidence" if self.name == "evidence" else "one-step RMSE"

    def score(self, predicted: Tensor, observed: Tensor) -> float:
        """The score of open-loop predictions ``[E, S, H, out]`` against the observations (lower is better)."""
        if self.name != "custom":
            return rmse(predicted, observed)
        assert self.fn is not None
        value = self.fn(predicted, observed)
        if isinstance(value, Tensor) and value.numel() == 1:
            value = value.item()
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"criterion {_name(self.fn)} must return a number (lower is better), got {value!r}")
        if math.isnan(value):
            raise ValueError(f"criterion {_name(self.fn)} returned NaN; return inf for a setting that cannot be used")
        return float(value)


def checked_criterion(criterion: str | Score, horizon: int | None = None) -> Criterion:
    """``criterion`` and ``horizon`` as a :class:`Criterion`, or an error that says what to pass.

    Example:
        >>> checked_criterion("one-step").key, checked_criterion("lookahead", 5).key
        ('one-step', 'lookahead:5')
    """
    if callable(criterion):
        return Criterion("custom", 1 if horizon is None else check_count(horizon, "horizon"), criterion)
    if not isinstance(criterion, str) or criterion not in CRITERIA:
        raise ValueError(
            f"criterion must be one of {list(CRITERIA)} or a callable score(predicted, observed) -> float, "
            f"got {criterion!r}"
        )
    if criterion == "lookahead":
        if horizon is None:
            raise ValueError(
                "criterion='lookahead' needs horizon=H: the steps ahead your planner or table scores, e.g. horizon=10"
            )
        return Criterion("lookahead", check_count(horizon, "horizon"))
    if horizon not in (None, 1):
        raise ValueError(
            f"criterion={criterion!r} scores one step ahead, so horizon={horizon!r} has no meaning; "
            "pass criterion='lookahead' to score H steps ahead"
        )
    return Criterion(criterion)


class Lookahead:
    """The episodes' open-loop targets, and each start's predictions of a running strategy (module doc).

    Built once per set of episodes; :func:`smcd_rl.tuning.diagnostics.trace_pairs` calls :meth:`predict`
    at every start with the strategy's state after the steps before it.
    """

    def __init__(self, model: AdaptiveModel, td: TensorDictBase, horizon: int) -> None:
        steps = int(td.batch_size[1])
        if steps <= horizon:
            raise ValueError(
                f"a {horizon}-step look-ahead needs episodes longer than {horizon} steps (it predicts from step 1 "
                f"on, after observing step 0), got {steps}; pass longer episodes or a shorter horizon"
            )
        what = "calibrate (episodes)"
        self.model, self.horizon = model, horizon
        self.dynamics = isinstance(model, AdaptiveDynamicsModel)
        self.raw_inputs = model._raw_inputs(td, what=what, exact=True)
        #: The recorded target of every step, ``[E, T, out]``, in its own units.
        self.targets = model._read(td, model.target_key, model.net.out_features, what=what, exact=True)
        windows = self.targets.unfold(1, horizon, 1).movedim(-1, 2)  # [E, T - H + 1, H, out]
        #: What the predictions of start ``t = 1..T-H`` are scored against, ``[E, S, H, out]``.
        self.observed = windows[:, 1 : steps - horizon + 1]

    @property
    def starts(self) -> int:
        return int(self.observed.shape[1])

    def predict(self, strategy: Adaptation, t: int, x: Tensor, y: Tensor) -> Tensor:
        """Steps ``t..t+H-1`` predicted with the strategy's present state, ``[E, H, out]`` in target units.

        ``x``, ``y`` are the normalised inputs and outputs ``[E, T, ...]`` of the episodes this
        look-ahead was built on (or :meth:`rows` of).
        """
        model, horizon = self.model, self.horizon
        std = model.output_norm.std
        if not self.dynamics:
            # The recorded inputs of each step; predicted - observed = (normalised difference) x std,
            # also where the target is a base plus the network's output.
            predicted = strategy.predict(x[:, t : t + horizon])
            return self.targets[:, t : t + horizon] + (predicted - y[:, t : t + horizon]) * std
        raw = self.raw_inputs
        size = model.net.out_features
        state, actions = raw[:, t, :size], raw[:, t : t + horizon, size:]
        rolled = []
        for h in range(horizon):
            output = model.output_norm.inverse(
                strategy.predict(model.input_norm(torch.cat([state, actions[:, h]], -1)))
            )
            state = state + output if model.base_key is not None else output
            rolled.append(state)
        return torch.stack(rolled, 1)

    def rows(self, rows: slice) -> Lookahead:
        """The same look-ahead on a slice of the episodes (a race's first episodes)."""
        part = copy.copy(self)
        part.raw_inputs, part.targets, part.observed = self.raw_inputs[rows], self.targets[rows], self.observed[rows]
        return part

    def rmse(self, ahead: Tensor) -> float:
        """The RMSE (pooled) of a run's open-loop predictions ``[E, S, H, out]`` against these episodes."""
        return rmse(ahead, self.observed)


def rmse(predicted: Tensor, observed: Tensor) -> float:
    """The root-mean-square difference, pooled over every entry, in float64."""
    return float((predicted.to(torch.float64) - observed.to(torch.float64)).square().mean().sqrt())


def _name(fn: object) -> str:
    return str(getattr(fn, "__name__", None) or type(fn).__name__)
