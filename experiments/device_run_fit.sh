#!/usr/bin/env bash
# Issue 13's fit-speed targets on a lent GPU machine (session of 2026-11-26, fifth): runs of
# experiments/bench_fit.py's worker, one after the other, every host core free:
#
#  per run TAILS:SLOW:LIMIT (RUNS): FitConfig.pulse_tails (2, the default; "auto": one tail, the
#  score test, a second tail only where the data support it), the slow pulse tail's share in the
#  simulated data (0: the default scene, which has none), and the run's time limit: a warm
#  Calibrator.fit (median of REPEATS), SEPARATE fits one call each, and a batch of BATCH fits in one
#  call with the plain vmapped batch and the compacting batch (fit_problem_compact) side by side.
#  Session of 2026-11-26, fifth: RUNS="auto:0:320 2:0:200" (fit_gpu_h200_auto.json / _two.json),
#  then PROFILE=1 RUNS="2:0.1:240".
#
# The batch's baselines (seeds 2000, 2001, ...) are simulated beforehand on another machine
# (`bench_fit.py --simulate-batch-only --batch-data .devdata/batchBATCH.npz`, same code and seeds)
# and carried, since simulating them on the device costs minutes of a short lease.
# Slow-tail runs read BATCH_DATA with _slow before .npz (`--slow-tail 0.1 --simulate-batch-only`).
# Writes under $OUT: env.txt, fit_gpu_tails{T}_slow{W}.json and .log per run, profile_warm_fit.json. All data simulated.
#
#   OUT=out/device bash experiments/device_run_fit.sh                             (on the device machine)
#   OUT=out/device PROFILE=1 RUNS="2:0.1:240" bash experiments/device_run_fit.sh   (profile, two tails on slow-tail data)
#   OUT=/tmp/dev BATCH=4 SEPARATE=2 FRAMES=10 bash experiments/device_run_fit.sh  (a smoke test on a CPU)
set -u
OUT=${OUT:-out/device}
BATCH=${BATCH:-100}
SEPARATE=${SEPARATE:-10}
REPEATS=${REPEATS:-5}
FRAMES=${FRAMES:-100}
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

# RUNS: the worker runs, each TAILS:SLOW (pulse_tails, slow-tail share of the simulated data; 0:
# none, the default scene) with its time limit in seconds after a second colon.
RUNS=${RUNS:-auto:0:300 2:0:220}
PROFILE=${PROFILE:-0}  # 1: first experiments/profile_warm_fit.py (where a warm Calibrator.fit's time goes)
if [ "$PROFILE" = 1 ]; then
  timeout 150 $PY experiments/profile_warm_fit.py --frames "$FRAMES" --pulse-tails 2 --out "$OUT/profile_warm_fit.json" \
    > "$OUT/profile.log" 2>&1
  echo "profile: exit $?"; cat "$OUT/profile.log"
fi
for run in $RUNS; do
  IFS=: read -r tails slow limit <<< "$run"
  data=$BATCH_DATA
  [ "$slow" != 0 ] && data=${BATCH_DATA%.npz}_slow.npz
  name=fit_gpu_tails${tails}_slow${slow}
  timeout "$limit" $PY experiments/bench_fit.py --worker --frames "$FRAMES" --captures 1 --repeats "$REPEATS" --no-stages \
    --no-compile --batch "$BATCH" --separate "$SEPARATE" --batch-data "$data" --batch-mode both \
    --pulse-tails "$tails" --slow-tail "$slow" --out "$OUT/$name.json" > "$OUT/$name.log" 2>&1
  echo "$name: exit $?"; grep "bench_fit worker" "$OUT/$name.log"; tail -3 "$OUT/$name.log"
done
ls -la "$OUT"
