"""Training with dropout: the network every strategy adapts.

* :mod:`~smcd_rl.training.fitting`: :func:`fit` (multi-task, samples pooled from many settings;
  with ``mask_training="task"`` the masks tied to the tasks), :func:`fit_dynamics` and
  :func:`fit_reptile` (Reptile meta-learning);
* :mod:`~smcd_rl.training.task_masks`: the machinery of ``mask_training="task"``.

Example:
    >>> import torch, smcd_rl
    >>> from tensordict import TensorDict
    >>> model = smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(2, 2, hidden=(16,)), in_keys=["q"], out_key="ee")
    >>> q = torch.rand(64, 2)
    >>> history = smcd_rl.fit(model, TensorDict({"q": q, "ee": q.cos()}, [64]), epochs=2, progress=False)
    >>> model.fitted
    True
"""

from __future__ import annotations

from smcd_rl.training.fitting import MaskTraining, fit, fit_dynamics, fit_reptile

__all__ = ["fit", "fit_dynamics", "fit_reptile", "MaskTraining"]
