"""The decision table: computed from the scoreboard's rows by its written rules, and checked against them."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

from smcd_rl.experiments.scoreboard.decisions import SITUATIONS, contradictions, decision_table, holds, parse_table
from smcd_rl.experiments.scoreboard.run import _rows, read_entries

ROOT = Path(__file__).resolve().parents[2]
SCOREBOARD = ROOT / "docs" / "experiments" / "scoreboard" / "scoreboard.json"


def _row(**means: float) -> dict:
    """A lower-is-better row with these means and intervals of +-0.01, no paired verdicts."""
    row = {"task": "toy T=3", "cell": "family=toy, regime=T=3", "lower_is_better": True, "ms": {}}
    for column, mean in means.items():
        row[column], row[f"{column} low"], row[f"{column} high"] = mean, mean - 0.01, mean + 0.01
    return row


def test_the_best_holds_a_tie_holds_and_a_significant_loss_does_not() -> None:
    strategies = ("GD", "SMCD (one-step)", "last layer")
    row = _row(GD=0.30, **{"SMCD (one-step)": 0.20, "last layer": 0.205})
    assert holds(row, "SMCD (one-step)", strategies)  # the best
    assert holds(row, "last layer", strategies)  # its interval overlaps the best's: tied
    assert not holds(row, "GD", strategies)  # far behind
    # A paired verdict decides over the intervals: the last layer significantly worse than SMCD.
    row["last layer vs SMCD (one-step)"] = "worse 0.005 [0.002, 0.008]"
    assert not holds(row, "last layer", strategies)
    # The best by mean but significantly worse than another by a paired verdict: not recommended.
    row["SMCD (one-step) vs GD"] = "worse 0.010 [0.001, 0.020]"
    assert not holds(row, "SMCD (one-step)", strategies)
    # A strategy that did not run never holds; higher-is-better rows pick the highest.
    assert not holds(_row(GD=0.3, **{"last layer": math.nan}), "last layer", ("GD", "last layer"))
    success = {**_row(GD=0.9, **{"last layer": 0.5}), "lower_is_better": False}
    assert holds(success, "GD", ("GD", "last layer")) and not holds(success, "last layer", ("GD", "last layer"))


def test_a_budget_keeps_only_strategies_timed_within_it() -> None:
    row = {**_row(GD=0.1, **{"last layer": 0.3}), "ms": {"GD": 5.0, "last layer": 0.3}}
    assert holds(row, "last layer", ("GD", "last layer"), max_ms=1.0)
    assert not holds(row, "GD", ("GD", "last layer"), max_ms=1.0)


def test_the_committed_readme_table_holds_and_a_tampered_scoreboard_contradicts_it(tmp_path) -> None:
    """Every recommendation of the README's table holds on every scoreboard row it cites; make one
    recommended strategy significantly worse on one cited row and the check names that row."""
    rows = _rows(read_entries(SCOREBOARD)[1])
    readme = (ROOT / "README.md").read_text()
    table = parse_table(readme[readme.index("| your situation") :].split("\n\n")[0])
    assert set(table) == {s.text for s in SITUATIONS}
    assert contradictions(table, rows) == []
    assert parse_table(decision_table(rows)) == table  # the README's is the computed one

    situation, strategy = next((text, used[0]) for text, used in table.items() if used)
    cited = next(s for s in SITUATIONS if s.text == situation)
    data = json.loads(SCOREBOARD.read_text())
    tampered = copy.deepcopy(data)
    index = next(i for i, row in enumerate(rows) if cited.cites(row))
    entry = tampered["entries"][index]["entry"]
    values = [v for e in entry["estimates"].values() for v in (e["low"], e["high"])]
    worst = max(values) + 1.0 if entry["lower_is_better"] else min(values) - 1.0  # beyond every other's interval
    estimate = entry["estimates"][strategy]
    estimate["mean"], estimate["low"], estimate["high"] = worst, worst - 0.1, worst + 0.1
    for verdicts in (entry["verdicts"], entry.get("pairs", {})):  # and every paired verdict says so
        for key in verdicts:
            if key.startswith(f"{strategy} vs "):
                verdicts[key] = "worse 1.000 [0.900, 1.100]"
            elif key.endswith(f" vs {strategy}"):
                verdicts[key] = "better -1.000 [-1.100, -0.900]"
    path = tmp_path / "scoreboard.json"
    path.write_text(json.dumps(tampered))
    found = contradictions(table, _rows(read_entries(path)[1]))
    assert found and all(situation in message for message in found), found
    assert any(rows[index]["task"] in message for message in found), found
