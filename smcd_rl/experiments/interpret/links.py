"""Fig. 9 (appendix A.5) of ``smcd-rl interpret``: do two-link masks encode the link lengths?

For each latent size ``ld`` a two-link forward-kinematics model is trained on motor babbling;
SMCD then infers a mask for each held-out arm after a burn-in, and an arm scores a hit at ``k``
when the arm nearest to it in link-length space is among its ``k`` nearest in mask space. The
held-out arms all babble along one joint path (unless ``--fig9-own-paths``), so their masks
differ by link lengths alone; with a path of their own per arm (and the default settings) the
accuracy measured at chance level, presumably because the MMSE mask then depends on the region
of joint space visited as much as on the link lengths. Chance is ``k / (arms - 1)``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.envs.two_link_arm import DEFAULT_DT, integrate_joints, motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.experiments.interpret.masks import filter_masks, shared_prior
from smcd_rl.experiments.shared.adaptations import StrategySettings
from smcd_rl.experiments.shared.outputs import format_table, save_figure

if TYPE_CHECKING:
    from smcd_rl.experiments.interpret.config import InterpretConfig

__all__ = [
    "HeldOutArms",
    "held_out_arms",
    "babbling",
    "make_model",
    "smcd_model",
    "mask_hits",
    "neighbour_hits",
    "table",
    "plot",
]


class HeldOutArms(NamedTuple):
    """The arms whose masks are compared: link lengths ``[arms, 2]`` and their babbling ``[arms, burn_in]``."""

    lengths: torch.Tensor
    sequence: TensorDict


def held_out_arms(config: InterpretConfig, device: torch.device) -> HeldOutArms:
    """Held-out arms from a seed disjoint from the training data's, shared by every latent size."""
    generator = torch.Generator().manual_seed(config.seed + 9_000_009)
    lengths = sample_link_lengths((config.fig9_arms,), generator=generator)
    paths = config.fig9_arms if config.fig9_own_paths else 1
    q = (torch.rand(paths, 2, generator=generator) * 2 - 1) * math.pi
    path = [q]
    for _ in range(config.fig9_burn_in - 1):
        q = integrate_joints(q, torch.randn(paths, 2, generator=generator), DEFAULT_DT)
        path.append(q)
    joints = torch.stack(path, 1).expand(config.fig9_arms, -1, -1)
    ee = two_link_fk(joints, lengths.unsqueeze(1)) + 0.01 * torch.randn(*joints.shape, generator=generator)
    sequence = TensorDict({"q": joints, "ee": ee}, [config.fig9_arms, config.fig9_burn_in], device=device)
    return HeldOutArms(lengths, sequence)


def babbling(config: InterpretConfig) -> TensorDict:
    """The training data: motor babbling of ``fig9_tasks`` arms, 10 steps per episode."""
    generator = torch.Generator().manual_seed(config.seed)
    return motor_babbling(config.fig9_tasks, config.fig9_episodes, 10, measurement_noise=0.01, generator=generator)


