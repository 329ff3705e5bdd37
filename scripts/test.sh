#!/usr/bin/env bash
# The test command: installs everything it needs into .venv, lints, then runs the suite.
# Extra arguments go to pytest (e.g. `bash scripts/test.sh -k hierarchy`).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
# shellcheck disable=SC1091
source scripts/install.sh
echo "[test] ruff check"
ruff check .
echo "[test] pytest"
export MPLBACKEND=Agg
# notebook cells get 15 minutes (nbmake: 5): a loaded 2-core machine can slow them far beyond their ~10 s
# --durations: the slowest tests, where the suite's time goes
python -m pytest --nbmake --nbmake-timeout=900 --durations=15 tests examples/notebooks "$@"
