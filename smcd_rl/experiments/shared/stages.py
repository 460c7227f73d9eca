"""One overall progress line for an experiment's stages: which stage of how many, time elapsed and left.

A command declares its plan (stage name -> relative cost) once; each stage then prints one line as
it starts, above the stage's own progress bars::

    two-link [4/9] tune M | 2 min 10 s elapsed, about 3 min left

The time left is the remaining cost at the speeds measured so far on this run's own stages, so
it needs one finished stage. Each kind of stage (the first word of its name: train, tune,
evaluate, ...) has a speed of its own, learned from the stages of that kind already run, since
the planned costs of different kinds are rougher relative to each other than those of one
kind; a kind not run yet takes the speed of all finished stages together. Every stage also costs
:data:`STAGE_OVERHEAD` (starting workers, building a model), so a tiny run whose planned work is
next to nothing does not extrapolate its overhead to hours. Stages that finish at once (resumed
from a checkpoint or the cache) do not count towards a speed. A stage the plan does not name
still prints its line.
"""

from __future__ import annotations

import math
import numbers
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from itertools import pairwise, product
from types import SimpleNamespace
from typing import Any, TextIO

__all__ = ["StagePlan", "duration", "estimate", "mlp_flops", "tuning_cost", "update_cost"]

#: A stage that finished faster than this was resumed, not computed: it says nothing about speed.
RESUMED_SECONDS = 1.0
#: What every stage costs beyond its planned work, in the plan's units (about seconds).
STAGE_OVERHEAD = 0.5


def _checked(costs: Mapping[str, float]) -> dict[str, float]:
    """``costs`` as floats, each finite and ``>= 0``, or a ``ValueError`` naming the first that is not."""
    for name, cost in costs.items():
        if not isinstance(cost, numbers.Real) or isinstance(cost, bool) or not math.isfinite(cost) or cost < 0:
            raise ValueError(f"stage {name!r} has a planned cost of {cost!r}; a cost is a finite number >= 0")
    return {name: float(cost) for name, cost in costs.items()}


def duration(seconds: float) -> str:
    """``seconds`` for people: "45 s", "3 min 5 s", "1 h 2 min".

    Example:
        >>> duration(42.4), duration(185), duration(3725)
        ('42 s', '3 min 5 s', '1 h 2 min')
    """
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"


#: Rough speeds of one CPU thread, the units of :func:`estimate`: seconds of Python and kernel
#: overhead per batched step of a loop (measured on the tiny test runs, where the networks cost
#: nothing), and floating-point operations per second on the small matrix products of these networks.
STEP_SECONDS = 3e-3
FLOPS = 1e10


def estimate(*, steps: float, forwards: float = 0.0, flops: float = 0.0) -> float:
    """A stage's rough seconds: ``steps`` batched steps and ``forwards`` one-sample network forwards of ``flops`` each.

    Only the ratios between a run's stages matter: the time left scales them by the run's speed.

    Example:
        >>> round(estimate(steps=100, forwards=1e6, flops=mlp_flops(2, (512, 512), 2)), 1)
        53.1
    """
    return steps * STEP_SECONDS + forwards * flops / FLOPS


def mlp_flops(inputs: int, hidden: Sequence[int], outputs: int) -> float:
    """Floating-point operations of one sample's forward through an MLP (a multiply-add counts 2).

    Example:
        >>> mlp_flops(2, (4,), 1)
        24.0
    """
    return 2.0 * sum(a * b for a, b in pairwise([inputs, *hidden, outputs]))


def update_cost(variant: str, config: Any) -> tuple[float, float]:
    """One observation's update by adaptation ``variant`` (one of ``VARIANTS``): (steps, forwards per item).

    SMCD runs ``particles`` forwards per item, with about twice a plain step's overhead; GD
    ``gd_steps`` gradient steps over ``gd_window`` transitions (the grid's mean: tuning picks one),
    a backward counted as two forwards and a gradient step as three steps' overhead (measured:
    ``smcd-rl panda`` at hidden 128); the combination ``C`` runs both, plus a forward for none.
    No adaptation costs nothing.

    Example:
        >>> from types import SimpleNamespace
        >>> update_cost("G", SimpleNamespace(gd_steps=(1, 5), gd_window=(5, 10), particles=100))
        (9.0, 67.5)
    """
    if variant.startswith("S"):  # SMCD, and SMCD with a Bayesian readout
        return 2.0, float(config.particles)
    if variant == "L":  # one forward and a readout update of (width + 1)^2
        return 1.0, 1.0
    if variant == "G":
        steps = sum(config.gd_steps) / len(config.gd_steps)
        return 3.0 * steps, 3.0 * steps * sum(config.gd_window) / len(config.gd_window)
    if variant == "C":
        (gd_steps, gd_forwards), (s_steps, s_forwards) = update_cost("G", config), update_cost("S", config)
        return gd_steps + s_steps + 1.0, gd_forwards + s_forwards + 1.0
    return 0.0, 0.0


