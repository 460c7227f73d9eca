#!/usr/bin/env bash
# Create .venv in this checkout (once) and install smcd-rl with the tested, pinned versions.
# constraints.txt pins torch==2.13.0+cpu so pip never resolves a CUDA build on a CPU machine.
# Re-running is cheap: pip runs again only when pyproject.toml or constraints.txt changed.
set -euo pipefail
cd "$(dirname "$0")"
python_bin=${PYTHON:-$(command -v python3.11 || command -v python3)}
[ -x .venv/bin/python ] || "$python_bin" -m venv .venv
stamp=.venv/.installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
    .venv/bin/python -m pip install --quiet --disable-pip-version-check \
        --constraint constraints.txt --editable ".[test]"
    touch "$stamp"
fi
