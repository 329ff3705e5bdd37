#!/usr/bin/env bash
# One-shot GPU check and benchmark, for a lent GPU machine (one run, well under 10 minutes).
#
#   bash benchmarks/gpu.sh               # on the GPU machine
#   bash benchmarks/gpu.sh --cpu-check   # every stage on the CPU with tiny sizes, to check this script
#
# Stages (each under `timeout`; a failed stage is recorded and the next one runs):
#   install     AMPN_EXTRAS=train,test bash scripts/install.sh (PyPI's CUDA torch), then the torch
#               version, CUDA availability and device name
#   cuda_tests  pytest tests -k "cuda or gpu": the tests parametrised over CUDA or marked gpu
#   rollout     benchmarks/rollout.py --device cuda --resolution paper, and with --mesh-scale 4
#   simulator   benchmarks/simulate.py --device cuda: paper-resolution trajectories, 8 at once, compiled
#   data        a small paper-resolution dataset (4 / 1 / 1 trajectories), in the background while
#               the stages above run (CPU only: 6 processes, nice 10)
#   fit         200 steps of examples/configs/paper.yaml on that dataset on the GPU, no validation;
#               a callback times every training step (CUDA synchronised): fit_step_times.json
# --cpu-check: install skipped if .venv is set up; the CUDA tests skip; rollout.py --device cpu
# --resolution coarse --quick; simulate.py on the CPU, coarse, 2 at once, eager; a coarse dataset of 2 / 1 / 0 trajectories; a 5-step fit on the CPU
# (paper.yaml with --model.num_levels 3: the coarse mesh has 3 levels).
#
# Logs, results and summary.txt go to ${OUT:-benchmarks/results/gpu} (--cpu-check:
# ${OUT:-$AMPN_BENCH_WORK/cpu_check}). The datasets and the fit's checkpoints go to
# ${AMPN_BENCH_WORK:-/tmp/torch-ampn-gpu-bench}; a second run reuses the datasets.
# AMPN_GPU_BUDGET (default 480 s) bounds the whole run: every stage's timeout is cut to what is
# left of it. Exit status 1 if any stage failed or was skipped.
set -uo pipefail
self="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/$(basename "${BASH_SOURCE[0]}")"
root="$(dirname "$(dirname "$self")")"
cd "$root"

# ---- one stage, run by the driver below as `timeout ... bash benchmarks/gpu.sh --stage NAME` -------
activate() {
    # shellcheck disable=SC1091
    source "${AMPN_VENV:-$root/.venv}/bin/activate"
}

stage_install() {
    if [ "$MODE" = cpu ] && [ -f "${AMPN_VENV:-$root/.venv}/.torch-ampn-install-stamp" ]; then
        echo "[gpu.sh] --cpu-check: .venv is set up, install skipped"
    else
        AMPN_EXTRAS=train,test bash scripts/install.sh || return
    fi
    activate
    python -c "import torch; print(torch.__version__, torch.cuda.is_available(), \
torch.cuda.get_device_name() if torch.cuda.is_available() else 'no CUDA device')"
}

stage_cuda_tests() {
    activate
    # CUDA tests: parametrised over "cuda" (torch_ampn.testing.DEVICES, tests/test_contact.py) or
    # marked gpu; without a GPU they are skipped or not collected. No -x: one run on the machine,
    # so every failure is wanted.
    python -m pytest -q -rs -p no:cacheprovider tests -k "cuda or gpu" \
        --junitxml "$OUT_DIR/cuda_tests.xml"
}

stage_rollout() {  # stage_rollout NAME [extra rollout.py flags]
    activate
    local name=$1
    shift
    if [ "$MODE" = cpu ]; then
        python benchmarks/rollout.py --device cpu --resolution coarse --quick --out "$OUT_DIR/$name" "$@"
    else
        python benchmarks/rollout.py --device cuda --resolution paper --out "$OUT_DIR/$name" "$@"
    fi
}

stage_simulator() {
    activate
    if [ "$MODE" = cpu ]; then
        python benchmarks/simulate.py --resolutions coarse --batch 2 --modes eager --out "$OUT_DIR/simulate.json"
    else
        python benchmarks/simulate.py --device cuda --resolutions paper --batch 8 --modes compiled \
            --out "$OUT_DIR/simulate_cuda.json"
    fi
}

stage_data() {
    activate
    if [ "$MODE" = cpu ]; then  # the coarse mesh, uncompiled solver: about 10 s per trajectory on one core
        nice -n 10 torch-ampn-data generate --out "$DATA_DIR" --resolution coarse \
            --num-train 2 --num-val 1 --num-test 0 --workers 1 --batch 4 --no-compile
    else  # one trajectory per process (each compiles the solver step once); leaves 10 cores to the GPU stages
        local compile=()
        if ! command -v c++ > /dev/null && ! command -v g++ > /dev/null; then
            echo "[gpu.sh] no C++ compiler for torch.compile: the solver runs eager (--no-compile)"
            compile=(--no-compile)
        fi
        nice -n 10 torch-ampn-data generate --out "$DATA_DIR" --resolution paper \
            --num-train 4 --num-val 1 --num-test 1 --workers 6 --batch 1 "${compile[@]}"
    fi
}

