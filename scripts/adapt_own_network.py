"""Adapt networks trained by other libraries' code: a torchrl ``MLP`` and an mbrl-lib ``GaussianMLP`` ensemble.

1. A torchrl ``MLP`` (2 x 128, ReLU, dropout 0.1) learns the two-link arms' forward kinematics
   (joint angles to end effector, in metres) with a plain Adam loop on motor babbling of 100 arms
   whose link lengths differ, the way a torchrl user trains a world model.
   ``smcd_rl.adaptive_model_from`` wraps it with its weights, ``smcd_rl.tune`` chooses every
   strategy on 20 held-out arms, and each strategy then predicts 50 fresh test arms after 10
   observations of each: its RMSE on 20 noise-free points per arm.
2. An mbrl-lib ``GaussianMLP`` ensemble (5 members, 3 x 200, mbrl-lib's defaults but the depth)
   learns the pendulum family's dynamics with mbrl-lib's own ``ModelTrainer``, as PETS trains it,
   on motor babbling of 100 poles whose mass and length differ.
   ``smcd_rl.integrations.mbrl_models.dynamics_models_from_mbrl`` wraps its members,
   ``smcd_rl.tune`` chooses the strategies on 20 held-out poles (on member 0; every member then
   adapts with the choice), and the adapted ensemble's mean predicts 50 fresh poles' next 20 steps
   after 10 observations of each. Runs where mbrl-lib is importable (``bash
   scripts/install_mbrl_lib.sh``); otherwise the report says it was skipped.

Each strategy's difference from the unadapted network is paired over the test tasks (mean and 95 %
bootstrap interval). Written as a Markdown report (``--out``) and printed, with the machine.

    python scripts/adapt_own_network.py
    python scripts/adapt_own_network.py --out docs/benchmarks/own-network.md
    python scripts/adapt_own_network.py --tiny   # a smoke run: 2 epochs, few tasks
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import MLP

import smcd_rl
from smcd_rl.envs.pendulum_family import pendulum_transitions
from smcd_rl.envs.two_link_arm import motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.experiments.shared.outputs import Transcript
from smcd_rl.experiments.shared.stats import mean_ci

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
    """Mean [95 % bootstrap interval] of differences paired over the test tasks."""
    estimate = mean_ci(differences)
    return f"{estimate.mean:+.4f} [{estimate.low:+.4f}, {estimate.high:+.4f}]"


def table(say: Callable[..., None], caption: str, unit: str, errors: dict[str, torch.Tensor]) -> None:
    """Each strategy's RMSE over the test tasks and its difference from no adaptation's, paired."""
    say(caption)
    say()
    say(f"| strategy | RMSE ({unit}) | minus no adaptation [95% CI] |")
    say("|---|---|---|")
    for kind, error in errors.items():
        versus = "" if kind == "none" else paired(error - errors["none"])
        say(f"| {LABELS[kind]} | {float(error.mean()):.4f} | {versus} |")
    say()


def torchrl_arms(args: argparse.Namespace, generator: torch.Generator) -> tuple[int, dict[str, torch.Tensor]]:
    """Part 1: a torchrl MLP trained by a plain Adam loop on the arms; each strategy's error per test arm."""
    epochs, test_arms, particles = (2, 6, 50) if args.tiny else (40, 50, 1000)
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
    return test_arms, errors


def mbrl_pendulum(args: argparse.Namespace, generator: torch.Generator) -> tuple[int, dict[str, torch.Tensor]]:
    """Part 2: an mbrl-lib GaussianMLP ensemble trained by mbrl-lib's ModelTrainer on the pendulum family."""
    import mbrl.models
    import mbrl.util
    import mbrl.util.common

    from smcd_rl.integrations.mbrl_models import dynamics_models_from_mbrl

    members, epochs, test_poles = (2, 2, 6) if args.tiny else (5, 50, 50)
    data = pendulum_transitions(100, 1, 10 if args.tiny else 100, measurement_noise=0.01, generator=generator)
    flat = data.reshape(-1)
    rows = flat.shape[0]
    buffer = mbrl.util.ReplayBuffer(rows, (3,), (1,), rng=np.random.default_rng(args.seed))
    never = np.zeros(rows, dtype=bool)
    buffer.add_batch(
        flat["observation"].numpy(),
        flat["action"].numpy(),
        flat["next", "observation"].numpy(),
        np.zeros(rows, dtype=np.float32),  # the reward comes from a reward function, not the model
        never,
        never,
    )
    gaussian = mbrl.models.GaussianMLP(4, 3, "cpu", num_layers=3, ensemble_size=members, hid_size=200)
    wrapper = mbrl.models.OneDTransitionRewardModel(
        gaussian, target_is_delta=True, normalize=True, learned_rewards=False
    )
    wrapper.update_normalizer(buffer.get_all())
    train_set, validation = mbrl.util.common.get_basic_buffer_iterators(buffer, 256, 0.1, ensemble_size=members)
    mbrl.models.ModelTrainer(wrapper, optim_lr=1e-3).train(train_set, validation, num_epochs=epochs, silent=True)

    def poles(count: int, steps: int) -> TensorDict:
        return pendulum_transitions(count, 1, steps, measurement_noise=0.01, generator=generator)[:, 0]

    held_out, test = poles(20, 30), poles(test_poles, 30)
    strategies = ["none", "gradient_descent", "last_layer", "combination"]
    result = smcd_rl.tune(dynamics_models_from_mbrl(wrapper)[0], held_out, strategies=strategies, progress=False)
    errors = {}
    for kind in result.best_of:
        ensemble = dynamics_models_from_mbrl(wrapper, adaptation=result.strategy(kind))
        predicted = []
        for model in ensemble:
            model.reset(batch_shape=(test_poles,))
            for t in range(10):
                model.observe(test[:, t])
            with torch.no_grad():
                steps = [model.step(test["observation"][:, t], test["action"][:, t]) for t in range(10, 30)]
            predicted.append(torch.stack(steps, 1))
        mean = torch.stack(predicted).mean(0)  # the ensemble's mean, as mbrl-lib's expectation propagation
        errors[kind] = (mean - test["next", "observation"][:, 10:]).square().sum(-1).mean(-1).sqrt()
    return test_poles, errors


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
    transcript = Transcript("python scripts/adapt_own_network.py")
    say = transcript.say

    count, errors = torchrl_arms(args, generator)
    caption = f"A torchrl `MLP` on the two-link arms: RMSE (m) on {count} test arms after 10 observations, tuned by `smcd_rl.tune`:"
    table(say, caption, "m", errors)
    try:
        import mbrl.models  # noqa: F401
    except Exception as err:  # hydra-core 1.0.3 (mbrl's own pin) fails on Python 3.11 with a ValueError
        say(f"The mbrl-lib part was skipped: mbrl-lib is not importable ({type(err).__name__}); install it with")
        say("`bash scripts/install_mbrl_lib.sh`.")
    else:
        count, errors = mbrl_pendulum(args, generator)
        caption = (
            f"An mbrl-lib `GaussianMLP` ensemble trained by mbrl-lib's `ModelTrainer` on the pendulum family: RMSE "
            f"(observation units) of the ensemble's mean one-step prediction on {count} test poles after 10 "
            "observations, tuned by `smcd_rl.tune`:"
        )
        table(say, caption, "observation units", errors)
    transcript.write(args.out)


if __name__ == "__main__":
    main()
