"""The experiment harness: what every ``smcd-rl`` experiment command shares, so a figure's module holds only its figure.

An experiment module declares a config (a dataclass deriving :class:`ExperimentConfig`, whose
field help is the command's ``--help``) and a ``run(config)`` that reads top to bottom::

    with Experiment(config) as ex:                      # validate, threads, device, out dir, seed
        data = make_data(ex.generator)
        losses = ex.train("train", smcd_rl.fit, model, data, epochs=config.epochs, ...)  # or resume
        done = ex.evaluate(methods, evaluate_one, content={"model": model_digest(model)})
        rows, comparisons = cell_statistics(scores_of(done), baseline="M+N", ...)  # 95 % CIs, paired verdicts
        ex.write(experiment=..., tables=..., rows=..., trials=..., comparisons=..., plots={"fig.png": draw})

Training checkpoints are named by everything that determines the trained model (its architecture
and initial weights, the trainer and all its settings, a digest of the data), and the per-method
result cache is keyed by content (the evaluated models' digests, the settings and the package's
code), never by a file name, so no rerun ever picks up a stale result.
"""

from __future__ import annotations

import contextlib
import functools
import json
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, TypeVar

import torch
from tqdm.auto import tqdm

from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.shared.config import OUTPUT_ONLY, ExperimentConfig, config_dict, setting
from smcd_rl.experiments.shared.outputs import settings_fingerprint, write_csv, write_json
from smcd_rl.experiments.shared.report import write_report
from smcd_rl.experiments.shared.result_store import ResultStore
from smcd_rl.experiments.shared.run_lock import lock_out, release
from smcd_rl.experiments.shared.runtime import machine_info, resolve_device, seed_everything, torch_threads
from smcd_rl.experiments.shared.stages import StagePlan, duration
from smcd_rl.experiments.shared.workers import auto_workers, computed, map_jobs

__all__ = [
    "ExperimentConfig",
    "Experiment",
    "setting",
    "OUTPUT_ONLY",
]

T = TypeVar("T")


