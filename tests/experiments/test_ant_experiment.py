"""``smcd-rl ant`` end to end at a tiny scale: files, table, every cell, resume, bad options."""

import csv
import json

from smcd_rl import cli
from smcd_rl.experiments import ant

TINY = [
    "--transitions",
    "400",
    "--data-episode-steps",
    "100",
    "--hidden",
    "16",
    "--epochs",
    "2",
    "--episodes",
    "2",
    "--episode-steps",
    "4",
    "--horizon",
    "3",
    "--candidates",
    "12",
    "--elites",
    "3",
    "--iterations",
    "2",
    "--particles",
    "8",
]


def test_ant_command_writes_every_cell_and_resumes(tmp_path, capsys, monkeypatch) -> None:
    out = tmp_path / "run"
    assert cli.main(["ant", "--out", str(out), *TINY]) == 0
    printed = capsys.readouterr().out
    assert "| planner" in printed and "healthy" in printed and "crippled" in printed
    for name in ("results.csv", "episodes.csv", "results.json", "ant.png", "model.pt", "data.pt", "partial.pt"):
        assert (out / name).is_file(), name

    rows = list(csv.DictReader(open(out / "results.csv")))
    cells = {(r["planner"], r["adaptation"], r["condition"]) for r in rows}
    expected = {(ant.PLANNERS[p], ant.ADAPTATIONS[a], c) for p, a, c in ant.CELLS}
    assert cells == expected and len(rows) == 18
    episodes = list(csv.DictReader(open(out / "episodes.csv")))
    assert len(episodes) == 18 * 2
    # Episode k is the same episode (seed, leg) in every cell; healthy episodes cripple no leg.
    legs = {(e["condition"], e["episode"]): set() for e in episodes}
    for e in episodes:
        legs[(e["condition"], e["episode"])].add(int(e["leg"]))
    assert all(len(v) == 1 for v in legs.values())
    assert legs[("healthy", "0")] == {-1} and legs[("crippled", "0")] <= {0, 1, 2, 3}
    payload = json.loads((out / "results.json").read_text())
    assert payload["config"]["episodes"] == 2 and len(payload["results"]) == 18
    assert len(payload["training"]["smcd_noise_std"]) == 41

    # A rerun finds every cell finished: evaluating one again would raise.
    def never(*args, **kwargs):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(ant, "_run_cell", never)
    assert cli.main(["ant", "--out", str(out), *TINY]) == 0
    assert capsys.readouterr().out.splitlines()[:20] == printed.splitlines()[:20]
    # A subset of the cells is found in the same cache.
    assert cli.main(["ant", "--out", str(out), *TINY, "--planners", "rs", "--conditions", "crippled"]) == 0
    assert len(list(csv.DictReader(open(out / "results.csv")))) == 3


def test_subset_of_cells_and_single_condition(tmp_path, capsys) -> None:
    out = tmp_path / "subset"
    options = ["--planners", "rs", "--adaptations", "none", "smcd", "--conditions", "crippled"]
    assert cli.main(["ant", "--out", str(out), *TINY, "--episodes", "1", *options]) == 0
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {(r["planner"], r["adaptation"], r["condition"]) for r in rows} == {
        ("RS", "none", "crippled"),
        ("RS", "SMCD", "crippled"),
    }
    assert "crippled" in capsys.readouterr().out


def test_full_preset_and_bad_options(capsys) -> None:
    config = cli.make_config("ant", {"full": True, "episodes": 7})
    assert config.episodes == 7 and config.hidden == 1024 and config.depth == 3
    assert config.transitions == 1_000_000 and config.episode_steps == 1000
    assert cli.make_config("ant", {}).hidden == ant.AntConfig().hidden
    assert cli.main(["ant", "--planners", "ilqr", "--out", "/tmp/never"]) == 2
    assert "unknown planners" in capsys.readouterr().err
    assert cli.main(["ant", "--data-policy", "expert", "--out", "/tmp/never"]) == 2
    assert "unknown data policy" in capsys.readouterr().err
    assert cli.main(["ant", "--crippled-legs", "4", "--out", "/tmp/never"]) == 2
    assert "crippled legs" in capsys.readouterr().err
