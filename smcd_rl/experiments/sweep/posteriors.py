"""How concentrated the masks study's posteriors are: on the training arms per epoch, and on held-out arms.

On the training arms (``fit``'s ``mask_callback``), a filter observes one arm's samples one after
the other; its log evidence per observation is compared with that of the same filter on the same
samples dealt to the arms at random. The difference, the *identity gap*, is how much better one
arm's samples are explained by a common mask than a mix of arms' samples: about 0 when the masks
do not carry the arm, positive when they do; *arms ahead* is the share of arms whose own log
evidence beats the dealt mixes' mean (about half by chance).

On held-out arms, after a few observations, the *specificity* of each arm's MMSE mask: how much
worse the other arms' masks predict this arm's next positions than its own mask does.

Both places also give the effective sample size (ESS) of the last update, as a share of the
particles: low when the weights sit on a few masks.

Example:
    >>> import torch
    >>> found = {"log_likelihood": torch.tensor([1.0, 2.0]), "shuffled_log_likelihood": torch.tensor([0.5, 0.5]),
    ...          "ess_share": torch.tensor([0.25, 0.5]), "distinct_share": torch.tensor([0.25, 0.25])}
    >>> training_posteriors(3, found)
    {'epoch': 3, 'identity_gap': 1.0, 'arms_ahead': 1.0, 'ess_share': 0.375, 'distinct_share': 0.25}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.experiments.shared.stats import bootstrap_indices, mean_ci

__all__ = [
    "POSTERIOR_METRICS",
    "training_posteriors",
    "held_out_posteriors",
    "held_out_table",
    "training_table",
    "plot",
]

#: The per-arm metrics :func:`held_out_posteriors` adds to a masks-study grid point.
POSTERIOR_METRICS = ("test_specificity", "test_ess_share")


def training_posteriors(epoch: int, found: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """One epoch's training posteriors (``fit``'s ``mask_callback``): means over the training arms, and
    the share of arms whose own log likelihood beats the mean of the dealt ones (``arms_ahead``)."""
    own, dealt = found["log_likelihood"].double(), found["shuffled_log_likelihood"].double()
    return {
        "epoch": epoch,
        "identity_gap": float((own - dealt).mean()),
        "arms_ahead": float((own > dealt.mean()).double().mean()),
        "ess_share": float(found["ess_share"].double().mean()),
        "distinct_share": float(found["distinct_share"].double().mean()),
    }


@torch.no_grad()
def held_out_posteriors(
    model: Any, q: torch.Tensor, ee: torch.Tensor, ee_true: torch.Tensor, *, steps: int, chunk: int
) -> dict[str, torch.Tensor]:
    """Per held-out arm, after its filter observed ``steps`` samples: the mask's specificity and the ESS share.

    ``model`` is an :class:`smcd_rl.AdaptiveModel` with an SMCD strategy; ``q, ee, ee_true`` are
    ``[arms, steps + H, 2]`` (measured and true positions). Each arm's filter observes its first
    ``steps`` samples; its MMSE mask then predicts the arm's next ``H`` positions, and so does every
    other arm's mask. The *specificity* (m^2) is the mean error of the other arms' masks minus that
    of the arm's own: about 0 when the posterior finds the same sub-network for every arm, large
    when it found one that belongs to this arm. Paired per arm, so an arm's own difficulty cancels.
    """
    arms = q.shape[0]
    masks, ess = [], []
    for begin in range(0, arms, chunk):
        rows = slice(begin, begin + chunk)
        batch = q[rows].shape[0]
        model.reset(batch_shape=(batch,))
        for t in range(steps):
            model.observe(TensorDict({"q": q[rows, t], "ee": ee[rows, t]}, [batch]))
        masks.append(model.mask)
        ess.append(model.summary()["ess"].double().cpu())
    mask = torch.cat(masks)
    future_q, future_ee = q[:, steps:], ee_true[:, steps:]
    horizon = future_q.shape[1]
    errors = torch.empty(arms, arms, dtype=torch.float64)  # [arm, whose mask]
    every_mask = mask.unsqueeze(1).expand(-1, horizon, -1)
    for k in range(arms):
        predicted = model.predict(future_q[k].expand(arms, -1, -1), mask=every_mask)
        errors[k] = (predicted - future_ee[k]).square().sum(-1).mean(-1).double().cpu()
    own = errors.diagonal()
    others = (errors.sum(1) - own) / max(arms - 1, 1)
    return {"test_specificity": others - own, "test_ess_share": torch.cat(ess) / model.adaptation.num_particles}


def training_table(runs: Sequence[tuple[Mapping[str, Any], Sequence[Mapping[str, float]]]]) -> str:
    """Each training run's posteriors at its first and last inferring epoch (epoch 0 trains without them)."""
    names = list(runs[0][0])
    body = []
    for parameters, epochs in runs:
        first, last = epochs[0], epochs[-1]
        body.append(
            [
                *parameters.values(),
                f"{first['identity_gap']:.3g} -> {last['identity_gap']:.3g}",
                f"{first['arms_ahead']:.3g} -> {last['arms_ahead']:.3g}",
                f"{first['ess_share']:.3g} -> {last['ess_share']:.3g}",
                f"{first['distinct_share']:.3g} -> {last['distinct_share']:.3g}",
            ]
        )
    span = f"epoch {runs[0][1][0]['epoch']} -> {runs[0][1][-1]['epoch']}"
    header = [*names, f"identity gap ({span})", "arms ahead", "ESS share", "distinct-mask share"]
    return format_table(body, header)


def held_out_table(
    rows: Sequence[Mapping[str, Any]], arms: Sequence[Mapping[str, torch.Tensor]], names: Sequence[str]
) -> str:
    """Each grid point's posteriors on the held-out arms: mean [95% CI] over the arms."""
    indices = bootstrap_indices(len(arms[0][POSTERIOR_METRICS[0]]))  # the same resamples of the arms everywhere
    body = [
        [*(row[n] for n in names), *(str(mean_ci(scores[m].double(), indices=indices)) for m in POSTERIOR_METRICS)]
        for row, scores in zip(rows, arms, strict=True)
    ]
    return format_table(body, [*names, "mask specificity (m^2)", "ESS share"])


def plot(runs: Sequence[tuple[Mapping[str, Any], Sequence[Mapping[str, float]]]], path: Path) -> None:
    """The training posteriors over epochs, one line per training run: identity gap, arms ahead, ESS share."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    panels = {
        "identity_gap": "identity gap per observation",
        "arms_ahead": "share of arms ahead of a dealt mix",
        "ess_share": "ESS share of the last update",
    }
    for parameters, epochs in runs:
        label = ", ".join(f"{k}={v}" for k, v in parameters.items())
        xs = [e["epoch"] for e in epochs]
        for ax, name in zip(axes, panels, strict=True):
            ax.plot(xs, [e[name] for e in epochs], marker=".", label=label)
    axes[0].axhline(0.0, color="0.5", lw=0.8)
    axes[1].axhline(0.5, color="0.5", lw=0.8)
    for ax, text in zip(axes, panels.values(), strict=True):
        ax.set_ylabel(text)
        ax.set_xlabel("epoch")
        ax.xaxis.get_major_locator().set_params(integer=True)
        ax.grid(alpha=0.3)
    axes[2].legend(fontsize=6)
    fig.suptitle("Training arms' mask posteriors over epochs (masks study)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
