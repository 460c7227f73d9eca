"""Running what a sweep has not finished yet as Ray tasks, and storing each result as it arrives.

Work is shared without changing any result: grid points that differ only in ``epochs`` are one
training run (:func:`smcd_rl.fit` is deterministic per (seed, epoch) with no schedule, so a shorter
run's losses are a prefix of a longer run's), and the filter studies (smcd, masks) train each model
once and evaluate every filter setting, and the reference methods, as separate Ray tasks on it.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from tqdm.auto import tqdm

from smcd_rl.digests import content_digest
from smcd_rl.experiments.shared.orphans import reaped
from smcd_rl.experiments.shared.result_store import ResultStore
from smcd_rl.experiments.sweep.config import FILTER_STUDIES
from smcd_rl.experiments.sweep.grid import EVALUATION_KEYS
from smcd_rl.experiments.sweep.trials import REFERENCES, arm_means, evaluate, timed_evaluate, train

if TYPE_CHECKING:
    from smcd_rl.experiments.sweep.config import SweepConfig

__all__ = ["SweepWork", "ray_session"]

#: What a reference method's result depends on besides the trained model (its filter settings do not).
_REFERENCE_KEYS = ("arms", "chunk", "burn_in", "horizons")
_GD_KEYS = ("gd_lr", "gd_steps", "gd_window")


@contextlib.contextmanager
def ray_session(config: SweepConfig) -> Iterator[Any]:
    """Ray, started locally (or connected to ``--address``) for the block; shut down after if we started it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError(
            'smcd-rl sweep runs its trials on Ray, which is not installed; in a checkout install it with: pip install -e ".[ray]" (or bash bootstrap.sh, which installs every extra)'
        ) from err
    started = not ray.is_initialized()
    with reaped() as watch:  # a local Ray's helpers die with this process, also of kill -9
        if started:
            if config.address:
                ray.init(address=config.address, logging_level=logging.WARNING)
            else:
                # "local": always a fresh instance, never a cluster that `ray start` once left behind.
                ray.init(
                    address="local",
                    num_cpus=config.cpus or None,
                    include_dashboard=False,
                    logging_level=logging.WARNING,
                )
                watch()
        try:
            available = ray.cluster_resources().get("CPU", 0)
            if config.cpus_per_trial > available:
                raise ValueError(
                    f"--cpus-per-trial {config.cpus_per_trial} exceeds the Ray cluster's {available:g} CPUs; "
                    "no trial could ever be scheduled"
                )
            yield ray
        finally:
            if started:
                ray.shutdown()


