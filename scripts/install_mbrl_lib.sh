#!/usr/bin/env bash
# Install mbrl-lib 0.2.0 into this checkout's .venv (made by bootstrap.sh), beside the pinned stack.
# mbrl 0.2.0 pins gymnasium 0.26.3 and hydra-core 1.0.3 (which fails to import on Python 3.11), so it goes
# in without its dependencies, with the few it needs at import, at the versions in constraints.txt.
# Re-running is cheap: pip runs again only when constraints.txt changed.
set -euo pipefail
cd "$(dirname "$0")/.."
pip=(.venv/bin/python -m pip install --quiet --disable-pip-version-check --constraint constraints.txt)
stamp=.venv/.installed-mbrl-lib
if [ ! -f "$stamp" ] || [ constraints.txt -nt "$stamp" ]; then
    echo "install_mbrl_lib: installing mbrl-lib 0.2.0 and the few packages it needs at import (no other dependencies)"
    # All in one --no-deps call: hydra-core and omegaconf need only these and packaging / PyYAML,
    # which the stack has; pip then reports no conflict with mbrl's own (unusable) pins.
    "${pip[@]}" --no-deps mbrl==0.2.0 hydra-core==1.3.2 omegaconf==2.3.0 antlr4-python3-runtime==4.9.3 termcolor==3.3.0
    # The mbrl 0.2.0 wheel also installs its own test suite as a top-level `tests` package, which
    # shadows any project's `tests` (ours imports tests.core...): remove the files its RECORD lists.
    .venv/bin/python - <<'PY'
import importlib.metadata, pathlib
dist = importlib.metadata.distribution("mbrl")
stray = [pathlib.Path(dist.locate_file(f)) for f in dist.files or [] if f.parts[0] == "tests"]
for path in stray:
    path.unlink(missing_ok=True)
for folder in sorted({p.parent for p in stray}, key=lambda p: len(p.parts), reverse=True):
    if folder.is_dir() and not any(folder.iterdir()):  # only what is empty now: mbrl's own folders
        folder.rmdir()
PY
    .venv/bin/python -c "import mbrl.models, mbrl.planning, mbrl.util.common"
    touch "$stamp"
else
    echo "install_mbrl_lib: mbrl-lib is up to date in .venv"
fi
