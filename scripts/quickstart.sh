#!/usr/bin/env bash
# The main job: installs everything into .venv, then runs the quickstart on the embedded
# default data. Outputs go to ./outputs (override with OUT=...).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
# shellcheck disable=SC1091
source scripts/install.sh
out="${OUT:-outputs}"
export MPLBACKEND=Agg
echo "[quickstart] AMG hierarchy of the paper-sized laminate mesh -> $out/hierarchy_levels.png"
python examples/hierarchy_levels.py --out "$out" --cache-dir "$out/cache"