class Experiment:
    """One run of an experiment command: its output directory, seeded generator, device and caches.

    Use it as a context manager: entering validates the config, sets the torch thread count,
    creates ``out`` and seeds torch; leaving restores the thread count.

    Example:
        >>> import tempfile
        >>> with Experiment(ExperimentConfig(out=tempfile.mkdtemp())) as ex:
        ...     ex.device
        device(type='cpu')
    """

    def __init__(self, config: ExperimentConfig, *, progress: bool = True) -> None:
        self.config = config
        self.progress = progress
        self.out = Path(config.out)
        self.device = torch.device("cpu")
        self.generator = torch.Generator()
        self.timings: dict[str, float] = {}
        self.store = ResultStore(self.out / "partial", what="finished result")  # pieces a rerun skips
        self.written: list[str] = []  # the files :meth:`write` wrote
        self.result: dict[str, Any] = {}  # what :meth:`write` returned
        self._stack = ExitStack()
        self._started = 0.0
        #: The overall progress line: each stage (train, tune, evaluate a method) prints one as it starts.
        self.stages = StagePlan(self.out.name or "experiment", quiet=not progress)

    def __enter__(self) -> Experiment:
        self.config.validate()
        self.device = torch.device(resolve_device(self.config.device))
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as err:  # a file in the way, no permission, ...: nothing has been done yet
            raise ValueError(
                f"--out {self.out}: cannot create the output directory ({err.strerror}); pick another"
            ) from err
        try:
            # Two runs in one --out would mix their files, and the first would report the second's.
            self._stack.callback(release, lock_out(self.out))
            self._stack.enter_context(torch_threads(self.config.threads))
        except BaseException:
            self._stack.close()
            raise
        self.generator = seed_everything(self.config.seed)
        self._started = time.perf_counter()
        self.stages = StagePlan(self.stages.command, self.stages.costs, quiet=not self.progress)
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    @property
    def elapsed(self) -> float:
        """Wall seconds since the run began."""
        return time.perf_counter() - self._started

    def checkpoint(
        self, name: str, trainer: Callable[..., Any], model: torch.nn.Module, data: Any, **settings: Any
    ) -> Path:
        """``out / "{name}-{fingerprint}.ckpt"``, named by the model before training, trainer, settings and data.

        The untrained model's digest covers its architecture and its seeded initial weights, so
        two runs that would train different models never share a checkpoint.
        """
        key = {
            "trainer": f"{trainer.__module__}.{trainer.__qualname__}",
            "model": model_digest(model),
            "data": content_digest(data),
            "settings": settings,
        }
        return self.out / f"{name}-{settings_fingerprint(key)[:12]}.ckpt"

    def plan(self, costs: Mapping[str, float]) -> None:
        """Declare the run's stages for the overall progress line: name -> relative cost.

        The names are those :meth:`train` (``"train NAME"``, or ``NAME`` if it starts with
        "train"), :meth:`evaluate` (``"evaluate NAME"``)
        and :meth:`stage` use; the costs need only be right relative to each other (e.g. the
        seconds each took on some machine), since the time left is scaled by this run's speed.
        """
        self.stages.plan(costs)

    def stage(self, name: str, *, members: Sequence[str] = ()) -> Any:
        """A context manager around one stage of work (or ``members`` side by side): prints the progress line."""
        return self.stages.stage(name, members=members)

    def train(self, name: str, trainer: Callable[..., T], model: torch.nn.Module, data: Any, **settings: Any) -> T:
        """Train ``model`` on ``data`` with ``trainer(model, data, **settings)``, or resume its checkpoint.

        The wall time is recorded in :attr:`timings` under ``"train " + name``.
        """
        return self._train(name, trainer, model, data, settings, announce=True)

    def train_all(self, jobs: Mapping[str, tuple[Callable[..., Any], torch.nn.Module, Any, Mapping[str, Any]]]) -> dict:
        """:meth:`train` every ``name -> (trainer, model, data, settings)``; independent ones side by side.

        With ``--workers`` (:class:`~smcd_rl.experiments.shared.config.EvaluationConfig`), worker
        processes train the models to their checkpoints first, then each is resumed here from its
        finished checkpoint: the same weights as training them one after the other. Returns name ->
        what its trainer returned (its losses).
        """
        stages = {name: _train_stage(name) for name in jobs}
        paths = {name: self.checkpoint(name, t, m, d, **settings) for name, (t, m, d, settings) in jobs.items()}
        workers = self.workers_for(list(stages.values())) if len(jobs) > 1 else 1
        if workers > 1:
            with self.stage(f"{', '.join(stages.values())} in {workers} workers", members=list(stages.values())):
                seconds = map_jobs(
                    {
                        name: functools.partial(_train_to, trainer, model, data, paths[name], dict(settings))
                        for name, (trainer, model, data, settings) in jobs.items()
                    },
                    computed,
                    workers=workers,
                    threads=self.config.threads,
                    progress=self.progress,
                    costs={name: self.stages.costs.get(stage, 0.0) for name, stage in stages.items()},
                )
        results = {
            name: self._train(name, trainer, model, data, settings, announce=workers <= 1)
            for name, (trainer, model, data, settings) in jobs.items()
        }
        if workers > 1:
            self.timings.update({f"train {name}": seconds[name] for name in jobs})
        return results

    def _train(
        self,
        name: str,
        trainer: Callable[..., T],
        model: torch.nn.Module,
        data: Any,
        settings: Mapping[str, Any],
        *,
        announce: bool,
    ) -> T:
        path = self.checkpoint(name, trainer, model, data, **settings)
        started = time.perf_counter()
        with self.stage(_train_stage(name)) if announce else contextlib.nullcontext():
            result = trainer(model, data, checkpoint=path, progress=self.progress and announce, **settings)
        self.timings[f"train {name}"] = time.perf_counter() - started
        return result

    def evaluate(
        self,
        methods: Mapping[str, Callable[[], T]],
        evaluate: Callable[[str, T], Mapping[str, Any]],
        *,
        content: Mapping[str, Any] | Callable[[str], Mapping[str, Any]],
        kind: str = "method",
    ) -> dict[str, dict[str, Any]]:
        """Run ``evaluate(name, methods[name]())`` for every method, skipping those a rerun already has.

        Each method's results are stored in ``out/partial/`` (a :class:`ResultStore`) under a key
        of everything that determines them: the method's name, the config's settings (less
        :attr:`ExperimentConfig.SELECTION`) and ``content``. Nothing is keyed by a file name, so a
        changed model file or dataset is evaluated afresh.

        With ``--workers`` (:class:`~smcd_rl.experiments.shared.config.EvaluationConfig`), the methods still to run are evaluated
        side by side in worker processes (:mod:`~smcd_rl.experiments.shared.workers`); then
        ``evaluate`` and the factories must be module-level functions or ``functools.partial``
        of them, so they can be sent to a worker. The results are the same either way.

        Args:
            methods: method name -> a factory of what ``evaluate`` runs (built only when needed).
            evaluate: runs one method over all trials and returns its results (tensors, numbers).
            content: what determines the results besides the settings, e.g. the digests of the
                trained models; a function of the method's name where methods use different models.
            kind: what the results are (the stored files' prefix); parts of one experiment that
                evaluate different things under the same method names use a kind each.

        Returns:
            method name -> its results, each with ``"seconds"`` (wall time of its evaluation).
        """
        settings = self.config.settings(exclude=self.config.SELECTION)
        keys = {name: {"method": name, "settings": settings, "content": _content(content, name)} for name in methods}
        label = (lambda name: f"evaluate {name}") if kind == "method" else (lambda name: f"{kind} {name}")
        pending = [name for name in methods if not self.store.path(kind, keys[name]).is_file()]
        workers = self.workers_for([label(name) for name in pending])
        results: dict[str, dict[str, Any]] = {}
        for name, factory in methods.items():
            if workers > 1 and name in pending:
                continue
            with self.stage(label(name)):
                done = self.store.get(kind, keys[name])
                if done is None:
                    done = _timed(evaluate, name, factory())
                    self.store.put(kind, keys[name], done)
            results[name] = done
        if workers > 1:

            def store(name: str, done: dict[str, Any]) -> None:  # as each finishes: Ctrl-C keeps it
                self.store.put(kind, keys[name], done)
                results[name] = done

            with self.stage(f"{label(', '.join(pending))} in {workers} workers", members=list(map(label, pending))):
                map_jobs(
                    {name: methods[name] for name in pending},
                    functools.partial(_timed, evaluate),
                    workers=workers,
                    threads=self.config.threads,
                    on_result=store,
                    progress=self.progress,
                    costs={name: self.stages.costs.get(label(name), 0.0) for name in pending},
                )
        for name in methods:
            self.timings[f"evaluate {name}"] = results[name]["seconds"]
        return {name: results[name] for name in methods}

    def workers_for(self, stages: Sequence[str]) -> int:
        """The worker processes for these pending stages: ``--workers``, or its choice when 0 (auto)."""
        requested = int(getattr(self.config, "workers", 1))
        if requested == 0:
            planned = sum(self.stages.costs.get(stage, 0.0) for stage in stages)
            return auto_workers(len(stages), self.config.threads, planned)
        return max(1, min(requested, len(stages)))

    def bar(self, items: Sequence[T], desc: str, unit: str = "trial") -> Iterator[T]:
        """A progress bar over ``items`` that honours ``progress``."""
        return iter(tqdm(items, desc=desc, unit=unit, disable=not self.progress))

    def write(
        self,
        *,
        experiment: str,
        tables: Mapping[str, str],
        rows: Sequence[Mapping[str, Any]],
        payload: Mapping[str, Any],
        trials: Sequence[Mapping[str, Any]] = (),
        comparisons: Sequence[Mapping[str, Any]] = (),
        plots: Mapping[str, Callable[[Path], None]] | None = None,
        files: Sequence[str] = (),
    ) -> dict[str, Any]:
        """Write the results, the plots and ``report.md``, print the tables, and return the JSON payload.

        Writes ``results.csv`` (``rows``), ``trials.csv`` (one row per trial), ``comparisons.csv``
        (the paired comparisons), ``results.json`` (the experiment's name, config, machine, wall
        times, ``payload``'s entries, rows and comparisons), each plot, and ``report.md``: the
        ``tables`` (caption -> Markdown table), the plots, the settings with their fingerprint,
        the machine and the wall time. The result is also kept as :attr:`result`.

        Args:
            experiment: the experiment's title.
            tables: caption -> Markdown table, printed and in the report in this order.
            rows: the table's rows, one per cell and method.
            payload: further ``results.json`` entries (training losses, ...).
            trials: one row per trial, cell and method.
            comparisons: the paired comparison rows.
            plots: file name -> a function drawing that figure at the given path.
            files: other files the command wrote in ``out``, listed with these.
        """
        plots = dict(plots or {})
        tables = {caption: text for caption, text in tables.items() if text}  # e.g. no comparisons ran
        # An earlier run's file that this run does not write would read as this run's: remove it.
        earlier = {"trials.csv", "comparisons.csv", *_files_of_earlier_run(self.out / "results.json")}
        written = ["results.csv"]
        write_csv(self.out / "results.csv", rows)
        for name, content in (("trials.csv", trials), ("comparisons.csv", comparisons)):
            if content:
                write_csv(self.out / name, content)
                written.append(name)
        result = {
            "experiment": experiment,
            "config": config_dict(self.config),
            "machine": machine_info(),
            "seconds": {**self.timings, "total": self.elapsed},
            **payload,
            "results": list(rows),
            **({"comparisons": list(comparisons)} if comparisons else {}),
            "files": [*written, "results.json", *plots, *files, "report.md"],
        }
        write_json(self.out / "results.json", result)
        written.append("results.json")
        for name, draw in plots.items():
            draw(self.out / name)
        written += [*plots, *files, "report.md"]
        write_report(self.out / "report.md", result, tables, list(plots))
        for name in earlier - set(written):
            (self.out / name).unlink(missing_ok=True)
        for caption, text in tables.items():
            print(f"{caption}\n\n{text}\n")
        print(f"wrote {self.out}/: {', '.join(written)}")
        if self.progress:
            print(f"{self.stages.command} done in {duration(self.elapsed)}", file=sys.stderr, flush=True)
        self.written = written
        self.result = result
        return result


