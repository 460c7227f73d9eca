"""Adaptive models: a trained masked network plus an adaptation strategy, as TensorDict modules."""

from __future__ import annotations

import copy
import os
import pickletools
import warnings
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor

from smcd_rl.checks import (
    check_key,
    check_real,
    check_real_tensor,
    check_shape,
    check_tensordict,
    read_inputs,
    read_tensor,
)
from smcd_rl.feature_readout import FeatureReadout
from smcd_rl.files import CheckpointMismatchError, UnreadableFileError, load_file, save_file
from smcd_rl.masked_mlp import MaskedMLP
from smcd_rl.normalization import Normalizer
from smcd_rl.strategies import SMCD, Adaptation, NoAdaptation
from smcd_rl.strategies.base import checked_noise
from smcd_rl.strategies.registry import from_spec, on_device, settings_of, spec

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self needs Python 3.11

__all__ = ["AdaptiveModel", "AdaptiveDynamicsModel", "save", "load", "CheckpointMismatchError", "UnfittedModelWarning"]

_FORMAT = "smcd_rl.AdaptiveModel/1"
#: What a model checkpoint holds besides its format (:meth:`AdaptiveModel.checkpoint`).
_CHECKPOINT_KEYS = ("class", "net", "keys", "state_dict", "adaptation")


class _FitRecord:
    """What is known about a model's trained network besides its weights, shared by its :meth:`with_adaptation` copies.

    Whether a user declared it trained (``model.fitted = True``), the residual scale its trainer
    measured, the noise and flip probability :func:`smcd_rl.calibrate` chose for it and the
    result of a tuning run on it.
    """

    def __init__(self) -> None:
        self.fitted = False
        self.residual_scale: Tensor | None = None
        self.calibration: dict[str, Any] | None = None
        self.tuning: dict[str, Any] | None = None


class UnfittedModelWarning(UserWarning):
    """A model whose network was never fitted is reset or adapted: its predictions mean nothing yet.

    Given once per model. Silence it where an untrained network is meant (a demo, a test) with
    ``warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)``, or set
    ``model.fitted = True`` after training the network with your own loop.
    """


