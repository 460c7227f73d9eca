"""Held-out episodes as the tuning functions take them: checked, stacked, and as normalised pairs.

:func:`smcd_rl.calibrate`, :func:`smcd_rl.tune` and :func:`smcd_rl.tuning.diagnostics.trace` take the
same episodes (a TensorDict of batch ``[E, T]`` in the model's keys, or a list of ``[T]`` ones) and
the same fitted model; this module checks both once, in one way, for all three.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
    >>> model.fitted = True  # a toy network: declare it trained
    >>> episode = TensorDict({"q": torch.rand(5, 2), "ee": torch.rand(5, 2)}, [5])
    >>> smcd_rl.tune(model, [episode, episode[:4]], progress=False)
    Traceback (most recent call last):
    ...
    ValueError: tune: the episodes have different lengths [4, 5]; cut them to a common length, e.g. [episode[:4] for episode in episodes]
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor

from smcd_rl.checks import check_tensordict
from smcd_rl.model import AdaptiveModel

__all__ = ["checked_model", "stacked", "pairs"]


def checked_model(model: AdaptiveModel, caller: str) -> AdaptiveModel:
    """``model``, fitted and on a real device, or an error that names ``caller`` (``"tune"``, ``"calibrate"``...)."""
    if not isinstance(model, AdaptiveModel):
        raise TypeError(f"{caller} takes a smcd_rl.AdaptiveModel, got {type(model).__name__}")
    if next(model.net.parameters()).device.type == "meta":
        raise ValueError(
            "the model's network is on the meta device, whose tensors have shapes but no values, so it cannot "
            "predict; load its trained weights onto a real device first (model.net.to_empty(device='cpu'), then "
            "model.load_checkpoint(...))"
        )
    if not model.fitted:
        raise ValueError(
            f"{caller} needs a fitted model (its residual scale and the evidence of an untrained network mean "
            "nothing); train it with smcd_rl.fit first, or set model.fitted = True if you trained it yourself"
        )
    return model


def stacked(episodes: TensorDictBase | Sequence[TensorDictBase], caller: str) -> TensorDictBase:
    """``episodes`` as one TensorDict of batch ``[E, T]``, ``E, T >= 2``, or an error that names ``caller``."""
    if isinstance(episodes, TensorDictBase):
        td = episodes
        if td.batch_dims != 2:
            hint = ""
            if td.batch_dims == 1:
                hint = f"; a batch [T] is one episode, and {caller} needs at least 2"
            elif td.batch_dims > 2:
                hint = f"; flatten the leading dims, e.g. episodes.reshape(-1, {td.batch_size[-1]})"
            raise ValueError(
                f"{caller} takes episodes as a TensorDict of batch [E, T] (E episodes of T steps) or a list of "
                f"[T] ones, got batch {list(td.batch_size)}{hint}"
            )
    elif isinstance(episodes, Sequence) and not isinstance(episodes, (str, bytes)):
        items = list(episodes)
        for i, episode in enumerate(items):
            check_tensordict(episode, f"{caller} (episodes[{i}])")
            if episode.batch_dims != 1:
                raise ValueError(
                    f"{caller}: episodes[{i}] has batch {list(episode.batch_size)}; a list holds one TensorDict "
                    "of batch [T] per episode"
                )
        lengths = sorted({int(episode.batch_size[0]) for episode in items})
        if len(lengths) > 1:
            raise ValueError(
                f"{caller}: the episodes have different lengths {lengths}; cut them to a common length, "
                f"e.g. [episode[:{lengths[0]}] for episode in episodes]"
            )
        if len(items) < 2:
            raise ValueError(f"{caller} needs at least 2 episodes, got {len(items)}")
        try:
            td = torch.stack(items, 0)
        except (RuntimeError, ValueError, KeyError) as err:
            raise ValueError(
                f"{caller}: the episodes do not all have the same keys and feature shapes ({err})"
            ) from err
    else:
        check_tensordict(episodes, caller)
        raise AssertionError("unreachable")  # check_tensordict refused it
    num_episodes, steps = td.batch_size
    if num_episodes < 2:
        raise ValueError(
            f"{caller} needs at least 2 episodes, got {num_episodes}: settings chosen "
            "on one episode mostly fit that episode"
        )
    if steps < 2:
        raise ValueError(
            f"{caller} needs episodes of at least 2 steps, got {steps}: the one-step error predicts each "
            "step from the steps before it"
        )
    return td


def pairs(model: AdaptiveModel, td: TensorDictBase, caller: str) -> tuple[Tensor, Tensor]:
    """Normalised network inputs and targets ``[E, T, features]`` of the episodes, checked (keys, shapes, NaN)."""
    what = f"{caller} (episodes)"
    x = model._raw_inputs(td, what=what, exact=True)
    target = model._read(td, model.target_key, model.net.out_features, what=what, exact=True)
    return model.input_norm(x), model.output_norm(model._to_output(td, target, exact=True))
