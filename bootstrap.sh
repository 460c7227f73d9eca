#!/usr/bin/env bash
# Create .venv in this checkout (once) and install smcd-rl with the tested, pinned versions.
# constraints.txt pins torch==2.13.0+cpu so pip never resolves a CUDA build on a CPU machine.
# Re-running is cheap: pip runs again only when pyproject.toml or constraints.txt changed.
# `bash bootstrap.sh --mbrl-lib` (or SMCD_MBRL_LIB=1) also installs mbrl-lib (scripts/install_mbrl_lib.sh).
set -euo pipefail
mbrl_lib=${SMCD_MBRL_LIB:-0}
for arg in "$@"; do
    case "$arg" in
        --mbrl-lib) mbrl_lib=1 ;;
        *) echo "bootstrap.sh: unknown option $arg (the only one is --mbrl-lib)" >&2; exit 2 ;;
    esac
done
cd "$(dirname "$0")"
python_bin=${PYTHON:-$(command -v python3.11 || command -v python3)}
[ -x .venv/bin/python ] || "$python_bin" -m venv .venv
stamp=.venv/.installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
    .venv/bin/python -m pip install --quiet --disable-pip-version-check \
        --constraint constraints.txt --editable ".[test]"
    touch "$stamp"
fi
if [ "$mbrl_lib" = 1 ]; then
    bash scripts/install_mbrl_lib.sh
fi
