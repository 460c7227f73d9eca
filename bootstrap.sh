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
        -h | --help)
            echo "usage: bash bootstrap.sh [--mbrl-lib]"
            echo "Creates .venv in this checkout and installs smcd-rl with the versions pinned in constraints.txt."
            echo "  --mbrl-lib  also install mbrl-lib 0.2.0 (its integration tests and scripts/pets_mbrl_lib.py)"
            exit 0
            ;;
        *) echo "bootstrap.sh: unknown option $arg (the only one is --mbrl-lib; see --help)" >&2; exit 2 ;;
    esac
done
cd "$(dirname "$0")"
say() { echo "bootstrap: $*"; }
started=$SECONDS
python_bin=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
    say "creating .venv with $("$python_bin" --version 2>&1) ($python_bin)"
    "$python_bin" -m venv .venv
fi
stamp=.venv/.installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
    say "installing smcd-rl and its pinned dependencies into .venv (a few minutes on a fresh machine)"
    # pip's own lines (Collecting ..., Installing ...) are the progress; only its version notice is off.
    .venv/bin/python -m pip install --disable-pip-version-check --progress-bar off \
        --constraint constraints.txt --editable ".[test]"
    touch "$stamp"
else
    say ".venv is up to date (pyproject.toml and constraints.txt unchanged since the last install)"
fi
if [ "$mbrl_lib" = 1 ]; then
    bash scripts/install_mbrl_lib.sh
fi
say "done in $((SECONDS - started)) s. Next: .venv/bin/smcd-rl two-link (the main experiment), .venv/bin/smcd-rl --help, or .venv/bin/python -m pytest"
