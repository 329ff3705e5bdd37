#!/usr/bin/env bash
# The test command: installs everything it needs into .venv, lints, then runs the suite.
# Extra arguments go to pytest (e.g. `bash scripts/test.sh -k hierarchy`).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
# shellcheck disable=SC1091
source scripts/install.sh
echo "[test] ruff check, ruff format --check (Python, notebooks and the Markdown code blocks)"
ruff check .
ruff format --check .
echo "[test] lint-imports (the generic core imports nothing of the forming application)"
lint-imports
echo "[test] pytest"
export MPLBACKEND=Agg
# One pytest worker per core (pytest-xdist), each with one thread: torch's OpenMP threads
# spin-wait, and two workers of two threads each on two cores would slow each other down.
# --dist loadgroup: the tests of one xdist_group (e.g. those that share the run's one fit, or
# compile the same graphs) run in one worker, in file order.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# the notebooks run smaller than their committed outputs (fewer meshes, steps and simulations):
# they check that every cell runs; the tests check the numbers
export AMPN_NOTEBOOK_QUICK="${AMPN_NOTEBOOK_QUICK:-1}"
# notebook cells get 15 minutes (nbmake: 5): a loaded 2-core machine can slow them far beyond their ~10 s
# --durations: the slowest tests, where the suite's time goes
python -m pytest -n "${AMPN_TEST_WORKERS:-auto}" --dist loadgroup \
    --nbmake --nbmake-timeout=900 --durations=15 tests examples/notebooks "$@"
