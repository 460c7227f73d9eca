"""How a strategy adapts, step by step: its one-step error and, for SMCD, ESS, evidence and kept share.

:func:`trace` runs one strategy over held-out episodes (all at once, one independent state per
episode) and records, at every step, the error of its prediction of that step from the steps
before it and, for SMCD, the filter's effective sample size before resampling, its log evidence
so far and the share of units the MMSE mask keeps. Where SMCD loses to another strategy, these
say why: an ESS that collapses to one particle at every step means the likelihood is too sharp
(or the model cannot explain the data); a kept share that drifts far from the training keep
probability means the filter is switching units off to fit noise. The one-step errors are also
kept per episode, to find the episodes a strategy fails on.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    >>> model.fitted = True  # a toy network: declare it trained
    >>> episodes = TensorDict({"q": torch.rand(3, 5, 2), "ee": torch.zeros(3, 5, 2)}, [3, 5])
    >>> result = trace(model, episodes, smcd_rl.SMCD(num_particles=10, noise_std=0.1))
    >>> len(result.one_step_rmse), len(result.ess), 0 < result.kept[0] < 1
    (4, 5, True)
    >>> len(result.per_episode_rmse), len(result.one_step_errors[0])  # 3 episodes, 4 one-step errors each
    (3, 4)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from smcd_rl.checks import check_count
from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies import SMCD, Adaptation
from smcd_rl.tuning.criteria import Lookahead
from smcd_rl.tuning.held_out import checked_model, pairs, stacked

__all__ = ["trace", "trace_pairs", "Trace"]


@dataclass
class Trace:
    """Per-step record of one strategy over episodes: means over the episodes, and the one-step errors of each."""

    #: RMSE (target units, dimensions pooled) of the prediction of step ``t`` from steps ``< t``, t = 2..T.
    one_step_rmse: list[float]
    #: The one-step RMSE over every episode and step 2..T (``inf`` if the strategy refused a step).
    rmse: float
    #: SMCD only (else empty): ESS of each update before resampling, as a share of the particles.
    ess: list[float]
    #: SMCD only: mean log evidence per episode of steps 1..t.
    log_evidence: list[float]
    #: Strategies with a mask: the mean share of units the adapted (MMSE) mask keeps after step t.
    kept: list[float]
    #: Per episode ``e``: the RMSE (target units, dimensions pooled) of its one-step predictions over
    #: steps 2..T (``inf`` for every episode if the strategy refused a step). The episodes have equal
    #: lengths, so ``rmse ** 2`` is the mean of ``per_episode_rmse[e] ** 2`` over the episodes.
    per_episode_rmse: list[float] = field(default_factory=list)
    #: ``one_step_errors[e][t - 2]``: the RMSE over the dimensions of episode ``e``'s prediction of
    #: step ``t`` (t = 2..T; each list ends at a refused step); ``one_step_rmse[t - 2] ** 2`` is the
    #: mean over the episodes of ``one_step_errors[e][t - 2] ** 2``.
    one_step_errors: list[list[float]] = field(default_factory=list)
    #: With a look-ahead (:class:`smcd_rl.tuning.criteria.Lookahead`): every start's open-loop predictions
    #: ``[E, S, H, out]`` in the target's units, ``None`` if the strategy refused a step.
    ahead: Tensor | None = field(default=None, repr=False, compare=False)
    #: With a look-ahead: the RMSE (target units, pooled) of :attr:`ahead` against the recorded
    #: steps (``inf`` if the strategy refused a step; ``nan`` without a look-ahead).
    lookahead_rmse: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        """The record as plain lists and floats (no :attr:`ahead` tensor; the look-ahead error only where measured)."""
        record = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "ahead"}
        if math.isnan(self.lookahead_rmse):
            del record["lookahead_rmse"]
        return record


def trace(
    model: AdaptiveModel,
    episodes: TensorDictBase | Sequence[TensorDictBase],
    strategy: Adaptation,
    *,
    horizon: int | None = None,
) -> Trace:
    """Run ``strategy`` on ``model`` over ``episodes`` and record it at every step (see the module doc).

    Args:
        model: a fitted model; its network is not changed.
        episodes: as :func:`smcd_rl.calibrate` takes them (batch ``[E, T]``, or a list of ``[T]``).
        strategy: a fresh strategy; it is attached to a copy of ``model`` and reset.
        horizon: also predict ``horizon`` steps ahead open loop from every start
            (:mod:`smcd_rl.tuning.criteria`): :attr:`Trace.ahead` and :attr:`Trace.lookahead_rmse`.

    Returns:
        The :class:`Trace`. A strategy that refuses an observation (an impossible one under every
        particle, or gradient descent whose weights or predictions would turn non-finite) stops the trace there:
        ``rmse`` is ``inf`` and the lists end at the refused step.
    """
    model = checked_model(model, "trace")
    if not isinstance(strategy, Adaptation):
        raise TypeError(f"trace takes a strategy such as smcd_rl.SMCD(...), got {type(strategy).__name__}")
    if strategy._net is not None:
        raise ValueError(
            "trace needs a fresh strategy: this one is attached to a model, whose state tracing would reset; "
            "pass a new one, e.g. smcd_rl.SMCD(**strategy.config())"
        )
    td = stacked(episodes, "trace")
    x, y = pairs(model, td, "trace")
    lookahead = None if horizon is None else Lookahead(model, td, check_count(horizon, "horizon"))
    return trace_pairs(model, x, y, strategy, lookahead=lookahead)


def trace_pairs(
    model: AdaptiveModel,
    x: Tensor,
    y: Tensor,
    strategy: Adaptation,
    *,
    predictions: list[Tensor] | None = None,
    lookahead: Lookahead | None = None,
) -> Trace:
    """:func:`trace` on episodes already checked and normalised: ``x [E, T, in]``, ``y [E, T, out]``.

    For the tuning functions, which check the episodes once and run many strategies on them.
    With ``predictions``, the strategy's normalised prediction of every step ``t = 1..T``, made
    before it observes that step, is appended to it (``[E, out]`` each; the first is made before
    any observation, which draws no random number, so the run is the same). With ``lookahead``
    (built on these episodes), every start's open-loop predictions go into :attr:`Trace.ahead`;
    they only read the strategy's state, so the run is the same.
    """
    num_episodes, steps = x.shape[:2]
    model.with_adaptation(strategy).reset(batch_shape=(num_episodes,))
    output_std = model.output_norm.std.to(torch.float64)
    result = Trace([], math.inf, [], [], [], [math.inf] * num_episodes, [[] for _ in range(num_episodes)])
    squared = 0.0
    episode_squared = torch.zeros(num_episodes, dtype=torch.float64)
    ahead: list[Tensor] = []
    with torch.no_grad():
        for t in range(steps):
            if lookahead is not None and 0 < t <= lookahead.starts:
                ahead.append(lookahead.predict(strategy, t, x, y))
            if predictions is not None:
                predictions.append(strategy.predict(x[:, t]))
            if t > 0:
                predicted = predictions[-1] if predictions is not None else strategy.predict(x[:, t])
                error = (predicted - y[:, t]).to(torch.float64) * output_std
                step_squared = float(error.square().sum())
                squared += step_squared
                result.one_step_rmse.append(math.sqrt(step_squared / (num_episodes * y.shape[-1])))
                per_episode = error.square().sum(-1).cpu()  # [E]
                episode_squared += per_episode
                for errors, value in zip(result.one_step_errors, per_episode.tolist(), strict=True):
                    errors.append(math.sqrt(value / y.shape[-1]))
            try:
                strategy.observe(x[:, t], y[:, t])
            except ValueError:
                result.lookahead_rmse = math.inf if lookahead is not None else math.nan
                return result
            if isinstance(strategy, SMCD):
                summary = strategy.summary()
                result.ess.append(float(summary["ess"].to(torch.float64).mean()) / strategy.num_particles)
                result.log_evidence.append(float(summary["log_evidence"].to(torch.float64).mean()))
            if strategy.mask is not None:
                result.kept.append(float(strategy.mask.to(torch.float64).mean()))
    result.rmse = math.sqrt(squared / (num_episodes * (steps - 1) * y.shape[-1]))
    result.per_episode_rmse = [math.sqrt(value / ((steps - 1) * y.shape[-1])) for value in episode_squared.tolist()]
    if lookahead is not None:
        result.ahead = torch.stack(ahead, 1)
        result.lookahead_rmse = lookahead.rmse(result.ahead)
    return result
