"""Closed-loop tracking with a telescoping link (paper appendix A.4, Fig. 8): ``smcd-rl telescoping``.

Reads top to bottom: seed, make motor-babbling data, train a multi-task (M) and a Reptile (R)
dropout model, then for every method run all trials at once: at each of the 100 steps the
method observes the joint angles and the measured end effector, and the paper's PD law
``u = -K1 J^+ (x - x_g) - K2 q_dot`` (``K1 = 20, K2 = 5``) drives the arm toward a target moving
on a circle, with ``J`` the Jacobian of the method's adapted kinematics at the current angles.
``x`` is the method's own prediction (``--feedback predicted``, the default: model-reference
control, so the adapted model sets both the position and the direction of every correction;
the model still observes a measurement at every step) or the measured end effector
(``--feedback measured``: the model then only sets the direction, through ``J``). A.4 does not
say which; its Fig. 8 differences (an oracle that struggles) appear only with ``predicted``. The second link telescopes, ``l2 = 1 + 0.25 sin(pi k / 20)``, so the
kinematics keep changing. Writes ``results.csv`` (the table), ``curves.csv`` (mean and std of
the error at every step), ``results.json`` (settings, table, curves, training losses, timings,
machine) and ``tracking.png``.
"""

from __future__ import annotations

import math
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor
from tqdm.auto import tqdm

import smcd_rl
from smcd_rl.agents.pd import JacobianPD
from smcd_rl.baselines import OracleModel
from smcd_rl.envs.two_link_arm import motor_babbling, sample_link_lengths, two_link_fk
from smcd_rl.envs.two_link_telescoping import (
    TARGET_ANGULAR_SPEED,
    TELESCOPING_DT,
    circle_target,
    integrate_acceleration,
    sample_initial_state,
    telescoping_link_lengths,
)
from smcd_rl.experiments.common import (
    ResultCache,
    config_dict,
    format_table,
    machine_info,
    option,
    resolve_device,
    seed_everything,
    write_csv,
    write_json,
)

__all__ = ["TelescopingConfig", "FULL", "METHODS", "run", "table"]

#: Fig. 8's methods, plus "true": the PD law with the true telescoping kinematics (the floor
#: that the controller's lag behind the moving target and link sets for every method).
METHODS = ("true", "O+P", "M+N", "M+G", "M+S", "R+N", "R+G", "R+S")


@dataclass
class TelescopingConfig:
    """Settings of ``smcd-rl telescoping``; the defaults finish in minutes on 2 CPU cores.

    Example:
        >>> config = TelescopingConfig(trials=10, feedback="measured")
        >>> config.horizon, config.k1, config.k2, config.methods[:2]
        (100, 20.0, 5.0, ('true', 'O+P'))
    """

    out: str = option("runs/telescoping", "output directory (results, plot, trained models)")
    seed: int = option(0, "seed of data, training and trials")
    model: str = option(
        "",
        "use this trained M model (e.g. runs/two-link/model.pt) instead of training one; --hidden etc. then shape R only",
    )
    tasks: int = option(200, "training arms (link-length draws)")
    episodes: int = option(50, "motor-babbling episodes per training arm")
    steps: int = option(10, "steps per motor-babbling episode")
    hidden: int = option(
        256, "width of each hidden layer (the paper's latent dimension; 256 keeps the default run short)"
    )
    depth: int = option(2, "number of hidden layers")
    dropout: float = option(0.5, "dropout probability p used in training")
    epochs: int = option(20, "training epochs of the multi-task (M) model")
    batch_size: int = option(256, "training batch size of the M model")
    lr: float = option(1e-3, "Adam learning rate of the M model")
    reptile_epochs: int = option(20, "Reptile (R) training epochs (passes over all tasks)")
    reptile_batch_size: int = option(64, "samples per inner SGD step of Reptile")
    reptile_lr: float = option(0.1, "Reptile outer (meta) step size")
    inner_lr: float = option(0.02, "Reptile inner SGD learning rate (the paper's 0.02)")
    inner_epochs: int = option(1, "Reptile inner epochs per task (the paper's 1)")
    tasks_per_batch: int = option(5, "tasks per Reptile meta step")
    measurement_noise: float = option(0.01, "std of the end-effector measurement noise (m), data and trials")
    trials: int = option(100, "tracking episodes per method (all run as one batch)")
    horizon: int = option(100, "steps per tracking episode (the paper's 100)")
    dt: float = option(TELESCOPING_DT, "step (s) of the joint double integrator")
    angular_speed: float = option(TARGET_ANGULAR_SPEED, "target speed around its circle (rad/s)")
    k1: float = option(20.0, "PD gain on the end-effector error (paper: 20)")
    k2: float = option(5.0, "PD gain on the joint velocity (paper: 5)")
    damping: float = option(0.0, "damped least-squares lambda of J^+ (0: the paper's Moore-Penrose inverse)")
    max_acceleration: float = option(100.0, "joint acceleration bound (rad/s^2), as in the env")
    feedback: str = option("predicted", "x in the PD law: 'measured' end effector or the method's 'predicted' one")
    report_steps: tuple[int, ...] = option((10, 25, 50, 100), "steps k whose mean error the table shows")
    methods: tuple[str, ...] = option(METHODS, "methods: true, O+P (oracle PF), M+N, M+G, M+S, R+N, R+G, R+S")
    particles: int = option(1000, "SMCD mask particles")
    flip_prob: float = option(0.01, "SMCD bit-flip probability per step")
    noise_std: float = option(0.05, "likelihood noise std (m) of SMCD and the oracle")
    gd_lr: float = option(0.01, "online gradient-descent learning rate (normalised units)")
    gd_steps: int = option(5, "gradient steps per observation")
    gd_window: int = option(10, "recent transitions in the gradient-descent loss")
    oracle_particles: int = option(1000, "oracle particle count over link lengths")
    oracle_jitter: float = option(0.005, "oracle random-walk std of link lengths per step")
    device: str = option("cpu", "torch device (auto: cuda when available)")
    full: bool = option(False, "the paper's scale: 1000 tasks x 150 episodes, hidden 1024, 1000 trials")


