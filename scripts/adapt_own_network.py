"""Adapt a network trained by your own code: a torchrl ``MLP`` on the two-link arm family.

A torchrl ``MLP`` (2 x 128, ReLU, dropout 0.1) learns the arms' forward kinematics (joint angles
to end effector, in metres) with a plain Adam loop on motor babbling of 100 arms whose link
lengths differ, the way a torchrl user trains a world model. ``smcd_rl.adaptive_model_from``
wraps it with its weights, ``smcd_rl.tune`` chooses every strategy on 20 held-out arms, and
each strategy then predicts 50 fresh test arms after 10 observations of each: its RMSE on 20
noise-free points per arm, and its difference from the unadapted network paired over the arms
(mean and 95 % interval). Written as a Markdown report (``--out``) and printed, with the machine.

    python scripts/adapt_own_network.py
    python scripts/adapt_own_network.py --out docs/benchmarks/own-network.md
    python scripts/adapt_own_network.py --tiny   # a smoke run: 2 epochs, few arms
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

import smcd_rl
from smcd_rl.envs.two_link_arm import motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.experiments.shared.outputs import Transcript

#: What each strategy is called in the report.
LABELS = {
    "none": "no adaptation",
    "gradient_descent": "gradient descent",
    "smcd": "SMCD",
    "last_layer": "Bayesian last layer",
    "smcd_last_layer": "SMCD with a Bayesian readout",
    "combination": "combination",
}


def arms(lengths: torch.Tensor, steps: int, noise: float, generator: torch.Generator) -> TensorDict:
    """Arms of these link lengths, ``steps`` observations each at random joint angles: ``q`` and ``ee``."""
    q = (torch.rand(lengths.shape[0], steps, 2, generator=generator) * 2 - 1) * math.pi
    ee = two_link_fk(q, lengths.unsqueeze(1))
    return TensorDict(
        {"q": q, "ee": ee + noise * torch.randn(ee.shape, generator=generator)}, [lengths.shape[0], steps]
    )


def train(module: nn.Module, data: TensorDict, epochs: int, generator: torch.Generator) -> None:
    """A plain supervised loop, as one trains a torchrl world model: Adam on the squared error."""
    q, ee = data["q"].reshape(-1, 2), data["ee"].reshape(-1, 2)
    optimiser = torch.optim.Adam(module.parameters(), lr=1e-3)
    module.train()
    for _ in range(epochs):
        for batch in torch.randperm(q.shape[0], generator=generator).split(128):
            optimiser.zero_grad()
            nn.functional.mse_loss(module(q[batch]), ee[batch]).backward()
            optimiser.step()
    module.eval()


def paired(differences: torch.Tensor) -> str:
    """Mean [95 % interval] of paired differences (normal approximation over the arms)."""
    mean = float(differences.mean())
    half = 1.96 * float(differences.std()) / math.sqrt(differences.numel())
    return f"{mean:+.4f} [{mean - half:+.4f}, {mean + half:+.4f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the data, the network and tune")
    parser.add_argument("--out", type=Path, default=None, help="also write the report here (Markdown)")
    parser.add_argument("--tiny", action="store_true", help="a smoke run: 2 epochs, few arms, few particles")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    epochs, test_arms, particles = (2, 6, 50) if args.tiny else (40, 50, 1000)
    transcript = Transcript("python scripts/adapt_own_network.py")
    say = transcript.say

    data = motor_babbling(100, 10 if args.tiny else 50, 10, measurement_noise=0.01, generator=generator)
    module = MLP(in_features=2, out_features=2, num_cells=[128, 128], dropout=0.1, activation_class=nn.ReLU)
    train(module, data.select("q", "ee"), epochs, generator)

    model = smcd_rl.adaptive_model_from(module, in_keys=["q"], out_key="ee")
    held_out = arms(sample_link_lengths((20,), generator=generator), 30, 0.01, generator)
    result = smcd_rl.tune(model, held_out, num_particles=particles, seed=args.seed, progress=False)
    lengths = sample_link_lengths((test_arms,), generator=generator)  # fresh arms: observed, then scored
    test, truth = arms(lengths, 10, 0.01, generator), arms(lengths, 20, 0.0, generator)

    errors = {}
    for kind in result.best_of:
        adaptive = model.with_adaptation(result.strategy(kind))
        adaptive.reset(batch_shape=(test_arms,))
        for t in range(test.shape[1]):
            adaptive.observe(test[:, t])
        with torch.no_grad():
            predicted = torch.stack([adaptive(truth[:, i].clone())["ee"] for i in range(truth.shape[1])], 1)
        errors[kind] = (predicted - truth["ee"]).square().sum(-1).mean(-1).sqrt()
    say(f"RMSE (m) of each strategy on {test_arms} test arms after 10 observations, tuned by `smcd_rl.tune`:")
    say()
    say("| strategy | RMSE (m) | minus no adaptation [95% CI] |")
    say("|---|---|---|")
    for kind, error in errors.items():
        versus = "" if kind == "none" else paired(error - errors["none"])
        say(f"| {LABELS[kind]} | {float(error.mean()):.4f} | {versus} |")
    transcript.write(args.out)


if __name__ == "__main__":
    main()
