"""The README's user example runs as printed and shows SMCD adapting."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow
def test_readme_example_adapts_a_users_model(capsys) -> None:
    section = README.read_text().split("## Adapting your own model", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert len([line for line in code.splitlines() if line.strip()]) < 25  # the promise
    exec(compile(code, str(README), "exec"), {"__name__": "readme_example"})
    printed = dict(re.findall(r"(no adaptation|SMCD): RMSE ([0-9.]+)", capsys.readouterr().out))
    # The README quotes these numbers; SMCD must at least halve the error on the unseen gravity.
    assert float(printed["SMCD"]) < 0.5 * float(printed["no adaptation"])
