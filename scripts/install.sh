#!/usr/bin/env bash
# Set up (or update) the project's virtual environment in .venv with the pinned versions
# from constraints/ci.txt. Idempotent: a second run only checks. Used by test.sh and
# quickstart.sh; source-able so that the venv stays active in the caller. On a GPU machine it
# installs PyPI's CUDA build of torch; AMPN_CPU_ONLY=1 (CI) refuses any nvidia-* package.
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
uv_install() {  # uv_install EXTRAS: uv pip install with pip's local settings; non-zero if it cannot
    python -m pip install --quiet --disable-pip-version-check uv >/dev/null 2>&1 || return 1
    local args=(--quiet --python "$venv/bin/python" -c "$root/constraints/ci.txt") value
    for value in ${PIP_FIND_LINKS:-} $(python -m pip config get global.find-links 2>/dev/null || true); do
        args+=(--find-links "$value")
    done
    for value in ${PIP_CONSTRAINT:-} $(python -m pip config get global.constraint 2>/dev/null || true); do
        [ -f "$value" ] && args+=(-c "$value")
    done
    "$venv/bin/uv" pip install "${args[@]}" torch -e "$root[$1]" || {
        echo "[install] uv failed; installing with pip" >&2
        return 1
    }
}
if ! installed_ok; then
    # keep the extras installed before (same hash) so that the stamp stays a superset
    if [ -f "$stamp" ] && [ "$(sed -n 1p "$stamp")" = "$want" ]; then
        extras="$(printf '%s,%s' "$(sed -n 2p "$stamp")" "$extras" | tr ',' '\n' | sed '/^$/d' | sort -u | paste -sd, -)"
    fi
    echo "[install] installing torch-ampn[$extras] with pinned dependencies (constraints/ci.txt)"
    # torch is named in the same command as everything else so that the resolver never
    # picks a newer torch (with CUDA packages) for lightning.
    # uv installs the same versions as pip in about a tenth of the time (2026-12-07: 15 s against
    # 124 s with cold caches); pip's find-links and constraint settings are passed on to it, and
    # pip does the work where uv cannot be installed or fails (AMPN_INSTALLER=pip: pip only).
    if ! { [ "${AMPN_INSTALLER:-uv}" = uv ] && uv_install "$extras"; }; then
        python -m pip install --quiet --disable-pip-version-check \
            -c "$root/constraints/ci.txt" torch -e "$root[$extras]"
    fi
    printf '%s\n%s\n' "$want" "$extras" > "$stamp"
fi

# CPU-only guard, on request (AMPN_CPU_ONLY=1, set by .ci/run): the CI machine has no GPU,
# and a CUDA torch build there means the pin failed. Without it, a CUDA build is fine (GPU machines).
if [ "${AMPN_CPU_ONLY:-0}" = 1 ] \
    && python -m pip list --disable-pip-version-check 2>/dev/null | grep -i '^nvidia-'; then
    echo "[install] ERROR: AMPN_CPU_ONLY=1 but nvidia-* packages were installed" \
         "(a CUDA torch build slipped in); check constraints/ci.txt" >&2
    exit 1
fi
# 2.13.0, 2.13.0+cpu and 2.13.0+cu128 all pass
python - <<'PY'
import torch
assert torch.__version__.startswith("2.13.0"), f"unexpected torch {torch.__version__}"
PY
