#!/usr/bin/env bash
# The paper's experiments at the paper's scale (--full), one command each. Sized for a GPU:
# pass --device cuda where a command has it. The defaults (no --full) are the quick versions the
# README reports. Each command resumes where an interrupted run stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
bash bootstrap.sh
.venv/bin/smcd-rl two-link --full --out runs/full/two-link "$@"
.venv/bin/smcd-rl ant --full --out runs/full/ant "$@"