class SweepWork:
    """The sweep's bookkeeping: grid points grouped by training run, and what the store already holds.

    Every result is stored under the configuration that determines it (a grid point; a training
    run, i.e. a point without its evaluation settings; a reference method on a training run), so
    a changed setting or dataset never reuses a stale result, and growing a grid reuses every
    finished point.

    Attributes:
        results: grid point index -> ``{"metrics": {name: mean}}``, with ``"arms"`` (per-arm
            scores) in the filter studies.
        references: ``(training run, method)`` -> ``{"metrics", "arms"}`` of :data:`REFERENCES`.
        posteriors: training run -> its training posteriors per epoch (masks study).
        reused: grid points finished before this run.
    """

    def __init__(self, config: SweepConfig, points: list[dict[str, Any]], store: ResultStore) -> None:
        self.config, self.points, self.store = config, points, store
        self.filtering = config.study in FILTER_STUDIES
        self.masks = config.study == "masks"
        self.groups: dict[str, list[int]] = {}  # training run's digest -> its grid points
        self.run_configs: dict[str, dict[str, Any]] = {}
        for index, point in enumerate(points):
            run_config = {k: v for k, v in point.items() if k not in EVALUATION_KEYS[config.study]}
            key = content_digest(run_config)
            self.groups.setdefault(key, []).append(index)
            self.run_configs[key] = run_config
        self.results: dict[int, dict[str, Any]] = {}
        for index, point in enumerate(points):
            if (done := store.get("point", point)) is not None:
                self.results[index] = done
        self.reused = len(self.results)
        self.posteriors: dict[str, list[dict[str, float]]] = {}
        for key in self.groups if self.masks else ():
            if (done := store.get("train", self.run_configs[key])) is not None:
                self.posteriors[key] = done["posteriors"]
        self.references: dict[tuple[str, str], dict[str, Any]] = {}
        for key in self.groups if self.filtering else ():
            for method in REFERENCES:
                if (done := store.get("reference", self.reference_config(key, method))) is not None:
                    self.references[key, method] = done
        if not self.filtering:  # new epoch counts of a stored training run are read off its losses, no Ray needed
            for key in self.groups:
                done = store.get("train", self.run_configs[key])
                if done is not None and len(done["losses"]) >= self._epochs(key):
                    self._read_losses(key, done)
        self.train_seconds: list[float] = []
        self.evaluate_seconds: list[float] = []

    @property
    def finished(self) -> bool:
        """Whether every grid point (and, in the filter studies, every reference; masks: posteriors) has its result."""
        return not any(self._missing_points(k) or self._missing_references(k) for k in self.groups)

    def reference_config(self, key: str, method: str) -> dict[str, Any]:
        """What a reference method's result on training run ``key`` depends on."""
        point = self.points[self.groups[key][0]]
        config = {**self.run_configs[key], **{k: point[k] for k in _REFERENCE_KEYS}, "method": method}
        if method == "M+G":
            config |= {k: getattr(self.config, k) for k in _GD_KEYS}
        return config

    def run(self, ray: Any, *, progress: bool) -> None:
        """Submit the missing training runs and evaluations at once; store each result as it finishes."""
        resources = {"num_cpus": self.config.cpus_per_trial, "num_gpus": self.config.gpus_per_trial}
        remote_train = ray.remote(train).options(**resources)
        remote_evaluate = ray.remote(timed_evaluate).options(**resources)
        pending: dict[Any, tuple[str, Any]] = {}  # object ref -> (what it computes, which)
        for key in self.groups:
            missing = self._missing_points(key)
            references = self._missing_references(key)
            if not missing and not references:
                continue
            epochs = self._epochs(key)
            done = self.store.get("train", self.run_configs[key])
            if self.filtering and done is not None and len(done["losses"]) >= epochs:  # evaluate on the stored model
                source = ray.put(done)
            else:
                source = remote_train.remote({**self.run_configs[key], "epochs": epochs})
                pending[source] = ("train", key)
            if (
                self.filtering
            ):  # each filter setting and reference is its own task on the (possibly still training) model
                for index in missing:
                    pending[remote_evaluate.remote(self.points[index], source)] = ("point", index)
                for method in references:
                    reference = self.reference_config(key, method)
                    pending[remote_evaluate.remote(reference, source)] = ("reference", (key, method))

        with tqdm(total=len(pending), desc=f"sweep {self.config.study}", unit="task", disable=not progress) as bar:
            bar.set_postfix(cached=self.reused)
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    kind, what = pending.pop(ref)
                    if kind == "train":
                        self._store_run(what, ray.get(ref))
                    else:
                        arms, seconds = ray.get(ref)
                        self.evaluate_seconds.append(seconds)
                        record = {"metrics": arm_means(arms), "arms": arms}
                        if kind == "point":
                            self.results[what] = record
                            self.store.put("point", self.points[what], record)
                        else:
                            self.references[what] = record
                            self.store.put("reference", self.reference_config(*what), record)
                    bar.update()

    def _missing_points(self, key: str) -> list[int]:
        """The training run's grid points without a result; all of them while its posteriors are missing."""
        if self.masks and key not in self.posteriors:
            return list(self.groups[key])
        return [i for i in self.groups[key] if i not in self.results]

    def _missing_references(self, key: str) -> list[str]:
        return [m for m in REFERENCES if (key, m) not in self.references] if self.filtering else []

    def _epochs(self, key: str) -> int:
        """Epochs of a training run: the most any of its grid points needs."""
        return max(int(self.points[i]["epochs"]) for i in self.groups[key])

    def _store_run(self, key: str, result: dict[str, Any]) -> None:
        self.train_seconds.append(result["seconds"])
        self.store.put("train", self.run_configs[key], result)  # with the filter study's model, for a rerun
        if self.masks:
            self.posteriors[key] = result["posteriors"]
        if not self.filtering:
            self._read_losses(key, result)

    def _read_losses(self, key: str, run: Mapping[str, Any]) -> None:
        for index in self.groups[key]:
            if index not in self.results:
                self.results[index] = {"metrics": evaluate(self.points[index], run)}
                self.store.put("point", self.points[index], self.results[index])
