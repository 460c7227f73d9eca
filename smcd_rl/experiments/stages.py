"""One overall progress line for an experiment's stages: which stage of how many, time elapsed and left.

A command declares its plan (stage name -> relative cost) once; each stage then prints one line as
it starts, above the stage's own progress bars::

    two-link [4/9] tune M | 2 min 10 s elapsed, about 3 min left

The time left is the remaining cost at the speed measured so far on this run's own stages, so
it needs one finished stage; stages that finish at once (resumed from a checkpoint or the cache)
do not count towards the speed. A stage the plan does not name still prints its line.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import TextIO

__all__ = ["StagePlan", "duration"]

#: A stage that finished faster than this was resumed, not computed: it says nothing about speed.
RESUMED_SECONDS = 1.0


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
        self.costs = dict(costs or {})
        self.stream = stream
        self.quiet = quiet
        self.done: set[str] = set()
        self._computed_cost = 0.0  # of the finished stages that were computed, not resumed
        self._computed_seconds = 0.0
        self._started = time.perf_counter()

    def plan(self, costs: Mapping[str, float]) -> None:
        """Declare (or replace) the stages still to come: name -> relative cost (e.g. expected seconds)."""
        self.costs = {**{k: v for k, v in self.costs.items() if k in self.done}, **costs}

    def remaining(self) -> float | None:
        """Estimated seconds for the planned stages not yet finished; None before any stage was timed."""
        if self._computed_cost <= 0:
            return None
        left = sum(cost for name, cost in self.costs.items() if name not in self.done)
        return left * self._computed_seconds / self._computed_cost

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Print the stage's line, run the block, and count the stage as done."""
        names = list(self.costs)
        position = f"{names.index(name) + 1}/{len(names)}" if name in self.costs else f"{len(self.done) + 1}"
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
        if seconds >= RESUMED_SECONDS and name in self.costs:
            self._computed_cost += self.costs[name]
            self._computed_seconds += seconds
        self.done.add(name)
