"""``smcd-rl task-masks``: which share and mask groups train the best task-mask network T on one family.

The masks sweep measures T's settings on two-link arms; this command measures them on the other
families' experiments, with each experiment's own network, data, trainer and criterion
(:mod:`.families`). For every (share, groups) of the grid, and always the experiment's own
setting, it trains T (:func:`smcd_rl.fit` with ``mask_training="task"``), calibrates SMCD on it
(:func:`smcd_rl.calibrate`, the experiment's particles, flips and criterion) on the first half
of twice the experiment's tuning episodes, and scores SMCD (``T+S``) and the network without
adaptation (``T+N``) on the second half: fresh tasks of the training distribution, never the
experiment's test tasks, so that the choice may set the experiment's default as its own tuning
does. Every grid point's T+S is paired with the experiment's own setting over the same episodes.
Where the lowest mean lies on the grid's edge, the grid extends past it (:func:`beyond_edge`).

Writes ``results.csv`` (per point and method: mean [95 % CI]), ``trials.csv`` (every episode's
score), ``comparisons.csv``, ``results.json``, ``task-masks.png`` and ``report.md``.

Example:
    >>> from smcd_rl.cli import make_config
    >>> make_config("task-masks", {"family": "panda", "groups": (8,)}).points()
    [(1.0, 16), (0.5, 8), (1.0, 8)]
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

import smcd_rl
from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.stats import cell_statistics, paired_comparisons
from smcd_rl.experiments.task_masks.config import TaskMasksConfig
from smcd_rl.experiments.task_masks.families import Family, load
from smcd_rl.experiments.task_masks.report import label, plot, tables
from smcd_rl.tuning.criteria import Lookahead
from smcd_rl.tuning.diagnostics import trace

__all__ = ["TaskMasksConfig", "run", "episode_scores", "beyond_edge"]

#: Relative stage costs (seconds on 2 CPU cores, one torch thread, of one grid point's training and scoring).
COSTS = {"load": 10.0, "train": 40.0, "score": 10.0}


def episode_scores(model: smcd_rl.AdaptiveModel, episodes: TensorDictBase, strategy: Any, family: Family) -> Tensor:
    """Each episode's error by the family's criterion ``[E]``: one-step RMSE, or the ``horizon``-step look-ahead's."""
    if family.criterion != "lookahead":
        return torch.tensor(trace(model, episodes, strategy).per_episode_rmse, dtype=torch.float64)
    assert family.horizon is not None
    ahead = trace(model, episodes, strategy, horizon=family.horizon).ahead
    if ahead is None:  # the strategy refused a step
        return torch.full((episodes.shape[0],), torch.inf, dtype=torch.float64)
    observed = Lookahead(model, episodes, family.horizon).observed
    return (ahead.double() - observed.double()).square().mean((1, 2, 3)).sqrt().cpu()


def beyond_edge(means: Mapping[tuple[float, int], float], width: int) -> tuple[float, int] | None:
    """The next point past the grid's edge, or ``None``: as tune extends GD's grid while its best lies on an edge.

    Where the lowest mean lies at the most (fewest) groups measured at its share, the next point
    doubles (halves) them at that share, if that still divides the layer's ``width`` and was not measured.

    Example:
        >>> beyond_edge({(1.0, 8): 0.3, (1.0, 16): 0.2}, width=256)
        (1.0, 32)
        >>> beyond_edge({(1.0, 8): 0.1, (1.0, 16): 0.2}, width=256), beyond_edge({(1.0, 8): 0.3, (1.0, 16): 0.2}, 16)
        ((1.0, 4), None)
    """
    share, groups = min(means, key=means.__getitem__)
    measured = sorted(g for s, g in means if s == share)
    if groups == measured[-1] and groups * 2 <= width and width % (groups * 2) == 0:
        return share, groups * 2
    if groups == measured[0] and groups % 2 == 0 and len(measured) > 1:
        return share, groups // 2
    return None