#: What ``--full`` changes (options given explicitly still win). The Reptile epochs follow the
#: paper's remark that its Reptile model trained for 1000 epochs against the M model's 200.
FULL = {
    "tasks": 1000,
    "episodes": 150,
    "hidden": 1024,
    "epochs": 200,
    "batch_size": 64,
    "lr": 1e-4,
    "reptile_epochs": 1000,
    "trials": 1000,
}


def run(config: TelescopingConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the experiment and write its files; returns the JSON payload."""
    _check(config)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(resolve_device(config.device))

    # --- seed, data, models -------------------------------------------------------------------
    generator = seed_everything(config.seed)
    families = {name[0] for name in config.methods if "+" in name} - {"O"}
    models: dict[str, smcd_rl.AdaptiveModel] = {}
    losses: dict[str, list[float]] = {}
    train_seconds: dict[str, float] = {}
    data = None
    if families - ({"M"} if config.model else set()):
        data = motor_babbling(
            config.tasks, config.episodes, config.steps, measurement_noise=config.measurement_noise, generator=generator
        ).to(device)
    if "M" in families:
        if config.model:
            models["M"] = _load_model(config.model, device)
        else:
            models["M"], losses["M"], train_seconds["M"] = _train("M", data, config, out, device, progress=progress)
    if "R" in families:
        models["R"], losses["R"], train_seconds["R"] = _train("R", data, config, out, device, progress=progress)

    # --- tracking trials ------------------------------------------------------------------------
    episodes, noise = _trials(config, device)
    settings = {k: v for k, v in config_dict(config).items() if k not in ("out", "full", "report_steps", "methods")}
    cache = ResultCache(out / "partial.pt", settings)
    errors: dict[str, Tensor] = {}
    timings: dict[str, float] = {}
    for name in config.methods:
        done = cache.get(name)
        if done is None:
            method = _method(name, models, config, device)
            started = time.perf_counter()
            tracked = _track(name, method, episodes, noise, config, progress=progress)
            done = {"errors": tracked, "seconds": time.perf_counter() - started}
            cache.put(name, done)
        errors[name], timings[name] = done["errors"], done["seconds"]

    # --- results --------------------------------------------------------------------------------
    rows = [_row(name, e, config) for name, e in errors.items()]
    curves = [
        {"method": name, "k": k, "error_mean": float(e[:, k].mean()), "error_std": float(e[:, k].std())}
        for name, e in errors.items()
        for k in range(config.horizon + 1)
    ]
    write_csv(out / "results.csv", rows)
    write_csv(out / "curves.csv", curves)
    payload = {
        "experiment": "two-link tracking with a telescoping link (paper appendix A.4, Fig. 8)",
        "config": config_dict(config),
        "machine": machine_info(),
        "train_loss": losses,
        "train_seconds": train_seconds,
        "method_seconds": timings,
        "results": rows,
        "curves": curves,
    }
    write_json(out / "results.json", payload)
    _plot(errors, config, out / "tracking.png")
    print(table(rows, config))
    print(f"\nwrote {out}/results.csv, curves.csv, results.json, tracking.png")
    return payload


def table(rows: list[dict[str, Any]], config: TelescopingConfig) -> str:
    """Mean distance (m) from end effector to target at the report steps, and over the episode.

    Example:
        >>> row = {"method": "M+S", "error_k10": 0.2, "error_k100": 0.1, "episode_mean": 0.15, "episode_std": 0.05}
        >>> print(table([row], TelescopingConfig(report_steps=(10, 100))))
        | method | k=10  | k=100 | episode mean | std   |
        |--------|-------|-------|--------------|-------|
        | M+S    | 0.200 | 0.100 | 0.150        | 0.050 |
    """
    header = ["method", *[f"k={k}" for k in config.report_steps], "episode mean", "std"]
    body = [
        [r["method"], *[r[f"error_k{k}"] for k in config.report_steps], r["episode_mean"], r["episode_std"]]
        for r in rows
    ]
    return format_table(body, header)


def _check(config: TelescopingConfig) -> None:
    unknown = set(config.methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; choose from {list(METHODS)}")
    if config.feedback not in ("measured", "predicted"):
        raise ValueError(f"unknown feedback {config.feedback!r}; use 'measured' or 'predicted'")
    if config.trials < 2 or config.horizon < 1:
        raise ValueError(f"need trials >= 2 (for a std) and horizon >= 1, got {config.trials} and {config.horizon}")
    bad = [k for k in config.report_steps if not 0 <= k <= config.horizon]
    if bad:
        raise ValueError(f"report_steps {bad} lie outside 0..horizon={config.horizon}; pass steps within the episode")
    if not (config.dt > 0 and config.max_acceleration > 0 and config.damping >= 0):
        raise ValueError(
            f"need dt > 0, max_acceleration > 0 and damping >= 0, got {config.dt}, "
            f"{config.max_acceleration}, {config.damping}"
        )
    if config.model and not Path(config.model).is_file():
        raise FileNotFoundError(
            f"--model {config.model}: no such file; train one with `smcd-rl two-link` or drop --model"
        )


def _load_model(path: str, device: torch.device) -> smcd_rl.AdaptiveModel:
    try:
        model = smcd_rl.load(path).to(device)
    except (pickle.UnpicklingError, EOFError, RuntimeError) as err:  # torch.load's ways of saying "not a checkpoint"
        raise ValueError(
            f"--model {path} is not a saved smcd_rl model ({err}); pass the model.pt of `smcd-rl two-link`"
        ) from err
    if model.in_keys != ["q"] or model.out_keys != ["ee"] or model.net.in_features != 2:
        raise ValueError(
            f"--model {path} maps {model.in_keys} -> {model.out_keys}; this experiment needs a two-link "
            "forward-kinematics model q -> ee, e.g. the model.pt of `smcd-rl two-link`"
        )
    return model


def _train(
    family: str, data: Any, config: TelescopingConfig, out: Path, device: torch.device, *, progress: bool
) -> tuple[smcd_rl.AdaptiveModel, list[float], float]:
    """Train the M (multi-task, :func:`smcd_rl.fit`) or R (:func:`smcd_rl.fit_reptile`) model, resumably."""
    # Own initial weights per family, so a run that trains only one of them trains the same one.
    torch.manual_seed(config.seed + (0 if family == "M" else 1))
    net = smcd_rl.MaskedMLP(2, 2, hidden=(config.hidden,) * config.depth, dropout=config.dropout, device=device)
    model = smcd_rl.AdaptiveModel(net, in_keys=["q"], out_key="ee")
    started = time.perf_counter()
    if family == "M":
        losses = smcd_rl.fit(
            model,
            data,
            epochs=config.epochs,
            batch_size=config.batch_size,
            lr=config.lr,
            seed=config.seed,
            checkpoint=out / "train.ckpt",
            progress=progress,
        )
        model.save(out / "model.pt")
    else:
        # Reptile samples by task: motor_babbling's first batch dim is the task.
        losses = smcd_rl.fit_reptile(
            model,
            data,
            epochs=config.reptile_epochs,
            batch_size=config.reptile_batch_size,
            lr=config.reptile_lr,
            inner_lr=config.inner_lr,
            inner_epochs=config.inner_epochs,
            tasks_per_batch=config.tasks_per_batch,
            seed=config.seed,
            checkpoint=out / "reptile.ckpt",
            progress=progress,
        )
        model.save(out / "reptile.pt")
    return model, losses, time.perf_counter() - started


def _trials(config: TelescopingConfig, device: torch.device) -> tuple[dict[str, Tensor], Tensor]:
    """The episodes every method faces (same arms, targets and measurement noise for all)."""
    generator = torch.Generator().manual_seed(config.seed + 1_000_003)  # disjoint from training data
    episodes = sample_initial_state((config.trials,), generator=generator)
    noise = config.measurement_noise * torch.randn(config.trials, config.horizon, 2, generator=generator)
    return {key: value.to(device) for key, value in episodes.items()}, noise.to(device)


def _method(
    name: str, models: dict[str, smcd_rl.AdaptiveModel], config: TelescopingConfig, device: torch.device
) -> Any:
    if name == "true":
        return None
    if name == "O+P":
        # The oracle knows the two-link kinematics but not that l2 telescopes: its link lengths
        # follow a random walk, the particle filter's usual model of slowly changing parameters.
        return OracleModel(
            lambda lengths, q: two_link_fk(q, lengths),
            lambda shape, g: sample_link_lengths(shape, generator=g, device=g.device),
            in_keys=["q"],
            out_key="ee",
            noise_std=config.noise_std,
            num_particles=config.oracle_particles,
            jitter_std=config.oracle_jitter,
            lower=0.1,
            generator=torch.Generator(device=device).manual_seed(config.seed + 7),
        )
    family, adaptation = name.split("+")
    strategy = {
        "N": lambda: smcd_rl.NoAdaptation(),
        "G": lambda: smcd_rl.GradientDescent(lr=config.gd_lr, steps=config.gd_steps, window=config.gd_window),
        "S": lambda: smcd_rl.SMCD(
            num_particles=config.particles,
            flip_prob=config.flip_prob,
            noise_std=config.noise_std,
            generator=torch.Generator(device=device).manual_seed(config.seed + 11),
        ),
    }[adaptation]()
    return models[family].with_adaptation(strategy)


def _kinematics(method: Any, k: int, l1: Tensor) -> Callable[[Tensor], Tensor]:
    """The method's current kinematics ``q [B, 2] -> ee [B, 2]``, differentiable in ``q``."""
    if method is None:
        lengths = telescoping_link_lengths(k, l1)
        return lambda q: two_link_fk(q, lengths)
    if isinstance(method, OracleModel):
        # The posterior predictive mean, as OracleModel.forward computes it, but on a plain tensor.
        particles, weights = method.filter.particles, method.filter.weights
        return lambda q: (weights.unsqueeze(-1) * two_link_fk(q.unsqueeze(-2), particles)).sum(-2)
    return method.predict


def _track(
    name: str, method: Any, episodes: dict[str, Tensor], noise: Tensor, config: TelescopingConfig, *, progress: bool
) -> Tensor:
    """Distances end effector - target ``[trials, horizon + 1]`` (k = 0 is the start) of one method."""
    l1, radius, start_angle = episodes["l1"], episodes["radius"], episodes["start_angle"]
    q = episodes["q"].clone()
    q_dot = torch.zeros_like(q)
    batch = q.shape[0]
    if method is not None:
        method.reset(batch_shape=(batch,))
    step_angle = config.angular_speed * config.dt
    errors = torch.empty(batch, config.horizon + 1)
    for k in tqdm(range(config.horizon + 1), desc=name, unit="step", disable=not progress):
        ee_true = two_link_fk(q, telescoping_link_lengths(k, l1))
        target = circle_target(k, radius, start_angle, step_angle=step_angle)
        errors[:, k] = (ee_true - target).norm(dim=-1).cpu()
        if k == config.horizon:
            break
        ee = ee_true + noise[:, k]
        with torch.no_grad():
            if method is not None:
                method.observe(TensorDict({"q": q, "ee": ee}, [batch]))
        controller = JacobianPD(_kinematics(method, k, l1), k1=config.k1, k2=config.k2, damping=config.damping)
        position = ee if config.feedback == "measured" else None
        with torch.no_grad():
            u = controller(q, q_dot, target, position=position).clamp(-config.max_acceleration, config.max_acceleration)
        q, q_dot = integrate_acceleration(q, q_dot, u, config.dt)
    return errors


def _row(name: str, errors: Tensor, config: TelescopingConfig) -> dict[str, Any]:
    episode = errors[:, 1:].mean(1)  # k = 0 is the common start, before any control
    row: dict[str, Any] = {"method": name}
    for k in config.report_steps:
        row[f"error_k{k}"] = float(errors[:, k].mean())
        row[f"std_k{k}"] = float(errors[:, k].std())
    row.update(
        episode_mean=float(episode.mean()),
        episode_std=float(episode.std()),
        episode_sem=float(episode.std() / math.sqrt(len(episode))),
        trials=len(episode),
    )
    return row


def _plot(errors: dict[str, Tensor], config: TelescopingConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    steps = torch.arange(config.horizon + 1)
    for name, e in errors.items():
        mean, std = e.mean(0), e.std(0)
        style = {"color": "black", "linestyle": "--"} if name == "true" else {}
        (line,) = ax.plot(steps, mean, label="true kinematics" if name == "true" else name, **style)
        ax.fill_between(steps, (mean - std).clamp_min(0), mean + std, color=line.get_color(), alpha=0.1)
    ax.set_xlabel("step k")
    ax.set_ylabel("distance end effector - target (m)")
    ax.set_title(f"PD tracking with a telescoping link ({config.trials} trials, 1-sigma bands, x {config.feedback})")
    ax.grid(alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
