"""How concentrated the masks study's posteriors are: on the training arms per epoch, and on held-out arms.

The measure is the same in both places. A filter observes one arm's samples one after the other;
its log evidence per observation is compared with that of the same filter on the same samples
dealt to the arms at random. The difference, the *identity gap*, is how much better one arm's
samples are explained by a common mask than a mix of arms' samples: about 0 when the masks do
not carry the arm, positive when they do. Beside it the effective sample size (ESS) of the last
update, as a share of the particles: low when the weights sit on a few masks.

Example:
    >>> import torch
    >>> found = {"log_likelihood": torch.tensor([1.0, 2.0]), "shuffled_log_likelihood": torch.tensor([0.5, 0.5]),
    ...          "ess_share": torch.tensor([0.25, 0.5]), "distinct_share": torch.tensor([0.25, 0.25])}
    >>> training_posteriors(3, found)
    {'epoch': 3, 'identity_gap': 1.0, 'ess_share': 0.375, 'distinct_share': 0.25}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.experiments.shared.stats import bootstrap_indices, mean_ci

__all__ = ["POSTERIOR_METRICS", "training_posteriors", "held_out_posteriors", "test_table", "training_table", "plot"]

#: The per-arm metrics :func:`held_out_posteriors` adds to a masks-study grid point.
POSTERIOR_METRICS = ("test_gap", "test_ess_share")


def training_posteriors(epoch: int, found: Mapping[str, torch.Tensor]) -> dict[str, float]:
    """One epoch's training posteriors (``fit``'s ``mask_callback``), as means over the training arms."""
    gap = found["log_likelihood"].double() - found["shuffled_log_likelihood"].double()
    return {
        "epoch": epoch,
        "identity_gap": float(gap.mean()),
        "ess_share": float(found["ess_share"].double().mean()),
        "distinct_share": float(found["distinct_share"].double().mean()),
    }


@torch.no_grad()
def held_out_posteriors(
    model: Any, q: torch.Tensor, ee: torch.Tensor, *, chunk: int, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """Per held-out arm: the identity gap (per observation) and the ESS share after observing ``q, ee [arms, T, 2]``.

    ``model`` is an :class:`smcd_rl.AdaptiveModel` with an SMCD strategy; each arm's filter
    observes its ``T`` samples, and again the same samples dealt to the arms at random
    (``generator``); row ``k`` of the gap is arm ``k``'s log evidence per observation minus that
    of the ``k``-th filter on dealt samples.
    """
    arms, steps = q.shape[:2]
    deal = torch.randperm(arms * steps, generator=generator).to(q.device)
    dealt_q, dealt_ee = (v.reshape(arms * steps, -1)[deal].reshape(v.shape) for v in (q, ee))
    own_evidence, own_ess = _filter_arms(model, q, ee, chunk)
    dealt_evidence, _ = _filter_arms(model, dealt_q, dealt_ee, chunk)
    particles = model.adaptation.num_particles
    return {"test_gap": (own_evidence - dealt_evidence) / steps, "test_ess_share": own_ess / particles}


def _filter_arms(model: Any, q: torch.Tensor, ee: torch.Tensor, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
    evidence, ess = [], []
    for begin in range(0, q.shape[0], chunk):
        qc, eec = q[begin : begin + chunk], ee[begin : begin + chunk]
        model.reset(batch_shape=(qc.shape[0],))
        for t in range(qc.shape[1]):
            model.observe(TensorDict({"q": qc[:, t], "ee": eec[:, t]}, [qc.shape[0]]))
        summary = model.summary()
        evidence.append(summary["log_evidence"].double().cpu())
        ess.append(summary["ess"].double().cpu())
    return torch.cat(evidence), torch.cat(ess)


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
                f"{first['ess_share']:.3g} -> {last['ess_share']:.3g}",
                f"{first['distinct_share']:.3g} -> {last['distinct_share']:.3g}",
            ]
        )
    span = f"epoch {runs[0][1][0]['epoch']} -> {runs[0][1][-1]['epoch']}"
    header = [*names, f"identity gap ({span})", "ESS share", "distinct-mask share"]
    return format_table(body, header)


def test_table(
    rows: Sequence[Mapping[str, Any]], arms: Sequence[Mapping[str, torch.Tensor]], names: Sequence[str]
) -> str:
    """Each grid point's posteriors on the held-out arms: mean [95% CI] over the arms."""
    indices = bootstrap_indices(len(arms[0][POSTERIOR_METRICS[0]]))  # the same resamples of the arms everywhere
    body = [
        [*(row[n] for n in names), *(str(mean_ci(scores[m].double(), indices=indices)) for m in POSTERIOR_METRICS)]
        for row, scores in zip(rows, arms, strict=True)
    ]
    return format_table(body, [*names, "identity gap", "ESS share"])


def plot(runs: Sequence[tuple[Mapping[str, Any], Sequence[Mapping[str, float]]]], path: Path) -> None:
    """The training posteriors over epochs, one line per training run: identity gap and ESS share."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for parameters, epochs in runs:
        label = ", ".join(f"{k}={v}" for k, v in parameters.items())
        xs = [e["epoch"] for e in epochs]
        axes[0].plot(xs, [e["identity_gap"] for e in epochs], marker=".", label=label)
        axes[1].plot(xs, [e["ess_share"] for e in epochs], marker=".", label=label)
    axes[0].axhline(0.0, color="0.5", lw=0.8)
    axes[0].set_ylabel("identity gap (log evidence per observation)")
    axes[1].set_ylabel("ESS share of the last update")
    axes[1].set_yscale("log")
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=6)
    fig.suptitle("Training arms' mask posteriors over epochs (masks study)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
