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

# Extras to install: the main job needs only `train`; the tests also `test` and `dev`.
extras="${AMPN_EXTRAS:-train,test,dev}"
stamp="$venv/.torch-ampn-install-stamp"
want="$(cat "$root/constraints/ci.txt" "$root/pyproject.toml" | sha256sum | cut -d' ' -f1)"
installed_ok() {  # the stamp has this hash and every requested extra
    [ -f "$stamp" ] || return 1
    [ "$(sed -n 1p "$stamp")" = "$want" ] || return 1
    local have extra
    have=",$(sed -n 2p "$stamp"),"
    for extra in ${extras//,/ }; do
        case "$have" in *",$extra,"*) ;; *) return 1 ;; esac
    done
}
if ! installed_ok; then
    # keep the extras installed before (same hash) so that the stamp stays a superset
    if [ -f "$stamp" ] && [ "$(sed -n 1p "$stamp")" = "$want" ]; then
        extras="$(printf '%s,%s' "$(sed -n 2p "$stamp")" "$extras" | tr ',' '\n' | sed '/^$/d' | sort -u | paste -sd, -)"
    fi
    echo "[install] installing torch-ampn[$extras] with pinned dependencies (constraints/ci.txt)"
    # torch is named in the same command as everything else so that pip never
    # resolves a newer torch (with CUDA packages) for lightning.
    python -m pip install --quiet --disable-pip-version-check \
        -c "$root/constraints/ci.txt" torch -e "$root[$extras]"
    printf '%s\n%s\n' "$want" "$extras" > "$stamp"
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