write_step_timer() {  # the timing callback, importable as step_timer.StepTimer from $1
    cat > "$1/step_timer.py" <<'PY'
"""Wall time of every training step (forward, backward, optimiser step), CUDA synchronised."""

import json
import statistics
import time

import torch
from lightning.pytorch.callbacks import Callback


class StepTimer(Callback):
    """Writes step_times.json (in the working directory) and prints a summary at the end of fit.

    ``compute``: from on_train_batch_start to on_train_batch_end (the batch is already on the
    device); ``wait``: from a step's end to the next step's start (data loading, transfer).
    The first ``skip`` steps (warm-up) are left out of the means.
    """

    def __init__(self, skip: int = 10) -> None:
        self.skip, self.compute, self.wait = skip, [], []
        self._start = self._end = None

    @staticmethod
    def _now(pl_module) -> float:
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)
        return time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._start = self._now(pl_module)
        if self._end is not None:
            self.wait.append(self._start - self._end)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._end = self._now(pl_module)
        self.compute.append(self._end - self._start)

    def on_train_end(self, trainer, pl_module) -> None:
        n = len(self.compute)
        skip = min(self.skip, n // 2)
        compute = self.compute[skip:]
        # a step's total: its compute plus the wait before it (self.wait[i - 1] precedes step i)
        total = [self.compute[i] + self.wait[i - 1] for i in range(max(skip, 1), min(n, len(self.wait) + 1))]
        wait = self.wait[max(skip, 1) - 1:]
        summary = {
            "device": str(pl_module.device),
            "gpu": torch.cuda.get_device_name(pl_module.device) if pl_module.device.type == "cuda" else None,
            "steps": n, "skipped_warmup_steps": skip,
            "mean_step_s": statistics.fmean(total) if total else None,
            "mean_compute_s": statistics.fmean(compute) if compute else None,
            "median_compute_s": statistics.median(compute) if compute else None,
            "mean_wait_s": statistics.fmean(wait) if wait else None,
            "first_step_s": self.compute[0] if self.compute else None,
            "peak_cuda_memory_gb": torch.cuda.max_memory_allocated(pl_module.device) / 1e9
            if pl_module.device.type == "cuda" else None,
        }
        with open("step_times.json", "w") as f:
            json.dump({"summary": summary, "compute_s": self.compute, "wait_s": self.wait}, f, indent=1)
        ms = {k: 1e3 * v for k, v in summary.items() if k.endswith("_s") and v is not None}
        print(f"[step_timer] {n} steps (means without the first {skip}): "
              f"{ms.get('mean_step_s', float('nan')):.1f} ms/step = compute "
              f"{ms.get('mean_compute_s', float('nan')):.1f} (median {ms.get('median_compute_s', float('nan')):.1f})"
              f" + data wait {ms.get('mean_wait_s', float('nan')):.1f}; first step {ms.get('first_step_s', 0):.0f} ms",
              flush=True)
PY
}

stage_fit() {
    activate
    local fit_dir="$WORK/fit_$MODE" steps=200
    rm -rf "${fit_dir:?}"
    mkdir -p "$fit_dir"
    write_step_timer "$fit_dir"
    local args=(--config "$root/examples/configs/paper.yaml"
        --data.data_dir "$DATA_DIR" --data.generate false
        --trainer.limit_val_batches 0 --trainer.num_sanity_val_steps 0
        --trainer.enable_progress_bar false --model.statistics_samples 20
        "--trainer.callbacks+=step_timer.StepTimer")
    if [ "$MODE" = cpu ]; then  # the coarse mesh has 3 levels
        steps=5
        args+=(--trainer.accelerator cpu --model.num_levels 3 --data.num_workers 1)
    else
        args+=(--trainer.accelerator gpu)
    fi
    args+=(--trainer.max_steps "$steps")
    # run in fit_dir: paper.yaml's relative outputs/paper (logs, checkpoints) land there, not in the repo
    local start=$SECONDS rc=0
    (cd "$fit_dir" && PYTHONPATH="$fit_dir${PYTHONPATH:+:$PYTHONPATH}" torch-ampn fit "${args[@]}") || rc=$?
    local wall=$((SECONDS - start))
    cp "$fit_dir/step_times.json" "$OUT_DIR/fit_step_times.json" 2>/dev/null
    cp "$fit_dir/outputs/paper/logs/version_0/config.yaml" "$OUT_DIR/fit_config.yaml" 2>/dev/null
    echo "[gpu.sh] fit wall time ${wall} s for $steps steps (start-up, statistics and data loading" \
         "included): $(python -c "print(f'{1e3 * $wall / $steps:.0f}')") ms/step"
    return $rc
}

