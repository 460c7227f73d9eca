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
from smcd_rl.strategies.combination import weight_path

if TYPE_CHECKING:
    from smcd_rl.experiments.two_link.config import TwoLinkConfig

__all__ = ["TEST_ARMS_SEED", "test_arms", "lookahead_errors", "combined_errors"]

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
    record: dict[str, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Squared look-ahead errors ``[trials, len(burn_in), max H]`` of one method.

    The method observes measured positions ``ee``; errors are against the noise-free ``ee_true``.
    With ``record`` (an adaptive model's run), its predictions go into it, in the model's
    normalised units: ``"one_step" [trials, max T, out]``, each burn-in position predicted before
    it is observed, and ``"ahead" [trials, len(burn_in), max H, out]``, what the errors are of:
    what :func:`combined_errors` takes.
    """
    trials, max_h, max_t = q.shape[0], max(config.horizons), max(config.burn_in)
    errors = torch.full((trials, len(config.burn_in), max_h), float("nan"))  # a cell left unfilled shows
    if record is not None:
        record["one_step"] = torch.full((trials, max_t, ee.shape[-1]), float("nan"))
        record["ahead"] = torch.full((trials, len(config.burn_in), max_h, ee.shape[-1]), float("nan"))
    chunks = range(0, trials, config.chunk)
    for begin in tqdm(chunks, desc=desc, unit="chunk", disable=not progress):
        rows = slice(begin, begin + config.chunk)
        qc, eec = q[rows], ee[rows]
        batch = qc.shape[0]
        method.reset(batch_shape=(batch,))
        for t in range(max_t):
            if record is not None:
                now = method(TensorDict({"q": qc[:, t]}, [batch]))["ee"]
                record["one_step"][rows, t] = method.output_norm(now).cpu()
            method.observe(TensorDict({"q": qc[:, t], "ee": eec[:, t]}, [batch]))
            if t + 1 in config.burn_in:
                ahead = slice(t + 1, t + 1 + max_h)
                predicted = method(TensorDict({"q": qc[:, ahead]}, [batch, max_h]))["ee"]
                truth = ee_true[rows, ahead]
                errors[rows, config.burn_in.index(t + 1)] = (predicted - truth).square().sum(-1).cpu()
                if record is not None:
                    record["ahead"][rows, config.burn_in.index(t + 1)] = method.output_norm(predicted).cpu()
    return errors


def combined_errors(
    members: list[dict[str, torch.Tensor]],
    ee: torch.Tensor,
    ee_true: torch.Tensor,
    output_norm: Any,
    config: TwoLinkConfig,
    *,
    eta: float,
    share: float,
) -> torch.Tensor:
    """Squared look-ahead errors of a :class:`~smcd_rl.strategies.combination.Combination`, from its members' records.

    The members run on the same observations whatever the weights, so their recorded predictions
    (:func:`lookahead_errors` with ``record``) give the combination's weights after each burn-in
    step (:func:`smcd_rl.strategies.combination.weight_path`) and its weighted look-ahead predictions, what
    running it would give, without running its members again.
    """
    max_t = max(config.burn_in)
    targets = output_norm(ee[:, :max_t].cpu())
    one_step = torch.stack([m["one_step"] for m in members], dim=-1)  # [trials, max T, out, K]
    weights = weight_path(one_step, targets, eta=eta, share=share).exp().to(one_step.dtype)  # [trials, T + 1, K]
    ahead = torch.stack([m["ahead"] for m in members], dim=-1)  # [trials, B, H, out, K]
    errors = torch.empty(ahead.shape[:3])
    for i, t in enumerate(config.burn_in):
        combined = (ahead[:, i] * weights[:, t].unsqueeze(1).unsqueeze(1)).sum(-1)  # [trials, H, out]
        predicted = output_norm.inverse(combined)
        errors[:, i] = (predicted - ee_true[:, t : t + ahead.shape[2]].cpu()).square().sum(-1)
    return errors
