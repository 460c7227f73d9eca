"""The two-link look-ahead evaluation: fresh test arms, and one method's errors H steps ahead after T.

Shared by ``smcd-rl two-link`` (paper Fig. 2) and the SMCD study of ``smcd-rl sweep`` (Fig. 6),
so that both score methods on the same arms in the same way.

Example:
    >>> from smcd_rl.experiments.two_link.config import TwoLinkConfig
    >>> q, ee, ee_true, lengths = test_arms(TwoLinkConfig(burn_in=(2,), horizons=(3,)), "cpu", count=4, seed=0)
    >>> tuple(q.shape), tuple(ee.shape), tuple(lengths.shape)
    ((4, 5, 2), (4, 5, 2), (4, 2))
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from smcd_rl.envs.two_link_arm import DEFAULT_DT, integrate_joints, sample_link_lengths, two_link_fk

if TYPE_CHECKING:
    from smcd_rl.experiments.two_link.config import TwoLinkConfig

__all__ = ["TEST_ARMS_SEED", "test_arms", "lookahead_errors"]

#: Offset of the test arms' seed from ``--seed`` (a stream of their own, disjoint from training and tuning).
TEST_ARMS_SEED = 1_000_003


def test_arms(config: TwoLinkConfig, device: torch.device, *, count: int, seed: int) -> tuple[torch.Tensor, ...]:
    """``count`` fresh arms: joint paths ``q [count, T+H, 2]``, measured and true ``ee``, link lengths.

    The test arms come from a generator of their own seed, disjoint from the training data's.
    """
    generator = torch.Generator().manual_seed(seed)
    length = max(config.burn_in) + max(config.horizons)
    lengths = sample_link_lengths((count,), generator=generator)
    q = (torch.rand(count, 2, generator=generator) * 2 - 1) * math.pi
    path = [q]
    for _ in range(length - 1):
        q = integrate_joints(q, torch.randn(count, 2, generator=generator), DEFAULT_DT)
        path.append(q)
    joints = torch.stack(path, 1)
    ee_true = two_link_fk(joints, lengths.unsqueeze(1))
    ee = ee_true + config.measurement_noise * torch.randn(ee_true.shape, generator=generator)
    return joints.to(device), ee.to(device), ee_true.to(device), lengths


@torch.no_grad()
def lookahead_errors(
    method: Any,
    q: torch.Tensor,
    ee: torch.Tensor,
    ee_true: torch.Tensor,
    config: TwoLinkConfig,
    *,
    desc: str,
    progress: bool,
) -> torch.Tensor:
    """Squared look-ahead errors ``[trials, len(burn_in), max H]`` of one method.

    The method observes measured positions ``ee``; errors are against the noise-free ``ee_true``.
    """
    trials, max_h = q.shape[0], max(config.horizons)
    errors = torch.full((trials, len(config.burn_in), max_h), float("nan"))  # a cell left unfilled shows
    chunks = range(0, trials, config.chunk)
    for begin in tqdm(chunks, desc=desc, unit="chunk", disable=not progress):
        qc, eec = q[begin : begin + config.chunk], ee[begin : begin + config.chunk]
        batch = qc.shape[0]
        method.reset(batch_shape=(batch,))
        for t in range(max(config.burn_in)):
            method.observe(TensorDict({"q": qc[:, t], "ee": eec[:, t]}, [batch]))
            if t + 1 in config.burn_in:
                ahead = slice(t + 1, t + 1 + max_h)
                predicted = method(TensorDict({"q": qc[:, ahead]}, [batch, max_h]))["ee"]
                truth = ee_true[begin : begin + batch, ahead]
                errors[begin : begin + batch, config.burn_in.index(t + 1)] = (predicted - truth).square().sum(-1).cpu()
    return errors
