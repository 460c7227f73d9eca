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

import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import IO, Any, TypeVar

import torch
from tqdm.auto import tqdm

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: runs are not locked
    fcntl = None  # type: ignore[assignment]

from smcd_rl.digests import content_digest, model_digest
from smcd_rl.experiments.common import (
    machine_info,
    resolve_device,
    seed_everything,
    settings_fingerprint,
    torch_threads,
    write_csv,
    write_json,
    write_text,
)
from smcd_rl.experiments.configs import OUTPUT_ONLY, ExperimentConfig, config_dict, setting
from smcd_rl.experiments.result_store import ResultStore
from smcd_rl.experiments.stages import StagePlan, duration

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
            self._stack.callback(_release, _lock(self.out))
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

    def stage(self, name: str) -> Any:
        """A context manager around one stage of work: prints the overall progress line as it starts."""
        return self.stages.stage(name)

    def train(self, name: str, trainer: Callable[..., T], model: torch.nn.Module, data: Any, **settings: Any) -> T:
        """Train ``model`` on ``data`` with ``trainer(model, data, **settings)``, or resume its checkpoint.

        The wall time is recorded in :attr:`timings` under ``"train " + name``.
        """
        path = self.checkpoint(name, trainer, model, data, **settings)
        started = time.perf_counter()
        with self.stage(name if name.startswith("train") else f"train {name}"):
            result = trainer(model, data, checkpoint=path, progress=self.progress, **settings)
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
        results: dict[str, dict[str, Any]] = {}
        for name, factory in methods.items():
            key = {"method": name, "settings": settings, "content": _content(content, name)}
            with self.stage(f"evaluate {name}" if kind == "method" else f"{kind} {name}"):
                done = self.store.get(kind, key)
                if done is None:
                    started = time.perf_counter()
                    done = {**evaluate(name, factory()), "seconds": time.perf_counter() - started}
                    self.store.put(kind, key, done)
            results[name] = done
            self.timings[f"evaluate {name}"] = done["seconds"]
        return results

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


#: The lock file of a run's output directory; it holds the running process's id and command line.
LOCK = ".lock"


def _lock(out: Path) -> IO[str] | None:
    """Take ``out``'s lock (``flock`` on ``out/.lock``), or refuse: another run is writing into ``out``.

    The operating system releases an ``flock`` when its process ends, however it ends, so a run
    that crashed never leaves ``out`` locked; its stale ``.lock`` file is simply locked again.
    Returns the open lock file (``None`` where there is no ``fcntl``, on Windows: no lock).
    """
    if fcntl is None:  # pragma: no cover - Windows
        return None
    path = out / LOCK
    while True:
        try:
            handle = open(path, "a+")  # not "w": the holder's process id stays readable until we hold the lock
        except OSError as err:
            raise ValueError(
                f"--out {out}: cannot write in the output directory ({err.strerror}); make it writable or pick another"
            ) from err
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.seek(0)
            holder = handle.read().strip()
            handle.close()
            raise ValueError(
                f"--out {out} is in use by another run ({f'process {holder}' if holder else 'process unknown'}); "
                "wait for it to finish, or give this run another --out"
            ) from None
        try:  # the run before us may have removed the file after we opened it: lock the one that is there now
            same = os.path.samestat(os.stat(path), os.fstat(handle.fileno()))
        except FileNotFoundError:
            same = False
        if same:
            break
        handle.close()
    try:  # who holds it, for the message of a run refused
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}: {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])}\n")
        handle.flush()
    except OSError as err:  # a full disk: nothing of this run could be saved either
        _release(handle)
        raise ValueError(
            f"--out {out}: cannot write in the output directory ({err.strerror}); free some space or pick another"
        ) from err
    return handle


def _release(handle: IO[str] | None) -> None:
    """Remove the lock file while still holding its lock, then let it go (see :func:`_lock`)."""
    if handle is None:  # pragma: no cover - Windows
        return
    try:
        os.unlink(handle.name)
    except OSError:
        pass
    handle.close()


def _files_of_earlier_run(results: Path) -> list[str]:
    """The result files an earlier run in this directory listed in its results.json (none if unreadable)."""
    try:
        files = json.loads(results.read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return []
    # Only plain names in this directory: a hand-edited results.json must not delete anything else.
    return [name for name in files if isinstance(name, str) and name == Path(name).name and name not in ("", ".", "..")]


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _content(content: Mapping[str, Any] | Callable[[str], Mapping[str, Any]], name: str) -> Mapping[str, Any]:
    return content(name) if callable(content) else content


def write_report(path: Path, result: Mapping[str, Any], tables: Mapping[str, str], plots: Sequence[str]) -> None:
    """``report.md``: an experiment's tables, plot, settings (with their fingerprint), machine and wall time.

    The fingerprint is that of the settings that determine the numbers, so a reader (or a test)
    can tell whether a committed report is what the current settings produce.
    """
    config = dict(result["config"])
    settings = {k: v for k, v in config.items() if k not in OUTPUT_ONLY}
    machine = result["machine"]
    lines = [f"# {result['experiment']}", ""]
    for caption, text in tables.items():
        lines += [f"**{caption}**", "", text, ""]
    for plot in plots:
        lines += [f"![{plot}]({plot})", ""]
    seconds = result["seconds"]["total"]
    lines += [
        f"Wall time {int(seconds // 60)} min {seconds % 60:.0f} s on {machine['processor']} "
        f"({machine['cpus']} CPUs, {_count(machine['torch_threads'], 'torch thread')}, torch {machine['torch']}"
        + (f", {machine['gpu']}" if "gpu" in machine else "")
        + ").",
        "",
        f"Settings (fingerprint `{settings_fingerprint(settings)[:12]}`):",
        "",
        "```json",
        json.dumps(config, indent=2, ensure_ascii=False),
        "```",
        "",
    ]
    write_text(path, "\n".join(lines), what="report")
