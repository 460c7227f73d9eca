"""Runs of strategies over checked episodes, scored by one criterion: what tune and calibrate compare.

One :class:`Scorer` serves a whole :func:`smcd_rl.tune` call, the SMCD calibration it runs
included: the episodes are checked and normalised once, and every candidate is scored the same way.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    >>> model.fitted = True  # a toy network: declare it trained
    >>> episodes = TensorDict({"q": torch.rand(3, 6, 2), "ee": torch.zeros(3, 6, 2)}, [3, 6])
    >>> result = smcd_rl.tune(model, episodes, strategies=["none", "gradient_descent"], criterion="lookahead",
    ...                       horizon=2, progress=False)
    >>> result.score_label
    '2-step look-ahead RMSE'
"""

from __future__ import annotations

import math

from tensordict import TensorDictBase
from torch import Tensor

from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies.base import Adaptation
from smcd_rl.tuning.criteria import Criterion, Lookahead
from smcd_rl.tuning.diagnostics import Trace, trace_pairs
from smcd_rl.tuning.held_out import pairs

__all__ = ["Scorer"]


class Scorer:
    """The episodes as normalised pairs (and open-loop targets), and how a run on them scores."""

    def __init__(self, model: AdaptiveModel, td: TensorDictBase, criterion: Criterion, caller: str) -> None:
        self.model, self.td, self.criterion = model, td, criterion
        self.x, self.y = pairs(model, td, caller)  # checks keys, shapes and values
        self.lookahead = Lookahead(model, td, criterion.horizon) if criterion.looks_ahead else None

    def run(self, strategy: Adaptation, rows: slice = slice(None), *, predictions: list[Tensor] | None = None) -> Trace:
        """``strategy`` (fresh) over the episodes ``rows``, step by step, with its open-loop predictions if scored by them."""
        lookahead = None if self.lookahead is None else self.lookahead.rows(rows)
        return trace_pairs(
            self.model, self.x[rows], self.y[rows], strategy, predictions=predictions, lookahead=lookahead
        )

    def score(self, run: Trace, rows: slice = slice(None)) -> float:
        """The criterion's value of a run on the episodes ``rows`` (``inf`` if the strategy refused a step).

        The evidence criterion compares kinds by their one-step error (only SMCD has an evidence).
        """
        if not math.isfinite(run.rmse):
            return math.inf
        if self.lookahead is None:
            return run.rmse
        if run.ahead is None:
            raise ValueError("this run recorded no open-loop predictions; run it with Scorer.run")
        return self.criterion.score(run.ahead, self.lookahead.observed[rows])

    def episode_scores(self, run: Trace) -> list[float]:
        """Each episode's score of a run on every episode, by the criterion."""
        if self.lookahead is None:
            return list(run.per_episode_rmse)
        assert run.ahead is not None
        return [
            self.criterion.score(run.ahead[e : e + 1], self.lookahead.observed[e : e + 1])
            for e in range(run.ahead.shape[0])
        ]

    def head_score(self, run: Trace, first: int) -> float:
        """The score of a run on every episode, over its first ``first`` episodes only."""
        if not math.isfinite(run.rmse):
            return math.inf
        if self.lookahead is None:  # equal lengths: the RMS of the episodes' RMSEs
            head = run.per_episode_rmse[:first]
            return math.sqrt(sum(v * v for v in head) / len(head))
        assert run.ahead is not None
        return self.criterion.score(run.ahead[:first], self.lookahead.observed[:first])
