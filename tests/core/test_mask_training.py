"""fit(mask_training=...): "random" is the old training bit for bit; "task" ties masks to tasks.

The identification test trains a family whose task is invisible in the input: y = sin(x + phase_k)
for 8 phases. Only the mask can tell the network which phase to draw, so how well SMCD's MMSE
mask on unseen samples of a task points back to that task measures whether training tied masks
to tasks.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

import smcd_rl

pytestmark = pytest.mark.usefixtures("one_thread")


def _data(n: int = 512) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    q = torch.rand(n, 2, generator=g) * 6 - 3
    ee = torch.stack([q[:, 0].cos() + q[:, 1].sin(), q[:, 0] * q[:, 1]], -1)
    # Ids that are neither contiguous nor start at 0: fit maps them.
    return TensorDict({"q": q, "ee": ee, "task": torch.tensor([3, 10, 11, 40])[torch.arange(n) % 4]}, [n])


def _model(hidden: int = 32) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    return smcd_rl.AdaptiveModel(
        smcd_rl.MaskedMLP(2, 2, hidden=(hidden, hidden), dropout=0.2), in_keys=["q"], out_key="ee"
    )


def _old_fit(model: smcd_rl.AdaptiveModel, data: TensorDict, *, epochs: int, batch_size: int, lr: float, seed: int):
    """fit's epoch loop as it was before mask training existed, op for op: one Bernoulli mask per
    sample, the shuffle drawn first, the generator reseeded from (seed, epoch)."""
    net = model.net
    x, y = model.training_pairs(data.reshape(-1))
    model.input_norm.fit(x)
    model.output_norm.fit(y)
    x, y = model.input_norm(x), model.output_norm(y)
    optimizer = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=0.0)
    generator = torch.Generator()
    losses = []
    for epoch in range(epochs):
        net.train()
        generator.manual_seed(seed * 1_000_003 + epoch)
        order = torch.randperm(x.shape[0], generator=generator)
        total = 0.0
        for begin in range(0, x.shape[0], batch_size):
            idx = order[begin : begin + batch_size]
            mask = torch.rand(idx.shape[0], net.mask_dim, generator=generator) < net.keep_prob
            loss = (net(x[idx], mask=mask) - y[idx]).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * idx.shape[0]
        losses.append(total / x.shape[0])
    net.eval()
    return losses


def _same_weights(a: smcd_rl.AdaptiveModel, b: smcd_rl.AdaptiveModel) -> bool:
    return all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values(), strict=True))


def test_random_is_the_old_training_bit_for_bit(tmp_path) -> None:
    """Tolerance 0 against the old loop run on this same CPU: same losses, same weights."""
    settings = {"epochs": 3, "batch_size": 64, "lr": 1e-3, "seed": 5}
    old, default, explicit = _model(), _model(), _model()
    reference = _old_fit(old, _data(), **settings)
    assert smcd_rl.fit(default, _data(), progress=False, **settings) == reference
    losses = smcd_rl.fit(
        explicit, _data(), progress=False, mask_training="random", checkpoint=tmp_path / "c.pt", **settings
    )
    assert losses == reference
    assert _same_weights(old, default) and _same_weights(old, explicit)
    # The checkpoint records the settings it always did: checkpoints written before mask
    # training existed compare equal and resume.
    saved = torch.load(tmp_path / "c.pt", weights_only=False)
    assert saved["settings"] == {"batch_size": 64, "lr": 1e-3, "weight_decay": 0.0, "seed": 5}
    assert "mask_groups" not in saved["model"]["net"]


def test_task_training_starts_as_random_and_then_differs() -> None:
    """Epoch 0 has no posterior and is random dropout exactly (on the grouped masks task training
    gives the network); epoch 1 trains through posteriors."""
    random_run, task_run = _model(), _model()
    random_run.net.group_masks(16)
    random_losses = smcd_rl.fit(random_run, _data(), epochs=2, lr=1e-3, progress=False)
    task_losses = smcd_rl.fit(task_run, _data(), epochs=2, lr=1e-3, progress=False, mask_training="task")
    assert task_losses[0] == random_losses[0]
    assert task_losses[1] != random_losses[1]


class Interrupt(Exception):
    pass


def test_task_training_resumes_to_the_same_result(tmp_path) -> None:
    """Interrupted after epoch 1 and resumed in a fresh model: losses, weights and the reported
    posteriors of the resumed epochs equal the uninterrupted run's."""
    settings = {"epochs": 4, "batch_size": 64, "lr": 1e-3, "seed": 2, "mask_training": "task", "mask_particles": 32}
    straight, reports = _model(), {}
    full = smcd_rl.fit(
        straight, _data(), progress=False, mask_callback=lambda e, p: reports.__setitem__(e, p), **settings
    )
    assert sorted(reports) == [1, 2, 3]
    assert reports[1]["tasks"].tolist() == [3, 10, 11, 40]

    def stop_after_two(epoch: int, loss: float) -> None:
        if epoch == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        smcd_rl.fit(
            _model(), _data(), progress=False, checkpoint=tmp_path / "c.pt", callback=stop_after_two, **settings
        )
    fresh, resumed_reports = _model(), {}
    history = smcd_rl.fit(
        fresh,
        _data(),
        progress=False,
        checkpoint=tmp_path / "c.pt",
        mask_callback=lambda e, p: resumed_reports.__setitem__(e, p),
        **settings,
    )
    assert history == full and _same_weights(straight, fresh)
    assert sorted(resumed_reports) == [2, 3]
    for epoch in (2, 3):
        for name, value in reports[epoch].items():
            assert torch.equal(value, resumed_reports[epoch][name]), name


