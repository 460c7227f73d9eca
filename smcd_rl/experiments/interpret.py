"""Mask interpretability and drone look-ahead (paper 4.3, 5, A.5, B.1-B.4): ``smcd-rl interpret``.

Three parts, each resumable (``--parts``):

* ``fig9`` (appendix A.5, Fig. 9): for each latent size, train a two-link forward-kinematics
  model on motor babbling, infer SMCD masks on held-out arms after a burn-in, and measure how
  often the arm nearest in link-length space is among the ``k`` nearest in mask space.
* ``confidence`` (Fig. 4 and Fig. 13): train a multi-task dropout behaviour-cloning model
  ``u = f(x)`` on the drone training trajectories; the stored set is the MMSE mask of every
  training trajectory after SMCD over the whole trajectory (for the per-step ``phase`` label: the
  masks every ``--phase-stride`` steps, labelled with the phase at that step). For every test
  trajectory and ``n`` observed steps, eq. (9) scores the true label from the ``k`` nearest
  stored masks; mean and 1-sigma over trajectories, known and unknown operators apart.
* ``lookahead`` (Fig. 14): per test trajectory, adapt on the first ``burn-in x T`` steps, then
  predict the operator's actions on the next ``horizon x T`` steps from the observed states with
  no further adaptation; RMSE for M+N, M+G, M+S and, with Reptile (:func:`smcd_rl.fit_reptile`,
  operators as tasks), R+N, R+G, R+S.

Data: :func:`~smcd_rl.envs.drone_operators.simulate_operators` (the paper's human data was never
released), or a user's own trajectories with ``--dataset PATH`` in the format of
:mod:`smcd_rl.envs.drone_operators`. Split as the paper: 83% training, 10% known-operators
testing, 7% unknown-operators testing.

Choices the paper leaves open, made here:

* Every SMCD run that produces masks for comparison starts from the same prior particle set
  (unless ``--independent-priors``): two trajectories' masks then differ because their data
  selected different particles, not because their filters drew different random masks. The
  paper does not say how its filters were initialised.
* Fig. 9's held-out arms all babble along one joint path (unless ``--fig9-own-paths``),
  so their masks differ by link lengths alone. With a path of their own per arm (and the
  default settings) the top-k accuracy measured at chance level, presumably because the MMSE
  mask then depends on the region of joint space visited as much as on the link lengths.
* Likelihood noise: ``--noise-scale`` times the model's training RMSE per action dimension.
* ``n`` counts observed steps; a test trajectory contributes at ``n`` when ``n < T`` (the paper's
  ``1 <= n < T``). ``chance`` is what masks unrelated to the label would score on average: the
  stored set's share of the query's true label.
* Look-ahead ratios: burn-in ``b = max(1, round(rb T))``, horizon ``h = max(1, round(rh T))``,
  clipped to ``b + h <= T``. RMSE over the horizon's steps and the 3 action dims, per
  trajectory; ``vs_mn_*`` is the paired difference to M+N on the same trajectories (negative:
  better than behaviour cloning alone), with its standard error.

Writes ``fig9.csv``, ``confidence.csv``, ``lookahead.csv``, ``results.csv`` (all rows, long
format), ``results.json`` (settings, dataset summary, rows, training losses, timings, machine),
``fig9.png``, ``fig4_skill_strategy.png``, ``fig13_phase_success.png``, ``fig14_lookahead.png``,
the dataset used (``dataset.npz``) and the trained models.

Example:
    >>> from smcd_rl.experiments.interpret import InterpretConfig, METHODS
    >>> InterpretConfig().k, METHODS
    (5, ('M+N', 'M+G', 'M+S', 'R+N', 'R+G', 'R+S'))
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.envs.drone_operators import (
    TrajectoryDataset,
    load_dataset,
    save_dataset,
    simulate_operators,
    split_dataset,
)
from smcd_rl.envs.two_link_arm import DEFAULT_DT, integrate_joints, motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    resolve_device,
    seed_everything,
    torch_threads,
    write_csv,
    write_json,
)
from smcd_rl.interpret import confidence_score, top_k_neighbour_accuracy

__all__ = ["InterpretConfig", "FULL", "PARTS", "METHODS", "run"]

#: The parts of the command (``--parts``).
PARTS: tuple[str, ...] = ("fig9", "confidence", "lookahead")
#: Fig. 14's methods: M multi-task / R Reptile training, N none / G gradient descent / S SMCD.
METHODS: tuple[str, ...] = ("M+N", "M+G", "M+S", "R+N", "R+G", "R+S")
_SETS = ("known", "unknown")


@dataclass
class InterpretConfig:
    """Settings of ``smcd-rl interpret``; the defaults finish in a few minutes on 2 CPU cores."""

    out: str = option("runs/interpret", "output directory (results, plots, dataset, trained models)")
    seed: int = option(0, "seed of data, training, filters and the split")
    parts: tuple[str, ...] = option(PARTS, "parts to run: fig9, confidence, lookahead")
    # --- Fig. 9: two-link masks against link lengths
    fig9_latents: tuple[int, ...] = option((32, 128, 512), "two-link hidden widths (latent sizes ld), one model each")
    fig9_tasks: int = option(200, "two-link training arms")
    fig9_episodes: int = option(25, "motor-babbling episodes (10 steps) per training arm")
    fig9_epochs: int = option(20, "two-link training epochs")
    fig9_arms: int = option(200, "held-out arms whose masks are compared")
    fig9_burn_in: int = option(20, "motor-babbling steps observed before the masks are read")
    fig9_particles: int = option(500, "SMCD particles for the two-link masks")
    fig9_own_paths: bool = option(
        False, "each held-out arm babbles along a joint path of its own (default: one shared path)"
    )
    fig9_ks: tuple[int, ...] = option((1, 2, 5, 10, 20, 50), "k of the top-k link-length accuracy")
    # --- drone data
    dataset: str = option(
        "", "a trajectory dataset (.npz, see smcd_rl.envs.drone_operators) instead of the simulated operators"
    )
    operators: int = option(33, "simulated operators")
    trajectories_per_operator: int = option(16, "landings per simulated operator")
    known_fraction: float = option(0.10, "share of all trajectories held out from training operators")
    unknown_fraction: float = option(0.07, "share of operators held out entirely")
    # --- behaviour-cloning model u = f(x)
    hidden: int = option(128, "width of each hidden layer")
    depth: int = option(2, "number of hidden layers")
    dropout: float = option(0.5, "dropout probability p used in training")
    epochs: int = option(20, "training epochs (multi-task)")
    batch_size: int = option(256, "training batch size (multi-task)")
    lr: float = option(1e-3, "Adam learning rate (multi-task)")
    # --- SMCD
    particles: int = option(300, "SMCD mask particles")
    flip_prob: float = option(0.002, "SMCD bit-flip probability per step")
    noise_scale: float = option(0.7, "SMCD likelihood noise, in units of the model's training RMSE per action dim")
    independent_priors: bool = option(
        False, "draw each mask-comparison filter's prior particles afresh (default: one shared set)"
    )
    chunk: int = option(64, "trajectories filtered at once (bounds memory: chunk x particles x hidden)")
    # --- confidence (Fig. 4, Fig. 13)
    labels: tuple[str, ...] = option(
        ("skill", "strategy", "phase", "success"), "labels to score (per-step or per-trajectory)"
    )
    k: int = option(5, "nearest stored masks in eq. (9)")
    steps: tuple[int, ...] = option((1, 5, 10, 20, 30, 40, 60, 80), "observed steps n at which test masks are scored")
    phase_stride: int = option(5, "steps between stored masks for per-step labels")
    # --- look-ahead (Fig. 14)
    methods: tuple[str, ...] = option(METHODS, "look-ahead methods: M+N M+G M+S R+N R+G R+S")
    burn_in: tuple[float, ...] = option((0.1, 0.25, 0.5), "burn-in as a fraction of the trajectory")
    horizons: tuple[float, ...] = option((0.1, 0.25, 0.5), "look-ahead horizon as a fraction of the trajectory")
    gd_lr: float = option(0.01, "online gradient-descent learning rate (normalised units)")
    gd_steps: int = option(1, "gradient steps per observation (5 over-fits the noisy commands: higher RMSE than M+N)")
    gd_window: int = option(10, "recent transitions in the gradient-descent loss")
    reptile_epochs: int = option(20, "Reptile epochs (operators as tasks)")
    reptile_batch_size: int = option(64, "Reptile inner mini-batch")
    reptile_lr: float = option(0.1, "Reptile outer step size")
    reptile_inner_lr: float = option(0.02, "Reptile inner SGD learning rate (the paper's 0.02)")
    reptile_tasks_per_batch: int = option(1, "operators per Reptile meta step")
    threads: int = option(
        1, "torch CPU threads (small networks run fastest on one, above all on a shared CPU; 0: default)"
    )
    device: str = option("cpu", "torch device: cpu, cuda, cuda:N or auto")
    full: bool = option(False, "the paper's scale (B.2, A.5): hidden 1024, 1000 particles, 400/1000 epochs at lr 1e-4")


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "fig9_latents": (64, 256, 1024),
    "fig9_tasks": 1000,
    "fig9_episodes": 150,
    "fig9_epochs": 200,
    "fig9_arms": 1000,
    "fig9_particles": 1000,
    "hidden": 1024,
    "epochs": 400,
    "batch_size": 64,
    "lr": 1e-4,
    "particles": 1000,
    "chunk": 16,
    "reptile_epochs": 1000,
    "threads": 0,
}


def run(config: InterpretConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the selected parts and write their files; returns the JSON payload."""
    _check(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(config.threads):
        return _run(config, out, progress)


def _run(config: InterpretConfig, out: Path, progress: bool) -> dict[str, Any]:
    device = torch.device(resolve_device(config.device))
    ignored = ("out", "full", "threads", "parts", "methods", "labels")
    settings = {k: v for k, v in config_dict(config).items() if k not in ignored}
    if config.dataset:
        settings["dataset_sha256"] = hashlib.sha256(Path(config.dataset).read_bytes()).hexdigest()
    cache = ResultCache(out / "partial.pt", settings)
    payload: dict[str, Any] = {
        "experiment": "mask interpretability (paper Fig. 4, 9, 13) and drone look-ahead (Fig. 14)",
        "config": config_dict(config),
        "machine": machine_info(),
        "seconds": {},
    }
    tables: list[str] = []
    all_rows: list[dict[str, Any]] = []

    # --- Fig. 9 -------------------------------------------------------------------------
    if "fig9" in config.parts:
        started = time.perf_counter()
        rows = _fig9(config, cache, out, device, progress)
        payload["fig9"] = rows
        payload["seconds"]["fig9"] = time.perf_counter() - started
        write_csv(out / "fig9.csv", rows)
        _plot_fig9(rows, out / "fig9.png")
        tables.append("Fig. 9: top-k link-length accuracy of two-link masks\n" + _fig9_table(rows, config))
        all_rows += [{"figure": "fig9", **r} for r in rows]

    # --- drone data and the multi-task behaviour-cloning model --------------------------------
    drone_parts = [p for p in ("confidence", "lookahead") if p in config.parts]
    if drone_parts:
        started = time.perf_counter()
        data, split = _drone_data(config, out)
        if "confidence" in config.parts:
            _check_labels(config, data, split)
        payload["dataset"] = _summary(data, split)
        model, losses = _train_bc(config, data.select(split["train"]), out, device, progress)
        payload["train_loss"] = losses
        payload["seconds"]["drone_data_and_training"] = time.perf_counter() - started

    if "confidence" in config.parts:
        started = time.perf_counter()
        rows = _confidence(config, cache, model, data, split, device, progress)
        payload["confidence"] = rows
        payload["seconds"]["confidence"] = time.perf_counter() - started
        write_csv(out / "confidence.csv", rows)
        _plot_confidence(rows, ("skill", "strategy"), out / "fig4_skill_strategy.png", config)
        _plot_confidence(rows, ("phase", "success"), out / "fig13_phase_success.png", config)
        tables.append(
            f"Fig. 4 / 13: eq. (9) confidence of the true label, k = {config.k} (mean±std over test trajectories)\n"
            + _confidence_table(rows, config)
        )
        all_rows += [{"figure": "confidence", **r} for r in rows]

    if "lookahead" in config.parts:
        started = time.perf_counter()
        rows, reptile_losses = _lookahead(config, cache, model, data, split, out, device, progress)
        payload["lookahead"] = rows
        if reptile_losses is not None:
            payload["reptile_train_loss"] = reptile_losses
        payload["seconds"]["lookahead"] = time.perf_counter() - started
        write_csv(out / "lookahead.csv", rows)
        _plot_lookahead(rows, config, out / "fig14_lookahead.png")
        tables.append(
            "Fig. 14: look-ahead action RMSE (m/s), rows burn-in ratio, columns horizon ratio\n"
            + _lookahead_table(rows, config)
        )
        all_rows += [{"figure": "lookahead", **r} for r in rows]

    write_csv(out / "results.csv", _long_format(all_rows))
    write_json(out / "results.json", payload)
    print("\n\n".join(tables))
    print(f"\nwrote {out}/results.csv, results.json and the figures' CSV and PNG files")
    return payload


def _check(config: InterpretConfig) -> None:
    unknown = set(config.parts) - set(PARTS)
    if unknown or not config.parts:
        raise ValueError(f"unknown part(s) {sorted(unknown)}; choose from {list(PARTS)}")
    unknown = set(config.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")
    if config.k < 1:
        raise ValueError(f"k must be >= 1, got {config.k}")
    if not config.steps or min(config.steps) < 1:
        raise ValueError(f"steps must be >= 1, got {config.steps}")
    if config.phase_stride < 1 or config.chunk < 1 or config.particles < 1:
        raise ValueError("phase_stride, chunk and particles must be >= 1")
    for name in ("burn_in", "horizons"):
        values = getattr(config, name)
        if not values or not all(0 < v < 1 for v in values):
            raise ValueError(f"{name} ratios must lie in (0, 1), got {values}")
    if "fig9" in config.parts:
        if config.fig9_arms < 2 or not config.fig9_ks or max(config.fig9_ks) > config.fig9_arms - 1:
            raise ValueError(f"fig9 needs 1 <= ks <= fig9_arms - 1 = {config.fig9_arms - 1}, got ks {config.fig9_ks}")
        if config.fig9_burn_in < 1 or not config.fig9_latents:
            raise ValueError("fig9 needs fig9_burn_in >= 1 and at least one latent size")
    if config.dataset and not Path(config.dataset).is_file():
        raise FileNotFoundError(f"--dataset {config.dataset}: no such file")


# ======================================================================== SMCD mask runs
def _smcd(config: InterpretConfig, seed: int, particles: int | None = None, noise_std: Any = 0.05) -> smcd_rl.SMCD:
    return smcd_rl.SMCD(
        num_particles=particles or config.particles,
        flip_prob=config.flip_prob,
        noise_std=noise_std,
        generator=torch.Generator(device=resolve_device(config.device)).manual_seed(seed),
    )


@torch.no_grad()
def _masks(
    model: smcd_rl.AdaptiveModel,
    sequence: TensorDict,
    record: torch.Tensor,
    *,
    prior: torch.Tensor | None,
    chunk: int,
    desc: str,
    progress: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """MMSE masks of an SMCD model run over sequences ``[B, T]``, read after the steps ``record`` marks.

    ``record[b, t]`` asks for sequence ``b``'s mask after observing steps ``0..t``. Returns
    ``(masks [R, mask_dim], rows [R], observed [R])`` with ``observed = t + 1``.
    """
    masks, rows, observed = [], [], []
    for begin in tqdm(range(0, sequence.shape[0], chunk), desc=desc, unit="chunk", disable=not progress):
        part, wanted = sequence[begin : begin + chunk], record[begin : begin + chunk]
        batch = part.shape[0]
        last = int(wanted.any(0).nonzero().max()) + 1 if bool(wanted.any()) else 0
        model.reset(batch_shape=(batch,))
        if prior is not None:
            filt = model.adaptation.filter  # type: ignore[attr-defined]
            filt.particles = prior.to(filt.device).expand(batch, *prior.shape).clone()
        for t in range(last):
            model.observe(part[:, t])
            if bool(wanted[:, t].any()):
                picked = wanted[:, t].nonzero().squeeze(-1)
                masks.append(model.mask[picked].float().cpu())
                rows.append(picked + begin)
                observed.append(torch.full_like(picked, t + 1))
    if not masks:
        raise ValueError("no masks were recorded: every trajectory is shorter than the steps asked for")
    return torch.cat(masks), torch.cat(rows).cpu(), torch.cat(observed).cpu()


def _prior(config: InterpretConfig, net: smcd_rl.MaskedMLP, particles: int, seed: int) -> torch.Tensor | None:
    if config.independent_priors:
        return None
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(particles, net.mask_dim, generator=generator) < net.keep_prob


# ======================================================================== Fig. 9
def _fig9(
    config: InterpretConfig, cache: ResultCache, out: Path, device: torch.device, progress: bool
) -> list[dict[str, Any]]:
    generator = torch.Generator().manual_seed(config.seed + 9_000_009)  # held-out arms, shared by every latent size
    lengths = sample_link_lengths((config.fig9_arms,), generator=generator)
    paths = config.fig9_arms if config.fig9_own_paths else 1
    q = (torch.rand(paths, 2, generator=generator) * 2 - 1) * math.pi
    path = [q]
    for _ in range(config.fig9_burn_in - 1):
        q = integrate_joints(q, torch.randn(paths, 2, generator=generator), DEFAULT_DT)
        path.append(q)
    joints = torch.stack(path, 1).expand(config.fig9_arms, -1, -1)
    ee = two_link_fk(joints, lengths.unsqueeze(1)) + 0.01 * torch.randn(*joints.shape, generator=generator)
    sequence = TensorDict({"q": joints, "ee": ee}, [config.fig9_arms, config.fig9_burn_in], device=device)
    record = torch.zeros(config.fig9_arms, config.fig9_burn_in, dtype=torch.bool)
    record[:, -1] = True

    rows = []
    for latent in config.fig9_latents:
        done = cache.get(f"fig9/{latent}")
        if done is None:
            seed_everything(config.seed)
            data = motor_babbling(
                config.fig9_tasks,
                config.fig9_episodes,
                10,
                measurement_noise=0.01,
                generator=torch.Generator().manual_seed(config.seed),
            )
            net = smcd_rl.MaskedMLP(2, 2, hidden=(latent, latent), dropout=config.dropout, device=device)
            model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
            smcd_rl.fit(
                model,
                data.to(device),
                epochs=config.fig9_epochs,
                batch_size=config.batch_size,
                lr=config.lr,
                seed=config.seed,
                checkpoint=out / f"fig9_ld{latent}.ckpt",
                progress=progress,
            )
            adaptive = model.with_adaptation(_smcd(config, config.seed + 19, config.fig9_particles, noise_std=0.05))
            masks, _, _ = _masks(
                adaptive,
                sequence,
                record,
                prior=_prior(config, net, config.fig9_particles, config.seed + 23),
                chunk=config.chunk,
                desc=f"fig9 ld={latent}",
                progress=progress,
            )
            accuracy = top_k_neighbour_accuracy(masks, lengths, config.fig9_ks)
            done = {"accuracy": accuracy.tolist()}
            cache.put(f"fig9/{latent}", done)
        for k, value in zip(config.fig9_ks, done["accuracy"], strict=True):
            rows.append({"latent": latent, "k": k, "accuracy": value, "chance": k / (config.fig9_arms - 1)})
    return rows


def _fig9_table(rows: list[dict[str, Any]], config: InterpretConfig) -> str:
    lookup = {(r["latent"], r["k"]): r["accuracy"] for r in rows}
    body = [[f"ld={ld}", *[lookup[(ld, k)] for k in config.fig9_ks]] for ld in config.fig9_latents]
    body.append(["chance", *[k / (config.fig9_arms - 1) for k in config.fig9_ks]])
    return format_table(body, ["masks", *[f"k={k}" for k in config.fig9_ks]])


# ======================================================================== drone data and model
def _drone_data(config: InterpretConfig, out: Path) -> tuple[TrajectoryDataset, dict[str, np.ndarray]]:
    if config.dataset:
        data = load_dataset(config.dataset)
    else:
        data = simulate_operators(config.operators, config.trajectories_per_operator, seed=config.seed)
    save_dataset(data, out / "dataset.npz")
    split = split_dataset(
        data, known_fraction=config.known_fraction, unknown_fraction=config.unknown_fraction, seed=config.seed
    )
    return data, split


def _check_labels(config: InterpretConfig, data: TrajectoryDataset, split: dict[str, np.ndarray]) -> None:
    """Before any training: the labels to score exist and the stored set has k masks."""
    missing = [label for label in config.labels if label not in data.labels]
    if missing or not config.labels:
        raise ValueError(
            f"the dataset has no label(s) {missing or '(none given)'}; it has {sorted(data.labels)}. "
            "Pass --labels with the ones to score"
        )
    if config.k > len(split["train"]):
        raise ValueError(f"k = {config.k} but only {len(split['train'])} training trajectories are stored; lower --k")


def _summary(data: TrajectoryDataset, split: dict[str, np.ndarray]) -> dict[str, Any]:
    """Trajectories, steps and label counts per split (what ``chance`` levels come from)."""
    summary: dict[str, Any] = {}
    for name, ids in split.items():
        part = data.select(ids)
        counts = {
            label: {
                part.class_name(label, int(c)): int(n)
                for c, n in zip(*np.unique(values, return_counts=True), strict=True)
            }
            for label, values in part.labels.items()
        }
        summary[name] = {
            "trajectories": part.num_trajectories,
            "steps": int(part.state.shape[0]),
            "operators": int(np.unique(part.operator).size),
            "label_counts": counts,
        }
    return summary


def _steps_td(data: TrajectoryDataset, device: torch.device) -> TensorDict:
    n = data.state.shape[0]
    return TensorDict(
        {"state": torch.from_numpy(data.state), "action": torch.from_numpy(data.action)}, [n], device=device
    )


def _padded(data: TrajectoryDataset, device: torch.device) -> TensorDict:
    """``[N, T_max]`` states and actions, each trajectory padded with copies of its last step."""
    lengths = torch.from_numpy(data.lengths)
    steps = torch.arange(int(lengths.max()))
    index = torch.from_numpy(data.offsets[:-1]).unsqueeze(1) + torch.minimum(steps, lengths.unsqueeze(1) - 1)
    return TensorDict(
        {"state": torch.from_numpy(data.state)[index], "action": torch.from_numpy(data.action)[index]},
        list(index.shape),
        device=device,
    )


def _make_model(config: InterpretConfig, data: TrajectoryDataset, device: torch.device) -> smcd_rl.AdaptiveModel:
    net = smcd_rl.MaskedMLP(
        data.state.shape[1],
        data.action.shape[1],
        hidden=(config.hidden,) * config.depth,
        dropout=config.dropout,
        device=device,
    )
    return smcd_rl.AdaptiveModel(net, in_keys=["state"], out_key="action")


def _train_bc(
    config: InterpretConfig, train: TrajectoryDataset, out: Path, device: torch.device, progress: bool
) -> tuple[smcd_rl.AdaptiveModel, list[float]]:
    seed_everything(config.seed)
    model = _make_model(config, train, device)
    losses = smcd_rl.fit(
        model,
        _steps_td(train, device),
        epochs=config.epochs,
        batch_size=config.batch_size,
        lr=config.lr,
        seed=config.seed,
        checkpoint=out / "bc.ckpt",
        progress=progress,
    )
    model.save(out / "bc_model.pt")
    return model, losses


@torch.no_grad()
def _noise_std(
    model: smcd_rl.AdaptiveModel, train: TrajectoryDataset, config: InterpretConfig, device: torch.device
) -> list[float]:
    """Likelihood noise per action dim: ``noise_scale`` x the model's training RMSE (no adaptation)."""
    plain = model.with_adaptation(smcd_rl.NoAdaptation())
    plain.reset()
    td = _steps_td(train, device)
    prediction = plain(td.exclude("action"))["action"]
    rmse = (prediction - td["action"]).square().mean(0).sqrt().clamp(min=1e-3)
    return (config.noise_scale * rmse).cpu().tolist()


# ======================================================================== Fig. 4 / Fig. 13
def _confidence(
    config: InterpretConfig,
    cache: ResultCache,
    model: smcd_rl.AdaptiveModel,
    data: TrajectoryDataset,
    split: dict[str, np.ndarray],
    device: torch.device,
    progress: bool,
) -> list[dict[str, Any]]:
    train = data.select(split["train"])
    noise = _noise_std(model, train, config, device)
    prior = _prior(config, model.net, config.particles, config.seed + 29)

    stored = cache.get("stored_masks")
    if stored is None:
        lengths = torch.from_numpy(train.lengths)
        steps = torch.arange(int(lengths.max()))
        # The whole trajectory (per-trajectory labels) and every phase_stride steps (per-step labels).
        final = steps.unsqueeze(0) == (lengths.unsqueeze(1) - 1)
        strided = ((steps + 1) % config.phase_stride == 0).unsqueeze(0) & (steps.unsqueeze(0) < lengths.unsqueeze(1))
        adaptive = model.with_adaptation(_smcd(config, config.seed + 31, noise_std=noise))
        masks, rows, observed = _sorted_masks(
            adaptive, train, final | strided, prior, config, device, "stored masks", progress
        )
        stored = {"masks": masks, "rows": rows, "observed": observed, "final": final[rows, observed - 1]}
        cache.put("stored_masks", stored)

    results = []
    for set_name in _SETS:
        test = data.select(split[set_name])
        queries = cache.get(f"query_masks/{set_name}")
        if queries is None:
            lengths = torch.from_numpy(test.lengths)
            steps = torch.arange(int(lengths.max()))
            scored = torch.isin(steps + 1, torch.tensor(config.steps)).unsqueeze(0)
            wanted = scored & (steps.unsqueeze(0) + 1 < lengths.unsqueeze(1))
            adaptive = model.with_adaptation(_smcd(config, config.seed + 37, noise_std=noise))
            masks, rows, observed = _sorted_masks(
                adaptive, test, wanted, prior, config, device, f"{set_name} masks", progress
            )
            queries = {"masks": masks, "rows": rows, "observed": observed}
            cache.put(f"query_masks/{set_name}", queries)
        for label in config.labels:
            results += _score(label, set_name, train, test, stored, queries, config)
    return results


def _sorted_masks(
    model: smcd_rl.AdaptiveModel,
    data: TrajectoryDataset,
    record: torch.Tensor,
    prior: torch.Tensor | None,
    config: InterpretConfig,
    device: torch.device,
    desc: str,
    progress: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_masks` over trajectories sorted by length, so a chunk pads little; rows are dataset ids."""
    order = torch.from_numpy(np.argsort(data.lengths, kind="stable"))
    sequence = _padded(data, device)[order]
    masks, rows, observed = _masks(
        model, sequence, record[order], prior=prior, chunk=config.chunk, desc=desc, progress=progress
    )
    return masks, order[rows], observed


def _score(
    label: str,
    set_name: str,
    train: TrajectoryDataset,
    test: TrajectoryDataset,
    stored: dict[str, torch.Tensor],
    queries: dict[str, torch.Tensor],
    config: InterpretConfig,
) -> list[dict[str, Any]]:
    """Eq. (9) for the true label of every query mask, summarised per observed step n (and per class)."""
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
    ).numpy()
    share = np.bincount(stored_labels, minlength=int(max(stored_labels.max(), true.max())) + 1) / stored_labels.size
    chance = share[true]
    observed = queries["observed"].numpy()
    rows = []
    for n in config.steps:
        for cls in [None, *np.unique(true).tolist()]:
            sel = (observed == n) & ((true == cls) if cls is not None else True)
            if not sel.any():
                continue
            rows.append(
                {
                    "set": set_name,
                    "label": label,
                    "class": "all" if cls is None else test.class_name(label, int(cls)),
                    "steps": n,
                    "mean": float(score[sel].mean()),
                    "std": float(score[sel].std()),
                    "chance": float(chance[sel].mean()),
                    "count": int(sel.sum()),
                }
            )
    return rows


def _confidence_table(rows: list[dict[str, Any]], config: InterpretConfig) -> str:
    lookup = {(r["set"], r["label"], r["steps"]): r for r in rows if r["class"] == "all"}
    body = []
    for label in config.labels:
        for set_name in _SETS:
            cells = [lookup.get((set_name, label, n)) for n in config.steps]
            chance = [c["chance"] for c in cells if c is not None]
            body.append(
                [
                    label,
                    set_name,
                    *[f"{c['mean']:.2f}±{c['std']:.2f}" if c else "-" for c in cells],
                    float(np.mean(chance)) if chance else "-",
                ]
            )
    return format_table(body, ["label", "operators", *[f"n={n}" for n in config.steps], "chance"])


# ======================================================================== Fig. 14
def _lookahead(
    config: InterpretConfig,
    cache: ResultCache,
    model: smcd_rl.AdaptiveModel,
    data: TrajectoryDataset,
    split: dict[str, np.ndarray],
    out: Path,
    device: torch.device,
    progress: bool,
) -> tuple[list[dict[str, Any]], list[float] | None]:
    train = data.select(split["train"])
    models = {"M": model}
    reptile_losses = None
    if any(m.startswith("R+") for m in config.methods):
        models["R"], reptile_losses = _train_reptile(config, train, out, device, progress)
    errors: dict[tuple[str, str], torch.Tensor] = {}
    for name in config.methods:
        base = models[name[0]]
        for set_name in _SETS:
            done = cache.get(f"lookahead/{name}/{set_name}")
            if done is None:
                method = base.with_adaptation(_lookahead_adaptation(name, base, train, config, device))
                done = _evaluate_lookahead(
                    method, data.select(split[set_name]), config, device, f"{name} {set_name}", progress
                )
                cache.put(f"lookahead/{name}/{set_name}", done)
            errors[name, set_name] = done
    rows = []
    for (name, set_name), done in errors.items():
        for i, rb in enumerate(config.burn_in):
            for j, rh in enumerate(config.horizons):
                rmse = done[:, i, j]
                valid = ~torch.isnan(rmse)
                row = {
                    "set": set_name,
                    "method": name,
                    "burn_in": rb,
                    "horizon": rh,
                    **_mean_sem(rmse[valid], "rmse"),
                    "count": int(valid.sum()),
                }
                if ("M+N", set_name) in errors:  # paired over the same trajectories: the spread between them cancels
                    row.update(_mean_sem((rmse - errors["M+N", set_name][:, i, j])[valid], "vs_mn"))
                rows.append(row)
    return rows, reptile_losses


def _mean_sem(values: torch.Tensor, name: str) -> dict[str, float]:
    count = len(values)
    std = float(values.std()) if count > 1 else 0.0
    return {f"{name}_mean": float(values.mean()), f"{name}_std": std, f"{name}_sem": std / math.sqrt(max(count, 1))}


def _train_reptile(
    config: InterpretConfig, train: TrajectoryDataset, out: Path, device: torch.device, progress: bool
) -> tuple[smcd_rl.AdaptiveModel, list[float]]:
    """Reptile with operators as tasks: each operator's training steps, subsampled to the smallest operator's count."""
    operators = np.unique(train.operator)
    if operators.size < 2:
        raise ValueError("Reptile needs at least 2 training operators (tasks)")
    per_step_operator = train.operator[train.trajectory]
    groups = [np.flatnonzero(per_step_operator == op) for op in operators]
    size = min(len(g) for g in groups)
    rng = np.random.default_rng(config.seed)
    index = torch.from_numpy(np.stack([np.sort(rng.choice(g, size=size, replace=False)) for g in groups]))
    td = TensorDict(
        {"state": torch.from_numpy(train.state)[index], "action": torch.from_numpy(train.action)[index]},
        list(index.shape),
        device=device,
    )
    seed_everything(config.seed)
    model = _make_model(config, train, device)
    losses = smcd_rl.fit_reptile(
        model,
        td,
        epochs=config.reptile_epochs,
        batch_size=config.reptile_batch_size,
        lr=config.reptile_lr,
        inner_lr=config.reptile_inner_lr,
        inner_epochs=1,
        tasks_per_batch=config.reptile_tasks_per_batch,
        seed=config.seed,
        checkpoint=out / "reptile.ckpt",
        progress=progress,
    )
    model.save(out / "reptile_model.pt")
    return model, losses


def _lookahead_adaptation(
    name: str, model: smcd_rl.AdaptiveModel, train: TrajectoryDataset, config: InterpretConfig, device: torch.device
) -> smcd_rl.Adaptation:
    strategy = name[2]
    if strategy == "N":
        return smcd_rl.NoAdaptation()
    if strategy == "G":
        return smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window)
    return _smcd(config, config.seed + 41, noise_std=_noise_std(model, train, config, device))


@torch.no_grad()
def _evaluate_lookahead(
    method: smcd_rl.AdaptiveModel,
    test: TrajectoryDataset,
    config: InterpretConfig,
    device: torch.device,
    desc: str,
    progress: bool,
) -> torch.Tensor:
    """Per-trajectory RMSE ``[N, len(burn_in), len(horizons)]`` (NaN where a trajectory is too short)."""
    lengths = torch.from_numpy(test.lengths)
    burn = torch.stack([(rb * lengths).round().clamp(min=1).long() for rb in config.burn_in])  # [R, N]
    horizon = torch.stack([(rh * lengths).round().clamp(min=1).long() for rh in config.horizons])  # [H, N]
    horizon = torch.minimum(horizon.unsqueeze(0), (lengths - burn).unsqueeze(1))  # [R, H, N]: b + h <= T
    result = torch.full((test.num_trajectories, len(config.burn_in), len(config.horizons)), float("nan"))
    padded = _padded(test, device)
    width = int(horizon.max().clamp(min=1))
    # Windows past a trajectory's end read its last step again; the horizon mask drops them.
    ends = torch.arange(padded.shape[1] + width).clamp(max=padded.shape[1] - 1)
    order = torch.from_numpy(np.argsort(test.lengths, kind="stable"))
    for begin in tqdm(range(0, len(order), config.chunk), desc=desc, unit="chunk", disable=not progress):
        rows = order[begin : begin + config.chunk]
        part = padded[rows]
        batch = len(rows)
        method.reset(batch_shape=(batch,))
        for t in range(int(burn[:, rows].max())):
            method.observe(part[:, t])
            for i in range(len(config.burn_in)):
                due = (burn[i, rows] == t + 1) & (burn[i, rows] < lengths[rows])
                if not bool(due.any()):
                    continue
                window = part[:, ends[t + 1 : t + 1 + width]]
                predicted = method(window.exclude("action"))["action"]
                error = (predicted - window["action"]).square().mean(-1).cpu()  # [B, width]
                for j in range(len(config.horizons)):
                    h = horizon[i, j, rows]
                    inside = torch.arange(width).unsqueeze(0) < h.unsqueeze(1)
                    rmse = ((error * inside).sum(1) / h.clamp(min=1)).sqrt()
                    result[rows[due], i, j] = rmse[due]
    return result


def _lookahead_table(rows: list[dict[str, Any]], config: InterpretConfig) -> str:
    lookup = {(r["set"], r["method"], r["burn_in"], r["horizon"]): r["rmse_mean"] for r in rows}
    body = [
        [set_name, method, rb, *[lookup[(set_name, method, rb, rh)] for rh in config.horizons]]
        for set_name in _SETS
        for method in config.methods
        for rb in config.burn_in
    ]
    return format_table(body, ["operators", "method", "burn-in", *[f"h={rh}" for rh in config.horizons]])


# ======================================================================== files and plots
def _long_format(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    columns = list(dict.fromkeys(key for row in rows for key in row))
    return [{c: row.get(c, "") for c in columns} for row in rows]


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plot_fig9(rows: list[dict[str, Any]], path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(4.5, 3.5))
    for latent in dict.fromkeys(r["latent"] for r in rows):
        sel = [r for r in rows if r["latent"] == latent]
        ax.plot([r["k"] for r in sel], [r["accuracy"] for r in sel], marker="o", label=f"ld = {latent}")
    sel = [r for r in rows if r["latent"] == rows[0]["latent"]]
    ax.plot([r["k"] for r in sel], [r["chance"] for r in sel], "k--", label="chance")
    ax.set_xscale("log")
    ax.set_xlabel("k (nearest masks)")
    ax.set_ylabel("top-k link-length accuracy")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_confidence(rows: list[dict[str, Any]], labels: tuple[str, ...], path: Path, config: InterpretConfig) -> None:
    labels = tuple(label for label in labels if label in config.labels)
    if not labels:
        return
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(labels), figsize=(4.5 * len(labels), 3.5), sharey=True, squeeze=False)
    for ax, label in zip(axes[0], labels, strict=True):
        for color, set_name in zip(("C0", "C1"), _SETS, strict=True):
            sel = [r for r in rows if r["label"] == label and r["set"] == set_name and r["class"] == "all"]
            if not sel:
                continue
            n = np.array([r["steps"] for r in sel])
            mean, std = np.array([r["mean"] for r in sel]), np.array([r["std"] for r in sel])
            ax.plot(n, mean, color=color, marker="o", label=f"{set_name} operators")
            ax.fill_between(n, mean - std, mean + std, color=color, alpha=0.2)
            ax.plot(n, [r["chance"] for r in sel], color=color, ls="--", lw=1)
        ax.set_title(f"{label} (dashed: chance)")
        ax.set_xlabel("observed steps n")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"confidence of the true label (k = {config.k})")
    axes[0][-1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_lookahead(rows: list[dict[str, Any]], config: InterpretConfig, path: Path) -> None:
    plt = _pyplot()
    fig, axes = plt.subplots(
        len(_SETS), len(config.burn_in), figsize=(3.4 * len(config.burn_in), 6), sharey=True, squeeze=False
    )
    for r_i, set_name in enumerate(_SETS):
        for c_i, rb in enumerate(config.burn_in):
            ax = axes[r_i][c_i]
            for method in config.methods:
                sel = [r for r in rows if r["set"] == set_name and r["method"] == method and r["burn_in"] == rb]
                ax.plot(
                    [r["horizon"] for r in sel],
                    [r["rmse_mean"] for r in sel],
                    marker="o",
                    label=method,
                    ls="-" if method.startswith("M") else "--",
                )
            ax.set_title(f"{set_name} operators, burn-in {rb:g} T", fontsize=9)
            ax.grid(alpha=0.3)
            if r_i == len(_SETS) - 1:
                ax.set_xlabel("horizon (fraction of T)")
        axes[r_i][0].set_ylabel("action RMSE (m/s)")
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
