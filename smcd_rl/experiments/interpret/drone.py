"""The drone data, its behaviour-cloning model and Figs. 4 and 13 of ``smcd-rl interpret``.

Data: :func:`~smcd_rl.envs.drone_operators.simulate_operators` (the paper's human data was never
released), or a user's own trajectories (``--dataset``), split as the paper: 83% training, 10%
known-operators testing, 7% unknown-operators testing. The model is a multi-task dropout
behaviour-cloning network ``u = f(x)``.

Figs. 4 and 13: the stored set is the MMSE mask of every training trajectory after SMCD over the
whole trajectory (for a per-step label such as ``phase``: the masks every ``--phase-stride``
steps, labelled with the phase at that step). For every test trajectory and ``n`` observed steps
(``1 <= n < T``), eq. (9) scores the true label from the ``k`` nearest stored masks. ``chance``
is what masks unrelated to the label would score on average: the stored set's share of the
query's true label. The likelihood noise is ``--noise-scale`` times the model's training RMSE per
action dimension.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.envs.drone_operators import TrajectoryDataset, load_dataset, simulate_operators, split_dataset
from smcd_rl.experiments.interpret.masks import sorted_masks
from smcd_rl.experiments.shared.outputs import format_table, save_figure
from smcd_rl.interpret import confidence_score

if TYPE_CHECKING:
    from smcd_rl.experiments.interpret.config import InterpretConfig

__all__ = [
    "SETS",
    "load",
    "check",
    "dataset_content",
    "summary",
    "steps",
    "make_model",
    "noise_std",
    "mask_record",
    "confidence_scores",
    "table",
    "plot",
]

#: The test sets: trajectories of operators seen in training, and of operators held out entirely.
SETS = ("known", "unknown")


def load(config: InterpretConfig) -> tuple[TrajectoryDataset, dict[str, np.ndarray]]:
    """The dataset (``--dataset`` or simulated operators) and its train / known / unknown split."""
    if config.dataset:
        data = load_dataset(config.dataset)
    else:
        data = simulate_operators(config.operators, config.trajectories_per_operator, seed=config.seed)
    split = split_dataset(
        data, known_fraction=config.known_fraction, unknown_fraction=config.unknown_fraction, seed=config.seed
    )
    return data, split


def check(config: InterpretConfig, data: TrajectoryDataset, split: dict[str, np.ndarray]) -> None:
    """Before any training: the labels to score exist, the stored set has k masks, Reptile has tasks."""
    if "confidence" in config.parts:
        missing = [label for label in config.labels if label not in data.labels]
        if missing:
            raise ValueError(
                f"the dataset has no label(s) {missing}; it has {sorted(data.labels)}. Pass --labels with the ones to score"
            )
        if config.k > len(split["train"]):
            raise ValueError(
                f"k = {config.k} but only {len(split['train'])} training trajectories are stored; lower --k"
            )
    if "lookahead" in config.parts and any(m.startswith("R+") for m in config.methods):
        operators = np.unique(data.operator[split["train"]]).size
        if operators < max(2, config.reptile_tasks_per_batch):
            raise ValueError(
                f"Reptile takes the training operators as tasks: {operators} of them, but it needs at least 2 "
                f"and --reptile-tasks-per-batch {config.reptile_tasks_per_batch}"
            )


def dataset_content(data: TrajectoryDataset) -> dict[str, Any]:
    """Everything a dataset holds, as tensors, for :func:`~smcd_rl.experiments.shared.harness.content_digest`.

    (The digest writes other objects by their ``repr``, which elides the middle of a long array.)
    """
    arrays = {"state": data.state, "action": data.action, "trajectory": data.trajectory, "operator": data.operator}
    return {
        **{name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()},
        "step_labels": {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in data.step_labels.items()},
        "trajectory_labels": {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in data.trajectory_labels.items()},
        "label_names": data.label_names,
    }


def summary(data: TrajectoryDataset, split: dict[str, np.ndarray]) -> dict[str, Any]:
    """Trajectories, steps and label counts per split (what ``chance`` levels come from)."""
    result: dict[str, Any] = {}
    for name, ids in split.items():
        part = data.select(ids)
        counts = {
            label: {
                part.class_name(label, int(c)): int(n)
                for c, n in zip(*np.unique(values, return_counts=True), strict=True)
            }
            for label, values in part.labels.items()
        }
        result[name] = {
            "trajectories": part.num_trajectories,
            "steps": int(part.state.shape[0]),
            "operators": int(np.unique(part.operator).size),
            "label_counts": counts,
        }
    return result


def steps(data: TrajectoryDataset, device: torch.device) -> TensorDict:
    """Every step of ``data`` as one batch of ``state`` -> ``action`` samples, with its operator as ``task``
    (what the T network's masks are trained to identify)."""
    n = data.state.shape[0]
    operator = torch.from_numpy(data.operator[data.trajectory]).to(torch.int64)
    return TensorDict(
        {"state": torch.from_numpy(data.state), "action": torch.from_numpy(data.action), "task": operator},
        [n],
        device=device,
    )


def make_model(
    config: InterpretConfig, data: TrajectoryDataset, device: torch.device, *, mask_groups: int | None = None
) -> smcd_rl.AdaptiveModel:
    """The untrained behaviour-cloning model ``action = f(state)``; its initial weights come from the seed alone
    (``mask_groups``: the T network's bits per layer)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        net = smcd_rl.MaskedMLP(
            data.state.shape[1],
            data.action.shape[1],
            hidden=(config.hidden,) * config.depth,
            dropout=config.dropout,
            mask_groups=mask_groups,
            device=device,
        )
    return smcd_rl.AdaptiveModel(net, in_keys=["state"], out_key="action")


@torch.no_grad()
def noise_std(
    model: smcd_rl.AdaptiveModel, train: TrajectoryDataset, config: InterpretConfig, device: torch.device
) -> list[float]:
    """Likelihood noise per action dim: ``noise_scale`` x the model's training RMSE (no adaptation)."""
    plain = model.with_adaptation(smcd_rl.NoAdaptation())
    plain.reset()
    td = steps(train, device)
    prediction = plain(td.exclude("action"))["action"]
    rmse = (prediction - td["action"]).square().mean(0).sqrt().clamp(min=1e-3)
    return (config.noise_scale * rmse).cpu().tolist()


def mask_record(
    name: str,
    model: smcd_rl.AdaptiveModel,
    data: TrajectoryDataset,
    prior: torch.Tensor | None,
    config: InterpretConfig,
    device: torch.device,
    *,
    progress: bool,
) -> dict[str, torch.Tensor]:
    """The masks of one set: ``"stored"`` (training trajectories) or a test set (the queries).

    Stored masks are read at a trajectory's end (``final``) and every ``phase_stride`` steps;
    query masks after each of ``steps`` observed steps short of the trajectory's end.
    """
    lengths = torch.from_numpy(data.lengths)
    step = torch.arange(int(lengths.max())).unsqueeze(0)
    if name == "stored":
        final = step == (lengths.unsqueeze(1) - 1)
        strided = ((step + 1) % config.phase_stride == 0) & (step < lengths.unsqueeze(1))
        record = final | strided
    else:
        record = torch.isin(step + 1, torch.tensor(config.steps)) & (step + 1 < lengths.unsqueeze(1))
    masks, rows, observed = sorted_masks(
        model, data, record, prior=prior, chunk=config.chunk, device=device, desc=f"{name} masks", progress=progress
    )
    result = {"masks": masks, "rows": rows, "observed": observed}
    if name == "stored":
        result["final"] = final[rows, observed - 1]
    return result


def confidence_scores(
    label: str,
    train: TrajectoryDataset,
    test: TrajectoryDataset,
    stored: dict[str, torch.Tensor],
    queries: dict[str, torch.Tensor],
    config: InterpretConfig,
) -> dict[tuple[int, str], dict[str, torch.Tensor]]:
    """Eq. (9) for the true label of every query, per (observed steps n, class): ``{"masks": ..., "chance": ...}``.

    Class ``"all"`` holds every query observed for n steps; each class holds those whose true label it is.
    """
    per_step = label in train.step_labels
    keep = torch.ones_like(stored["final"]) if per_step else stored["final"]
    store_rows, store_observed = stored["rows"][keep], stored["observed"][keep]
    if per_step:  # the label at the last observed step
        stored_labels = train.step_labels[label][train.offsets[store_rows.numpy()] + store_observed.numpy() - 1]
        true = test.step_labels[label][test.offsets[queries["rows"].numpy()] + queries["observed"].numpy() - 1]
    else:
        stored_labels = train.trajectory_labels[label][store_rows.numpy()]
        true = test.trajectory_labels[label][queries["rows"].numpy()]
    if config.k > int(keep.sum()):
        raise ValueError(f"k = {config.k} but only {int(keep.sum())} masks are stored for {label!r}; lower --k")
    score = confidence_score(
        queries["masks"], stored["masks"][keep], torch.from_numpy(stored_labels), config.k, label=torch.from_numpy(true)
    )
    share = np.bincount(stored_labels, minlength=int(max(stored_labels.max(), true.max())) + 1) / stored_labels.size
    chance = torch.from_numpy(share[true])
    observed = queries["observed"].numpy()
    cells: dict[tuple[int, str], dict[str, torch.Tensor]] = {}
    for n in config.steps:
        for cls in [None, *np.unique(true).tolist()]:
            sel = torch.from_numpy((observed == n) & ((true == cls) if cls is not None else True))
            if bool(sel.any()):
                name = "all" if cls is None else test.class_name(label, int(cls))
                cells[n, name] = {"masks": score[sel].double(), "chance": chance[sel]}
    return cells


def _cell(row: dict[str, Any] | None) -> str:
    if row is None:
        return "-"
    return f"{row['confidence_mean']:.2f} [{row['confidence_low']:.2f}, {row['confidence_high']:.2f}]"


def table(rows: list[dict[str, Any]], config: InterpretConfig) -> str:
    """Confidence of the true label, mean [95% CI] over test trajectories, per label and test set; chance last."""
    lookup = {(r["set"], r["label"], r["steps"], r["method"]): r for r in rows if r["class"] == "all"}
    body = []
    for label in config.labels:
        for set_name in SETS:
            chance = [
                lookup[c]["confidence_mean"] for n in config.steps if (c := (set_name, label, n, "chance")) in lookup
            ]
            body.append(
                [
                    label,
                    set_name,
                    *[_cell(lookup.get((set_name, label, n, "masks"))) for n in config.steps],
                    float(np.mean(chance)) if chance else "-",
                ]
            )
    return format_table(body, ["label", "operators", *[f"n={n}" for n in config.steps], "chance"])


def plot(rows: list[dict[str, Any]], labels: tuple[str, ...], config: InterpretConfig, path: Path) -> None:
    """Confidence against observed steps for ``labels`` (one panel each), 95% CI bands, chance dashed."""
    labels = tuple(label for label in labels if label in config.labels)
    if not labels:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(labels), figsize=(4.5 * len(labels), 3.5), sharey=True, squeeze=False)
    for ax, label in zip(axes[0], labels, strict=True):
        for color, set_name in zip(("C0", "C1"), SETS, strict=True):
            cell = [r for r in rows if r["label"] == label and r["set"] == set_name and r["class"] == "all"]
            sel = [r for r in cell if r["method"] == "masks"]
            if not sel:
                continue
            n = np.array([r["steps"] for r in sel])
            ax.plot(n, [r["confidence_mean"] for r in sel], color=color, marker="o", label=f"{set_name} operators")
            low, high = [r["confidence_low"] for r in sel], [r["confidence_high"] for r in sel]
            ax.fill_between(n, low, high, color=color, alpha=0.2)
            chance = [r for r in cell if r["method"] == "chance"]
            ax.plot([r["steps"] for r in chance], [r["confidence_mean"] for r in chance], color=color, ls="--", lw=1)
        ax.set_title(f"{label} (dashed: chance)")
        ax.set_xlabel("observed steps n")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"confidence of the true label (k = {config.k})")
    axes[0][-1].legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def evaluate_masks(
    model: Any,
    sets: Mapping[str, Any],
    prior: Any,
    config: InterpretConfig,
    device: Any,
    progress: bool,
    name: str,
    strategy: Any,
) -> dict[str, Any]:
    """The mask record of one operator set under ``strategy`` (a function, so a worker process can run it)."""
    return mask_record(name, model.with_adaptation(strategy), sets[name], prior, config, device, progress=progress)
