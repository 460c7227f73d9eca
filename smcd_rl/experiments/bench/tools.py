"""What the ``smcd-rl bench`` commands share: their config base, the random network they time, their output.

A benchmark is not a method comparison: it times contenders side by side and reports their
ratios, so it runs inside :class:`~smcd_rl.experiments.shared.harness.Experiment` (validated options,
threads, device, out dir, seed) but writes its own ``results.json``, ``results.csv`` and ``report.md`` and
prints either its report or, with ``--json``, the JSON alone for tools (which the harness's
``write``, always printing tables, cannot do).

Example:
    >>> import torch, smcd_rl
    >>> net = smcd_rl.MaskedMLP(3, 2, hidden=(16,))
    >>> scale_to_unit_spread(net, torch.Generator().manual_seed(0))
    >>> masks = torch.rand(256, net.mask_dim) < net.keep_prob
    >>> 0.8 < float(net(torch.randn(256, 3), mask=masks).std()) < 1.25
    True
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

import smcd_rl
from smcd_rl.experiments.bench.config import BenchConfig
from smcd_rl.experiments.shared.outputs import write_csv, write_json
from smcd_rl.files import write_text

__all__ = ["BenchConfig", "scale_to_unit_spread", "machine_line", "publish"]


def scale_to_unit_spread(net: smcd_rl.MaskedMLP, generator: torch.Generator, probes: int = 256) -> None:
    """Scale the output layer so that predictions under random masks have unit std, as after training.

    A network trained on normalised targets predicts with spread about 1, the scale in which the
    benchmarks' likelihood noise is given; random weights alone predict with a much smaller one.
    Draws ``probes`` inputs and masks from ``generator`` (CPU), in that order.
    """
    device = next(net.parameters()).device
    last = net.linears[-1]
    assert isinstance(last, torch.nn.Linear)
    with torch.no_grad():
        probe = torch.randn(probes, net.in_features, generator=generator).to(device)
        masks = (torch.rand(probes, net.mask_dim, generator=generator) < net.keep_prob).to(device)
        scale = 1.0 / net(probe, mask=masks).std()
        last.weight.mul_(scale)
        last.bias.mul_(scale)


def machine_line(payload: Mapping[str, Any]) -> str:
    """``machine: k=v, ..., device=...``: the first line of every benchmark report."""
    return "machine: " + ", ".join(f"{k}={v}" for k, v in payload["machine"].items()) + f", device={payload['device']}"


def publish(
    out: Path, payload: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], report: str, *, as_json: bool
) -> None:
    """Write ``results.json`` (the payload), ``results.csv`` (the rows) and ``report.md`` (the report, which a
    docs page includes as it is); print the report, or the JSON alone."""
    write_json(out / "results.json", payload)
    write_csv(out / "results.csv", rows)
    write_text(out / "report.md", report.rstrip("\n") + "\n", what="report")
    print(json.dumps(payload, indent=2, default=str) if as_json else report)