def make_model(latent: int, config: InterpretConfig, device: torch.device) -> smcd_rl.AdaptiveModel:
    """The untrained two-link model of one latent size; its initial weights come from the seed alone."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        net = smcd_rl.MaskedMLP(2, 2, hidden=(latent, latent), dropout=config.dropout, device=device)
    return smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")


def smcd_model(model: smcd_rl.AdaptiveModel, config: InterpretConfig, device: torch.device) -> smcd_rl.AdaptiveModel:
    """The trained two-link model with a fresh SMCD filter (its own seed, the same for every latent size)."""
    settings = StrategySettings(
        particles=config.fig9_particles,
        noise_std=0.05,
        flip_prob=config.flip_prob,
        gd_lr=config.gd_lr[0],  # unused by SMCD
        gd_steps=config.gd_steps[0],
        gd_window=config.gd_window[0],
    )
    return model.with_adaptation(settings.strategy("S", seed=config.seed + 19, device=device))


def mask_hits(
    adaptive: smcd_rl.AdaptiveModel, arms: HeldOutArms, config: InterpretConfig, *, desc: str, progress: bool
) -> torch.Tensor:
    """``[arms, len(fig9_ks)]`` hits (1.0 or 0.0) of the masks an SMCD model infers after the burn-in."""
    record = torch.zeros(config.fig9_arms, config.fig9_burn_in, dtype=torch.bool)
    record[:, -1] = True
    prior = None if config.independent_priors else shared_prior(adaptive.net, config.fig9_particles, config.seed + 23)
    masks, _, _ = filter_masks(
        adaptive, arms.sequence, record, prior=prior, chunk=config.chunk, desc=desc, progress=progress
    )
    return neighbour_hits(masks, arms.lengths, config.fig9_ks)


def neighbour_hits(masks: torch.Tensor, properties: torch.Tensor, ks: tuple[int, ...]) -> torch.Tensor:
    """Per item, :func:`smcd_rl.interpret.top_k_neighbour_accuracy`'s hit at each ``k``: ``[n, len(ks)]``.

    Its mean over items is that accuracy; per item, it is what a confidence interval resamples.

    Example:
        >>> import torch
        >>> lengths = torch.tensor([[1.0], [1.1], [3.0], [3.2]])
        >>> neighbour_hits(torch.tensor([[0.0], [5.0], [0.1], [5.1]]), lengths, (1, 2)).mean(0)
        tensor([0.0000, 0.5000], dtype=torch.float64)
    """
    n = masks.shape[0]
    eye = torch.eye(n, dtype=torch.bool)
    nearest = torch.cdist(properties.double(), properties.double()).masked_fill(eye, float("inf")).argmin(-1)
    mask_distance = torch.cdist(masks.double().cpu(), masks.double().cpu()).masked_fill(eye, float("inf"))
    # Rank of the property neighbour among the mask neighbours: how many others are strictly closer.
    rank = (mask_distance < mask_distance.gather(1, nearest.unsqueeze(-1))).sum(-1)
    return torch.stack([(rank < k).double() for k in ks], -1)


def _cell(row: dict[str, Any]) -> str:
    return f"{row['accuracy_mean']:.3f} [{row['accuracy_low']:.3f}, {row['accuracy_high']:.3f}]"


def table(rows: list[dict[str, Any]], config: InterpretConfig) -> str:
    """Top-k accuracy, mean [95% CI] over held-out arms: one row per latent size, then chance."""
    lookup = {(r["method"], r["k"]): r for r in rows}
    body: list[list[Any]] = [
        [f"ld={ld}", *[_cell(lookup[(f"ld={ld}", k)]) for k in config.fig9_ks]] for ld in config.fig9_latents
    ]
    body.append(["chance", *[k / (config.fig9_arms - 1) for k in config.fig9_ks]])
    return format_table(body, ["masks", *[f"k={k}" for k in config.fig9_ks]])


def plot(rows: list[dict[str, Any]], config: InterpretConfig, path: Path) -> None:
    """``fig9.png``: accuracy against k (log scale) per latent size, 95% CIs as error bars, chance dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    for latent in config.fig9_latents:
        sel = [r for r in rows if r["method"] == f"ld={latent}"]
        ax.errorbar(
            [r["k"] for r in sel],
            [r["accuracy_mean"] for r in sel],
            yerr=[
                [r["accuracy_mean"] - r["accuracy_low"] for r in sel],
                [r["accuracy_high"] - r["accuracy_mean"] for r in sel],
            ],
            marker="o",
            capsize=2,
            label=f"ld = {latent}",
        )
    ks = list(config.fig9_ks)
    ax.plot(ks, [k / (config.fig9_arms - 1) for k in ks], "k--", label="chance")
    ax.set_xscale("log")
    ax.set_xlabel("k (nearest masks)")
    ax.set_ylabel("top-k link-length accuracy")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def evaluate_hits(arms: Any, config: InterpretConfig, progress: bool, name: str, adaptive: Any) -> dict[str, Any]:
    """Fig. 9's mask hits of one network (a function, so a worker process can run it)."""
    return {"hits": mask_hits(adaptive, arms, config, desc=name, progress=progress)}
