#!/usr/bin/env bash
# The paper's experiments at the paper's scale (--full), one command each. Sized for a GPU:
# pass --device cuda where a command has it. The defaults (no --full) are the quick versions the
# README reports. Each command resumes where an interrupted run stopped.
set -euo pipefail
cd "$(dirname "$0")/.."
bash bootstrap.sh
.venv/bin/smcd-rl two-link --full --out runs/full/two-link "$@"
.venv/bin/smcd-rl panda --full --out runs/full/panda "$@"
.venv/bin/smcd-rl telescoping --full --out runs/full/telescoping "$@"
.venv/bin/smcd-rl interpret --full --out runs/full/interpret "$@"
for study in training smcd drone; do
    .venv/bin/smcd-rl sweep --study "$study" --full --out "runs/full/sweep-$study" "$@"  # on a cluster: --address auto
done
.venv/bin/smcd-rl ant --full --out runs/full/ant "$@"
