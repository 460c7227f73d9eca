"""Combination: several adaptation strategies on one observation stream, mixed by exponential weights.

No single strategy wins everywhere: SMCD adapts to a task its masks can explain, gradient descent
to a shift they cannot, and the frozen network is best on the training tasks. :class:`Combination`
runs them side by side on the same transitions and predicts with their predictions weighted by
how well each predicted the stream so far (exponentially weighted forecasting, Cesa-Bianchi and
Lugosi, *Prediction, Learning, and Games*, 2006, ch. 2), with Herbster and Warmuth's fixed share
(1998) so that the weight can move to another member when the task switches.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.registry import from_spec, spec

__all__ = ["Combination", "mixed_log_weights", "weight_path"]


class Combination(Adaptation):
    """Predict with a weighted mean of member strategies' predictions, weighted by their past errors.

    Every member adapts to every observation, each with its own state (SMCD its particles,
    gradient descent its private copy of the weights); the network they share is never changed.
    Before the members adapt to an observation, each is scored by its one-step squared error
    ``l_i = ||prediction_i - target||^2`` (summed over outputs, in the model's normalised units),
    and the weights become

    * ``v_i ∝ w_i exp(-eta l_i)`` (with ``share=0``: ``w_i ∝ exp(-eta L_i)``, ``L_i`` the
      cumulative loss :attr:`losses`), then
    * ``w_i = (1 - share) v_i + share / K`` for ``K`` members (fixed share): no weight falls
      below ``share / K``, so a member that was bad before a task switch can take over within a
      few steps after it.

    For squared errors in ``[0, B]`` and ``share=0`` the cumulative squared error of the
    combined prediction is at most that of the best member plus ``ln(K) / eta + eta T B^2 / 8``
    after ``T`` steps (the mixture's loss bounds the mixed prediction's, the loss being convex).
    An SMCD member contributes its point prediction (:meth:`smcd_rl.SMCD.predict`: the MMSE
    mask, or its ``prediction="predictive"`` mean). The combination has no mask and no particle
    set: :attr:`mask` is ``None`` and :meth:`predict_particles` gives the combined prediction as
    one sample. :meth:`summary` holds each member's weight (``"weight[i]"``) and each member's
    own diagnostics (``"ess[i]"``, ...).

    Args:
        members: the strategies, each a distinct instance (a strategy serves one model at a time),
            or a ``{"name": ..., "settings": {...}}`` spec as :meth:`config` lists them
            (:func:`smcd_rl.strategies.registry.spec`).
        eta: learning rate of the weights, finite and ``>= 0``; ``0`` averages the members
            uniformly, a larger one follows the best member sooner and more closely. Losses are
            in the model's normalised units, where the trained network's squared error per
            output is about its validation error divided by the target's variance.
        share: the fraction of the weight spread evenly over the members after each step, in
            ``[0, 1)``; ``0`` is plain exponential weights.

    Example:
        >>> import torch, smcd_rl
        >>> from tensordict import TensorDict
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
        >>> model.fitted = True  # a toy network: declare it trained
        >>> combination = smcd_rl.Combination(
        ...     [smcd_rl.NoAdaptation(), smcd_rl.GradientDescent(lr=0.1), smcd_rl.SMCD(num_particles=50)],
        ...     eta=2.0, share=0.01)
        >>> adaptive = model.with_adaptation(combination)
        >>> adaptive.reset()
        >>> combination.weights
        tensor([0.3333, 0.3333, 0.3333])
        >>> adaptive.observe(TensorDict({"q": torch.zeros(2), "ee": torch.ones(2)}, []))
        >>> combination.losses.shape, adaptive(TensorDict({"q": torch.zeros(2)}, []))["ee"].shape
        (torch.Size([3]), torch.Size([2]))
    """

    name = "combination"

    def __init__(
        self,
        members: Sequence[Adaptation | Mapping[str, Any]],
        *,
        eta: float = 1.0,
        share: float = 0.0,
    ) -> None:
        super().__init__()
        self.eta = _checked_eta(eta)
        self.share = _checked_share(share)
        self._members = _checked_members(members)
        # [*B, K] in float64, normalised (logsumexp over K is 0): ``eta * loss`` of a large eta
        # overflows float32, and -inf for every member would leave no weight at all.
        self._log_weights: Tensor | None = None
        self._losses: Tensor | None = None  # [*B, K], cumulative squared error of each member

    # -------------------------------------------------------------- what it exposes
    @property
    def members(self) -> tuple[Adaptation, ...]:
        """The member strategies, in the order of the weights' last dim."""
        return self._members

    @property
    def weights(self) -> Tensor:
        """Current weight of each member, ``[*B, K]``, summing to 1 over ``K`` (in the network's dtype)."""
        return self._state()[0].exp().to(self._state()[1].dtype)

    @property
    def losses(self) -> Tensor:
        """Cumulative one-step squared error of each member since :meth:`reset`, ``[*B, K]`` (normalised units)."""
        return self._state()[1].clone()

    def config(self) -> dict[str, Any]:
        return {
            "members": [spec(member) for member in self._members],
            "eta": self.eta,
            "share": self.share,
        }

    def __repr__(self) -> str:
        return f"Combination([{', '.join(map(repr, self._members))}], eta={self.eta!r}, share={self.share!r})"

    # -------------------------------------------------------------- called by the model
    def bind(self, net: MaskedMLP, output_scale: Tensor, *, calibration: Mapping[str, Any] | None = None) -> None:
        super().bind(net, output_scale, calibration=calibration)
        for member in self._members:
            member.bind(net, output_scale, calibration=calibration)

    def check_batch(self, batch_shape: tuple[int, ...]) -> None:
        for member in self._members:
            member.check_batch(batch_shape)

    def reset(self, batch_shape: tuple[int, ...]) -> None:
        self.check_batch(batch_shape)  # before any member changes
        for member in self._members:
            member.reset(batch_shape)
        self._batch_shape = batch_shape
        like = next(self.net.parameters())  # the weights take the network's device and dtype
        count = len(self._members)
        self._log_weights = like.new_full((*batch_shape, count), -math.log(count), dtype=torch.float64)
        self._losses = like.new_zeros((*batch_shape, count))

    def observe(self, inputs: Tensor, targets: Tensor) -> None:
        log_weights, losses = self._state()
        self._check_transition(inputs, targets)
        # Scored before they adapt: each member's prediction of what it has not seen yet.
        predictions = torch.stack([member.predict(inputs) for member in self._members], dim=-1)  # [*B, out, K]
        step = (predictions - targets.unsqueeze(-1)).square().sum(-2)  # [*B, K]
        if not bool(torch.isfinite(step).all()):
            bad = sorted({int(i) for i in (~torch.isfinite(step)).nonzero()[:, -1]})
            raise ValueError(
                f"Combination: members {bad} ({', '.join(repr(self._members[i]) for i in bad)}) predict inf or NaN "
                "for this observation, so it cannot be scored; the adaptation state is unchanged. Drop the "
                "transition, or check those members' settings"
            )
        # Each member's observe is all or nothing; an earlier member must be undone if a later one refuses.
        saved = [member.state_dict() for member in self._members[:-1]]
        for i, member in enumerate(self._members):
            try:
                member.observe(inputs, targets)
            except BaseException as err:
                for done, state in zip(self._members[:i], saved, strict=False):
                    done.load_state_dict(state)
                if isinstance(err, ValueError):
                    raise ValueError(
                        f"Combination: member {i} ({member!r}) refused the observation, so no member adapted and the "
                        f"weights are unchanged: {err}"
                    ) from err
                raise
        self._losses = losses + step
        self._log_weights = self._mixed(log_weights - self.eta * step.to(torch.float64))

    def predict(self, inputs: Tensor) -> Tensor:
        extra = self._extra_dims(inputs)
        log_weights, _ = self._state()
        predictions = torch.stack([member.predict(inputs) for member in self._members], dim=-1)  # [..., out, K]
        weights = log_weights.exp().to(predictions.dtype)
        weights = weights.reshape(*self._batch_shape, *([1] * extra), 1, len(self._members))
        return (predictions * weights).sum(-1)

    def summary(self) -> dict[str, Tensor]:
        weights = self.weights
        found: dict[str, Tensor] = {}
        for i, member in enumerate(self._members):
            found[f"weight[{i}]"] = weights[..., i]
            found.update({f"{key}[{i}]": value for key, value in member.summary().items()})
        return found

    def state_dict(self) -> dict[str, Any]:
        log_weights, losses = self._state()
        return {
            "log_weights": log_weights.clone(),
            "losses": losses.clone(),
            "members": [member.state_dict() for member in self._members],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        saved = state["members"]
        if len(saved) != len(self._members):
            raise ValueError(
                f"the state holds {len(saved)} members' states but this Combination has {len(self._members)} members; "
                "load a state_dict of a Combination of the same members"
            )
        for member, member_state in zip(self._members, saved, strict=True):
            member.load_state_dict(member_state)
        # A state saved while the weights were kept in the network's dtype loads in float64 too.
        self._log_weights = state["log_weights"].to(torch.float64, copy=True)
        self._losses = state["losses"].clone()

    def restore_rows(self, state: dict[str, Any], rows: Tensor) -> None:
        log_weights, losses = self._state()
        for member, member_state in zip(self._members, state["members"], strict=True):
            member.restore_rows(member_state, rows)
        keep = rows.to(log_weights.device).reshape(*self._batch_shape, 1)
        self._log_weights = torch.where(keep, state["log_weights"], log_weights)
        self._losses = torch.where(keep, state["losses"], losses)

    # -------------------------------------------------------------- internals
    def _mixed(self, log_scores: Tensor) -> Tensor:
        return mixed_log_weights(log_scores, self.share)

    def _state(self) -> tuple[Tensor, Tensor]:
        if self._log_weights is None or self._losses is None:
            raise RuntimeError("Combination has no weights yet; call model.reset() first")
        return self._log_weights, self._losses


def weight_path(predictions: Tensor, targets: Tensor, *, eta: float, share: float) -> Tensor:
    """The log weights of a :class:`Combination` along a stream, from its members' recorded predictions.

    ``predictions [*B, T, out, K]`` are the members' predictions of each step before observing it
    and ``targets [*B, T, out]`` the observations, both in the model's normalised units. Returns
    ``[*B, T + 1, K]``: the log weights before the first observation (uniform) and after each,
    operation for operation as :meth:`Combination.observe` updates them, so a combination's
    predictions can be computed from its members' runs instead of running it.

    Example:
        >>> preds = torch.tensor([[[[0.0, 1.0]]], [[[0.0, 1.0]]]]).transpose(0, 1)  # [1, 2, 1, 2]: two steps
        >>> weight_path(preds, torch.ones(1, 2, 1), eta=10.0, share=0.0).exp()[0, -1]  # the second member is right
        tensor([2.0612e-09, 1.0000e+00], dtype=torch.float64)
    """
    count = predictions.shape[-1]
    log_weights = predictions.new_full((*predictions.shape[:-3], count), -math.log(count), dtype=torch.float64)
    path = [log_weights]
    for t in range(predictions.shape[-3]):
        step = (predictions[..., t, :, :] - targets[..., t, :].unsqueeze(-1)).square().sum(-2)
        log_weights = mixed_log_weights(log_weights - eta * step.to(torch.float64), share)
        path.append(log_weights)
    return torch.stack(path, dim=-2)


def mixed_log_weights(log_scores: Tensor, share: float) -> Tensor:
    """Normalised log weights from unnormalised ones (last dim), with ``share`` of the weight spread evenly.

    What :class:`Combination` does after each observation; :func:`smcd_rl.tune` scores its grid
    with it from the members' recorded predictions.

    Example:
        >>> mixed_log_weights(torch.tensor([0.0, -100.0]), 0.02).exp()
        tensor([0.9900, 0.0100])
    """
    log_posterior = torch.log_softmax(log_scores, dim=-1)
    if share == 0.0:
        return log_posterior
    count = log_scores.shape[-1]
    # log((1 - share) v + share / K), without the underflow of exp(log v) for a far-behind member.
    return torch.logaddexp(log_posterior + math.log1p(-share), torch.full_like(log_posterior, math.log(share / count)))


#: The largest ``eta``: times the largest float32 loss it stays finite in float64.
MAX_ETA = 1e100


def _checked_eta(eta: Any) -> float:
    if isinstance(eta, bool) or not isinstance(eta, numbers.Real):
        raise TypeError(f"eta must be a real number, got {eta!r} ({type(eta).__name__})")
    if not math.isfinite(float(eta)) or not 0 <= float(eta) <= MAX_ETA:
        raise ValueError(
            f"eta must be a finite number in [0, {MAX_ETA:g}], got {eta}: the learning rate of the weights (0 averages "
            "the members uniformly, a larger one follows the best member sooner; at 1e100 the first observation "
            "already gives all the weight to the member that predicted it best), e.g. eta=1.0"
        )
    return float(eta)


def _checked_share(share: Any) -> float:
    if isinstance(share, bool) or not isinstance(share, numbers.Real):
        raise TypeError(f"share must be a real number, got {share!r} ({type(share).__name__})")
    if not 0.0 <= float(share) < 1.0:  # NaN fails too
        raise ValueError(
            f"share must be in [0, 1), got {share}: the fraction of the weight spread evenly over the members after "
            "each step (0 for plain exponential weights, e.g. 0.01 to follow task switches)"
        )
    return float(share)


def _checked_members(members: Any) -> tuple[Adaptation, ...]:
    """``members`` as a tuple of distinct strategy instances (dict entries built), or a clear error."""
    if isinstance(members, Adaptation) or isinstance(members, (str, bytes)) or not isinstance(members, Sequence):
        raise TypeError(
            f"members must be a list of strategies such as [smcd_rl.NoAdaptation(), smcd_rl.SMCD()], got "
            f"{type(members).__name__}; wrap a single strategy in a list"
        )
    if not members:
        raise ValueError(
            "members is empty: a Combination needs at least one strategy, e.g. [smcd_rl.NoAdaptation(), smcd_rl.SMCD()]"
        )
    built = tuple(_member(value, i) for i, value in enumerate(members))
    seen: dict[int, str] = {}
    for i, member in enumerate(built):
        for where, strategy in _strategies(member, f"members[{i}]"):
            if id(strategy) in seen:
                raise ValueError(
                    f"{where} is the same {type(strategy).__name__} object as {seen[id(strategy)]}; every member keeps "
                    "its own adaptation state, so pass separate instances, e.g. type(s)(**s.config())"
                )
            seen[id(strategy)] = where
    return built


def _member(value: Any, index: int) -> Adaptation:
    if isinstance(value, Adaptation):
        return value
    if isinstance(value, Mapping) and isinstance(value.get("name"), str):
        return from_spec(value)
    hint = ""
    if isinstance(value, type) and issubclass(value, Adaptation):
        hint = f"; pass an instance, {value.__name__}(...), not the class"
    raise TypeError(
        f"members[{index}] must be a smcd_rl.Adaptation (NoAdaptation, GradientDescent, SMCD, Combination) or a "
        f"{{'name': ..., 'settings': {{...}}}} spec, got {value!r} ({type(value).__name__}){hint}"
    )


def _strategies(strategy: Adaptation, where: str) -> list[tuple[str, Adaptation]]:
    """``strategy`` and, for a nested Combination, every strategy inside it, with where each sits."""
    found = [(where, strategy)]
    if isinstance(strategy, Combination):
        for i, member in enumerate(strategy.members):
            found += _strategies(member, f"{where}.members[{i}]")
    return found