def test_a_task_checkpoint_does_not_resume_as_random_or_with_other_mask_settings(tmp_path) -> None:
    path = tmp_path / "c.pt"
    smcd_rl.fit(_model(), _data(), epochs=1, progress=False, checkpoint=path, mask_training="task")
    others = [{}, {"task_share": 0.9}, {"mask_particles": 7}, {"mask_noise_scale": 2.0}]
    for other in others:  # {} resumes it as "random"; the others change one mask setting
        other = {"mask_training": "task", **other} if other else other
        with pytest.raises(smcd_rl.CheckpointMismatchError, match="settings"):
            smcd_rl.fit(_model(), _data(), epochs=2, progress=False, checkpoint=path, **other)


def test_posterior_diagnostics_are_shaped_and_in_range() -> None:
    reports = []
    smcd_rl.fit(
        _model(),
        _data(),
        epochs=2,
        progress=False,
        mask_training="task",
        mask_particles=40,
        mask_callback=lambda e, p: reports.append(p),
    )
    (p,) = reports
    mask_dim = 32  # two layers of 16 blocks: the grouping task training gives the network
    assert p["mean_masks"].shape == (4, mask_dim) and bool(((p["mean_masks"] >= 0) & (p["mean_masks"] <= 1)).all())
    for name in ("ess_share", "distinct_share"):
        assert p[name].shape == (4,) and bool(((p[name] >= 1 / 40) & (p[name] <= 1)).all()), name
    assert p["shuffled_log_likelihood"].shape == (4,) and bool(torch.isfinite(p["shuffled_log_likelihood"]).all())
    assert p["noise"].shape == (2,) and bool((p["noise"] > 0).all())
    assert bool(torch.isfinite(p["log_likelihood"]).all())


def _unchanged_after(call, model: smcd_rl.AdaptiveModel) -> None:
    before = {k: v.clone() for k, v in model.state_dict().items()}
    call()
    assert not model.fitted, "a refused call must not fit the normalisation"
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


@pytest.mark.parametrize(
    ("change", "kwargs", "error", "message"),
    [
        ("drop", {}, KeyError, "no such key; it has .*pass the key that holds the ids as task_key"),
        ("float", {}, TypeError, "must be an integer tensor, got torch.float32; .*ids.long"),
        ("nan", {}, TypeError, r"float32 \(some are NaN\)"),
        ("one", {}, ValueError, "holds a single task .*mask_training='random'"),
        ("shape", {}, ValueError, r"one task id per sample, shape \[512\]"),
        ("none", {"task_key": "id"}, KeyError, "task_key='id'"),
        ("none", {"mask_training": "tasks"}, ValueError, "mask_training must be 'random' or 'task'"),
        ("none", {"task_share": 1.5}, ValueError, r"task_share must be in \[0, 1\]"),
        ("none", {"mask_particles": 0}, ValueError, "mask_particles must be >= 1"),
        ("none", {"mask_observations": 2.0}, TypeError, "mask_observations must be an int"),
        ("none", {"mask_flip_prob": 0.9}, ValueError, "too large for the keep_rate transition"),
        ("none", {"mask_noise_scale": 0.0}, ValueError, r"mask_noise_scale must be in \(0"),
        ("nan_target", {}, ValueError, "'ee' contains NaN"),
    ],
)
def test_bad_task_inputs_are_refused_before_training(change, kwargs, error, message) -> None:
    data = _data()
    if change == "drop":
        del data["task"]
    elif change in ("float", "nan"):
        data["task"] = data["task"].float()
        if change == "nan":
            data["task"][7] = math.nan
    elif change == "one":
        data["task"] = torch.zeros(512, dtype=torch.long)
    elif change == "shape":
        data["task"] = torch.zeros(512, 2, dtype=torch.long)
    elif change == "nan_target":
        data["ee"][3, 0] = math.nan
    model = _model()
    kwargs = {"mask_training": "task", **kwargs}

    def call() -> None:
        with pytest.raises(error, match=message):
            smcd_rl.fit(model, data, epochs=2, progress=False, **kwargs)

    _unchanged_after(call, model)


