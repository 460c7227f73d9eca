"""``smcd-rl panda`` at a tiny scale (files, tables, resume, refused options) and the reaching loop's semantics."""

import csv
import json
import math

import pytest
import torch

import smcd_rl
from smcd_rl import cli
from smcd_rl.envs.panda_reach import panda_fk, sample_goals, sample_tool_lengths
from smcd_rl.experiments.panda import run as panda
from smcd_rl.experiments.shared import stages, tuning
from smcd_rl.experiments.shared.runtime import torch_threads
from smcd_rl.experiments.shared.scoreboard_entry import COLUMNS, HEADLINE, TASK_MASKS
from tests.experiments.test_stages import planned_stages

TINY = [
    "--samples",
    "2000",
    "--hidden",
    "32",
    "--depth",
    "2",
    "--epochs",
    "2",
    "--tasks",
    "4",
    "--seeds",
    "2",
    "--intervals",
    "2",
    "5",
    "--steps",
    "25",
    "--particles",
    "20",
    "--gd-steps",
    "1",
    "--gd-window",
    "3",
    "--tuning-episodes",
    "4",
    "--tuning-steps",
    "5",
    # A small tuning (smcd_rl.tune scores GD, SMCD and the combination twice, unbudgeted and budgeted).
    "--gd-lr",
    "0.1",
    "--calibrate-flips",
    "0.03",
]
LABELS = [
    "FK",
    "M+N",
    "M+G",
    "M+S",
    "M+S(evidence)",
    "M+S(paper)",
    "M+C",
    "M+L",
    "M+SL",
    "T+N",
    "T+G",
    "T+S",
    "T+L",
    "T+SL",
]


class Interrupted(RuntimeError):
    """Stands for a Ctrl-C mid-run (pytest would stop the session on a real KeyboardInterrupt)."""


def _table(printed: str) -> list[str]:
    """The first Markdown table printed (the success rates; the verdict table follows it)."""
    lines = printed.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return lines[start:end]


def _without_times(table: list[str]) -> list[str]:
    """The table without its last column, the ms per observation: wall times differ between runs that tune afresh."""
    return [line.rsplit("|", 2)[0] for line in table]


