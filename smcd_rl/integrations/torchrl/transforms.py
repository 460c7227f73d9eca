"""The environment-step hook: a torchrl ``Transform`` that adapts a model on every real step."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from smcd_rl.model import AdaptiveModel
from smcd_rl.strategies import SMCD

__all__ = ["AdaptationTransform"]


class AdaptationTransform(Transform):
    """The environment-step hook: adapt a model on every real step of a torchrl env.

    On each step it calls ``model.observe`` on the transition, read from the step's tensordict
    (keys without ``"next"`` from the state before the step, ``("next", ...)`` keys from the new
    one), and writes the model's summary, one value per env with a trailing dim of 1, to
    ``prefix + name``: for :class:`~smcd_rl.SMCD` ``smcd_ess`` (effective sample size, in
    ``[1, N]``) and ``smcd_log_evidence`` (log p(z_1..t), reset to 0). These keys are added to
    the observation spec. On reset it calls ``model.reset(batch_shape=env.batch_size)``, so a
    batched env (``SerialEnv``, ``ParallelEnv``, a vectorised ``GymEnv``) keeps one particle set
    per sub-env; a partial reset (``"_reset"`` mask) restarts only the particle sets of the
    sub-envs that reset. Append the transform to the batched env, not inside its workers, so
    that there is one model.

    Args:
        model: the adaptive model; its keys must be in the env's tensordicts.
        prefix: prepended to each summary name to form its key.
        summary_keys: which entries of ``model.summary()`` to write (default: all an
            :class:`~smcd_rl.SMCD` model reports, none for other strategies).

    Example:
        >>> import torch, smcd_rl
        >>> from torchrl.envs import GymEnv, TransformedEnv
        >>> from smcd_rl.integrations.torchrl import AdaptationTransform
        >>> net = smcd_rl.MaskedMLP(4 + 2, 4, hidden=(32,))
        >>> model = smcd_rl.AdaptiveDynamicsModel(net, smcd_rl.SMCD(num_particles=10))
        >>> model.fitted = True  # a random stand-in for a trained network
        >>> env = TransformedEnv(GymEnv("smcd_rl/TwoLinkArm-v0"), AdaptationTransform(model))
        >>> td = env.rollout(3)
        >>> td["next", "smcd_ess"].shape, td["smcd_log_evidence"][0].item()
        (torch.Size([3, 1]), 0.0)
    """

    def __init__(
        self, model: AdaptiveModel, *, prefix: str = "smcd_", summary_keys: Sequence[str] | None = None
    ) -> None:
        if not isinstance(model, AdaptiveModel):
            raise TypeError(f"model must be a smcd_rl.AdaptiveModel, got {type(model).__name__}")
        if summary_keys is None:
            summary_keys = ("ess", "log_evidence") if isinstance(model.adaptation, SMCD) else ()
        self.summary_keys = tuple(summary_keys)
        super().__init__(in_keys=[], out_keys=[prefix + name for name in self.summary_keys])
        self.model = model

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        transition = TensorDict(batch_size=next_tensordict.batch_size, device=next_tensordict.device)
        for key in [*self.model.in_keys, self.model.target_key]:
            if isinstance(key, tuple) and key[0] == "next":
                value = next_tensordict.get(key[1:], None)
            else:
                value = tensordict.get(key, None)
            if value is not None:  # a missing key is reported by model.observe, with the keys there are
                transition.set(key, value)
        step_mask = tensordict.get("_step", None)
        self._where(step_mask, lambda: self.model.observe(transition), batch_shape=tuple(next_tensordict.batch_size))
        return self._write_summary(next_tensordict)

    def _reset(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_shape = tuple(tensordict_reset.batch_size)
        reset_mask = tensordict.get("_reset", None) if tensordict is not None else None
        try:
            same_batch = self.model.batch_shape == batch_shape
        except RuntimeError:  # never reset yet
            same_batch = False
        if not same_batch:
            reset_mask = None
        self.model.reset(batch_shape=batch_shape, where=reset_mask)
        return self._write_summary(tensordict_reset)

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Outside an env (e.g. the transform applied to stored data) there is no transition to observe.
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for key in self.out_keys:
            observation_spec[key] = Unbounded(
                shape=(*observation_spec.shape, 1), device=observation_spec.device, dtype=torch.float32
            )
        return observation_spec

    def _write_summary(self, td: TensorDictBase) -> TensorDictBase:
        if not self.summary_keys:
            return td
        summary = self.model.summary()
        for name, key in zip(self.summary_keys, self.out_keys, strict=True):
            if name not in summary:
                raise KeyError(f"the model's summary has no {name!r}; it has {sorted(summary)}")
            td.set(key, summary[name].detach().to(torch.float32).reshape(*td.batch_size, 1).to(td.device))
        return td

    def _where(self, mask: Tensor | None, update: Callable[[], None], *, batch_shape: tuple[int, ...]) -> None:
        """Run ``update`` for the batch elements where ``mask`` is True (all when it is None)."""
        if mask is None or bool(mask.all()):
            update()
            return
        if not bool(mask.any()):
            return
        mask = mask.reshape(batch_shape)
        # The core resets and updates every batch element at once: act on all, then put back
        # the old state where the mask is not set.
        adaptation = self.model.adaptation
        old = adaptation.state_dict()
        update()
        adaptation.restore_rows(old, ~mask)