def test_mask_callback_without_task_training_is_refused() -> None:
    model = _model()

    def call() -> None:
        with pytest.raises(ValueError, match="pass mask_training='task'"):
            smcd_rl.fit(model, _data(), epochs=1, progress=False, mask_callback=lambda e, p: None)

    _unchanged_after(call, model)


# ---------------------------------------------------------------- the task is recoverable from the mask
TASKS = 8
PHASES = torch.arange(TASKS) * (2 * math.pi / TASKS)


def _sines(per_task: int, seed: int) -> TensorDict:
    """``per_task`` samples of each task k: x ~ U(-pi, pi), y = sin(x + phase_k); batch [per_task * 8]."""
    x = torch.rand(TASKS, per_task, 1, generator=torch.Generator().manual_seed(seed)) * 2 * math.pi - math.pi
    y = torch.sin(x + PHASES.view(-1, 1, 1))
    task = torch.arange(TASKS).view(-1, 1).expand(-1, per_task)
    return TensorDict({"x": x, "y": y, "task": task}, [TASKS, per_task]).reshape(-1)


def _trained(how: str) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(1, 1, hidden=(64, 64), dropout=0.5, mask_groups=8)
    model = smcd_rl.AdaptiveModel(net, in_keys=["x"], out_key="y")
    smcd_rl.fit(
        model, _sines(128, seed=0), epochs=40, batch_size=64, lr=3e-3, progress=False, mask_training=how, seed=0
    )
    return model


def _mmse_masks(model: smcd_rl.AdaptiveModel, data: TensorDict, steps: int, seed: int) -> torch.Tensor:
    """SMCD's MMSE mask of each task ``[8, mask_dim]`` after ``steps`` of its samples, one filter per task."""
    smcd = smcd_rl.SMCD(
        num_particles=200,
        flip_prob=0.01,
        noise_std=model.residual_scale.tolist(),  # the dropout-off residual fit recorded
        generator=torch.Generator().manual_seed(seed),
    )
    adapted = model.with_adaptation(smcd)
    adapted.reset(batch_shape=(TASKS,))
    per_task = data.reshape(TASKS, -1)
    for t in range(steps):
        adapted.observe(per_task[:, t])
    return adapted.mask.clone()


def _identification(model: smcd_rl.AdaptiveModel, repeats: int) -> float:
    """Share of held-out filter runs whose MMSE mask is nearest (Euclidean) to its own task's
    reference mask, among the 8 references inferred from training samples."""
    references = _mmse_masks(model, _sines(16, seed=0), steps=16, seed=100)  # training samples
    hits = 0
    for r in range(repeats):
        queries = _mmse_masks(model, _sines(16, seed=1 + r), steps=16, seed=200 + r)  # unseen samples
        nearest = torch.cdist(queries, references).argmin(-1)
        hits += int((nearest == torch.arange(TASKS)).sum())
    return hits / (TASKS * repeats)


def test_task_training_makes_the_mask_identify_the_task() -> None:
    """Held-out samples of a training task lead the filter back to that task's mask.

    48 identifications (8 tasks x 6 held-out sample sets); chance is 1/8. With masks that carry
    no task, each identification succeeds with probability 1/8, and P(Binomial(48, 1/8) >= 24)
    is about 3e-10: a share of 0.5 or more cannot be reached by chance. Measured on a 2-core
    x86 CPU: task training identifies 0.88, random training 0.25 (a randomly trained network's
    sub-networks fit some phases better than others, but little ties the mask found on one
    sample set to the one found on another). Without groups (128 bits, the filter covers far
    less of the space) the same training identified 0.35 against 0.12 for random training.
    """
    repeats = 6
    chance_tail = sum(math.comb(48, k) * (1 / 8) ** k * (7 / 8) ** (48 - k) for k in range(24, 49))
    assert chance_tail < 1e-9
    task = _identification(_trained("task"), repeats)
    random = _identification(_trained("random"), repeats)
    print(f"task identification: task-trained {task:.2f}, random-trained {random:.2f} (chance {1 / TASKS:.3f})")
    assert task >= 0.5
    assert task > random