def test_panda_command_writes_files_and_a_resumed_run_gives_the_same_table(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "run"
    monkeypatch.setattr(stages, "RESUMED_SECONDS", 0.0)  # tiny stages count as timed: the time left shows
    assert cli.main(["panda", "--out", str(out), *TINY]) == 0
    captured = capsys.readouterr()
    printed = captured.out
    assert planned_stages(captured.err, "run")[:5] == ["train", "train T", "tune M", "tune T", "evaluate FK n=1"]
    table = _table(printed)
    assert [cell.strip() for cell in table[0].split("|")[1:-1]] == ["method", "n=2", "n=5", "ms / observation"]
    assert [line.split("|")[1].strip() for line in table[2:]] == LABELS
    # The last column: every method of the network has its time per observation, FK none.
    timed = {line.split("|")[1].strip(): line.split("|")[-2].strip() for line in table[2:]}
    assert timed["FK"] == "-" and all(0 < float(timed[m]) < math.inf for m in LABELS[1:])
    # The headline verdicts: M+S against M+N, M+G, M+S(evidence) and M+S(paper); then the tuning tables.
    assert "M+S paired with M+N, M+G, M+S(evidence) and M+S(paper)" in printed
    assert "| 5        | M+S    | M+G " in printed and "| 5        | M+S    | M+S(evidence) |" in printed
    assert "Tuning of M on 4 held-out training-task episodes x 5 steps" in printed
    assert "M: tuned on 4 held-out training-task episodes x 5 steps" in printed
    assert "M: tuned under 10 ms per observation" in printed
    # T, whose masks were trained to identify the tool, is tuned on the same episodes and paired with M's methods.
    assert "T: tuned on 4 held-out training-task episodes x 5 steps" in printed
    assert "T+S (masks trained to identify the task) paired with M+G, M+L, M+S, M+SL" in printed
    assert (out / "task_model.pt").is_file()
    files = ("results.csv", "trials.csv", "comparisons.csv", "results.json", "panda.png", "tuning-M.png", "report.md")
    for name in (*files, "model.pt"):
        assert (out / name).is_file(), name
    assert len(list(out.glob("train-*.ckpt"))) == 1
    rows = list(csv.DictReader(open(out / "results.csv")))
    # FK also runs at n = 1 (the reference line of Fig. 3) although 1 is not among the intervals.
    assert {(r["method"], int(r["interval"])) for r in rows} == {
        ("FK", 1),
        ("FK", 2),
        ("FK", 5),
        *((m, n) for m in LABELS[1:] for n in (2, 5)),
    }
    for r in rows:
        low, mean, high = float(r["success_low"]), float(r["success_mean"]), float(r["success_high"])
        assert 0.0 <= low <= mean <= high <= 1.0 and int(r["seeds"]) == 2 and int(r["trials"]) == 2 * 4
        assert (r["ms_per_observation"] == "") if r["method"] == "FK" else float(timed[r["method"]]) > 0
    assert len(list(csv.DictReader(open(out / "trials.csv")))) == len(rows) * 2 * 4
    # Every adaptive method against M+N, and pairwise (M+S, M+S(evidence), M+S(paper), M+C, M+G, FK), at each
    # interval both run at.
    pairs = {(c["interval"], c["method"], c["against"]) for c in csv.DictReader(open(out / "comparisons.csv"))}
    for n in ("2", "5"):
        assert {(n, "M+S", "M+N"), (n, "M+S", "M+G"), (n, "M+S", "M+S(paper)"), (n, "M+G", "FK")} <= pairs
        assert {(n, "M+S", "M+S(evidence)"), (n, "M+C", "M+N"), (n, "M+C", "M+G"), (n, "M+S(evidence)", "FK")} <= pairs
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["tasks"] == 4 and payload["machine"]["torch_threads"] >= 1
    assert payload["held_out_rmse_m"] > 0 and len(payload["train_loss"]) == 2
    report = (out / "report.md").read_text()
    assert "M+S(paper)" in report and "Tuning of M" in report and "tuning-M.png" in report
    assert "M+C" in report and "ms / observation" in report

    # A rerun finds every (method, n) run and the tuning done: it must not control a single arm again.
    def no_reaching(*args, **kwargs):
        raise AssertionError("a finished run was redone")

    monkeypatch.setattr(panda, "reach", no_reaching)
    monkeypatch.setattr(tuning, "_tune", no_reaching)
    assert cli.main(["panda", "--out", str(out), *TINY]) == 0
    assert _table(capsys.readouterr().out) == table
    monkeypatch.undo()

    # Interrupted in the 7th batch of arms (FK's three intervals x two seeds finished): the
    # resumed run redoes only the other (method, n) runs and prints the same table.
    reach, calls, interrupt_at = panda.reach, [], [7]

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) in interrupt_at:
            raise Interrupted
        return reach(*args, **kwargs)

    monkeypatch.setattr(panda, "reach", interrupted)
    resumed = tmp_path / "resumed"
    with pytest.raises(Interrupted):
        cli.main(["panda", "--out", str(resumed), *TINY])
    capsys.readouterr()
    calls.clear()
    interrupt_at.clear()
    assert cli.main(["panda", "--out", str(resumed), *TINY]) == 0
    assert _without_times(_table(capsys.readouterr().out)) == _without_times(table)  # tuned afresh in this folder
    assert len(calls) == (len(rows) - 3) * 2  # the two seeds of every run but FK's three

    # Which runs there are does not change what a run computes: FK alone first, then every
    # method, and the FK runs are reused.
    subset = tmp_path / "subset"
    assert cli.main(["panda", "--out", str(subset), *TINY, "--methods", "FK"]) == 0
    capsys.readouterr()
    calls.clear()
    assert cli.main(["panda", "--out", str(subset), *TINY]) == 0
    assert _without_times(_table(capsys.readouterr().out)) == _without_times(table)
    assert len(calls) == (len(rows) - 3) * 2


