"""``smcd-rl task-masks``: T trained at every (share, groups) on one family with its experiment's data and
criterion, SMCD calibrated on half of the held-out training-task episodes and scored on the other half."""

import csv
import dataclasses
import json

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl import cli
from smcd_rl.experiments.task_masks import config as task_masks_config
from smcd_rl.experiments.task_masks import families
from smcd_rl.experiments.task_masks.run import beyond_edge, episode_scores
from smcd_rl.tuning.diagnostics import trace


def _rows(path) -> list[dict[str, str]]:
    with open(path) as handle:
        return list(csv.DictReader(handle))


_DEFAULT = task_masks_config.experiment_config


def _small(family: str, seed: int = 0):
    """The pendulum experiment's config at a scale that trains in a second (same code path)."""
    config = _DEFAULT(family, seed)
    return dataclasses.replace(
        config, hidden=32, epochs=2, pendulum_tasks=8, pendulum_episodes=4, tuning_episodes=6, particles=40
    )


def test_the_grid_always_holds_the_experiments_own_setting_first() -> None:
    config = cli.make_config("task-masks", {"family": "telescoping", "shares": (0.5,), "groups": (8, 32)})
    assert config.points() == [(1.0, 32), (0.5, 8), (0.5, 32)]  # telescoping trains T with share 1, 32 groups
    inside = cli.make_config("task-masks", {"family": "telescoping", "shares": (0.5, 1.0), "groups": (32,)})
    assert inside.points() == [(0.5, 32), (1.0, 32)]


def test_groups_that_do_not_divide_the_width_are_refused_before_any_work(tmp_path) -> None:
    out = tmp_path / "run"
    assert cli.main(["task-masks", "--family", "fetch", "--groups", "16", "24", "--out", str(out)]) == 2
    assert not out.exists()
    config = cli.make_config("task-masks", {"family": "fetch", "groups": (24,)})
    with pytest.raises(ValueError, match=r"--groups \[24\] do not divide the fetch network's width 128"):
        config.validate()


def test_look_ahead_scores_per_episode_pool_to_the_traces_error() -> None:
    # Each episode's look-ahead RMSE, squared and averaged over equal-length episodes, is the pooled
    # RMSE the trace reports: the per-episode scores the grid pairs are the criterion's own.
    torch.manual_seed(0)
    net = smcd_rl.MaskedMLP(3, 2, hidden=(16,), dropout=0.5)
    model = smcd_rl.AdaptiveDynamicsModel(net)
    model.fitted = True
    obs = torch.randn(5, 9, 2)
    episodes = TensorDict(
        {"observation": obs[:, :-1], "action": torch.randn(5, 8, 1), "next": {"observation": obs[:, 1:]}}, [5, 8]
    )
    family = dataclasses.make_dataclass("F", [("criterion", str), ("horizon", int)])("lookahead", 3)
    strategy = smcd_rl.SMCD(num_particles=20, noise_std=0.3, generator=torch.Generator().manual_seed(1))
    scores = episode_scores(model, episodes, strategy, family)
    again = trace(
        model,
        episodes,
        smcd_rl.SMCD(num_particles=20, noise_std=0.3, generator=torch.Generator().manual_seed(1)),
        horizon=3,
    )
    assert scores.shape == (5,)
    assert float(scores.square().mean().sqrt()) == pytest.approx(again.lookahead_rmse, rel=1e-6)
    one_step = dataclasses.make_dataclass("F", [("criterion", str), ("horizon", type(None))])("one-step", None)
    plain = episode_scores(model, episodes, smcd_rl.NoAdaptation(), one_step)
    assert plain.tolist() == pytest.approx(trace(model, episodes, smcd_rl.NoAdaptation()).per_episode_rmse)


def test_a_run_pairs_every_point_with_the_experiments_setting_and_names_the_lowest(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(families, "experiment_config", _small)
    monkeypatch.setattr(task_masks_config, "experiment_config", _small)
    out = tmp_path / "run"
    assert cli.main(["task-masks", "--family", "pendulum", "--shares", "0.5", "--groups", "8", "--out", str(out)]) == 0
    for name in ("results.csv", "trials.csv", "comparisons.csv", "results.json", "task-masks.png", "report.md"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "results.json").read_text())["summary"]
    # The grid, and past its edge while its lowest mean lay there (each extension doubles or halves the groups).
    points = [(1.0, 16), (0.5, 8), *(tuple(p) for p in summary["extended"])]  # the regimes pendulum's own first
    for k, (share, groups) in enumerate(points[2:], start=2):
        assert {(share, groups * 2), (share, groups / 2)} & set(points[:k])
    names = [f"share {p[0]:g}, {p[1]} groups" for p in points]
    trials = _rows(out / "trials.csv")
    methods = [f"{name} {m}" for name in names for m in ("T+S", "T+N")]
    assert sorted({r["method"] for r in trials}) == sorted(methods)
    assert all(sum(r["method"] == m for r in trials) == 6 for m in methods)  # scored on the second half of 2 x 6
    error = {m: torch.tensor([float(r["error"]) for r in trials if r["method"] == m]) for m in methods}
    # Every other point is paired with the experiment's own setting, over the same episodes.
    comparisons = {c["method"]: c for c in _rows(out / "comparisons.csv")}
    assert set(comparisons) == {f"{name} T+S" for name in names[1:]}
    assert {c["against"] for c in comparisons.values()} == {"share 1, 16 groups T+S"}
    for name in names[1:]:
        expected = float((error[f"{name} T+S"] - error["share 1, 16 groups T+S"]).mean())
        assert float(comparisons[f"{name} T+S"]["difference"]) == pytest.approx(expected, abs=1e-7)  # CSV digits
    lowest = min(points, key=lambda p: float(error[f"share {p[0]:g}, {p[1]} groups T+S"].mean()))
    assert tuple(summary["best"]) == lowest and tuple(summary["current"]) == (1.0, 16)
    assert summary["calibrated_on"] == summary["scored_on"] == 6
    report = (out / "report.md").read_text()
    assert "The choice (lowest mean T+S error)" in report and "(the experiment's)" in report


def test_the_grid_extends_past_an_edge_where_its_lowest_mean_lies() -> None:
    # Best at the most groups: double them at that share; at the fewest: halve them; inside: stop.
    assert beyond_edge({(0.5, 16): 0.2, (1.0, 16): 0.1, (1.0, 32): 0.05}, width=512) == (1.0, 64)
    assert beyond_edge({(1.0, 8): 0.05, (1.0, 16): 0.1}, width=512) == (1.0, 4)
    assert beyond_edge({(1.0, 8): 0.2, (1.0, 16): 0.1, (1.0, 32): 0.3}, width=512) is None
    # Not past the width, and never a group count that does not divide it.
    assert beyond_edge({(1.0, 16): 0.2, (1.0, 32): 0.1}, width=32) is None
    assert beyond_edge({(1.0, 20): 0.2, (1.0, 40): 0.1}, width=200) is None
