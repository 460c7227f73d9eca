"""The experiment harness: options checked first, checkpoints and results keyed by content, honest statistics."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

import smcd_rl
from smcd_rl.experiments.shared.harness import Experiment, ExperimentConfig, setting
from smcd_rl.experiments.shared.stats import cell_statistics, mean_ci, paired_comparisons


@dataclass
class ToyConfig(ExperimentConfig):
    particles: int = setting(10, "particles", low=1)
    dropout: float = setting(0.5, "dropout", above=0.0, below=1.0)
    methods: tuple[str, ...] = setting(("a", "b"), "methods", choices=("a", "b", "c"))
    epochs: int = setting(2, "epochs", low=1)

    NON_EMPTY = ("methods",)
    SELECTION = ("methods",)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"particles": -5}, "--particles must be >= 1, got -5"),
        ({"particles": 2.5}, "--particles must be a int, got 2.5"),
        ({"dropout": 1.0}, "--dropout must be < 1.0"),
        ({"dropout": float("nan")}, "--dropout must be a finite number, got nan"),
        ({"methods": ("a", "x")}, "--methods: unknown value 'x'"),
        ({"methods": ()}, "--methods needs at least one value"),
        ({"threads": -1}, "--threads must be >= 0"),
        ({"device": "tpu"}, "unknown device 'tpu'"),
        ({"dropout": float("inf")}, "--dropout must be a finite number, got inf"),
        ({"methods": ("a", "b", "a")}, "--methods repeats ['a']; give each value once"),
        ({"seed": 2**40}, "--seed must be <= 2147483647"),
        ({"threads": 100_000}, "--threads must be <= 256"),
        ({"out": " "}, "--out must name a directory"),
    ],
)
def test_a_bad_option_is_refused_before_the_output_directory_exists(tmp_path: Path, change, message) -> None:
    config = dataclasses.replace(ToyConfig(out=str(tmp_path / "run")), **change)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace("[", r"\[")):
        with Experiment(config, progress=False):
            pass
    assert not (tmp_path / "run").exists()


def _data(n: int = 64, shift: float = 0.0) -> TensorDict:
    q = torch.linspace(-1, 1, n).unsqueeze(-1)
    return TensorDict({"q": q, "ee": torch.sin(3 * q) + shift}, [n])


def _model(seed: int = 0) -> smcd_rl.AdaptiveModel:
    torch.manual_seed(seed)
    return smcd_rl.AdaptiveModel(smcd_rl.MaskedMLP(1, 1, hidden=(16,)), in_keys=["q"], out_key="ee")


def test_a_checkpoint_is_named_by_the_untrained_model_the_trainer_settings_and_the_data(tmp_path: Path) -> None:
    with Experiment(ToyConfig(out=str(tmp_path)), progress=False) as ex:
        name = ex.checkpoint("train", smcd_rl.fit, _model(), _data(), epochs=2, lr=1e-3)
        assert name == ex.checkpoint("train", smcd_rl.fit, _model(), _data(), epochs=2, lr=1e-3)
        others = {
            ex.checkpoint("train", smcd_rl.fit, _model(), _data(), epochs=3, lr=1e-3),
            ex.checkpoint("train", smcd_rl.fit, _model(), _data(), epochs=2, lr=1e-2),
            ex.checkpoint("train", smcd_rl.fit, _model(), _data(shift=1e-3), epochs=2, lr=1e-3),
            ex.checkpoint("train", smcd_rl.fit, _model(seed=1), _data(), epochs=2, lr=1e-3),
            ex.checkpoint("train", smcd_rl.fit_reptile, _model(), _data(), epochs=2, lr=1e-3),
        }
    assert name not in others and len(others) == 5


def test_fewer_epochs_in_the_same_out_trains_that_many_instead_of_reusing_a_longer_run(tmp_path: Path) -> None:
    """A rerun with --epochs 1 where a 2-epoch checkpoint lies used to return the 2-epoch model."""
    settings = {"batch_size": 16, "lr": 1e-2, "seed": 0}
    with Experiment(ToyConfig(out=str(tmp_path)), progress=False) as ex:
        two = _model()
        assert len(ex.train("train", smcd_rl.fit, two, _data(), epochs=2, **settings)) == 2
        one = _model()
        assert len(ex.train("train", smcd_rl.fit, one, _data(), epochs=1, **settings)) == 1
    assert len(list(tmp_path.glob("train-*.ckpt"))) == 2
    assert not torch.equal(one.net.linears[0].weight, two.net.linears[0].weight)


def test_results_are_reused_for_the_same_content_and_recomputed_for_other_content(tmp_path: Path) -> None:
    calls: list[str] = []

    def evaluate(name: str, method: float) -> dict[str, torch.Tensor]:
        calls.append(name)
        return {"scores": torch.full((3,), method)}

    def run(config: ToyConfig, content: dict) -> dict:
        with Experiment(config, progress=False) as ex:
            return ex.evaluate({m: (lambda m=m: float(ord(m))) for m in config.methods}, evaluate, content=content)

    config = ToyConfig(out=str(tmp_path), methods=("a",))
    first = run(config, {"model": "digest-1"})
    assert calls == ["a"]
    assert torch.equal(run(config, {"model": "digest-1"})["a"]["scores"], first["a"]["scores"]) and calls == ["a"]
    run(dataclasses.replace(config, methods=("a", "b")), {"model": "digest-1"})  # a selection: a is reused
    assert calls == ["a", "b"]
    run(config, {"model": "digest-2"})  # another model under the same file names
    run(dataclasses.replace(config, particles=11), {"model": "digest-2"})  # another setting
    assert calls == ["a", "b", "a", "a"]


def test_the_report_carries_the_tables_and_a_fingerprint_of_the_settings(tmp_path: Path) -> None:
    def write(config: ToyConfig) -> str:
        with Experiment(config, progress=False) as ex:
            ex.write(experiment="toy", tables={"Scores": "| a |\n|---|\n| 1 |"}, rows=[{"a": 1}], payload={})
        return (Path(config.out) / "report.md").read_text()

    def fingerprint(report: str) -> str:
        return report.split("fingerprint `")[1][:12]

    report = write(ToyConfig(out=str(tmp_path / "one")))
    assert "# toy" in report and "**Scores**" in report and "| 1 |" in report and "1 torch thread," in report
    assert fingerprint(report) == fingerprint(write(ToyConfig(out=str(tmp_path / "two"))))  # out is no setting
    assert fingerprint(report) != fingerprint(write(ToyConfig(out=str(tmp_path / "three"), particles=3)))


def test_the_95_percent_interval_covers_the_true_mean_about_95_percent_of_the_time() -> None:
    """400 samples of 40 normal trials: the coverage of a 95% interval has a binomial standard
    deviation of 1.1%, so a coverage outside [0.89, 0.99] means a wrong interval, not bad luck
    (the percentile bootstrap runs ~1-2% under nominal at n = 40)."""
    generator = torch.Generator().manual_seed(0)
    covered = 0
    for _ in range(400):
        estimate = mean_ci(1.0 + torch.randn(40, generator=generator, dtype=torch.float64))
        covered += estimate.low <= 1.0 <= estimate.high
    assert 0.89 <= covered / 400 <= 0.99


def test_pairing_detects_a_small_consistent_difference_that_the_trials_spread_would_hide() -> None:
    """Trials differ by ~1.0 from each other, the methods by 0.05 on every trial: the unpaired
    intervals overlap, yet the paired difference excludes zero."""
    generator = torch.Generator().manual_seed(1)
    base = 2.0 + torch.randn(60, generator=generator, dtype=torch.float64)
    noise = 0.01 * torch.randn(60, generator=generator, dtype=torch.float64)
    scores = {"none": base, "smcd": base - 0.05 + noise}
    a, b = mean_ci(scores["none"]), mean_ci(scores["smcd"])
    assert b.high > a.low  # unpaired, the intervals overlap
    (smcd,) = paired_comparisons(scores, baseline="none", adaptive=["smcd"])
    assert smcd.verdict == "better" and smcd.high < 0 and smcd.low < -0.04
    (higher,) = paired_comparisons(scores, baseline="none", adaptive=["smcd"], lower_is_better=False)
    assert higher.verdict == "worse"


def test_no_difference_is_called_significant_about_5_percent_of_the_time() -> None:
    """200 pairs of methods with the same distribution: a false verdict has probability ~5%;
    more than 12% of 200 (binomial sd 1.5%) would mean the intervals are too narrow."""
    generator = torch.Generator().manual_seed(2)
    false = 0
    for seed in range(200):
        a, b = torch.randn(2, 50, generator=generator, dtype=torch.float64)
        (c,) = paired_comparisons({"none": a, "gd": b}, baseline="none", adaptive=["gd"], seed=seed)
        false += c.verdict != "no significant difference"
    assert false / 200 <= 0.12


def test_cell_statistics_compares_every_adaptive_method_with_the_baseline_and_each_other() -> None:
    generator = torch.Generator().manual_seed(3)
    trials = torch.rand(30, generator=generator)
    scores = {(1,): {"M+N": trials + 1, "M+G": trials + 0.5, "M+S": trials}, (5,): {"M+N": trials, "M+S": trials}}
    rows, comparisons = cell_statistics(scores, cell=("T",), baseline="M+N", adaptive=["M+S", "M+G"], metric="rmse")
    assert [(r["T"], r["method"]) for r in rows] == [(1, "M+N"), (1, "M+G"), (1, "M+S"), (5, "M+N"), (5, "M+S")]
    assert all(r["rmse_low"] <= r["rmse_mean"] <= r["rmse_high"] and r["trials"] == 30 for r in rows)
    verdicts = {(c["T"], c["method"], c["against"]): c["verdict"] for c in comparisons}
    assert verdicts == {
        (1, "M+S", "M+N"): "better",
        (1, "M+G", "M+N"): "better",
        (1, "M+S", "M+G"): "better",
        (5, "M+S", "M+N"): "no significant difference",
    }
    with pytest.raises(ValueError, match="same trials for every method"):
        paired_comparisons({"M+N": trials, "M+S": trials[:10]}, baseline="M+N", adaptive=["M+S"])
    with pytest.raises(ValueError, match="NaN or inf"):
        mean_ci(torch.tensor([1.0, float("nan")]))


def test_an_out_that_is_a_file_is_refused_in_one_line(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("not a directory")
    with pytest.raises(ValueError, match="cannot create the output directory"):
        with Experiment(ToyConfig(out=str(tmp_path / "afile" / "run")), progress=False):
            pass


def test_a_rerun_removes_the_files_of_the_earlier_run_that_it_does_not_write(tmp_path: Path) -> None:
    """A run of one method used to leave the previous run's comparisons.csv (and a part's plot or
    CSV it did not redo) beside its new results, as if they were this run's."""

    def write(comparisons: list, files: list[str]) -> dict:
        for name in files:
            (tmp_path / name).write_text("part")
        with Experiment(ToyConfig(out=str(tmp_path)), progress=False) as ex:
            return ex.write(
                experiment="toy", tables={}, rows=[{"a": 1}], payload={}, comparisons=comparisons, files=files
            )

    write([{"method": "b", "against": "a", "verdict": "better"}], ["fig9.csv"])
    (tmp_path / "model.pt").write_text("not a result file")
    assert (tmp_path / "comparisons.csv").is_file() and (tmp_path / "fig9.csv").is_file()
    result = write([], [])
    assert not (tmp_path / "comparisons.csv").exists() and "comparisons.csv" not in result["files"]
    assert not (tmp_path / "fig9.csv").exists() and (tmp_path / "model.pt").is_file()