def test_results_json_has_the_tuning_and_the_scoreboard_entry(tmp_path, capsys) -> None:
    """GD's chosen settings come from the grid (or its extension past an edge); the scoreboard shows all six
    strategies at n = 20, each with its time per observation."""
    out = tmp_path / "run"
    grid = ["--gd-lr", "0.01", "0.1", "--gd-window", "3", "6"]
    assert cli.main(["panda", "--out", str(out), *TINY, *grid, "--intervals", "5", "20"]) == 0
    capsys.readouterr()
    payload = json.loads((out / "results.json").read_text())
    entry = payload["tuning"]["M"]
    ran = {m.partition("+")[2] for m in panda.PandaConfig().methods if m.startswith("M+")}  # each variant that runs
    assert set(entry["specs"]) == set(entry["traces"]) == set(entry["ms_per_observation"]) == ran
    gd = entry["specs"]["G"]
    assert gd["name"] == "gradient_descent" and gd["settings"]["loss"] in ("mse", "huber", "tukey")
    # The grid, extended past an edge by its own ratio (lr x10) or by doubling (steps, window).
    assert math.log10(gd["settings"]["lr"] / 0.01) == pytest.approx(round(math.log10(gd["settings"]["lr"] / 0.01)))
    assert gd["settings"]["steps"] in (1, 2, 4, 8) and gd["settings"]["window"] in (3, 6, 12, 24, 48)
    assert entry["specs"]["C"]["name"] == "combination" and entry["specs"]["S(evidence)"]["name"] == "smcd"
    assert entry["episodes"] == 4 and entry["steps"] == 5
    board = payload["scoreboard"]
    assert board["task"] == "Panda reaching" and board["cell"] == {"interval": panda.HEADLINE_INTERVAL}
    assert board["metric"] == "success" and board["lower_is_better"] is False
    ran = list(HEADLINE)  # every strategy of M, the last layers too, and every strategy of T
    assert set(board["estimates"]) == {*ran, TASK_MASKS, "T+N", "T+G", "T+L", "T+SL"} == set(COLUMNS)
    assert [board["estimates"][c]["method"] for c in ran] == [f"M+{HEADLINE[c]}" for c in ran]
    assert all(e["trials"] == 2 * 4 and 0.0 <= e["mean"] <= 1.0 for e in board["estimates"].values())
    assert all(v != "not compared" for v in board["verdicts"].values())
    # Each strategy's time is its method's, measured on the tuning episodes.
    expected = {c: entry["ms_per_observation"][HEADLINE[c]] for c in ran}
    on_t = payload["tuning"]["T"]["ms_per_observation"]
    on_t_ms = {TASK_MASKS: on_t["S"], **{f"T+{v}": on_t[v] for v in ("N", "G", "L", "SL")}}
    assert board["ms_per_observation"] == {**expected, **on_t_ms}
    assert all(0 < ms < math.inf for ms in board["ms_per_observation"].values())
    # --gd-lr with one value is a one-point grid.
    assert cli.make_config("panda", {"gd_lr": (0.01,)}).gd_lr == (0.01,)


def test_m_s_paper_is_smcd_at_exactly_noise_std_and_flip_prob(tmp_path, capsys, monkeypatch) -> None:
    built = []
    strategy = tuning.Tuning.strategy

    def recording(self, variant, **kwargs):
        built.append((variant, result := strategy(self, variant, **kwargs)))
        return result

    monkeypatch.setattr(tuning.Tuning, "strategy", recording)
    out = tmp_path / "run"
    paper = ["--noise-std", "0.037", "--flip-prob", "0.02", "--methods", "M+S(paper)", "M+S", "--intervals", "5"]
    assert cli.main(["panda", "--out", str(out), *TINY, *paper]) == 0
    capsys.readouterr()
    by_variant = {variant: s for variant, s in built}
    assert [variant for variant, _ in built] == ["S", "S", "S(paper)", "S(paper)"]  # two seeds each
    assert isinstance(by_variant["S(paper)"], smcd_rl.SMCD)
    assert by_variant["S(paper)"].noise_std == 0.037 and by_variant["S(paper)"].flip_prob == 0.02
    assert by_variant["S(paper)"].num_particles == 20
    specs = json.loads((out / "results.json").read_text())["tuning"]["M"]["specs"]
    assert specs["S(paper)"]["settings"]["noise_std"] == 0.037 and specs["S(paper)"]["settings"]["flip_prob"] == 0.02
    assert specs["S"]["settings"]["noise_std"] != 0.037  # tuned: M+S's own likelihood noise


