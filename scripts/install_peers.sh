#!/usr/bin/env bash
# A separate virtual environment for the peers' benchmark (benchmarks/compare.py's
# physicsnemo_* variants): NVIDIA PhysicsNeMo 2.2.2 needs psutil >= 6, lasso-python (the
# d3plot extra, in the test environment) psutil 5, so they cannot share .venv. Installs
# torch-ampn[train] with the pinned versions of constraints/ci.txt, PhysicsNeMo, pytest and
# torch-scatter (PhysicsNeMo's MeshGraphNets aggregate with it; built from source against the
# installed torch: about 9 minutes on 2 cores, then pip's wheel cache) into
# ${AMPN_PEERS_VENV:-.venv-peers}; idempotent. Source it to keep the venv active.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${AMPN_PEERS_VENV:-$root/.venv-peers}"
if [ ! -x "$venv/bin/python" ]; then
    echo "[install-peers] creating virtual environment in $venv"
    "${PYTHON:-python3}" -m venv "$venv"
fi
# shellcheck disable=SC1091
source "$venv/bin/activate"
stamp="$venv/.torch-ampn-peers-stamp"
want="$(cat "$root/constraints/ci.txt" "$root/pyproject.toml" "${BASH_SOURCE[0]}" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "[install-peers] installing torch-ampn[train], nvidia-physicsnemo==2.2.2 and pytest"
    python -m pip install --quiet --disable-pip-version-check -c "$root/constraints/ci.txt" \
        torch "nvidia-physicsnemo==2.2.2" pytest pytest-xdist -e "$root[train]"
    echo "[install-peers] building torch-scatter 2.1.2 against torch $(python -c 'import torch; print(torch.__version__)')"
    python -m pip install --quiet --disable-pip-version-check --no-build-isolation "torch-scatter==2.1.2"
    # PhysicsNeMo asks for timm, which pulls PyPI's torchvision: a CUDA build that fails to import
    # beside CPU-only torch ('operator torchvision::nms does not exist'), and torchmetrics (under
    # Lightning) imports it wherever it is installed. The MeshGraphNets need neither: remove a
    # torchvision that does not import (benchmarks/peers.py stands in for timm then).
    if ! python -c "import torchvision" >/dev/null 2>&1 && python -m pip show torchvision >/dev/null 2>&1; then
        echo "[install-peers] removing torchvision $(python -m pip show torchvision | sed -n 's/^Version: //p'): it does not import beside torch $(python -c 'import torch; print(torch.__version__)')"
        python -m pip uninstall --quiet --yes torchvision
    fi
    echo "$want" > "$stamp"
fi