class AdaptiveModel(TensorDictModuleBase):
    """A masked network that adapts online, reading and writing TensorDict keys.

    The inputs are the ``in_keys`` concatenated along the last dim; the prediction is written to
    ``out_key``. With ``base_key`` the network predicts the change ``target - td[base_key]``
    (the default for dynamics). Inputs and network outputs are standardised with statistics
    that :func:`smcd_rl.fit` computes from the training data and that are saved with the model.

    Batch conventions: after ``reset(batch_shape=(B,))`` the model keeps ``B`` independent
    adaptation states, and a TensorDict passed to :meth:`observe` must have batch ``[B]``. A model
    reset with ``batch_shape=()`` treats a TensorDict of batch ``[T]`` as ``T`` consecutive
    transitions. For prediction, batch dims beyond the model's broadcast (e.g. planning candidates).

    Args:
        net: the trained (or to be trained) masked network.
        in_keys: keys whose values, concatenated, are the network input.
        out_key: where :meth:`forward` writes the adapted prediction.
        target_key: key of the real measurement in :meth:`observe` (default ``out_key``).
        base_key: if given, the network predicts ``target - td[base_key]``.
        adaptation: the strategy (default :class:`smcd_rl.NoAdaptation`).

    Example:
        >>> import torch, smcd_rl, warnings
        >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
        >>> from tensordict import TensorDict
        >>> net = smcd_rl.MaskedMLP(2, 2, hidden=(32, 32))
        >>> model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee",
        ...                               adaptation=smcd_rl.SMCD(num_particles=50, noise_std=0.05))
        >>> model.reset()
        >>> model.observe(TensorDict({"q": torch.zeros(2), "ee": torch.ones(2)}, []))
        >>> model(TensorDict({"q": torch.zeros(2)}, []))["ee"].shape
        torch.Size([2])
    """

    def __init__(
        self,
        net: MaskedMLP,
        *,
        in_keys: Sequence[NestedKey],
        out_key: NestedKey,
        target_key: NestedKey | None = None,
        base_key: NestedKey | None = None,
        adaptation: Adaptation | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(net, MaskedMLP):
            raise TypeError(
                f"net must be a smcd_rl.MaskedMLP (or a smcd_rl.FeatureReadout around a network of your own), got "
                f"{type(net).__name__}"
            )
        if isinstance(in_keys, (str, tuple)) or not isinstance(in_keys, Sequence):
            raise TypeError(f"in_keys must be a list of keys such as ['q'], got {in_keys!r}")
        if not in_keys:
            raise ValueError("in_keys must name at least one input key")
        for name, key in [*(("in_keys", k) for k in in_keys), ("out_key", out_key), ("target_key", target_key)]:
            check_key(key, name, optional=name == "target_key")
        check_key(base_key, "base_key", optional=True)
        self.net = net
        self.in_keys = list(in_keys)
        self.out_keys = [out_key]
        self.out_key = out_key
        self.target_key = out_key if target_key is None else target_key
        self.base_key = base_key
        # The normalisers take the network's dtype and device, so a float64 network makes a float64 model.
        like = next((p for p in net.parameters() if p.is_floating_point()), torch.empty(0))
        self.input_norm = Normalizer(net.in_features).to(device=like.device, dtype=like.dtype)
        self.output_norm = Normalizer(net.out_features).to(device=like.device, dtype=like.dtype)
        self.adaptation: Adaptation = NoAdaptation() if adaptation is None else adaptation
        self._batch_shape: tuple[int, ...] | None = None
        self._warned_unfitted = False
        self._declared = _FitRecord()  # shared with with_adaptation's copies, like the network
        self._bind(self.adaptation)

    @property
    def fitted(self) -> bool:
        """Whether the network was trained: by :func:`smcd_rl.fit` (or another trainer), or as declared.

        The trainers' record is the normalisation fitted to the training data. Set ``fitted = True``
        after training :attr:`net` with your own loop (or for a network random on purpose), so that
        :meth:`reset` and :meth:`observe` do not warn with :class:`UnfittedModelWarning`; it is
        saved with the model, and a later :func:`smcd_rl.fit` still fits the normalisation.
        """
        return bool(self.input_norm.fitted) or self._declared.fitted

    @fitted.setter
    def fitted(self, value: bool) -> None:
        if not isinstance(value, bool):  # bool("no") is True: a string or a tensor would declare it trained
            raise TypeError(f"model.fitted must be True or False, got {value!r}")
        self._declared.fitted = value

    @property
    def residual_scale(self) -> Tensor | None:
        """RMS residual per output dimension of the trained network with dropout off, in the target's units.

        :func:`smcd_rl.fit` (and :func:`smcd_rl.fit_reptile`) measure it after training, on their
        ``validation`` data if given, else on the training data (then it is optimistic: the network
        has seen those samples). :func:`smcd_rl.calibrate` starts its search for the likelihood
        noise there. ``None`` if the model was never fitted by them (set it yourself after your own
        training loop, a 1-d tensor of ``out_features`` positive values). Saved with the model.
        For a model with a ``base_key`` the units are those of the change the network predicts,
        which are also those of :class:`smcd_rl.SMCD`'s ``noise_std``.
        """
        scale = self._declared.residual_scale
        return None if scale is None else scale.clone()

    @residual_scale.setter
    def residual_scale(self, value: Tensor | Sequence[float] | None) -> None:
        self._declared.residual_scale = None if value is None else _checked_scale(value, self.net.out_features)

    @property
    def calibration(self) -> dict[str, Any] | None:
        """The likelihood settings :func:`smcd_rl.calibrate` chose for this network, or ``None``.

        A dict with ``noise_std`` (a float, or one per output dimension) and ``flip_prob``, plus
        what they were chosen from (``log_evidence`` per episode, ``episodes``, ``steps``,
        ``num_particles``). ``SMCD(noise_std="auto", flip_prob="auto")`` takes its settings from
        here. Saved with the model; :func:`smcd_rl.fit` clears it, since it belonged to the old
        weights.
        """
        calibration = self._declared.calibration
        return None if calibration is None else copy.deepcopy(calibration)

    @calibration.setter
    def calibration(self, value: dict[str, Any] | None) -> None:
        self._declared.calibration = None if value is None else _checked_calibration(value, self.net.out_features)

    @property
    def tuning(self) -> dict[str, Any] | None:
        """The result of a tuning run on this model (chosen settings, scores), as a JSON-ready dict, or ``None``.

        What :func:`smcd_rl.tune` (or another tuning procedure, such as the experiments' fair
        protocol) chose for this network, kept beside :attr:`calibration` and saved with the model,
        so that a loaded model carries it. Its values must be JSON types: dicts with string keys,
        lists or tuples, strings, numbers, booleans and ``None`` (``tensor.tolist()`` turns a tensor
        into one). Reading it gives a copy.

        Raises:
            TypeError: on setting anything else; the model keeps its old value.

        Example:
            >>> import smcd_rl
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
            >>> model.tuning is None
            True
            >>> model.tuning = {"gd_lr": 0.01, "one_step_rmse": [0.12, 0.08]}
            >>> model.tuning["gd_lr"]
            0.01
        """
        tuning = self._declared.tuning
        return None if tuning is None else copy.deepcopy(tuning)

    @tuning.setter
    def tuning(self, value: dict[str, Any] | None) -> None:
        self._declared.tuning = None if value is None else _checked_tuning(value)

    # ------------------------------------------------------------------ adaptation
    def reset(self, batch_shape: Sequence[int] = (), *, where: Tensor | None = None) -> None:
        """Start adapting afresh, with one independent state per element of ``batch_shape``.

        Args:
            batch_shape: one adaptation state per element (one per env of a vector env).
            where: bool ``[*batch_shape]``: reset only these elements and keep the others'
                state (a vector env whose sub-envs finish at different times). Needs the
                model to have been reset with this ``batch_shape`` before.

        Example:
            >>> import torch, smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee",
            ...                               adaptation=smcd_rl.SMCD(num_particles=10))
            >>> model.reset(batch_shape=(3,))
            >>> model.reset(batch_shape=(3,), where=torch.tensor([False, True, False]))  # only env 1
        """
        batch_shape = check_shape(batch_shape, "batch_shape")
        self._warn_if_unfitted()
        if where is not None:
            if self._batch_shape is None or self._batch_shape != batch_shape:
                raise ValueError(
                    f"reset(where=...) resets rows of the current batch {self._batch_shape}, "
                    f"not of {batch_shape}; call reset(batch_shape={batch_shape}) first"
                )
            where = _checked_where(where, batch_shape)
            if not bool(where.all()):
                if bool(where.any()):  # reset all, then put back the rows that keep adapting
                    kept = self.adaptation.state_dict()
                    self.adaptation.reset(batch_shape)
                    self.adaptation.restore_rows(kept, ~where)
                return
        self.adaptation.check_batch(batch_shape)  # a batch shape it refuses leaves everything as it was
        self.net.eval()
        # Bind again: training sets the output scale and .to(device) moves the network since.
        self._bind(self.adaptation)
        self._batch_shape = batch_shape
        self.adaptation.reset(self._batch_shape)

    def observe(self, td: TensorDictBase) -> None:
        """Adapt to real transitions (see the class docstring for batch conventions).

        A sequence (batch ``[T]`` on a model reset with ``batch_shape=()``) is all or nothing: if
        any of its transitions is refused, none of them is applied.

        Raises:
            TypeError: ``td`` is not a TensorDict, or a value is not a real tensor (e.g. complex,
                or on the meta device, where it has no values).
            KeyError: a key the model needs is missing.
            ValueError: shapes do not match the model or the TensorDict's batch, a value is NaN
                or infinite in the model's dtype, the observation is impossible under every
                particle (:class:`smcd_rl.SMCD`, in any dtype: its likelihood is checked in the
                filter's), or it would make :class:`smcd_rl.GradientDescent`'s weights or
                predictions inf or NaN. The adaptation state is unchanged after any error, so
                the model never holds NaN weights or predicts inf from them.
        """
        check_tensordict(td, "observe")
        batch_shape = self._require_reset()
        self._warn_if_unfitted()
        td_batch = tuple(td.batch_size)
        sequence = batch_shape == () and len(td_batch) == 1
        if td_batch != batch_shape and not sequence:
            raise ValueError(
                f"observe got a TensorDict of batch {list(td_batch)} but the model was reset with "
                f"batch_shape={list(batch_shape)}; call model.reset(batch_shape={list(td_batch)}) "
                "for one adaptation state per env, or pass one transition per env"
            )
        inputs = self._inputs(td, what="observe", exact=True)
        target = self._read(td, self.target_key, self.net.out_features, what="observe", exact=True)
        outputs = self.output_norm(self._to_output(td, target, exact=True))
        with torch.no_grad():
            if sequence:
                self._observe_sequence(inputs, outputs)
            else:
                self.adaptation.observe(inputs, outputs)

    def _observe_sequence(self, inputs: Tensor, outputs: Tensor) -> None:
        """Observe ``inputs [T, in]``, ``outputs [T, out]`` in order, all or nothing."""
        steps = inputs.shape[0]
        # One update is atomic by itself; a later refused one must also undo the earlier ones.
        saved = self.adaptation.state_dict() if steps > 1 else None
        for t in range(steps):
            try:
                self.adaptation.observe(inputs[t], outputs[t])
            except BaseException as err:
                if saved is not None:
                    self.adaptation.load_state_dict(saved)
                if isinstance(err, ValueError):
                    raise ValueError(
                        f"observe: transition {t} of the sequence of {steps} was refused, so none of them was "
                        f"applied and the adaptation state is unchanged: {err}"
                    ) from err
                raise

    @property
    def mask(self) -> Tensor | None:
        """Current mask estimate, ``[mask_dim]`` or ``[*batch_shape, mask_dim]`` (None without masks)."""
        self._require_reset()
        return self.adaptation.mask

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self._require_reset()

    @property
    def particle_weights(self) -> Tensor:
        """The normalised weights of the SMCD filter's particles, ``[*batch_shape, N]``: each row sums to 1.

        Weight ``[..., i]`` belongs to the mask :attr:`particles` ``[..., i, :]`` and to the
        prediction :meth:`predict_particles` ``[..., i, :]``. A copy: changing it changes nothing.

        Raises:
            TypeError: the strategy is not :class:`smcd_rl.SMCD`, the only one with weighted particles.
            RuntimeError: the model was not reset since it was built.

        Example:
            >>> import smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee",
            ...                               adaptation=smcd_rl.SMCD(num_particles=4))
            >>> model.reset(batch_shape=(3,))
            >>> weights = model.particle_weights
            >>> weights.shape, round(float(weights[0, 0]), 4)  # uniform until the first observation
            (torch.Size([3, 4]), 0.25)
        """
        smcd = self._smcd("particle_weights")
        self._require_reset()
        return smcd._filter.weights.clone()

    def predictive(self, td: TensorDictBase) -> tuple[Tensor, Tensor]:
        """Mean and variance of the strategy's posterior predictive, in the target's units, each ``[*batch, out]``.

        For SMCD the mean is the weighted mean of the particles' predictions (what ``forward``
        predicts with ``SMCD(prediction="predictive")``); the variance, per output, is their
        weighted spread around it plus the variance of the likelihood's noise (``noise_std**2``
        for the Gaussian, see :meth:`smcd_rl.SMCD.predictive`). For the Bayesian last layer it is
        the readout's posterior predictive (:meth:`smcd_rl.BayesianLastLayer.predictive`). With a ``base_key`` the mean is of the target
        (base plus predicted change), and the variance that of the change, the base being known.

        Args:
            td: inputs, as :meth:`forward` takes them; batch dims beyond the model's broadcast.

        Raises:
            TypeError: the strategy has no posterior (no adaptation, gradient descent).
            RuntimeError: the model was not reset since it was built.

        Example:
            >>> import torch, smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> from tensordict import TensorDict
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee",
            ...                               adaptation=smcd_rl.SMCD(num_particles=20, noise_std=0.1))
            >>> model.reset()
            >>> mean, variance = model.predictive(TensorDict({"q": torch.zeros(2)}, []))
            >>> mean.shape, bool((variance >= 0.1**2 - 1e-6).all())  # never below the noise
            (torch.Size([2]), True)
        """
        check_tensordict(td, "predictive")
        strategy = self.adaptation
        if not callable(getattr(strategy, "predictive", None)):
            raise TypeError(
                f"model.predictive needs an SMCD strategy (weighted mask particles) or another with a posterior "
                f"(BayesianLastLayer, SMCDLastLayer), but this model adapts with {type(strategy).__name__}; use "
                "model.with_adaptation(smcd_rl.SMCD(...)) and reset it"
            )
        self._require_reset()
        inputs = self._inputs(td, what="predictive", check_finite=False)
        strategy._extra_dims(inputs)  # the batch check, before any work
        mean, variance = strategy.predictive(inputs)  # type: ignore[attr-defined]
        mean = self.output_norm.inverse(mean)
        variance = variance * self.output_norm.std.square()
        if self.base_key is not None:
            base = self._read(td, self.base_key, self.net.out_features, what="predictive", check_finite=False)
            mean = mean + base
        return mean, variance

    def summary(self) -> dict[str, Tensor]:
        """Diagnostics of the adaptation (SMCD: ``ess`` and ``log_evidence``) per batch element."""
        self._require_reset()
        return self.adaptation.summary()

    def with_adaptation(self, adaptation: Adaptation) -> AdaptiveModel:
        """The same trained network and normalisation with another strategy (M+N, M+G, M+S...).

        The network is shared, not copied; strategies never modify it.
        """
        other = _assemble(type(self), self.net, self._key_config(), adaptation)
        other.input_norm = self.input_norm
        other.output_norm = self.output_norm
        other._declared = self._declared
        return other

    # ------------------------------------------------------------------ prediction
    def forward(self, td: TensorDictBase, *, mask: Tensor | None = None) -> TensorDictBase:
        """Write the adapted prediction to ``out_key``.

        Args:
            td: inputs; batch dims beyond the model's batch shape broadcast.
            mask: predict with these masks instead of the adapted one, ``[..., mask_dim]``
                broadcast against the inputs (e.g. one particle per planning candidate,
                taken from :attr:`particles`).
        """
        check_tensordict(td, "forward")
        self._require_reset()
        # No NaN check here: prediction changes no state, NaN in gives NaN out, and planners call
        # this in their inner loop (the check cost ~20% of a planning step). observe() checks.
        inputs = self._inputs(td, what="forward", check_finite=False)
        output = self._predict_normalised(inputs, mask, what="forward")
        td.set(self.out_key, self._from_output(td, self.output_norm.inverse(output)))
        return td

    def predict(self, inputs: Tensor, *, mask: Tensor | None = None) -> Tensor:
        """The adapted prediction from a raw input tensor: ``model(td)[out_key]`` without the TensorDict.

        Differentiable in ``inputs`` (no ``no_grad`` inside), so a controller can take the
        Jacobian of the adapted network, e.g. with ``torch.func.jacrev``. Models with a
        ``base_key`` (dynamics) use :meth:`AdaptiveDynamicsModel.step` instead.

        Args:
            inputs: the ``in_keys`` values concatenated, ``[*batch, in_features]``, in raw units.
            mask: as in :meth:`forward`.

        Example:
            >>> import torch, smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 3, hidden=(8,)), in_keys=["q"], out_key="ee")
            >>> model.reset()
            >>> torch.func.jacrev(model.predict)(torch.zeros(2)).shape  # d ee / d q
            torch.Size([3, 2])
        """
        self._require_reset()
        if self.base_key is not None:
            raise ValueError(
                f"predict returns the network's target, but this model predicts the change from {self.base_key!r}; "
                "use model.step(observation, action) for dynamics models"
            )
        inputs = check_real_tensor(inputs, "predict: inputs")
        if inputs.dim() == 0 or inputs.shape[-1:] != (self.net.in_features,):
            raise ValueError(f"predict needs inputs [..., {self.net.in_features}], got {list(inputs.shape)}")
        x = self.input_norm(self._as_model_dtype(inputs))
        return self.output_norm.inverse(self._predict_normalised(x, mask, what="predict"))

    @property
    def particles(self) -> Tensor:
        """The mask particles ``[*batch_shape, N, mask_dim]`` (strategies with a particle set only)."""
        self._require_reset()
        particles = getattr(self.adaptation, "particles", None)
        if particles is None:
            # Not AttributeError: nn.Module's __getattr__ would swallow it and report a missing attribute.
            raise TypeError(f"{type(self.adaptation).__name__} keeps no mask particles; use smcd_rl.SMCD")
        return particles

    def predict_particles(self, td: TensorDictBase) -> Tensor:
        """Posterior predictive samples of eq. (5): ``[*batch, N, out]``, one per particle."""
        check_tensordict(td, "predict_particles")
        self._require_reset()
        inputs = self._inputs(td, what="predict_particles", check_finite=False)
        self.adaptation._extra_dims(inputs)  # the batch check, before any work
        prediction = self.output_norm.inverse(self.adaptation.predict_particles(inputs))
        if self.base_key is not None:
            base = self._read(td, self.base_key, self.net.out_features, what="predict", check_finite=False)
            prediction = prediction + base.unsqueeze(-2)
        return prediction

    # ------------------------------------------------------------------ persistence
    def checkpoint(self) -> dict[str, Any]:
        """Everything needed to rebuild this model: architecture, keys, weights, strategy."""
        return {
            "format": _FORMAT,
            "class": type(self).__name__,
            "net": self.net.config,
            "keys": self._key_config(),
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
            "adaptation": spec(self.adaptation),
            "declared_fitted": self._declared.fitted,
            "residual_scale": None if self._declared.residual_scale is None else self._declared.residual_scale.tolist(),
            "calibration": self.calibration,
            "tuning": self.tuning,
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Save to ``path`` (written atomically), as :func:`smcd_rl.save` does; :func:`smcd_rl.load` rebuilds the model.

        Raises:
            smcd_rl.files.FileWriteError: the directory is read-only, the disk is full, ...
        """
        save_file(self.checkpoint(), path, what="model checkpoint")

    def load_checkpoint(self, checkpoint: dict[str, Any] | str | os.PathLike[str]) -> None:
        """Load trained weights and normalisation into this model, after checking they fit it.

        Raises:
            CheckpointMismatchError: the checkpoint is of another architecture or keys, or its
                weights are damaged (inf or NaN, a normaliser scale that is not positive); the
                model is left as it was.
            smcd_rl.files.UnreadableFileError: the file is empty, truncated or corrupt.
        """
        if not isinstance(checkpoint, dict):
            checkpoint = _read_checkpoint(checkpoint)
        missing = [key for key in ("net", "keys", "state_dict") if key not in checkpoint]
        if missing:
            raise CheckpointMismatchError(
                f"the checkpoint has no {missing} entries; pass a dict from model.checkpoint() or a file from model.save()"
            )
        if checkpoint.get("net") != self.net.config:
            raise CheckpointMismatchError(
                f"checkpoint holds a network {checkpoint.get('net')} but this model has {self.net.config}; "
                "build the model with the checkpoint's architecture, or use smcd_rl.load(path) to rebuild it"
            )
        if checkpoint.get("keys") != self._key_config():
            raise CheckpointMismatchError(
                f"checkpoint was saved with keys {checkpoint.get('keys')} but this model uses {self._key_config()}"
            )
        # Files written before these were recorded lack them: the model then has none.
        scale, calibration = checkpoint.get("residual_scale"), checkpoint.get("calibration")
        tuning = checkpoint.get("tuning")
        try:
            scale = None if scale is None else _checked_scale(scale, self.net.out_features)
            calibration = None if calibration is None else _checked_calibration(calibration, self.net.out_features)
            tuning = None if tuning is None else _checked_tuning(tuning)
        except (TypeError, ValueError) as err:
            raise CheckpointMismatchError(
                f"the checkpoint's residual scale, calibration or tuning does not fit its network ({err}); "
                "save the model again"
            ) from err
        state = _checked_weights(checkpoint["state_dict"], self.state_dict())
        declared = checkpoint.get("declared_fitted", False)
        if not isinstance(declared, bool):
            raise CheckpointMismatchError(
                f"the checkpoint's declared_fitted is {declared!r}, not True or False; save the model again"
            )
        self.load_state_dict(state)  # checked first: torch copies tensor by tensor and raises at the end
        self._declared.fitted = declared
        self._declared.residual_scale, self._declared.calibration = scale, calibration
        self._declared.tuning = tuning

    def to(self, *args: Any, **kwargs: Any) -> Self:
        """Move or cast the model as :meth:`torch.nn.Module.to` does; the meta device and non-real dtypes are refused.

        Raises:
            ValueError: the target is the meta device, where tensors have shapes but no values: the
                move would throw the trained weights away; or a dtype that is not a real floating
                one (complex, integer). The model is left as it was.
        """
        device, dtype = torch._C._nn._parse_to(*args, **kwargs)[:2]  # how nn.Module.to reads its arguments
        if dtype is not None and not dtype.is_floating_point:
            # torch casts only the floating tensors to a complex dtype, and then no forward runs.
            raise ValueError(
                f"model.to({dtype}): the network computes in a real floating dtype (torch.float32 or torch.float64); "
                "the model is unchanged"
            )
        if device is not None and device.type == "meta":
            raise ValueError(
                "model.to('meta'): the meta device holds tensors with shapes but no values, so the move would "
                "throw the trained weights away and leave a model that cannot predict; the model is unchanged. "
                "Move it to a real device ('cpu', 'cuda')"
            )
        return super().to(*args, **kwargs)

    # ------------------------------------------------------------------ internals
    def _bind(self, adaptation: Adaptation) -> None:
        if not isinstance(adaptation, Adaptation):
            raise TypeError(f"adaptation must be a smcd_rl.Adaptation, got {type(adaptation).__name__}")
        if next(self.net.parameters()).device.type == "meta":  # constructor, or a net moved there since
            raise ValueError(
                "the network is on the meta device, whose tensors have shapes but no values, so it cannot "
                "predict or adapt; materialise it first (net.to_empty(device='cpu'), then load its trained "
                "weights) or build it on a real device"
            )
        adaptation.bind(self.net, self.output_norm.std, calibration=self._declared.calibration)

    def _key_config(self) -> dict[str, Any]:
        return {
            "in_keys": [list(k) if isinstance(k, tuple) else k for k in self.in_keys],
            "out_key": list(self.out_key) if isinstance(self.out_key, tuple) else self.out_key,
            "target_key": list(self.target_key) if isinstance(self.target_key, tuple) else self.target_key,
            "base_key": list(self.base_key) if isinstance(self.base_key, tuple) else self.base_key,
        }

    def _smcd(self, what: str) -> SMCD:
        """The model's strategy if it is SMCD, else a TypeError naming ``what`` and the fix."""
        if not isinstance(self.adaptation, SMCD):
            raise TypeError(
                f"model.{what} needs an SMCD strategy (weighted mask particles), but this model adapts with "
                f"{type(self.adaptation).__name__}; use model.with_adaptation(smcd_rl.SMCD(...)) and reset it"
            )
        return self.adaptation

    def _require_reset(self) -> tuple[int, ...]:
        if self._batch_shape is None:
            raise RuntimeError("call model.reset() (or model.reset(batch_shape=(B,))) before using the model")
        return self._batch_shape

    def _warn_if_unfitted(self) -> None:
        if self._warned_unfitted or self.fitted:
            return
        self._warned_unfitted = True
        warnings.warn(
            "this model's network was never fitted, so it adapts an untrained network whose predictions mean "
            "nothing; train it first (smcd_rl.fit, fit_dynamics or fit_reptile, or smcd_rl.load a trained one), "
            "or set model.fitted = True if you trained it with your own loop",
            UnfittedModelWarning,
            stacklevel=3,
        )

    def _as_model_dtype(self, value: Tensor) -> Tensor:
        """``value`` in the model's dtype and on its device (ints and bools become floats)."""
        param = self.input_norm.mean
        return value.to(device=param.device, dtype=param.dtype)

    def _predict_normalised(self, x: Tensor, mask: Tensor | None, *, what: str) -> Tensor:
        """The network's normalised prediction for normalised inputs ``x``, with the adapted or the given mask."""
        if mask is None:
            return self.adaptation.predict(x)
        mask = check_real_tensor(mask, f"{what}: mask")
        if mask.dim() == 0 or mask.shape[-1] != self.net.mask_dim:
            raise ValueError(f"{what}: mask must have shape [..., {self.net.mask_dim}], got {list(mask.shape)}")
        try:
            torch.broadcast_shapes(x.shape[:-1], mask.shape[:-1])
        except RuntimeError as err:
            raise ValueError(
                f"{what}: mask {list(mask.shape)} does not broadcast against the inputs {list(x.shape)} "
                "(their dims before the last must match or be 1)"
            ) from err
        return self.net(x, mask=mask)

    def _read(
        self,
        td: TensorDictBase,
        key: NestedKey,
        size: int | None,
        *,
        what: str,
        check_finite: bool = True,
        exact: bool = False,
    ) -> Tensor:
        """``td[key]`` checked and in the model's dtype (see :func:`smcd_rl.checks.read_tensor`)."""
        return read_tensor(td, key, size, what=what, like=self.input_norm.mean, check_finite=check_finite, exact=exact)

    def training_pairs(self, td: TensorDictBase) -> tuple[Tensor, Tensor]:
        """Raw (unnormalised) network inputs and regression targets of a batch of transitions."""
        x = self._raw_inputs(td, what="fit")
        target = self._read(td, self.target_key, self.net.out_features, what="fit")
        return x, self._to_output(td, target)

    def _inputs(self, td: TensorDictBase, *, what: str, check_finite: bool = True, exact: bool = False) -> Tensor:
        return self.input_norm(self._raw_inputs(td, what=what, check_finite=check_finite, exact=exact))

    def _raw_inputs(self, td: TensorDictBase, *, what: str, check_finite: bool = True, exact: bool = False) -> Tensor:
        like = self.input_norm.mean
        x = read_inputs(td, self.in_keys, what=what, like=like, check_finite=check_finite, exact=exact)
        if x.shape[-1] != self.net.in_features:
            shapes = {str(k): list(td.get(k).shape) for k in self.in_keys}  # as read: the dtype changed, not the shape
            raise ValueError(
                f"{what}: inputs {shapes} give {x.shape[-1]} features but the network takes {self.net.in_features}"
            )
        return x

    def _to_output(self, td: TensorDictBase, target: Tensor, *, exact: bool = False) -> Tensor:
        if self.base_key is None:
            return target
        base = self._read(td, self.base_key, self.net.out_features, what="target", exact=exact)
        if base.shape != target.shape:  # [..., out] both; other leading dims would broadcast silently
            raise ValueError(
                f"{self.base_key!r} {list(base.shape)} and {self.target_key!r} {list(target.shape)} must have the same shape"
            )
        return target - base

    def _from_output(self, td: TensorDictBase, output: Tensor) -> Tensor:
        if self.base_key is None:
            return output
        return output + self._read(td, self.base_key, self.net.out_features, what="forward", check_finite=False)


class AdaptiveDynamicsModel(AdaptiveModel):
    """An :class:`AdaptiveModel` of dynamics: (observation, action) -> ("next", "observation").

    The network predicts the change of observation (``predict_delta=True``, the default).

    Example:
        >>> import torch, smcd_rl, warnings
        >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
        >>> from tensordict import TensorDict
        >>> net = smcd_rl.MaskedMLP(3 + 1, 3, hidden=(32, 32))
        >>> model = smcd_rl.AdaptiveDynamicsModel(net, adaptation=smcd_rl.SMCD(num_particles=50))
        >>> model.reset()
        >>> td = TensorDict({"observation": torch.zeros(3), "action": torch.zeros(1)}, [])
        >>> model(td)["next", "observation"].shape
        torch.Size([3])
    """

    def __init__(
        self,
        net: MaskedMLP,
        adaptation: Adaptation | None = None,
        *,
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        predict_delta: bool = True,
    ) -> None:
        check_key(observation_key, "observation_key")
        check_key(action_key, "action_key")
        if not isinstance(predict_delta, bool):
            raise TypeError(f"predict_delta must be True or False, got {predict_delta!r}")
        if net.in_features <= net.out_features:
            raise ValueError(
                f"the network takes {net.in_features} inputs and predicts {net.out_features} outputs; a dynamics "
                "model takes observation + action, so it needs more inputs than outputs"
            )
        next_key = ("next", observation_key) if isinstance(observation_key, str) else ("next", *observation_key)
        super().__init__(
            net,
            in_keys=[observation_key, action_key],
            out_key=next_key,
            target_key=next_key,
            base_key=observation_key if predict_delta else None,
            adaptation=adaptation,
        )

    def step(self, observation: Tensor, action: Tensor, *, mask: Tensor | None = None) -> Tensor:
        """The predicted next observation, from tensors: ``model(td)["next", "observation"]`` without the TensorDict.

        For planners' inner loops, where building a TensorDict per step costs about as much as a
        small network's forward. Like :meth:`forward` it does not check for NaN.

        Args:
            observation: ``[*batch, observation_dim]``.
            action: ``[*batch, action_dim]`` with the same batch dims.
            mask: as in :meth:`forward`.

        Example:
            >>> import torch, smcd_rl, warnings
            >>> warnings.simplefilter("ignore", smcd_rl.UnfittedModelWarning)  # an untrained toy network
            >>> model = smcd_rl.AdaptiveDynamicsModel(smcd_rl.MaskedMLP(3 + 1, 3, hidden=(32,)))
            >>> model.reset()
            >>> model.step(torch.zeros(5, 3), torch.ones(5, 1)).shape
            torch.Size([5, 3])
        """
        self._require_reset()
        observation = check_real_tensor(observation, "step: observation")
        action = check_real_tensor(action, "step: action")
        if (
            observation.shape[-1:] != (self.observation_dim,)
            or action.shape[-1:] != (self.action_dim,)
            or observation.shape[:-1] != action.shape[:-1]
        ):
            raise ValueError(
                f"step needs observation [..., {self.observation_dim}] and action [..., {self.action_dim}] "
                f"with the same batch dims, got {list(observation.shape)} and {list(action.shape)}"
            )
        observation, action = self._as_model_dtype(observation), self._as_model_dtype(action)
        inputs = self.input_norm(torch.cat([observation, action], dim=-1))
        prediction = self.output_norm.inverse(self._predict_normalised(inputs, mask, what="step"))
        return observation + prediction if self.base_key is not None else prediction

    @property
    def observation_dim(self) -> int:
        """Size of the observation the model predicts."""
        return self.net.out_features

    @property
    def action_dim(self) -> int:
        """Size of the action input (network input = observation + action)."""
        return self.net.in_features - self.net.out_features


_CLASSES: dict[str, type[AdaptiveModel]] = {
    "AdaptiveModel": AdaptiveModel,
    "AdaptiveDynamicsModel": AdaptiveDynamicsModel,
}


def _read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The checkpoint dict in ``path``, or an error that says whether the file is a damaged checkpoint or none at all.

    A damaged checkpoint (empty, truncated, records missing) gets the advice to save the model
    again; a file that was never a checkpoint (a user's ``torch.save(net.state_dict())``, an
    ``.npz``, a text file) gets what it is and how to load it instead.
    """
    try:
        return load_file(
            path,
            what="smcd_rl model checkpoint",
            expect_format=_FORMAT,
            expect_keys=_CHECKPOINT_KEYS,
            fix="save the model again (smcd_rl.save), or delete the file and rerun what wrote it",
        )
    except (UnreadableFileError, CheckpointMismatchError) as err:
        foreign = _foreign_file(Path(path))
        if foreign is None:  # a checkpoint of ours, damaged: the advice above fits
            raise
        message = f"{path} is not an smcd-rl model checkpoint: {foreign}"
        if isinstance(err, UnreadableFileError):
            raise UnreadableFileError(message, Path(path)) from err
        raise CheckpointMismatchError(message) from err


#: What :func:`load` reads, for the errors about files it cannot.
_WHAT_LOAD_READS = "smcd_rl.load reads the files smcd_rl.save(model, path) (or model.save(path)) writes"


def _foreign_file(path: Path) -> str | None:
    """What ``path`` holds and how to load it, if it is not an smcd-rl model checkpoint; ``None`` if it is one, maybe damaged.

    Looked at only after a load failed, so reading the file a second time costs nothing that matters.
    """
    try:
        with path.open("rb") as handle:
            head = handle.read(4)
    except OSError:
        return None
    if not head:
        return None  # empty: a write that was interrupted
    if head[:1] != b"\x80" and head != b"PK\x03\x04":  # neither a zip archive (torch.save) nor a pickle
        return f"it is not a file torch.save wrote (it starts with {head!r}); {_WHAT_LOAD_READS}"
    if head[:1] == b"\x80" and _foreign_pickle(path):
        return f"it is a pickle that torch.save did not write (pickle.dump?); {_WHAT_LOAD_READS}"
    if head == b"PK\x03\x04":
        try:
            with zipfile.ZipFile(path) as archive:
                names = archive.namelist()
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError, OSError):
            return None  # a truncated archive: a damaged checkpoint
        if not any(name.endswith("data.pkl") for name in names):
            return f"it is a zip archive (an .npz?) but not a file torch.save wrote; {_WHAT_LOAD_READS}"
    try:
        # weights_only=False as load_file does: it has just unpickled this same file.
        loaded = torch.load(path, map_location="cpu", weights_only=False)
    except Exception:  # unreadable: a damaged checkpoint, and load_file's error says so
        return None
    if not isinstance(loaded, Mapping):
        return f"it holds a {type(loaded).__name__}, not a checkpoint dict; {_WHAT_LOAD_READS}"
    found = loaded.get("format")
    if found == _FORMAT:
        return None  # ours, with entries missing
    if found is not None:
        return f"it is a file of format {found!r}, not {_FORMAT!r}; {_WHAT_LOAD_READS}"
    if loaded and all(isinstance(value, Tensor) for value in loaded.values()):
        return (
            f"it is a bare state_dict ({len(loaded)} tensors, as torch.save(net.state_dict(), path) writes): "
            "build the network and call net.load_state_dict(torch.load(path)), or save the whole model with "
            "smcd_rl.save(model, path) and load it with smcd_rl.load(path)"
        )
    keys = sorted(map(str, loaded))
    shown = ", ".join(repr(k) for k in keys[:5]) + (", ..." if len(keys) > 5 else "")
    return f"it is a dict without a 'format' entry (keys {shown}); {_WHAT_LOAD_READS}"


#: The number torch.save's legacy (non-zip) format pickles first.
_TORCH_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _foreign_pickle(path: Path) -> bool:
    """Whether ``path`` is a whole pickle that torch.save did not write (read op by op; nothing is run).

    torch.save's legacy format pickles its magic number first; a pickle that breaks off is a damaged
    file, not a foreign one.
    """
    try:
        with path.open("rb") as handle:
            for op, arg, _ in pickletools.genops(handle):
                if op.name.startswith("LONG") and arg == _TORCH_LEGACY_MAGIC:
                    return False
    except Exception:  # breaks off or is no pickle: damaged
        return False
    return True


def _checked_weights(state: Any, own: Mapping[str, Tensor]) -> Mapping[str, Tensor]:
    """A checkpoint's ``state_dict``, refused unless it holds exactly ``own``'s tensors, of their
    shapes, finite, with positive normaliser scales (a scale of 0 predicts a constant)."""
    if not isinstance(state, Mapping):
        raise CheckpointMismatchError(
            f"the checkpoint's state_dict is a {type(state).__name__}, not a dict of tensors; save the model again"
        )
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    if missing or unexpected:
        raise CheckpointMismatchError(
            f"the checkpoint's weights do not fit its own architecture (missing {missing}, unexpected "
            f"{unexpected}); save the model again"
        )
    for key, tensor in own.items():
        value = state[key]
        if not isinstance(value, Tensor) or value.shape != tensor.shape:
            got = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
            if key.startswith("net.body."):  # a FeatureReadout's own features module: the user's, not the file's
                raise CheckpointMismatchError(
                    f"the features module's {key.removeprefix('net.body.')!r} is {list(tensor.shape)} here but {got} in "
                    "the checkpoint; pass features= of the shapes the model was saved with"
                )
            raise CheckpointMismatchError(
                f"the checkpoint's weights do not fit its own architecture ({key!r} is {got}, the model's "
                f"{list(tensor.shape)}); save the model again"
            )
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise CheckpointMismatchError(
                f"the checkpoint's {key!r} holds inf or NaN, so every prediction would; the file is corrupt or "
                "the training diverged: train the model again"
            )
        if key.endswith("norm.std") and not bool((value > 0).all()):
            raise CheckpointMismatchError(
                f"the checkpoint's {key!r} is not positive everywhere, so the model would predict a constant; "
                "the file is corrupt: save the model again"
            )
    return state


def _checked_where(where: Any, batch_shape: tuple[int, ...]) -> Tensor:
    """``where`` of ``reset(where=...)`` as a bool tensor of ``batch_shape``, or a ValueError naming the mismatch."""
    try:
        rows = torch.as_tensor(where)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"reset(where=...) needs a bool tensor or array, got {type(where).__name__}") from err
    if rows.dtype != torch.bool:
        raise TypeError(f"reset(where=...) needs bools (True: reset that element), got {rows.dtype}")
    # [*batch, 1] too: torchrl's "_reset" flags have the shape of its done flags.
    if tuple(rows.shape) not in (batch_shape, (*batch_shape, 1)):
        raise ValueError(
            f"reset(where=...) needs one bool per batch element, shape {list(batch_shape)}, got {list(rows.shape)}"
        )
    return rows.reshape(batch_shape)


def _checked_scale(value: Any, size: int) -> Tensor:
    """A residual scale as a float32 CPU tensor of ``size`` positive finite values, or a clear error."""
    try:
        scale = torch.as_tensor(value).detach().to("cpu", torch.float32).clone()
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"residual_scale must be a tensor or sequence of {size} numbers, got {value!r}") from err
    if scale.shape != (size,) or not bool((scale > 0).all()) or not bool(torch.isfinite(scale).all()):
        raise ValueError(f"residual_scale must hold {size} positive finite values (one per output), got {value!r}")
    return scale


def _checked_calibration(value: Any, size: int) -> dict[str, Any]:
    """A calibration dict with a valid ``noise_std`` (scalar or ``size`` values) and ``flip_prob``, copied."""
    if not isinstance(value, dict) or "noise_std" not in value or "flip_prob" not in value:
        raise TypeError(f"calibration must be a dict with 'noise_std' and 'flip_prob', got {value!r}")
    noise: Any = value["noise_std"]
    noise = noise.tolist() if isinstance(noise, Tensor) else noise
    checked = checked_noise(noise)  # float32: the stored values are the caller's, as float64 Python floats
    if checked.dim() == 1 and checked.shape[0] not in (1, size):
        raise ValueError(f"calibration noise_std has {checked.shape[0]} values but the model predicts {size} outputs")
    flip = check_real(value["flip_prob"], "calibration flip_prob", low=0.0, high=1.0)
    plain = [float(v) for v in noise] if checked.dim() == 1 else float(noise)
    return {**value, "noise_std": plain, "flip_prob": flip}


def _checked_tuning(value: Any) -> dict[str, Any]:
    """A deep copy of ``value`` if it is a dict of JSON types, else a TypeError naming the first value that is not."""
    if not isinstance(value, dict):
        raise TypeError(
            f"tuning must be a dict of JSON types (or None), got {type(value).__name__}; the model keeps its old tuning"
        )

    def check(item: Any, where: str) -> None:
        if item is None or isinstance(item, (str, bool, int, float)):
            return
        if isinstance(item, dict):
            for key, inner in item.items():
                if not isinstance(key, str):
                    raise TypeError(
                        f"tuning{where} has the key {key!r}; JSON keys are strings (use str(key)), "
                        "the model keeps its old tuning"
                    )
                check(inner, f"{where}[{key!r}]")
            return
        if isinstance(item, (list, tuple)):
            for i, inner in enumerate(item):
                check(inner, f"{where}[{i}]")
            return
        hint = " (use tensor.tolist())" if isinstance(item, Tensor) else ""
        raise TypeError(
            f"tuning{where} is a {type(item).__name__}, not a JSON type (dict, list, str, number, bool, None){hint}; "
            "the model keeps its old tuning"
        )

    check(value, "")
    return copy.deepcopy(value)


def _key(value: Any) -> NestedKey | None:
    return tuple(value) if isinstance(value, list) else value


def save(model: AdaptiveModel, path: str | os.PathLike[str]) -> None:
    """Save ``model`` to ``path``: network, normalisation, calibration, tuning and strategy settings.

    :func:`load` rebuilds it. The same as ``model.save(path)``; the file is written atomically
    and is a pickle, as :func:`torch.save` writes it (load only files you trust). The adaptation
    state (particles, adapted weights) is not saved: a loaded model starts unadapted.

    Args:
        model: the model (an :class:`AdaptiveModel` or :class:`AdaptiveDynamicsModel`).
        path: the file to write (replaced if it exists; its directories are created).

    Raises:
        TypeError: ``model`` is not an :class:`AdaptiveModel` (save a bare network with
            ``torch.save(net.state_dict(), path)``).
        smcd_rl.files.FileWriteError: the directory is read-only, the disk is full, ...

    Example:
        >>> import tempfile, smcd_rl
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
        >>> path = tempfile.mkdtemp() + "/model.pt"
        >>> smcd_rl.save(model, path)
        >>> smcd_rl.load(path).net.config == model.net.config
        True
    """
    if not isinstance(model, AdaptiveModel):
        raise TypeError(
            f"smcd_rl.save takes an smcd_rl.AdaptiveModel, got {type(model).__name__}; save a bare network with "
            "torch.save(net.state_dict(), path), or wrap it in an AdaptiveModel"
        )
    model.save(path)


def load(
    path: str | os.PathLike[str], *, adaptation: Adaptation | None = None, features: torch.nn.Module | None = None
) -> AdaptiveModel:
    """Rebuild a model saved with :func:`save` (or :meth:`AdaptiveModel.save`).

    A model whose network is a :class:`~smcd_rl.feature_readout.FeatureReadout` holds your own
    features module, whose class smcd_rl cannot rebuild: pass a module of the same architecture
    back as ``features`` (its weights are then restored from the file; the module you pass is not
    changed).

    Args:
        path: the checkpoint file.
        adaptation: strategy to attach instead of the saved one (a fresh copy of it by default).
        features: for a ``FeatureReadout`` model, a features module of the saved one's class and
            shapes; for any other model, leave it out.

    Raises:
        FileNotFoundError: there is no file at ``path``.
        smcd_rl.UnreadableFileError: the checkpoint is empty, truncated or corrupt (save the model
            again), or the file is not a dict that :func:`torch.save` wrote.
        CheckpointMismatchError: the file is a dict but no model checkpoint, e.g. a bare
            ``state_dict`` (load it with ``net.load_state_dict(torch.load(path))``). For a file
            that is not an smcd-rl model checkpoint at all, the message says what it is and how
            to load it. Also: a ``FeatureReadout`` model loaded without ``features``, or with a
            module of another class or shapes than the saved one.

    Example:
        >>> import tempfile, smcd_rl
        >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(8,)), in_keys=["q"], out_key="ee")
        >>> path = tempfile.mkdtemp() + "/model.pt"
        >>> smcd_rl.save(model, path)
        >>> type(smcd_rl.load(path)).__name__
        'AdaptiveModel'
    """
    checkpoint = _read_checkpoint(path)
    try:
        # The architecture's config has no dtype: the saved weights carry it (a float64 model stays float64).
        net = _rebuilt_net(checkpoint["net"], _saved_dtype(checkpoint), features, path)
        if adaptation is None:
            saved = checkpoint["adaptation"]
            # The network is rebuilt on the CPU: so are the random generators of its SMCDs.
            adaptation = from_spec(
                {"name": saved["name"], "settings": on_device(saved["name"], settings_of(saved), "cpu")}
            )
        cls = _CLASSES[checkpoint["class"]]
        model = _assemble(cls, net, checkpoint["keys"], adaptation)
    except CheckpointMismatchError:
        raise
    except (TypeError, ValueError, KeyError) as err:  # a configuration this version cannot rebuild
        raise UnreadableFileError(
            f"smcd_rl model checkpoint {path} holds a configuration this version of smcd_rl cannot rebuild "
            f"({type(err).__name__}: {err}); save the model again with this version",
            Path(path),
        ) from err
    model.load_checkpoint(checkpoint)
    return model


def _rebuilt_net(
    config: dict[str, Any], dtype: torch.dtype | None, features: torch.nn.Module | None, path: str | os.PathLike[str]
) -> MaskedMLP:
    """The saved architecture: a :class:`MaskedMLP` from its config, or a ``FeatureReadout`` around ``features``."""
    saved = config.get("features") if isinstance(config, dict) else None
    if saved is None:
        if features is not None:
            raise CheckpointMismatchError(
                f"{path} holds a MaskedMLP, which smcd_rl rebuilds itself; load it without features="
            )
        return MaskedMLP(**config, dtype=dtype)
    if features is None:
        raise CheckpointMismatchError(
            f"{path} holds a network with your own features module ({saved}), which smcd_rl cannot rebuild; pass "
            f"one back: smcd_rl.load(path, features=<a {saved.rpartition('.')[2]} of the same shapes>), and its "
            "weights are restored from the file"
        )
    given = f"{type(features).__module__}.{type(features).__qualname__}"
    if given != saved:
        raise CheckpointMismatchError(f"{path} holds a features module {saved}, but features= is a {given}")
    readout = torch.nn.Linear(config["width"], config["out_features"], dtype=dtype)
    try:
        return FeatureReadout(
            copy.deepcopy(features).to(dtype) if dtype else features, readout, in_features=config["in_features"]
        )
    except ValueError as err:
        raise CheckpointMismatchError(f"features= does not fit the network saved in {path}: {err}") from err


def _saved_dtype(checkpoint: dict[str, Any]) -> torch.dtype | None:
    """The floating dtype of the saved weights (``None``: no float weight saved, torch's default)."""
    weights = checkpoint.get("state_dict")
    found = (
        [v.dtype for v in weights.values() if isinstance(v, Tensor) and v.is_floating_point()]
        if isinstance(weights, dict)
        else []
    )
    return found[0] if found else None


def _assemble(cls: type[AdaptiveModel], net: MaskedMLP, keys: dict[str, Any], adaptation: Adaptation) -> AdaptiveModel:
    """Build ``cls`` from a key configuration, bypassing subclass constructors' key defaults."""
    model = AdaptiveModel.__new__(cls)
    AdaptiveModel.__init__(
        model,
        net,
        in_keys=[_key(k) for k in keys["in_keys"]],
        out_key=_key(keys["out_key"]),
        target_key=_key(keys["target_key"]),
        base_key=_key(keys["base_key"]),
        adaptation=adaptation,
    )
    return model
