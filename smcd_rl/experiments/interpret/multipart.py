"""One report for an experiment command made of several parts, each a figure with its own table.

:meth:`Experiment.write <smcd_rl.experiments.shared.harness.Experiment.write>` writes one experiment's
rows, trials and comparisons and draws one plot. A command with several parts (``smcd-rl
interpret``: Fig. 9, Figs. 4/13, Fig. 14), each scored over trials of its own and with a metric
of its own, adds each part here; :meth:`PartsReport.write` then writes one CSV per part beside
the harness's files, which hold every part in long format with a ``figure`` column, and every
part's plots.

Example:
    >>> import tempfile, torch
    >>> from smcd_rl.experiments.shared.harness import Experiment, ExperimentConfig
    >>> report = PartsReport()
    >>> scores = {(1,): {"none": torch.ones(20), "smcd": torch.linspace(0.1, 0.3, 20)}}
    >>> rows = report.add("fig", scores, cell=("T",), baseline="none", adaptive=["smcd"], metric="rmse")
    >>> report.comparisons["fig"][0]["verdict"]
    'better'
    >>> with Experiment(ExperimentConfig(out=tempfile.mkdtemp()), progress=False) as ex:
    ...     _ = report.write(ex, experiment="demo")  # doctest: +ELLIPSIS
    wrote ...
    >>> sorted(p.name for p in ex.out.iterdir())
    ['comparisons.csv', 'fig.csv', 'report.md', 'results.csv', 'results.json', 'trials.csv']
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from smcd_rl.experiments.shared.harness import Experiment
from smcd_rl.experiments.shared.outputs import write_csv
from smcd_rl.experiments.shared.stats import cell_statistics

__all__ = ["PartsReport"]


class PartsReport:
    """Tables, plots, rows, trials and paired comparisons of every part of one experiment run.

    Attributes:
        tables: caption -> Markdown table, printed and in ``report.md`` in the order added.
        plots: file name -> a function drawing that figure at the given path.
        payload: extra ``results.json`` entries; each part's rows are added under its name.
        rows: part -> its table rows (``{metric}_mean``, ``_low``, ``_high``, ``_std``, ``trials``).
        comparisons: part -> its paired comparison rows.
    """

    def __init__(self) -> None:
        self.tables: dict[str, str] = {}
        self.plots: dict[str, Callable[[Path], None]] = {}
        self.payload: dict[str, Any] = {}
        self.rows: dict[str, list[dict[str, Any]]] = {}
        self.comparisons: dict[str, list[dict[str, Any]]] = {}
        self._trials: list[dict[str, Any]] = []

    def add(
        self,
        part: str,
        scores: Mapping[tuple[Any, ...], Mapping[str, torch.Tensor]],
        *,
        cell: Sequence[str],
        baseline: str | None,
        adaptive: Sequence[str],
        metric: str,
        lower_is_better: bool = True,
        seed: int = 0,
        trials_where: Callable[[dict[str, Any]], bool] = lambda where: True,
    ) -> list[dict[str, Any]]:
        """A part's rows with 95% CIs and its paired comparisons, by :func:`~smcd_rl.experiments.shared.stats.cell_statistics`.

        Args:
            part: the part's name: its CSV file's stem and its ``figure`` value in the long files.
            scores: cell -> method -> per-trial scores, as ``cell_statistics`` takes them.
            cell, baseline, adaptive, metric, lower_is_better, seed: as ``cell_statistics`` takes them.
            trials_where: which cells' trials go into ``trials.csv`` (e.g. not cells that only
                regroup the trials of another cell).

        Returns:
            The part's rows.
        """
        rows, comparisons = cell_statistics(
            scores,
            cell=cell,
            baseline=baseline,
            adaptive=adaptive,
            metric=metric,
            lower_is_better=lower_is_better,
            seed=seed,
        )
        self.rows[part], self.comparisons[part] = rows, comparisons
        self.payload[part] = rows
        for key, by_method in scores.items():
            where = dict(zip(cell, key, strict=True))
            if trials_where(where):
                self._trials += [
                    {"figure": part, **where, "method": name, "trial": k, metric: float(v)}
                    for name, values in by_method.items()
                    for k, v in enumerate(values)
                ]
        return rows

    def write(self, ex: Experiment, *, experiment: str) -> dict[str, Any]:
        """Each part's ``{part}.csv``, then :meth:`Experiment.write` with every part in long format and every plot."""
        for part, rows in self.rows.items():
            write_csv(ex.out / f"{part}.csv", rows)
        return ex.write(
            experiment=experiment,
            tables=self.tables,
            rows=[{"figure": part, **r} for part, rows in self.rows.items() for r in rows],
            trials=self._trials,
            comparisons=[{"figure": part, **c} for part, cs in self.comparisons.items() for c in cs],
            payload=self.payload,
            plots=self.plots,
            files=[f"{part}.csv" for part in self.rows],
        )
