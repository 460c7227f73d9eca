"""Adapt the dynamics model mbrl-lib trained: a ``GaussianMLP`` ensemble as one adaptive model per member.

:func:`members_from_gaussian_mlp` reads each ensemble member of an ``mbrl.models.GaussianMLP`` (its
hidden layers and the mean half of its ``mean_and_logvar`` head) as a :class:`~smcd_rl.MaskedMLP`
with the member's trained weights: it predicts exactly the member's mean. :func:`dynamics_models_from_mbrl`
wraps the members of an ``mbrl.models.OneDTransitionRewardModel`` (what PETS and MBPO train with
mbrl-lib's ``ModelTrainer``) as :class:`~smcd_rl.AdaptiveDynamicsModel` s, with its input
normaliser and its delta target, so each predicts the next observation as mbrl-lib's model does.
:class:`~smcd_rl.integrations.mbrl_lib.MbrlLibModel` plans with the list, the ensemble adapted.

What is read, and what is not:

* **the mean head is the readout.** The Bayesian last layer and gradient descent adapt it (and
  gradient descent the hidden layers); a learned reward column (``learned_rewards=True``) is left
  out, since the planners take the reward from a reward function.
* **the log-variance head is left as trained, and not used.** It predicts the noise of the
  training data around the member's mean, before adapting; after adapting, the residual that is
  left is what the strategies' own noise describes (``smcd_rl.tune`` sets it from the unadapted
  residual on held-out episodes). A planner that samples from the trained variance would add
  noise the adapted mean no longer makes.
* **SMCD needs dropout**, which a ``GaussianMLP`` has none of: every member is wrapped with
  dropout 0, and an ``SMCD`` adaptation is refused with a message that says so (see
  :func:`smcd_rl.adaptive_model_from` for networks with ``Dropout`` layers).

Members default to mbrl-lib's elite members where it chose them (``model.elite_models``, what
PETS plans with), else every member. This module imports without mbrl-lib: it reads the layers
by their attributes.

Example:
    >>> import torch, smcd_rl
    >>> from smcd_rl.integrations.mbrl_models import members_from_gaussian_mlp
    >>> mbrl_models = __import__("pytest").importorskip("mbrl.models")
    >>> gaussian = mbrl_models.GaussianMLP(4, 3, "cpu", num_layers=2, ensemble_size=2, hid_size=16)
    >>> nets = members_from_gaussian_mlp(gaussian)
    >>> x = torch.rand(5, 4)
    >>> mean, _ = gaussian(x.expand(2, 5, 4))  # every member on the same inputs
    >>> bool(max((net(x) - mean[i]).abs().max() for i, net in enumerate(nets)) < 1e-5)
    True
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from smcd_rl.masked_mlp import _ACTIVATIONS, MaskedMLP
from smcd_rl.model import AdaptiveDynamicsModel
from smcd_rl.strategies import SMCD
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.registry import from_spec, spec

__all__ = ["members_from_gaussian_mlp", "dynamics_models_from_mbrl"]


def members_from_gaussian_mlp(
    gaussian_mlp: nn.Module, *, members: Sequence[int] | None = None, outputs: int | None = None
) -> list[MaskedMLP]:
    """Each ensemble member of an mbrl-lib ``GaussianMLP`` as a :class:`~smcd_rl.MaskedMLP` of its mean.

    Args:
        gaussian_mlp: an ``mbrl.models.GaussianMLP`` (its weights are copied, never changed).
        members: which members (default: the elite ones where mbrl-lib chose them, else all).
        outputs: read the first ``outputs`` columns of the mean head (default: all of them).

    Returns:
        One network per member, in eval mode, with dropout 0: ``net(x)`` is member ``i``'s mean.

    Raises:
        TypeError: ``gaussian_mlp`` has no ``hidden_layers`` of ensemble linear layers and one
            activation each, or an activation :class:`~smcd_rl.MaskedMLP` does not have.
        ValueError: an unknown member, or more outputs than the mean head has.
    """
    hidden = _hidden_layers(gaussian_mlp)
    head = getattr(gaussian_mlp, "mean_and_logvar", None)
    if not _is_ensemble_linear(head):
        raise TypeError("the GaussianMLP has no mean_and_logvar ensemble layer; pass an mbrl.models.GaussianMLP")
    assert head is not None
    head_weight: torch.Tensor = head.weight
    ensemble = int(head_weight.shape[0])
    chosen = _members(gaussian_mlp, members, ensemble)
    means = int(getattr(gaussian_mlp, "out_size", head_weight.shape[-1]))
    width = means if outputs is None else outputs
    if isinstance(width, bool) or not isinstance(width, int) or not 1 <= width <= means:
        raise ValueError(f"outputs must be an int in [1, {means}] (the mean head's size), got {outputs!r}")
    weights: list[torch.Tensor] = [linear.weight for linear, _ in hidden]  # type: ignore[misc]  # checked 3-d
    activation = _activation_name({type(act) for _, act in hidden})
    nets = []
    for member in chosen:
        net = MaskedMLP(
            int(weights[0].shape[1]),  # an ensemble layer's weight is [members, in, out]
            width,
            hidden=tuple(int(weight.shape[2]) for weight in weights),
            dropout=0.0,
            activation=activation,  # type: ignore[arg-type]  # a key of _ACTIVATIONS
            device=head_weight.device,
            dtype=head_weight.dtype,
        )
        with torch.no_grad():
            for mine, (theirs, _) in zip(net.linears[:-1], hidden, strict=True):
                _copy(mine, theirs, member, slice(None))
            _copy(net.linears[-1], head, member, slice(0, width))  # the mean half; the log-variance is not read
        nets.append(net.eval())
    return nets


def dynamics_models_from_mbrl(
    model: Any, *, adaptation: Adaptation | None = None, members: Sequence[int] | None = None
) -> list[AdaptiveDynamicsModel]:
    """The members of an mbrl-lib ``OneDTransitionRewardModel`` as adaptive dynamics models.

    Each predicts the next observation as the wrapper does with that member's mean: the input
    ``[obs, action]`` standardised by the wrapper's input normaliser, the output the change of
    observation (``target_is_delta=True``) or the next observation itself. They are declared
    trained; each gets its own copy of ``adaptation`` (default: none), and adapts on what you
    observe with it (``for m in models: m.observe(td)``).

    Args:
        model: an ``mbrl.models.OneDTransitionRewardModel`` around a ``GaussianMLP``, trained.
        adaptation: the strategy every member adapts with (copied per member); not ``SMCD``, which
            needs dropout the ``GaussianMLP`` does not have.
        members: as in :func:`members_from_gaussian_mlp`.

    Raises:
        TypeError: ``model`` is not such a wrapper.
        ValueError: it processes observations (``obs_process_fn``) or keeps some outputs out of the
            delta (``no_delta_list``), which an :class:`~smcd_rl.AdaptiveDynamicsModel` cannot
            express; or ``adaptation`` is SMCD.
    """
    inner = getattr(model, "model", None)
    if inner is None or not hasattr(model, "target_is_delta"):
        raise TypeError(
            f"expected an mbrl.models.OneDTransitionRewardModel (the wrapper mbrl-lib's ModelTrainer trains), got "
            f"{type(model).__name__}; for a bare GaussianMLP use members_from_gaussian_mlp"
        )
    if getattr(model, "obs_process_fn", None) is not None:
        raise ValueError(
            "the model processes observations before its network (obs_process_fn); an adaptive dynamics model feeds "
            "[observation, action] as they are: wrap the environment's observations instead"
        )
    if list(getattr(model, "no_delta_list", []) or []):
        raise ValueError(
            f"the model predicts outputs {list(model.no_delta_list)} as values and the rest as changes "
            "(no_delta_list); an adaptive dynamics model predicts all of them one way"
        )
    if isinstance(adaptation, SMCD):
        raise ValueError(
            "SMCD filters dropout masks, and a GaussianMLP has no dropout: adapt its members with "
            "smcd_rl.BayesianLastLayer, smcd_rl.GradientDescent or a Combination of them"
        )
    outputs = int(inner.out_size) - (1 if getattr(model, "learned_rewards", False) else 0)
    nets = members_from_gaussian_mlp(inner, members=members, outputs=outputs)
    normalizer = getattr(model, "input_normalizer", None)
    wrapped = []
    for net in nets:
        member = AdaptiveDynamicsModel(
            net,
            None if adaptation is None else from_spec(spec(adaptation)),  # a fresh copy per member
            predict_delta=bool(model.target_is_delta),
        )
        if normalizer is not None:
            dtype = next(net.parameters()).dtype
            member.input_norm.mean.copy_(normalizer.mean.reshape(-1).to(dtype))
            member.input_norm.std.copy_(normalizer.std.reshape(-1).to(dtype))
        member.fitted = True  # trained by mbrl-lib
        wrapped.append(member)
    return wrapped


def _hidden_layers(gaussian_mlp: nn.Module) -> list[tuple[nn.Module, nn.Module]]:
    """``(ensemble linear, activation)`` of each hidden layer."""
    hidden = getattr(gaussian_mlp, "hidden_layers", None)
    if not isinstance(hidden, nn.Sequential) or len(hidden) == 0:
        raise TypeError(
            f"expected an mbrl.models.GaussianMLP (hidden_layers of ensemble linear layers), got "
            f"{type(gaussian_mlp).__name__}; for a torch MLP use smcd_rl.adaptive_model_from"
        )
    layers = []
    for i, block in enumerate(hidden):
        parts = list(block) if isinstance(block, nn.Sequential) else [block]
        if len(parts) != 2 or not _is_ensemble_linear(parts[0]):
            raise TypeError(
                f"hidden layer {i} is {[type(p).__name__ for p in parts]}; a GaussianMLP's hidden layer is an ensemble "
                "linear layer and one activation"
            )
        layers.append((parts[0], parts[1]))
    return layers


def _is_ensemble_linear(layer: Any) -> bool:
    weight = getattr(layer, "weight", None)
    return isinstance(weight, torch.Tensor) and weight.dim() == 3


def _activation_name(kinds: set[type]) -> str:
    names = {kind: name for name, kind in _ACTIVATIONS.items()}
    if len(kinds) != 1 or next(iter(kinds)) not in names:
        found = sorted(kind.__name__ for kind in kinds)
        raise TypeError(
            f"the GaussianMLP's activations are {found}; a MaskedMLP has one of "
            f"{sorted(kind.__name__ for kind in names)}"
        )
    return names[next(iter(kinds))]


def _members(gaussian_mlp: nn.Module, members: Sequence[int] | None, ensemble: int) -> list[int]:
    if members is None:
        elite = getattr(gaussian_mlp, "elite_models", None)
        return list(elite) if elite else list(range(ensemble))
    chosen = list(members)
    if not chosen or any(isinstance(m, bool) or not isinstance(m, int) or not 0 <= m < ensemble for m in chosen):
        raise ValueError(f"members must be indices in [0, {ensemble}) of the ensemble's members, got {members!r}")
    return chosen


def _copy(linear: nn.Module, ensemble_layer: nn.Module, member: int, columns: slice) -> None:
    """``linear`` := member ``member`` of ``ensemble_layer`` (``x @ W[member] + b[member]``), output ``columns``."""
    assert isinstance(linear, nn.Linear)
    weights: torch.Tensor = ensemble_layer.weight  # type: ignore[assignment]  # checked 3-d
    weight = weights[member][:, columns]  # [in, out]
    linear.weight.copy_(weight.t())
    bias = getattr(ensemble_layer, "bias", None) if getattr(ensemble_layer, "use_bias", True) else None
    linear.bias.copy_(torch.zeros_like(linear.bias) if bias is None else bias[member].reshape(-1)[columns])