def test_help_full_preset_and_bad_options(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["panda", "--help"])
    printed = capsys.readouterr().out
    assert exit_info.value.code == 0 and "--intervals" in printed
    for option in ("--tuning-episodes", "--tuning-steps", "--gd-lr", "--calibrate-flips", "S(paper)", "S(evidence)"):
        assert option in printed, option
    defaults = cli.make_config("panda", {})
    assert defaults.tasks * defaults.seeds >= 250  # power for a 0.1 success-rate difference (see panda.py)
    assert defaults.noise_std == 0.02 and panda.HEADLINE_INTERVAL in defaults.intervals
    config = cli.make_config("panda", {"full": True, "tasks": 7})
    assert config.tasks == 7 and config.hidden == 1024 and config.samples == 100_000 and config.seeds == 5
    assert cli.make_config("panda", {}).threads == 1


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--methods", "FK", "X+Y"], "--methods: unknown value 'X+Y'"),
        (["--intervals", "0"], "--intervals must be >= 1"),
        (["--particles", "0"], "--particles must be >= 1"),
        (["--particles", "-5"], "--particles must be >= 1"),
        (["--gd-lr", "0"], "--gd-lr must be > 0"),
        (["--tuning-episodes", "1"], "--tuning-episodes must be >= 2"),
        (["--gd-steps", "1", "20"], "--gd-steps 20 is above --gd-max-steps 10"),
        (["--tuning-steps", "1"], "--tuning-steps must be >= 2"),
        (["--epochs", "0"], "--epochs must be >= 1"),
        (["--seeds", "0"], "--seeds must be >= 1"),
        (["--dropout", "1"], "--dropout must be < 1"),
        (["--flip-prob", "2"], "--flip-prob must be <= 1"),
        (["--noise-std", "0"], "--noise-std must be > 0"),
        (["--dt", "-0.1"], "--dt must be > 0"),
        (["--tool-range", "-1"], "--tool-range must be >= 0"),
        (["--device", "tpu"], "unknown device 'tpu'"),
    ],
)
def test_bad_options_are_refused_before_any_training(tmp_path, capsys, option, message) -> None:
    """Validation runs before any work: no data, no training, not even the output directory."""
    out = tmp_path / "run"
    assert cli.main(["panda", "--out", str(out), *TINY, *option]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_measurements_arrive_every_nth_step_and_model_reference_control_needs_a_true_model() -> None:
    config = panda.PandaConfig(steps=120)
    generator = torch.Generator().manual_seed(0)
    tools = sample_tool_lengths(12, generator=generator)
    goals = sample_goals(tools, generator=generator)
    seen: list[int] = []
    calls = iter(range(10**6))

    def observe(q: torch.Tensor, measured: torch.Tensor) -> None:
        torch.testing.assert_close(measured, panda_fk(q, tools))  # exact, noise-free measurements
        seen.append(next(calls))

    # The last goal lies out of reach, so the loop runs all 120 steps (it stops once all arrive).
    far_goals = torch.cat([goals[:-1], torch.tensor([[3.0, 0.0, 0.0]])])
    with torch_threads(1):
        # The true kinematics needs no measurements: model-reference control alone reaches the goals.
        true = panda.reach(lambda q: panda_fk(q, tools), observe, tools, far_goals, interval=7, config=config)
        # The chain without the tool, measured once at the start: it settles where its own
        # prediction meets the goal, so the true end effector ends |l| away (the tool's length).
        blind = panda.reach(lambda q: panda_fk(q, 0.0), None, tools, goals, interval=10**6, config=config)
    assert len(seen) == len(range(0, 120, 7))
    assert int(true["reached"][:-1].sum()) >= 10 and not true["reached"][-1]
    # Measured: 10 of 12 end within 1 cm of |l|; two never bring their own prediction onto the goal
    # (one is held by a joint limit, one stalls). A final distance that matches the tool's own
    # length to 1 cm by accident is rare, and 8 leaves room for such arms.
    settled = (blind["final_distance"] - tools.abs()).abs() < 0.01
    assert int(settled.sum()) >= 8


def test_the_plan_ranks_the_evaluations_as_the_default_run_measured_them() -> None:
    """Counted in forwards, the plan put SMCD's updates above gradient descent's, which the default
    run measured six times dearer (every arm steps its own weights): the time left swung from 18
    minutes to over an hour as the stages ran. Measured there: the combination and GD at n = 1
    are the two longest evaluations, and M+G at n = 1 took seven times M+S's."""
    costs = panda.stage_costs(panda.PandaConfig())
    evaluations = sorted((cost, name) for name, cost in costs.items() if name.startswith("evaluate "))
    assert [name for _, name in evaluations[-2:]] == ["evaluate M+G n=1", "evaluate M+C n=1"]
    assert costs["evaluate M+G n=1"] > 5 * costs["evaluate M+S n=1"]
    assert costs["evaluate M+SL n=1"] > costs["evaluate M+S(paper) n=1"] > costs["evaluate M+S n=1"]
    # The settings scale it: twice the arms, twice each evaluation; SMCD's updates follow the particles.
    wider = panda.stage_costs(panda.PandaConfig(tasks=200, particles=200))
    assert wider["evaluate M+N n=1"] == pytest.approx(2 * costs["evaluate M+N n=1"])
    assert wider["evaluate M+S n=1"] > 3 * costs["evaluate M+S n=1"]
