"""How concentrated the masks study's posteriors are: on the training arms per epoch, and on held-out arms.

On the training arms (``fit``'s ``mask_callback``), a filter observes one arm's samples one after
the other; its log evidence per observation is compared with that of the same filter on the same
samples dealt to the arms at random. The difference, the *identity gap*, is how much better one
arm's samples are explained by a common mask than a mix of arms' samples: about 0 when the masks
do not carry the arm, positive when they do; *arms ahead* is the share of arms whose own log
evidence beats the dealt mixes' mean (about half by chance).

On held-out arms, after a few observations, the *specificity* of each arm's MMSE mask: how much
worse the other arms' masks predict this arm's next positions than its own mask does.

Both places give how spread the posterior still is (:func:`mask_spread`: 1 for the prior, 0
when the particles of weight agree on one mask) and the effective sample size (ESS) of the last
update, as a share of the particles: low when the weights sit on a few masks, and high both when
the likelihood cannot tell the particles apart and when they have settled on one mask.

Example:
    >>> import torch
    >>> found = {"log_likelihood": torch.tensor([1.0, 2.0]), "shuffled_log_likelihood": torch.tensor([0.5, 0.5]),
    ...          "mean_masks": torch.tensor([[0.5, 0.5], [1.0, 0.0]]),
    ...          "ess_share": torch.tensor([0.25, 0.5]), "distinct_share": torch.tensor([0.25, 0.25])}
    >>> training_posteriors(3, found, keep_prob=0.5)
    {'epoch': 3, 'identity_gap': 1.0, 'arms_ahead': 1.0, 'spread': 0.5, 'ess_share': 0.375, 'distinct_share': 0.25}
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
POSTERIOR_METRICS = ("test_specificity", "test_spread", "test_ess_share")


def mask_spread(mean_mask: torch.Tensor, keep_prob: float) -> torch.Tensor:
    """How spread a mask posterior still is: its bits' mean variance ``m (1 - m)`` over the prior's ``k (1 - k)``.

    1 for the prior (independent Bernoulli(``keep_prob``) bits), 0 when every particle of weight
    carries the same mask; one value per row of ``mean_mask [..., mask_dim]`` (the MMSE mask).

    Example:
        >>> mask_spread(torch.tensor([[0.5, 0.5], [1.0, 0.0]]), 0.5)
        tensor([1., 0.], dtype=torch.float64)
    """
    m = mean_mask.double()
    return (m * (1 - m)).mean(-1) / (keep_prob * (1 - keep_prob))


def training_posteriors(epoch: int, found: Mapping[str, torch.Tensor], keep_prob: float) -> dict[str, float]:
    """One epoch's training posteriors (``fit``'s ``mask_callback``): means over the training arms, and
    the share of arms whose own log likelihood beats the mean of the dealt ones (``arms_ahead``)."""
    own, dealt = found["log_likelihood"].double(), found["shuffled_log_likelihood"].double()
    return {
        "epoch": epoch,
        "identity_gap": float((own - dealt).mean()),
        "arms_ahead": float((own > dealt.mean()).double().mean()),
        "spread": float(mask_spread(found["mean_masks"], keep_prob).mean()),
        "ess_share": float(found["ess_share"].double().mean()),
        "distinct_share": float(found["distinct_share"].double().mean()),
    }


@torch.no_grad()
def held_out_posteriors(
    model: Any, q: torch.Tensor, ee: torch.Tensor, ee_true: torch.Tensor, *, steps: int, chunk: int
) -> dict[str, torch.Tensor]:
    """Per held-out arm, after its filter observed ``steps`` samples: the mask's specificity, spread and ESS share.

    ``model`` is an :class:`smcd_rl.AdaptiveModel` with an SMCD strategy; ``q, ee, ee_true`` are
    ``[arms, steps + H, 2]`` (measured and true positions). Each arm's filter observes its first
    ``steps`` samples; its MMSE mask then predicts the arm's next ``H`` positions, and so does every
    other arm's mask. The *specificity* (m^2) is the mean error of the other arms' masks minus that
    of the arm's own: about 0 when the posterior finds the same sub-network for every arm, large
    when it found one that belongs to this arm. Paired per arm, so an arm's own difficulty cancels.
    """
    arms = q.shape[0]
    masks, ess = [], []  # the MMSE masks and ESS, chunk by chunk
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
    return {
        "test_specificity": others - own,
        "test_spread": mask_spread(mask, model.net.keep_prob).cpu(),
        "test_ess_share": torch.cat(ess) / model.adaptation.num_particles,
    }


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
                *(f"{first[k]:.3g} -> {last[k]:.3g}" for k in ("arms_ahead", "spread", "ess_share")),
            ]
        )
    span = f"epoch {runs[0][1][0]['epoch']} -> {runs[0][1][-1]['epoch']}"
    header = [*names, f"identity gap ({span})", "arms ahead", "spread", "ESS share"]
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
    return format_table(body, [*names, "mask specificity (m^2)", "spread", "ESS share"])


def plot(runs: Sequence[tuple[Mapping[str, Any], Sequence[Mapping[str, float]]]], path: Path) -> None:
    """The training posteriors over epochs, one line per training run: identity gap, arms ahead, spread.

    The runs' first parameter sets the colour, the second the line style, the third the width.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    names = list(runs[0][0])[:3]
    values = [list(dict.fromkeys(parameters[n] for parameters, _ in runs)) for n in names]
    cmap = plt.get_cmap("viridis")
    styles = {
        "color": lambda i, n: cmap(0.85 * i / max(n - 1, 1)),
        "linestyle": lambda i, n: ("-", "--", ":", "-.")[i % 4],
        "linewidth": lambda i, n: 0.9 + 1.2 * i / max(n - 1, 1),
    }
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.4))
    panels = {
        "identity_gap": "identity gap per observation",
        "arms_ahead": "share of arms ahead of a dealt mix",
        "spread": "posterior spread (1: the prior)",
    }
    for parameters, epochs in runs:
        look = {
            key: style(vs.index(parameters[n]), len(vs))
            for (key, style), n, vs in zip(styles.items(), names, values, strict=False)
        }
        xs = [e["epoch"] for e in epochs]
        for ax, name in zip(axes, panels, strict=True):
            ax.plot(xs, [e[name] for e in epochs], marker="o" if len(xs) == 1 else None, **look)
    axes[0].axhline(0.0, color="0.5", lw=0.8)
    axes[1].axhline(0.5, color="0.5", lw=0.8)
    for ax, text in zip(axes, panels.values(), strict=True):
        ax.set_ylabel(text)
        ax.set_xlabel("epoch")
        ax.xaxis.get_major_locator().set_params(integer=True)
        ax.grid(alpha=0.3)
    handles = [
        Line2D([], [], **{"color": "0.3", key: style(i, len(vs))}, label=f"{n}={v}")
        for (key, style), n, vs in zip(styles.items(), names, values, strict=False)
        for i, v in enumerate(vs)
    ]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 9), fontsize=8, frameon=False)
    fig.suptitle("Training arms' mask posteriors over epochs (masks study)")
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    save_figure(fig, path, dpi=120)
    plt.close(fig)