def tuning_cost(config: Any, *, episodes: int, steps: int, flops: float, options: bool = True) -> float:
    """Rough seconds of :func:`~smcd_rl.experiments.shared.tuning.tune` on ``episodes`` x ``steps`` at ``config``.

    It counts filter runs over all episodes at once: :func:`smcd_rl.tune` calibrates SMCD once
    (the noise's factor and its three shapes, about ``len(calibrate_flips) + 17`` runs) and scores
    eight combinations, the evidence calibration runs as many again, the diagnosis five times,
    and the options (5x particles, predictive mean, a Student-t calibration)
    ``len(calibrate_flips) + 15`` times more; each run is ``steps`` SMCD updates
    (:func:`update_cost`) of every episode. The GD grid traces each (lr, steps, window) with both
    losses, one update per step (its extensions are not foreseen).

    Example:
        >>> from types import SimpleNamespace
        >>> grid = {"gd_lr": (0.1,), "gd_steps": (1,), "gd_window": (5,)}
        >>> config = SimpleNamespace(calibrate_flips=(0.01, 0.03), particles=100, **grid)
        >>> round(tuning_cost(config, episodes=32, steps=20, flops=mlp_flops(2, (64, 64), 2)), 1)
        12.4
    """
    flips = len(config.calibrate_flips)
    runs = 2 * (flips + 17) + 8 + 5 + (flips + 15 if options else 0)
    overhead, forwards = update_cost("S", config)
    smcd = estimate(steps=runs * steps * overhead, forwards=runs * episodes * steps * forwards, flops=flops)
    gd = 0.0
    for _, s, w in product(config.gd_lr, config.gd_steps, config.gd_window):
        one = SimpleNamespace(gd_steps=(s,), gd_window=(w,))
        overhead, forwards = update_cost("G", one)
        gd += 2 * estimate(steps=steps * (1 + overhead), forwards=episodes * steps * (1 + forwards), flops=flops)
    return smcd + gd


class StagePlan:
    """The stages of one run and the line each prints as it starts.

    Example:
        >>> import io
        >>> plan = StagePlan("demo", {"train M": 2.0, "evaluate M+S": 1.0}, stream=io.StringIO())
        >>> with plan.stage("train M"):
        ...     pass
        >>> plan.stream.getvalue()
        'demo [1/2] train M | 0 s elapsed\\n'
    """

    def __init__(
        self,
        command: str,
        costs: Mapping[str, float] | None = None,
        *,
        stream: TextIO | None = None,
        quiet: bool = False,
    ) -> None:
        self.command = command
        self.costs = _checked(costs or {})
        self.stream = stream
        self.quiet = quiet
        self.done: set[str] = set()
        # Per kind of stage: [cost, seconds] of its finished stages that were computed, not resumed.
        self._timed: dict[str, list[float]] = {}
        self._started = time.perf_counter()

    def plan(self, costs: Mapping[str, float]) -> None:
        """Declare (or replace) the stages still to come: name -> relative cost (e.g. expected seconds).

        Raises:
            ValueError: a cost is not a finite number ``>= 0`` (the time left would be nonsense);
                the plan is left as it was.
        """
        self.costs = {**{k: v for k, v in self.costs.items() if k in self.done}, **_checked(costs)}

    def remaining(self) -> float | None:
        """Estimated seconds for the planned stages not yet finished; None before any stage was timed."""
        if not self._timed:
            return None
        pooled = sum(seconds for _, seconds in self._timed.values()) / sum(cost for cost, _ in self._timed.values())
        rates = {kind: seconds / cost for kind, (cost, seconds) in self._timed.items()}
        return sum(
            (cost + STAGE_OVERHEAD) * rates.get(_kind(name), pooled)
            for name, cost in self.costs.items()
            if name not in self.done
        )

    @contextmanager
    def stage(self, name: str, *, members: Sequence[str] = ()) -> Iterator[None]:
        """Print the stage's line, run the block, and count the stage as done.

        ``members``: planned stages that the block runs side by side (in worker processes),
        shown as one line, e.g. ``[5-7/9] evaluate M+G, M+S, M+S(paper) in 2 workers``.

        Example:
            >>> import io
            >>> plan = StagePlan("demo", {"a": 1.0, "b": 1.0, "c": 1.0}, stream=io.StringIO())
            >>> with plan.stage("evaluate b, c in 2 workers", members=["b", "c"]):
            ...     pass
            >>> plan.stream.getvalue(), sorted(plan.done)
            ('demo [2-3/3] evaluate b, c in 2 workers | 0 s elapsed\\n', ['b', 'c'])
        """
        names = list(self.costs)
        stages = list(members) or [name]
        planned = sorted(names.index(s) + 1 for s in stages if s in self.costs)
        if not planned:
            position = f"{len(self.done) + 1}"
        elif len(planned) == 1:
            position = f"{planned[0]}/{len(names)}"
        else:
            position = f"{planned[0]}-{planned[-1]}/{len(names)}"
        elapsed = time.perf_counter() - self._started
        left = self.remaining()
        line = f"{self.command} [{position}] {name} | {duration(elapsed)} elapsed"
        if left is not None:
            line += f", about {duration(left)} left"
        if not self.quiet:
            print(line, file=self.stream or sys.stderr, flush=True)
        started = time.perf_counter()
        yield
        seconds = time.perf_counter() - started
        costed = [s for s in stages if s in self.costs]
        if seconds >= RESUMED_SECONDS and costed:
            # Side-by-side stages are of one kind (a command's workers train, tune or evaluate).
            timed = self._timed.setdefault(_kind(costed[0]), [0.0, 0.0])
            timed[0] += sum(self.costs[s] + STAGE_OVERHEAD for s in costed)
            timed[1] += seconds
        self.done.update(stages)


def _kind(stage: str) -> str:
    """A stage's kind, the first word of its name: ``"tune M"`` is a ``"tune"`` stage."""
    return stage.split(" ", 1)[0]
