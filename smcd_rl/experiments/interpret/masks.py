"""SMCD masks read off filters run over sequences: what ``smcd-rl interpret``'s figures compare.

Fig. 9 compares the masks of two-link arms, Figs. 4 and 13 those of drone trajectories; both run
an SMCD filter over a batch of sequences and read its MMSE mask after chosen steps. Every filter
whose masks are compared can start from one shared prior particle set (:func:`shared_prior`),
so that two sequences' masks differ because their data selected different particles, not
because their filters drew different random masks.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.envs.drone_operators import TrajectoryDataset

__all__ = ["shared_prior", "filter_masks", "sorted_masks", "padded"]


def shared_prior(net: smcd_rl.MaskedMLP, particles: int, seed: int) -> torch.Tensor:
    """``[particles, mask_dim]`` Bernoulli(keep_prob) masks, the same for a given seed."""
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(particles, net.mask_dim, generator=generator) < net.keep_prob


@torch.no_grad()
def filter_masks(
    model: smcd_rl.AdaptiveModel,
    sequence: TensorDict,
    record: torch.Tensor,
    *,
    prior: torch.Tensor | None,
    chunk: int,
    desc: str,
    progress: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """MMSE masks of an SMCD model run over sequences ``[B, T]``, read after the steps ``record`` marks.

    ``record[b, t]`` asks for sequence ``b``'s mask after observing steps ``0..t``. Each chunk of
    sequences is filtered at once, from ``prior`` when given (else the filter's own draw).

    Returns:
        ``(masks [R, mask_dim], rows [R], observed [R])`` with ``observed = t + 1``.
    """
    adaptation = model.adaptation
    if not isinstance(adaptation, smcd_rl.SMCD):
        raise TypeError(f"masks come from an SMCD model, got {type(adaptation).__name__}")
    masks, rows, observed = [], [], []
    for begin in tqdm(range(0, sequence.shape[0], chunk), desc=desc, unit="chunk", disable=not progress):
        part, wanted = sequence[begin : begin + chunk], record[begin : begin + chunk]
        batch = part.shape[0]
        last = int(wanted.any(0).nonzero().max()) + 1 if bool(wanted.any()) else 0
        model.reset(batch_shape=(batch,))
        if prior is not None:
            filt = adaptation.filter
            assert filt is not None  # reset attached it
            filt.particles = prior.to(filt.device).expand(batch, *prior.shape).clone()
        for t in range(last):
            model.observe(part[:, t])
            if bool(wanted[:, t].any()):
                picked = wanted[:, t].nonzero().squeeze(-1)
                mask = model.mask
                assert mask is not None  # an SMCD model always has one
                masks.append(mask[picked].float().cpu())
                rows.append(picked + begin)
                observed.append(torch.full_like(picked, t + 1))
    if not masks:
        raise ValueError("no masks were recorded: every trajectory is shorter than the steps asked for")
    return torch.cat(masks), torch.cat(rows).cpu(), torch.cat(observed).cpu()


def sorted_masks(
    model: smcd_rl.AdaptiveModel,
    data: TrajectoryDataset,
    record: torch.Tensor,
    *,
    prior: torch.Tensor | None,
    chunk: int,
    device: torch.device,
    desc: str,
    progress: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`filter_masks` over trajectories sorted by length, so a chunk pads little; rows are dataset ids."""
    order = torch.from_numpy(np.argsort(data.lengths, kind="stable"))
    sequence = padded(data, device)[order]
    masks, rows, observed = filter_masks(
        model, sequence, record[order], prior=prior, chunk=chunk, desc=desc, progress=progress
    )
    return masks, order[rows], observed


def padded(data: TrajectoryDataset, device: torch.device) -> TensorDict:
    """``[N, T_max]`` states and actions, each trajectory padded with copies of its last step."""
    lengths = torch.from_numpy(data.lengths)
    steps = torch.arange(int(lengths.max()))
    index = torch.from_numpy(data.offsets[:-1]).unsqueeze(1) + torch.minimum(steps, lengths.unsqueeze(1) - 1)
    return TensorDict(
        {"state": torch.from_numpy(data.state)[index], "action": torch.from_numpy(data.action)[index]},
        list(index.shape),
        device=device,
    )
