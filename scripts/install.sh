#!/usr/bin/env bash
# Set up (or update) the project's virtual environment in .venv with the pinned versions
# from constraints/ci.txt. Idempotent: a second run only checks. Used by test.sh and
# quickstart.sh; source-able so that the venv stays active in the caller.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python_bin="${PYTHON:-python3}"
venv="${AMPN_VENV:-$root/.venv}"

if [ ! -x "$venv/bin/python" ]; then
    echo "[install] creating virtual environment in $venv"
    "$python_bin" -m venv "$venv"
fi
# shellcheck disable=SC1091
source "$venv/bin/activate"

stamp="$venv/.torch-ampn-install-stamp"
want="$(cat "$root/constraints/ci.txt" "$root/pyproject.toml" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "[install] installing torch-ampn with pinned dependencies (constraints/ci.txt)"
    # torch is named in the same command as everything else so that pip never
    # resolves a newer torch (with CUDA packages) for lightning.
    python -m pip install --quiet --disable-pip-version-check \
        -c "$root/constraints/ci.txt" torch -e "$root[train,test,dev]"
    echo "$want" > "$stamp"
fi

# CPU-only guard: the CI machine has no GPU, and a CUDA torch build means the pin failed.
if python -m pip list --disable-pip-version-check 2>/dev/null | grep -i '^nvidia-'; then
    echo "[install] ERROR: nvidia-* packages were installed (a CUDA torch build slipped in);" \
         "check constraints/ci.txt" >&2
    exit 1
fi
python - <<'PY'
import torch
assert torch.__version__.startswith("2.13.0"), f"unexpected torch {torch.__version__}"
PY