if [ "${1:-}" = --stage ]; then
    "stage_$2" "${@:3}"
    exit
fi

# ---- the driver ------------------------------------------------------------------------------------
case "${1:-}" in
    "") MODE=gpu ;;
    --cpu-check) MODE=cpu ;;
    *) echo "usage: bash benchmarks/gpu.sh [--cpu-check]" >&2; exit 2 ;;
esac
WORK="${AMPN_BENCH_WORK:-${TMPDIR:-/tmp}/torch-ampn-gpu-bench}"
DATA_DIR="$WORK/data_$MODE"
if [ "$MODE" = cpu ]; then  # not into the repository's results
    OUT_DIR="${OUT:-$WORK/cpu_check}"
else
    OUT_DIR="${OUT:-benchmarks/results/gpu}"
fi
mkdir -p "$WORK" "$OUT_DIR" && OUT_DIR="$(cd "$OUT_DIR" && pwd)"
export MODE OUT_DIR WORK DATA_DIR MPLBACKEND=Agg
budget="${AMPN_GPU_BUDGET:-480}"
deadline=$((SECONDS + budget))
summary="$OUT_DIR/summary.txt"
: > "$summary"
failed=0

{
    echo "mode: $MODE, budget ${budget} s, started $(date -u +%FT%TZ), $(getconf _NPROCESSORS_ONLN) cores"
    command -v nvidia-smi > /dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
} | tee "$OUT_DIR/machine.txt"

limit_for() {  # limit_for CAP: min(CAP, time left of the budget)
    local left=$((deadline - SECONDS))
    echo $(($1 < left ? $1 : left))
}

record() {  # record NAME RC SECONDS LOG: one summary line, with the stage's result lines
    local name=$1 rc=$2 secs=$3 log=$4 result
    case "$name" in
        install) result="$(tail -n 1 "$log")" ;;
        cuda_tests) result="$(grep -E '(passed|failed|skipped|error|deselected|no tests ran)' "$log" | tail -n 1)" ;;
        data) result="$(grep -E 'trajectories in' "$log" | tail -n 1)" ;;
        fit) result="$(grep -E '^\[(step_timer|gpu.sh)\]' "$log" | tr '\n' ' ')" ;;
        *) result="$(tail -n 3 "$log" | tr '\n' ' ')" ;;
    esac
    [ "$rc" = 124 ] || [ "$rc" = 137 ] && result="TIMED OUT; $result"
    [ "$rc" = 0 ] || failed=1
    printf '%-14s rc=%-4s %4ss  %s\n' "$name" "$rc" "$secs" "$result" | tee -a "$summary"
}

run_stage() {  # run_stage NAME CAP STAGE [ARGS]: foreground, log in $OUT_DIR/NAME.log
    local name=$1 limit start rc
    limit=$(limit_for "$2")
    shift 2
    if [ "$limit" -lt 20 ]; then
        printf '%-14s skipped: the budget is spent\n' "$name" | tee -a "$summary"
        failed=1
        return
    fi
    echo "[gpu.sh] $name (timeout ${limit} s) ..."
    start=$SECONDS
    timeout --kill-after=10 "$limit" bash "$self" --stage "$@" > "$OUT_DIR/$name.log" 2>&1
    rc=$?
    record "$name" "$rc" $((SECONDS - start)) "$OUT_DIR/$name.log"
}

run_stage install 240 install
# the dataset for the fit, on the CPU while the GPU stages run
data_start=$SECONDS
data_limit=$(limit_for 240)
timeout --kill-after=10 "$data_limit" bash "$self" --stage data > "$OUT_DIR/data.log" 2>&1 &
data_pid=$!
echo "[gpu.sh] data (timeout ${data_limit} s) in the background ..."
run_stage cuda_tests 60 cuda_tests
# 50 steps, plain vs fast (compiled; + bf16 autocast at paper size); the simulator on its own stage
run_stage rollout_paper 120 rollout rollout_paper --batch-sizes 1 --bf16 --no-simulator
run_stage rollout_paper_x4 90 rollout rollout_paper_x4 --mesh-scale 4 --batch-sizes 1 --repeats 2 --no-simulator
run_stage simulator 75 simulator
wait "$data_pid"
record data $? $((SECONDS - data_start)) "$OUT_DIR/data.log"
run_stage fit 150 fit

echo "[gpu.sh] total $SECONDS s; logs and results in $OUT_DIR" | tee -a "$summary"
echo "---- summary ($summary)"
cat "$summary"
exit "$failed"