def test_results_are_recomputed_after_the_code_changes(tmp_path: Path, monkeypatch) -> None:
    """The cache was keyed by the package version, which does not change with the code."""
    from smcd_rl.experiments.shared import result_store

    calls: list[str] = []

    def run() -> None:
        with Experiment(ToyConfig(out=str(tmp_path), methods=("a",)), progress=False) as ex:
            ex.evaluate({"a": lambda: 1.0}, lambda name, m: calls.append(name) or {"x": m}, content={})

    run()
    run()
    assert calls == ["a"]
    monkeypatch.setattr(result_store, "code_digest", lambda: "other code")
    run()
    assert calls == ["a", "a"]


def test_a_verdict_table_of_no_comparisons_is_left_out_of_the_report(tmp_path: Path, capsys) -> None:
    """Without the baseline a command used to print a verdict table of headers only."""
    from smcd_rl.experiments.shared.stats import verdict_table

    with Experiment(ToyConfig(out=str(tmp_path)), progress=False) as ex:
        tables = {"Scores": "| a |\n|---|\n| 1 |", "Verdicts": verdict_table([], cell=["T"])}
        ex.write(experiment="toy", tables=tables, rows=[{"a": 1}], payload={})
    assert "Verdicts" not in capsys.readouterr().out and "Verdicts" not in (tmp_path / "report.md").read_text()