def run(config: TaskMasksConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the grid on ``config.family`` and write its files; returns the JSON payload."""
    with Experiment(config, progress=progress) as ex:
        points = config.points()
        ex.plan({"load": COSTS["load"], **_stages(points)})
        with ex.stage("load"):
            family = load(config.family, seed=config.seed, device=ex.device, generator=ex.generator)
        half = family.episodes.shape[0] // 2
        calibrate_on, scored_on = family.episodes[:half], family.episodes[half:]
        scores: dict[str, Tensor] = {}
        settings: dict[str, dict[str, Any]] = {}
        losses: dict[str, list[float]] = {}

        def measure(point: tuple[float, int]) -> None:
            name = label(point)
            model = family.build(point[1])
            losses[name] = ex.train(name, family.trainer, model, family.data, **family.fit_settings(point[0]))
            with ex.stage(f"score {name}"):
                calibration = smcd_rl.calibrate(
                    model,
                    calibrate_on,
                    base=smcd_rl.SMCD(num_particles=family.particles),
                    flip_probs=family.flips,
                    criterion=family.criterion,  # type: ignore[arg-type]
                    horizon=family.horizon,
                    seed=config.seed,
                    progress=False,
                )
                smcd = smcd_rl.SMCD(
                    **calibration.strategy.config(),
                    generator=torch.Generator(device=ex.device).manual_seed(config.seed + 11),
                )
                scores[f"{name} T+S"] = episode_scores(model, scored_on, smcd, family)
                scores[f"{name} T+N"] = episode_scores(model, scored_on, smcd_rl.NoAdaptation(), family)
                settings[name] = {"noise_std": calibration.noise_std, "flip_prob": calibration.flip_prob}

        for point in points:
            measure(point)
        extended: list[tuple[float, int]] = []
        means = lambda: {p: float(scores[f"{label(p)} T+S"].mean()) for p in points}  # noqa: E731
        while (beyond := beyond_edge(means(), family.width)) is not None:
            ex.plan(_stages([beyond]))
            measure(beyond)
            points.append(beyond)
            extended.append(beyond)

        reference = f"{label(family.current)} T+S"
        # Rows only: each point is paired with the experiment's setting below, not with every other point.
        rows, _ = cell_statistics(
            {(config.family,): scores}, cell=("family",), baseline=None, adaptive=(), metric="error", seed=config.seed
        )
        comparisons = [
            {"family": config.family, **vars(c)}
            for p in points
            if p != family.current
            for c in paired_comparisons(
                {reference: scores[reference], f"{label(p)} T+S": scores[f"{label(p)} T+S"]},
                baseline=reference,
                adaptive=[f"{label(p)} T+S"],
                seed=config.seed,
            )
        ]
        best = min(points, key=lambda p: float(scores[f"{label(p)} T+S"].mean()))
        trials = [
            {"family": config.family, "method": method, "episode": e, "error": float(v)}
            for method, values in scores.items()
            for e, v in enumerate(values)
        ]
        summary = {
            "family": config.family,
            "experiment": family.experiment,
            "task": family.task,
            "criterion": family.criterion if family.horizon is None else f"{family.horizon}-step look-ahead",
            "current": list(family.current),
            "best": list(best),
            "calibrated_on": half,
            "scored_on": scored_on.shape[0],
            "smcd": settings,
            "extended": [list(p) for p in extended],
        }
        return ex.write(
            experiment=f"task-mask network settings on the {config.family} family ({family.experiment})",
            tables=tables(rows, comparisons, summary, points),
            rows=rows,
            trials=trials,
            comparisons=comparisons,
            payload={"summary": summary, "train_loss": losses},
            plots={"task-masks.png": lambda path: plot(scores, points, summary, path)},
        )


def _stages(points: list[tuple[float, int]]) -> dict[str, float]:
    """The planned stages of ``points``: each one's training and scoring."""
    return {f"{kind} {label(p)}": COSTS[kind] for p in points for kind in ("train", "score")}