def _last_report(task_share: float) -> dict[str, torch.Tensor]:
    """The posteriors reported at the last epoch of the sines' task training with ``task_share``."""
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(1, 1, hidden=(64, 64), dropout=0.5, mask_groups=8)
    model = smcd_rl.AdaptiveModel(net, in_keys=["x"], out_key="y")
    reports: dict[int, dict[str, torch.Tensor]] = {}
    smcd_rl.fit(
        model,
        _sines(128, seed=0),
        epochs=40,
        batch_size=64,
        lr=3e-3,
        progress=False,
        mask_training="task",
        task_share=task_share,
        seed=0,
        mask_callback=lambda epoch, posteriors: reports.__setitem__(epoch, posteriors),
    )
    return reports[39]


def test_the_log_likelihood_of_a_tasks_own_samples_beats_a_shuffled_deal_only_after_task_training() -> None:
    """``log_likelihood - shuffled_log_likelihood`` measures how much a mask is a task's.

    Each task's filter explains its own samples better than the same samples dealt to the tasks at
    random only if some mask stands for the task. With task_share = 0 (random dropout, reported)
    nothing ties a mask to a phase, and the two are equal up to the filters' noise. Measured on a
    2-core x86 CPU: a mean gap of 0.19 nats per observation after task training (every task's
    positive), 0.0005 after random training (some tasks' negative). The thresholds sit halfway.
    """
    task, random = _last_report(0.5), _last_report(0.0)
    for p in (task, random):
        assert p["shuffled_log_likelihood"].shape == p["log_likelihood"].shape == (TASKS,)
    task_gap = task["log_likelihood"] - task["shuffled_log_likelihood"]
    random_gap = random["log_likelihood"] - random["shuffled_log_likelihood"]
    print(f"gap: task-trained {task_gap.mean():.3f}, random-trained {random_gap.mean():.4f}")
    assert float(task_gap.mean()) > 0.1 and bool((task_gap > 0).all())
    assert float(random_gap.mean()) < 0.1


def test_reporting_the_posteriors_does_not_change_the_training() -> None:
    """The shuffled diagnostic draws from a generator of its own: same losses and weights with or without it."""
    settings = {"epochs": 3, "lr": 1e-3, "progress": False, "mask_training": "task", "mask_particles": 16}
    quiet, reported = _model(), _model()
    losses = smcd_rl.fit(quiet, _data(), **settings)
    assert smcd_rl.fit(reported, _data(), mask_callback=lambda e, p: None, **settings) == losses
    assert _same_weights(quiet, reported)


def test_task_training_groups_a_network_of_one_bit_per_unit_and_reattaches_its_strategy() -> None:
    """A network built with its defaults gets the grouping task-mask training was measured best
    with (the divisor of its widths nearest 16), before any epoch; its SMCD then runs on the
    grouped masks. A network built with mask_groups keeps its own."""
    model = smcd_rl.AdaptiveModel(
        smcd_rl.MaskedMLP(2, 2, hidden=(48, 48), dropout=0.2),
        in_keys=["q"],
        out_key="ee",
        adaptation=smcd_rl.SMCD(num_particles=8),
    )
    assert model.net.mask_dim == 96
    smcd_rl.fit(model, _data(), epochs=2, lr=1e-3, progress=False, mask_training="task")
    assert model.net.mask_groups == 16 and model.net.mask_dim == 32
    model.reset(batch_shape=(2,))
    model.observe(_data()[:2].exclude("task"))
    assert model.adaptation.particles.shape == (2, 8, 32)
    own = _model()
    own.net.group_masks(8)
    smcd_rl.fit(own, _data(), epochs=1, lr=1e-3, progress=False, mask_training="task")
    assert own.net.mask_groups == 8
    random = _model()
    smcd_rl.fit(random, _data(), epochs=1, lr=1e-3, progress=False)
    assert random.net.mask_groups is None  # random training keeps one bit per unit
