"""The regimes as one plan of steps per family, and one method's errors over it.

For ``count`` test tasks A (and a second task B each) a :class:`Plan` holds, in order:

1. **T = t**: a reset, then ``max(burn_in)`` observations of A; after the t-th, the error on A.
2. **switch: new task** / **switch: back**: right after, ``switch_steps`` observations of B (the
   error on B), then ``switch_steps`` of A again (the error on A): what a method carries across a
   change of task and whether it comes back.
3. **outlier**: a reset, ``outlier_burn_in`` observations of A with the middle one's target moved
   by ``outlier_scale`` times the unadapted model's held-out residual; the error on A.
4. **every n-th** (families whose observations form a trajectory): a reset, ``every_steps`` steps
   of A of which every n-th is observed; the error on A at the end.

Every error is the RMSE over ``eval_points`` noise-free points of the task as it is at the next
stream step (new joint configurations of the arm; fresh states of the pendulum), predicted
without further observations.

Example:
    >>> import torch
    >>> from smcd_rl.experiments.regimes.config import SEQUENTIAL, RegimesConfig
    >>> config = RegimesConfig(trials=3, burn_in=(1, 2), switch_steps=2, outlier_burn_in=2, every_steps=4, every=2)
    >>> plan = make_plan("two-link", config, residual=torch.tensor([0.1, 0.1]))
    >>> [s.regime for s in plan.steps if s.kind == "score"]
    ['T=1', 'T=2', 'switch: new task', 'switch: back', 'outlier']
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

import smcd_rl
from smcd_rl.experiments.regimes.config import SEQUENTIAL, RegimesConfig
from smcd_rl.experiments.regimes.families import FAMILIES, TEST_SEED

__all__ = ["Step", "Plan", "make_plan", "regime_errors"]


@dataclass
class Step:
    """``reset``, ``observe`` one transition per task (``td [count]``) or ``score`` on ``td [count, points]``."""

    kind: str
    regime: str = ""
    td: TensorDictBase | None = None


@dataclass
class Plan:
    """One family's regimes for ``count`` test tasks as a list of steps, the same for every method."""

    family: str
    count: int
    steps: list[Step] = field(default_factory=list)

    def reset(self) -> None:
        self.steps.append(Step("reset"))

    def observe(self, td: TensorDictBase) -> None:
        self.steps += [Step("observe", td=td[:, t]) for t in range(td.batch_size[1])]

    def score(self, regime: str, td: TensorDictBase) -> None:
        self.steps.append(Step("score", regime, td))


def make_plan(family_name: str, config: RegimesConfig, *, residual: Tensor) -> Plan:
    """The regimes of ``config.trials`` test tasks of a family, drawn from the family's test seed.

    Args:
        family_name: a key of :data:`~smcd_rl.experiments.regimes.families.FAMILIES`.
        config: the run's settings.
        residual: per output dimension, the RMS one-step error of the unadapted model on the
            tuning episodes (target units): the outlier's scale.
    """
    family = FAMILIES[family_name]
    generator = torch.Generator().manual_seed(config.seed + TEST_SEED + sorted(FAMILIES).index(family_name))
    count, points = config.trials, config.eval_points
    a, b = family.sample(count, generator), family.sample(count, generator)
    plan = Plan(family_name, count)

    longest = max(config.burn_in)
    stream = family.observed(a, longest, 0, generator, config)
    plan.reset()
    for t in range(1, longest + 1):
        plan.observe(stream[:, t - 1 : t])
        if t in config.burn_in:
            plan.score(f"T={t}", family.truth(a, points, t, generator))
    switch = config.switch_steps
    plan.observe(family.observed(b, switch, longest, generator, config))
    plan.score("switch: new task", family.truth(b, points, longest + switch, generator))
    plan.observe(family.observed(a, switch, longest + switch, generator, config))
    plan.score("switch: back", family.truth(a, points, longest + 2 * switch, generator))

    steps = config.outlier_burn_in
    corrupted = family.observed(a, steps, 0, generator, config).clone()
    sign = torch.randint(0, 2, (count, residual.numel()), generator=generator) * 2 - 1
    target = corrupted.get(family.target)
    target[:, steps // 2] += config.outlier_scale * residual * sign
    plan.reset()
    plan.observe(corrupted)
    plan.score("outlier", family.truth(a, points, steps, generator))

    if family_name in SEQUENTIAL:
        path = family.observed(a, config.every_steps, 0, generator, config)
        plan.reset()
        plan.observe(path[:, :: config.every])
        plan.score("every n-th", family.truth(a, points, config.every_steps, generator))
    return plan


@torch.no_grad()
def regime_errors(model: smcd_rl.AdaptiveModel, plan: Plan, target: Any) -> dict[str, Any]:
    """Run ``model`` (with its strategy) over the plan: per regime, the per-task RMSE ``[count]``.

    An observation the strategy refuses (gradient descent whose weights would become inf or
    NaN) leaves its state as it was; the count of refusals is returned under ``"refused"``.
    """
    errors: dict[str, Tensor] = {}
    refused = 0
    for step in plan.steps:
        if step.kind == "reset":
            model.reset(batch_shape=(plan.count,))
        elif step.kind == "observe":
            assert step.td is not None
            try:
                model.observe(step.td)
            except ValueError:
                refused += 1
        else:
            assert step.td is not None
            truth = step.td
            predicted = model(truth.exclude(target))[target]
            errors[step.regime] = (predicted - truth.get(target)).square().mean((1, 2)).sqrt().cpu()
    return {"errors": errors, "refused": refused}
