#!/usr/bin/env bash
# Issue 13's fit-speed targets on a lent GPU machine (session of 2026-11-26, fifth): one run of
# experiments/bench_fit.py's worker per pulse-tail rule, one after the other, every host core free:
#
#  1. pulse_tails = "auto" (the default since this session: one tail, the score test, a second
#     tail only where the data support it): warm Calibrator.fit (median of REPEATS), SEPARATE fits
#     one call each through the same rule, and a batch of BATCH fits through the rule with the plain
#     vmapped batch and with the compacting batch (fit_problem_compact) side by side.
#  2. pulse_tails = 2 (what the earlier GPU runs measured): the same, the vmapped and compacting
#     batch side by side.
#
# The batch's baselines (seeds 2000, 2001, ...) are simulated beforehand on another machine
# (`bench_fit.py --simulate-batch-only --batch-data .devdata/batchBATCH.npz`, same code and seeds)
# and carried, since simulating them on the device costs minutes of a short lease.
# Writes under $OUT: env.txt, fit_gpu_auto.json, fit_gpu_two.json, and each worker's log. All data simulated.
#
#   OUT=out/device bash experiments/device_run_fit.sh                             (on the device machine)
#   OUT=/tmp/dev BATCH=4 SEPARATE=2 FRAMES=10 bash experiments/device_run_fit.sh  (a smoke test on a CPU)
set -u
OUT=${OUT:-out/device}
BATCH=${BATCH:-100}
SEPARATE=${SEPARATE:-10}
REPEATS=${REPEATS:-5}
FRAMES=${FRAMES:-100}
LIMIT_AUTO=${LIMIT_AUTO:-300}
LIMIT_TWO=${LIMIT_TWO:-220}
BATCH_DATA=${BATCH_DATA:-.devdata/batch${BATCH}.npz}
PY=${PY:-python3}
mkdir -p "$OUT"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 MPLBACKEND=Agg
export TOFJAX_PROGRAM_STORE=0 TOFJAX_COMPILATION_CACHE=0
{
  date -u; uname -a; nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null
  $PY -c "import sys, jax, equinox, optimistix; print(sys.version.split()[0], 'jax', jax.__version__, 'equinox', equinox.__version__, 'optimistix', optimistix.__version__, jax.devices())"
  git log -1 --format='%H %s' 2>/dev/null
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

common=(--worker --frames "$FRAMES" --captures 1 --repeats "$REPEATS" --no-stages --no-compile
        --batch "$BATCH" --separate "$SEPARATE" --batch-data "$BATCH_DATA" --batch-mode both)
timeout "$LIMIT_AUTO" $PY experiments/bench_fit.py "${common[@]}" --pulse-tails auto --out "$OUT/fit_gpu_auto.json" \
  > "$OUT/fit_auto.log" 2>&1
echo "auto: exit $?"; grep "bench_fit worker" "$OUT/fit_auto.log"; tail -3 "$OUT/fit_auto.log"
timeout "$LIMIT_TWO" $PY experiments/bench_fit.py "${common[@]}" --pulse-tails 2 --out "$OUT/fit_gpu_two.json" \
  > "$OUT/fit_two.log" 2>&1
echo "two tails: exit $?"; grep "bench_fit worker" "$OUT/fit_two.log"; tail -3 "$OUT/fit_two.log"
ls -la "$OUT"
