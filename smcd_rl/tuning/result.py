"""What :func:`smcd_rl.tune` chose and every candidate it chose from: :class:`TuneResult`.

The result lists every candidate with its score and time, the best of each kind, ``.best``
(ready for ``model.with_adaptation``) and ``.combination``; :func:`smcd_rl.tune` stores its
:meth:`~TuneResult.to_dict` in ``model.tuning``, saved with the model. Each candidate's settings
are the strategy's stored settings (:mod:`smcd_rl.strategies.registry`).

Example:
    >>> import smcd_rl
    >>> from smcd_rl.tuning import TuneResult
    >>> model = smcd_rl.load("model.pt")  # doctest: +SKIP
    >>> result = TuneResult.from_dict(model.tuning)  # doctest: +SKIP
    >>> adaptive = model.with_adaptation(result.best)  # doctest: +SKIP
    >>> print(result)  # doctest: +SKIP
    tuned by one-step on 16 episodes x 30 steps
    ...
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from smcd_rl.strategies import SMCD, BayesianLastLayer, Combination, GradientDescent
from smcd_rl.strategies.base import Adaptation
from smcd_rl.strategies.registry import build, with_generators
from smcd_rl.tuning.advice import advice
from smcd_rl.tuning.calibration import Calibration
from smcd_rl.tuning.defaults import KINDS, SEARCHED
from smcd_rl.tuning.diagnostics import Trace
from smcd_rl.tuning.search import TuneCandidate, setting_key

__all__ = ["TuneResult", "describe_settings"]


@dataclass
class TuneResult:
    """What :func:`tune` chose and every candidate it chose from (``print`` it for a table)."""

    #: ``"one-step"``, ``"evidence"`` (SMCD calibrated by its evidence; the kinds compared by one-step
    #: error), ``"lookahead"`` or ``"custom"`` (a score of your own, :attr:`score_label`).
    criterion: str
    #: The per-observation budget in milliseconds, or ``None``.
    budget_ms: float | None
    candidates: list[TuneCandidate]
    #: Kind -> its best candidate.
    best_of: dict[str, TuneCandidate]
    #: What the search did beyond its first grid (extended GD edges, halved particles).
    notes: list[str] = field(default_factory=list)
    episodes: int = 0
    steps: int = 0
    seconds: float = 0.0
    #: A digest of the model, the episodes and the seed: which results ``tune(..., reuse=...)`` may reuse.
    data: str = ""
    #: Every time per observation measured (ms), by setting: ``tune(..., reuse=...)`` takes them from here.
    timings: dict[str, float] = field(default_factory=dict)
    #: Every run on the episodes, step by step, by setting (this call's; not in :meth:`to_dict`).
    traces: dict[str, Trace] = field(default_factory=dict, repr=False, compare=False)
    #: Raced settings' runs on the first episodes, by setting (this call's; not in :meth:`to_dict`).
    heads: dict[str, tuple[Trace, Any]] = field(default_factory=dict, repr=False, compare=False)
    #: SMCD's calibration, ``{"search": ...}`` (this call's, every noise shape searched; not in
    #: :meth:`to_dict`): ``calibrate(..., reuse=...)`` of the other criterion runs fewer filters from them.
    calibrations: dict[str, Calibration] = field(default_factory=dict, repr=False, compare=False)
    #: The steps ahead the criterion scores (1 for one-step and evidence).
    horizon: int = 1
    #: The name of the score the kinds are compared by (``"one-step RMSE"``, ``"10-step look-ahead RMSE"``...).
    score_label: str = "one-step RMSE"
    #: The score function of your own it was tuned by (this call's; not in :meth:`to_dict`): reuse
    #: with a score of your own needs this very function.
    score_fn: Callable[..., float] | None = field(default=None, repr=False, compare=False)
    #: Wall seconds of each kind's search (its runs and its best's timing), in the order tuned.
    kind_seconds: dict[str, float] = field(default_factory=dict)

    @property
    def best_kind(self) -> str:
        """The kind of lowest score (the first of :data:`KINDS` among equals)."""
        return min(self.best_of, key=lambda kind: (self.best_of[kind].score, KINDS.index(kind)))

    @property
    def best(self) -> Adaptation:
        """A fresh instance of the overall best strategy, ready for ``model.with_adaptation``."""
        return self.strategy(self.best_kind)

    @property
    def combination(self) -> Combination | None:
        """A fresh instance of the tuned combination, or ``None`` if none was tuned."""
        strategy = self.strategy("combination") if "combination" in self.best_of else None
        return strategy if isinstance(strategy, Combination) else None

    def trace(self, kind: str) -> Trace | None:
        """The run of the best strategy of ``kind`` on the tuning episodes, step by step (``None`` if not at hand).

        The same as :func:`smcd_rl.tuning.diagnostics.trace` of :meth:`strategy` on those episodes, for a
        strategy this call ran (a setting reused from an earlier call has none). A combination's
        holds its one-step errors only.
        """
        best = self.best_of.get(kind)
        return None if best is None else self.traces.get(setting_key(kind, best.settings))

    def strategy(self, kind: str, *, device: torch.device | str | None = None) -> Adaptation:
        """A fresh instance of the best strategy of ``kind``.

        ``device``: where SMCD's random generator lives (the model's device); default: where it
        was tuned. A tuning recorded on a GPU rebuilds on a CPU-only machine with ``device="cpu"``.
        """
        if kind not in self.best_of:
            raise KeyError(f"no {kind!r} was tuned; tuned: {sorted(self.best_of)}")
        settings = self.best_of[kind].settings
        return build(kind, settings if device is None else with_generators(kind, settings, device=str(device)))

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> TuneResult:
        """Rebuild a result from its :meth:`to_dict` record, such as a loaded model's ``model.tuning``.

        Raises:
            ValueError: ``record`` is not a record of :meth:`to_dict` (another tuning procedure's).

        Example:
            >>> result = TuneResult("one-step", None, [TuneCandidate("none", {}, 0.5, 0.1)], {})
            >>> result.best_of["none"] = result.candidates[0]
            >>> TuneResult.from_dict(result.to_dict()).best_kind
            'none'
        """
        needed = ("criterion", "budget_ms", "best_of", "candidates")
        if not isinstance(record, Mapping) or any(key not in record for key in needed):
            raise ValueError(
                f"not a record of TuneResult.to_dict (it needs the entries {list(needed)}); a model's tuning holds "
                "one after smcd_rl.tune(model, ...)"
            )

        def candidate(entry: Mapping[str, Any]) -> TuneCandidate:
            # to_dict writes inf as None (JSON has no infinity).
            rmse, ms, score = entry["one_step_rmse"], entry["ms_per_step"], entry.get("score", math.nan)
            return TuneCandidate(
                entry["kind"],
                dict(entry["settings"]),
                math.inf if rmse is None else float(rmse),
                math.inf if ms is None else float(ms),
                entry.get("skipped", ""),
                math.inf if score is None else float(score),
            )

        return cls(
            criterion=record["criterion"],
            budget_ms=record["budget_ms"],
            candidates=[candidate(c) for c in record["candidates"]],
            best_of={kind: candidate(c) for kind, c in record["best_of"].items()},
            notes=list(record.get("notes", [])),
            episodes=int(record.get("episodes", 0)),
            steps=int(record.get("steps", 0)),
            seconds=float(record.get("seconds", 0.0)),
            data=str(record.get("data", "")),
            timings={k: math.inf if v is None else float(v) for k, v in record.get("timings", {}).items()},
            horizon=int(record.get("horizon", 1)),
            score_label=str(record.get("score_label", "one-step RMSE")),
            kind_seconds={k: float(v) for k, v in record.get("kind_seconds", {}).items()},
        )

    def table(self) -> str:
        """The best of each kind: settings, score(s) and time per observation, then what to use."""
        ahead = self.criterion in ("lookahead", "custom")
        by = self.score_label if ahead else self.criterion
        lines = [
            f"tuned by {by} on {self.episodes} episodes x {self.steps} steps"
            + (f", budget {self.budget_ms:g} ms per observation" if self.budget_ms is not None else ""),
            "",
            "| strategy | settings | one-step RMSE |"
            + (f" {self.score_label} |" if ahead else "")
            + " ms / observation |",
            "|---|---|---|" + ("---|" if ahead else "") + "---|",
        ]
        for kind in KINDS:
            if kind in self.best_of:
                c = self.best_of[kind]
                mark = " (best)" if kind == self.best_kind else ""
                score = f" {c.score:.4g} |" if ahead else ""
                lines.append(
                    f"| {kind}{mark} | {describe_settings(c.settings)} | {c.one_step_rmse:.4g} |{score} {c.ms_per_step:.3g} |"
                )
        return "\n".join(lines + ["", *self.notes, *([""] if self.notes else []), *advice(self)])

    def __str__(self) -> str:
        return self.table()

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready record (what ``model.tuning`` holds; an infinite score or time is ``None``)."""
        return _json_numbers(
            {
                "criterion": self.criterion,
                "horizon": self.horizon,
                "score_label": self.score_label,
                "budget_ms": self.budget_ms,
                "best_kind": self.best_kind,
                "best_of": {kind: asdict(c) for kind, c in self.best_of.items()},
                "candidates": [asdict(c) for c in self.candidates],
                "notes": list(self.notes),
                "episodes": self.episodes,
                "steps": self.steps,
                "seconds": self.seconds,
                "data": self.data,
                "timings": dict(self.timings),
                "kind_seconds": dict(self.kind_seconds),
            }
        )


def describe_settings(settings: dict[str, Any]) -> str:
    """A candidate's settings in a few words, as :meth:`TuneResult.table` shows them.

    What :func:`tune` searches is always shown (SMCD's particles, flip probability and noise;
    gradient descent's learning rate, steps and window); any other setting only where it differs
    from its default, so a row says what was chosen, not the strategy's whole config.

    Example:
        >>> describe_settings({"lr": 0.1, "steps": 5, "window": 10, "loss": "mse", "huber_delta": 1.0})
        'lr 0.1, steps 5, window 10'
        >>> describe_settings({**SMCD(num_particles=500, noise_std=[0.0134, 0.01325]).config(), "seed": 3})
        'num_particles 500, flip_prob 0.01, noise_std [0.0134, 0.0132]'
        >>> describe_settings(BayesianLastLayer(prior_scale=0.3, drift=0.01).config())
        'prior_scale 0.3, noise_std 0.1, drift 0.01, likelihood gaussian'
        >>> describe_settings({"smcd": {"num_particles": 500}, "last_layer": {"prior_scale": 0.3}, "weighing": "mean"})
        'num_particles 500; readout prior_scale 0.3; weighing mean'
    """
    if "members" in settings:
        return f"{' + '.join(m['name'] for m in settings['members'])}, eta {settings['eta']:g}, share {settings['share']:g}"
    if "last_layer" in settings:
        weighing = settings.get("weighing", "predictive")  # shown where it is not the default
        weighed = "" if weighing == "predictive" else f"; weighing {weighing}"
        return f"{describe_settings(settings['smcd'])}; readout {describe_settings(settings['last_layer'])}{weighed}"
    kind = "smcd" if "num_particles" in settings else "last_layer" if "prior_scale" in settings else "gradient_descent"
    searched, defaults = SEARCHED[kind], _DEFAULTS[kind]
    shown = {
        k: v
        for k, v in settings.items()
        if k not in ("seed", "device") and (k in searched or defaults.get(k, _UNSET) != v)
    }
    if shown.get("loss", "mse") == "mse":  # the squared error's Huber delta is unused
        shown.pop("huber_delta", None)
    parts = []
    for k, v in shown.items():
        if isinstance(v, (list, tuple)) and len(v) > 3:
            v = f"rms {math.sqrt(sum(float(u) ** 2 for u in v) / len(v)):.3g} ({len(v)} dims)"
        elif isinstance(v, (list, tuple)):
            v = "[" + ", ".join(f"{float(u):.3g}" for u in v) + "]"
        parts.append(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}")
    return ", ".join(parts) or "-"


#: Each kind's default settings: :func:`describe_settings` leaves out what equals them.
_DEFAULTS: dict[str, dict[str, Any]] = {
    "smcd": SMCD().config(),
    "gradient_descent": GradientDescent().config(),
    "last_layer": BayesianLastLayer().config(),
}
_UNSET = object()


def _json_numbers(value: Any) -> Any:
    """``value`` with every float that JSON cannot hold as ``None`` (inf, NaN: unusable) or ``"-inf"``
    (a score of your own at its best), which :meth:`TuneResult.from_dict` reads back."""
    if isinstance(value, float) and value == -math.inf:
        return "-inf"
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_numbers(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_numbers(v) for v in value]
    return value
