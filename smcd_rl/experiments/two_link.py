"""Two-link arm look-ahead prediction (paper section 4.1, Fig. 2): ``smcd-rl two-link``.

Reads top to bottom: seed, make data, train the models on the same data (a multi-task dropout
network M, the same architecture trained with Reptile R, and the latent-variable VRNN LV), then
for every method adapt for T burn-in steps on a held-out arm and predict the end effector H steps
ahead with no further observations. Writes ``results.csv`` (the table), ``trials.csv`` (every
trial's RMSE), ``results.json`` (settings, table, training losses, timings, machine) and
``lookahead.png``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.baselines import LatentVariableModel, OracleModel, fit_latent
from smcd_rl.envs.two_link_arm import (
    DEFAULT_DT,
    integrate_joints,
    motor_babbling,
    sample_link_lengths,
    two_link_fk,
)
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    seed_everything,
    write_csv,
    write_json,
)

__all__ = ["TwoLinkConfig", "FULL", "METHODS", "run", "table"]

#: Method labels of Fig. 2 that this command runs.
METHODS = ("O+P", "M+N", "M+G", "M+S", "R+N", "R+G", "R+S", "LV+N")


@dataclass
class TwoLinkConfig:
    """Settings of ``smcd-rl two-link``; the defaults finish in minutes on 2 CPU cores."""

    out: str = option("runs/two-link", "output directory (results, plot, trained model)")
    seed: int = option(0, "seed of data, training and trials")
    tasks: int = option(200, "training arms (link-length draws)")
    episodes: int = option(50, "motor-babbling episodes per training arm")
    steps: int = option(10, "steps per motor-babbling episode")
    hidden: int = option(512, "width of each hidden layer (the paper's latent dimension)")
    depth: int = option(2, "number of hidden layers")
    dropout: float = option(0.5, "dropout probability p used in training")
    epochs: int = option(20, "training epochs")
    batch_size: int = option(256, "training batch size")
    lr: float = option(1e-3, "Adam learning rate")
    measurement_noise: float = option(0.01, "std of the end-effector measurement noise (m), data and trials")
    trials: int = option(500, "held-out arms to evaluate on")
    chunk: int = option(100, "trials evaluated at once (bounds memory: chunk x particles x hidden)")
    burn_in: tuple[int, ...] = option((1, 5, 10, 20), "burn-in (adaptation) steps T")
    horizons: tuple[int, ...] = option((1, 5, 10, 20), "look-ahead horizons H")
    methods: tuple[str, ...] = option(
        METHODS, "methods to run: O+P (oracle PF); M (multi-task) or R (Reptile) + N, G or S; LV+N (VRNN)"
    )
    reptile_epochs: int = option(20, "Reptile epochs (passes over all tasks) of the R network")
    reptile_batch_size: int = option(64, "Reptile inner mini-batch size")
    reptile_lr: float = option(0.1, "Reptile outer (meta) step size")
    reptile_inner_lr: float = option(0.02, "Reptile inner SGD learning rate (the paper's 0.02)")
    reptile_tasks_per_batch: int = option(1, "tasks per Reptile meta step")
    lv_epochs: int = option(20, "training epochs of the latent-variable (VRNN) model")
    lv_width: int = option(128, "width of the VRNN's layers (its recurrent state h has 8 dims)")
    lv_batch_size: int = option(256, "VRNN batch size (two-step windows)")
    lv_lr: float = option(1e-3, "VRNN Adam learning rate")
    particles: int = option(1000, "SMCD mask particles")
    flip_prob: float = option(0.01, "SMCD bit-flip probability per step")
    noise_std: float = option(0.05, "likelihood noise std (m) of SMCD and the oracle")
    gd_lr: float = option(0.01, "online gradient-descent learning rate (normalised units)")
    gd_steps: int = option(5, "gradient steps per observation")
    gd_window: int = option(10, "recent transitions in the gradient-descent loss")
    oracle_particles: int = option(1000, "oracle particle count over link lengths")
    oracle_jitter: float = option(0.005, "oracle random-walk std of link lengths per step")
    device: str = option("cpu", "torch device")
    full: bool = option(
        False, "the paper's scale: 1000 tasks x 150 episodes, hidden 1024, 1000 trials, Reptile 1000 and LV 200 epochs"
    )


#: What ``--full`` changes (options given explicitly still win).
FULL = {
    "tasks": 1000,
    "episodes": 150,
    "hidden": 1024,
    "epochs": 200,
    "batch_size": 64,
    "lr": 1e-4,
    "trials": 1000,
    "chunk": 25,
    "reptile_epochs": 1000,
    "lv_epochs": 200,
    "lv_batch_size": 64,
}


def run(config: TwoLinkConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    unknown = set(config.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")
    if min(config.burn_in) < 1 or min(config.horizons) < 1:
        raise ValueError("burn_in and horizons must be >= 1")
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(config.device)

    # --- seed, data, model ------------------------------------------------------------
    generator = seed_everything(config.seed)
    data = motor_babbling(
        config.tasks, config.episodes, config.steps, measurement_noise=config.measurement_noise, generator=generator
    )
    net = smcd_rl.MaskedMLP(2, 2, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=device)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    started = time.perf_counter()
    losses = smcd_rl.fit(
        model,
        data.to(device),
        epochs=config.epochs,
        batch_size=config.batch_size,
        lr=config.lr,
        seed=config.seed,
        checkpoint=out / "train.ckpt",
        progress=progress,
    )
    train_seconds = time.perf_counter() - started
    model.save(out / "model.pt")
    extra = _train_baselines(config, data, device, out, progress=progress)

    # --- held-out trials ----------------------------------------------------------------
    q, ee, ee_true, lengths = _trials(config, device)
    methods = {
        name: _method(name, model, extra.get("reptile_model"), extra.get("latent_model"), config)
        for name in config.methods
    }
    settings = {k: v for k, v in config_dict(config).items() if k not in ("out", "full")}
    cache = ResultCache(out / "partial.pt", settings)
    sq_errors: dict[str, torch.Tensor] = {}
    timings: dict[str, float] = {}
    for name, method in methods.items():
        done = cache.get(name)
        if done is None:
            started = time.perf_counter()
            errors = _evaluate(method, q, ee, ee_true, config, desc=name, progress=progress)
            done = {"sq_errors": errors, "seconds": time.perf_counter() - started}
            cache.put(name, done)
        sq_errors[name], timings[name] = done["sq_errors"], done["seconds"]

    # --- results --------------------------------------------------------------------------
    rows, trial_rows = [], []
    for name, errors in sq_errors.items():  # errors: [trials, len(burn_in), max H]
        for i, t in enumerate(config.burn_in):
            for h in config.horizons:
                rmse = errors[:, i, :h].mean(-1).sqrt()
                rows.append(
                    {
                        "method": name,
                        "burn_in": t,
                        "horizon": h,
                        "rmse_mean": float(rmse.mean()),
                        "rmse_std": float(rmse.std()),
                        "rmse_sem": float(rmse.std() / math.sqrt(len(rmse))),
                        "trials": len(rmse),
                    }
                )
                trial_rows += [
                    {"method": name, "burn_in": t, "horizon": h, "trial": k, "rmse": float(v)}
                    for k, v in enumerate(rmse)
                ]
    write_csv(out / "results.csv", rows)
    write_csv(out / "trials.csv", trial_rows)
    payload = {
        "experiment": "two-link look-ahead prediction (paper Fig. 2)",
        "config": config_dict(config),
        "machine": machine_info(),
        "train_loss": losses,
        "train_seconds": train_seconds,
        **{k: v for k, v in extra.items() if not k.endswith("_model")},
        "method_seconds": timings,
        "test_link_lengths": lengths.tolist(),
        "results": rows,
    }
    write_json(out / "results.json", payload)
    _plot(rows, config, out / "lookahead.png")
    print(table(rows, config))
    print(f"\nwrote {out}/results.csv, trials.csv, results.json, lookahead.png")
    return payload


def table(rows: list[dict[str, Any]], config: TwoLinkConfig) -> str:
    """RMSE (mean over trials) with burn-in T down and horizon H across, one block per method."""
    header = ["method", "T", *[f"H={h}" for h in config.horizons]]
    lookup = {(r["method"], r["burn_in"], r["horizon"]): r["rmse_mean"] for r in rows}
    methods = list(dict.fromkeys(r["method"] for r in rows))
    body = [[m, t, *[lookup[(m, t, h)] for h in config.horizons]] for m in methods for t in config.burn_in]
    return format_table(body, header)


def _trials(config: TwoLinkConfig, device: torch.device) -> tuple[torch.Tensor, ...]:
    """Held-out arms: joint paths ``q [trials, T+H, 2]``, measured and true ``ee``, link lengths."""
    generator = torch.Generator().manual_seed(config.seed + 1_000_003)  # disjoint from training data
    length = max(config.burn_in) + max(config.horizons)
    lengths = sample_link_lengths((config.trials,), generator=generator)
    q = (torch.rand(config.trials, 2, generator=generator) * 2 - 1) * math.pi
    path = [q]
    for _ in range(length - 1):
        q = integrate_joints(q, torch.randn(config.trials, 2, generator=generator), DEFAULT_DT)
        path.append(q)
    joints = torch.stack(path, 1)
    ee_true = two_link_fk(joints, lengths.unsqueeze(1))
    ee = ee_true + config.measurement_noise * torch.randn(ee_true.shape, generator=generator)
    return joints.to(device), ee.to(device), ee_true.to(device), lengths


def _train_baselines(
    config: TwoLinkConfig, data: TensorDict, device: torch.device, out: Path, *, progress: bool
) -> dict[str, Any]:
    """Train (or load from their checkpoints) the Reptile network and the VRNN that the chosen methods need."""
    result: dict[str, Any] = {}
    # Their initial weights come from seeds of their own, and the global RNG is left as it was,
    # so adding or dropping these methods changes nothing for the others.
    if any(name.startswith("R+") for name in config.methods):
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed + 17)
            net = smcd_rl.MaskedMLP(2, 2, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=device)
        reptile = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
        started = time.perf_counter()
        result["reptile_train_loss"] = smcd_rl.fit_reptile(
            reptile,
            data.to(device),
            epochs=config.reptile_epochs,
            batch_size=config.reptile_batch_size,
            lr=config.reptile_lr,
            inner_lr=config.reptile_inner_lr,
            tasks_per_batch=config.reptile_tasks_per_batch,
            seed=config.seed,
            checkpoint=out / "reptile.ckpt",
            progress=progress,
        )
        result["reptile_train_seconds"] = time.perf_counter() - started
        reptile.save(out / "reptile_model.pt")
        result["reptile_model"] = reptile
    if "LV+N" in config.methods:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed + 19)
            latent = LatentVariableModel(2, 2, in_keys=["q"], out_key="ee", width=config.lv_width, device=device)
        started = time.perf_counter()
        result["latent_train_loss"] = fit_latent(
            latent,
            data.to(device),
            epochs=config.lv_epochs,
            batch_size=config.lv_batch_size,
            lr=config.lv_lr,
            seed=config.seed,
            checkpoint=out / "latent.ckpt",
            progress=progress,
        )
        result["latent_train_seconds"] = time.perf_counter() - started
        result["latent_model"] = latent
    return result


def _method(
    name: str,
    model: smcd_rl.AdaptiveModel,
    reptile: smcd_rl.AdaptiveModel | None,
    latent: LatentVariableModel | None,
    config: TwoLinkConfig,
) -> Any:
    if name == "LV+N":
        return latent
    if name == "O+P":
        return OracleModel(
            lambda lengths, q: two_link_fk(q, lengths),
            lambda shape, g: sample_link_lengths(shape, generator=g),
            in_keys=["q"],
            out_key="ee",
            noise_std=config.noise_std,
            num_particles=config.oracle_particles,
            jitter_std=config.oracle_jitter,
            lower=0.1,
            generator=torch.Generator().manual_seed(config.seed + 7),
        )
    # M and R differ only in how the network was trained; they adapt with identical strategies.
    trained = {"M": model, "R": reptile}[name[0]]
    assert trained is not None
    strategy = {
        "N": lambda: smcd_rl.NoAdaptation(),
        "G": lambda: smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window),
        "S": lambda: smcd_rl.SMCD(
            num_particles=config.particles,
            flip_prob=config.flip_prob,
            noise_std=config.noise_std,
            generator=torch.Generator(device=config.device).manual_seed(config.seed + 11),
        ),
    }[name[2]]()
    return trained.with_adaptation(strategy)


@torch.no_grad()
def _evaluate(
    method: Any,
    q: torch.Tensor,
    ee: torch.Tensor,
    ee_true: torch.Tensor,
    config: TwoLinkConfig,
    *,
    desc: str,
    progress: bool,
) -> torch.Tensor:
    """Squared look-ahead errors ``[trials, len(burn_in), max H]`` of one method.

    The method observes measured positions ``ee``; errors are against the noise-free ``ee_true``.
    """
    trials, max_h = q.shape[0], max(config.horizons)
    errors = torch.empty(trials, len(config.burn_in), max_h)
    chunks = range(0, trials, config.chunk)
    for begin in tqdm(chunks, desc=desc, unit="chunk", disable=not progress):
        qc, eec = q[begin : begin + config.chunk], ee[begin : begin + config.chunk]
        batch = qc.shape[0]
        method.reset(batch_shape=(batch,))
        for t in range(max(config.burn_in)):
            method.observe(TensorDict({"q": qc[:, t], "ee": eec[:, t]}, [batch]))
            if t + 1 in config.burn_in:
                ahead = slice(t + 1, t + 1 + max_h)
                predicted = method(TensorDict({"q": qc[:, ahead]}, [batch, max_h]))["ee"]
                truth = ee_true[begin : begin + batch, ahead]
                errors[begin : begin + batch, config.burn_in.index(t + 1)] = (predicted - truth).square().sum(-1).cpu()
    return errors


def _plot(rows: list[dict[str, Any]], config: TwoLinkConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(config.burn_in), figsize=(3.2 * len(config.burn_in) + 1.0, 3.2), sharey=True)
    axes = [axes] if len(config.burn_in) == 1 else list(axes)
    for ax, t in zip(axes, config.burn_in, strict=True):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["method"] == method and r["burn_in"] == t]
            ax.errorbar(
                [r["horizon"] for r in sel],
                [r["rmse_mean"] for r in sel],
                yerr=[r["rmse_sem"] for r in sel],
                marker="o",
                capsize=2,
                label=method,
            )
        ax.set_title(f"burn-in T = {t}")
        ax.set_xlabel("look-ahead H (steps)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("end-effector RMSE (m)")
    axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside: eight methods would hide lines
    fig.suptitle(f"Two-link look-ahead prediction ({config.trials} held-out arms)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