def _files_of_earlier_run(results: Path) -> list[str]:
    """The result files an earlier run in this directory listed in its results.json (none if unreadable)."""
    try:
        files = json.loads(results.read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return []
    # Only plain names in this directory: a hand-edited results.json must not delete anything else.
    return [name for name in files if isinstance(name, str) and name == Path(name).name and name not in ("", ".", "..")]


def _train_stage(name: str) -> str:
    return name if name.startswith("train") else f"train {name}"


def _train_to(trainer: Callable[..., Any], model: Any, data: Any, path: Path, settings: dict[str, Any]) -> float:
    """In a worker: train ``model`` to its checkpoint at ``path``; returns the wall seconds it took."""
    started = time.perf_counter()
    trainer(model, data, checkpoint=path, progress=False, **settings)
    return time.perf_counter() - started


def _timed(evaluate: Callable[[str, Any], Mapping[str, Any]], name: str, built: Any) -> dict[str, Any]:
    """``evaluate(name, built)`` with its wall seconds under ``"seconds"``."""
    started = time.perf_counter()
    return {**evaluate(name, built), "seconds": time.perf_counter() - started}


def _content(content: Mapping[str, Any] | Callable[[str], Mapping[str, Any]], name: str) -> Mapping[str, Any]:
    return content(name) if callable(content) else content
