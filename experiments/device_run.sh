#!/usr/bin/env bash
# One device run on a lent GPU machine (16 host cores), two jobs side by side:
#
#  1. Issue 16 item 4: the posterior coverage study at >= 100 replicates, as PARTS parts of PER replicates
#     (configs/studies/coverage.toml with its seed moved to SEED0 + PER k), each part on one host core
#     (taskset, JAX_PLATFORMS=cpu), merged with study_coverage.py --merge. Seeds differ from earlier runs,
#     so a merge with an earlier run's coverage.json is a larger study on disjoint replicates.
#  2. Issue 13's batch target on the GPU: experiments/bench_fit.py's worker (warm Calibrator.fit, then
#     fit_problem on --separate captures one call each against fit_problem_batch on BATCH captures in one
#     call), on the two remaining host cores; the batch's data simulated beforehand on another machine
#     (--batch-data, same seeds and code) because simulating them on the GPU took minutes of a short lease.
#
# Writes under $OUT (the device tool's output folder; out/device elsewhere): coverage.json/.md (merged),
# coverage_parts.tar.gz (every part's files), fit_gpu.json, logs.tar.gz, env.txt. All data simulated.
#
#   OUT=out/device PARTS=14 PER=8 bash experiments/device_run.sh          (on the device machine)
#   OUT=/tmp/dev PARTS=2 PER=1 BATCH=4 SEPARATE=2 bash experiments/device_run.sh   (a smoke test on a CPU)
set -u
OUT=${OUT:-out/device}
PARTS=${PARTS:-14}
PER=${PER:-8}
SEED0=${SEED0:-20112}
BATCH=${BATCH:-100}
SEPARATE=${SEPARATE:-5}
FIT_LIMIT=${FIT_LIMIT:-420}
COV_LIMIT=${COV_LIMIT:-470}
FIRST_CORE=${FIRST_CORE:-2}
BATCH_DATA=${BATCH_DATA:-.devdata/batch${BATCH}.npz}
PY=${PY:-python3}
W=$(mktemp -d)
mkdir -p "$OUT" "$W/parts" "$W/logs"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 MPLBACKEND=Agg
{
  date -u; uname -a; nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null
  $PY -c "import sys, jax, equinox, optimistix; print(sys.version.split()[0], 'jax', jax.__version__, 'equinox', equinox.__version__, 'optimistix', optimistix.__version__, jax.devices())"
  git log -1 --format='%H %s' 2>/dev/null
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

ncores=$(nproc)
for k in $(seq 0 $((PARTS - 1))); do
  cfg=$W/parts/cov$k.toml
  sed -e "s/^replicates = .*/replicates = $PER/" -e "s/^posterior_replicates = .*/posterior_replicates = $PER/" \
      -e "s/^seed = .*/seed = $((SEED0 + PER * k))/" configs/studies/coverage.toml > "$cfg"
  core=$(( (FIRST_CORE + k) % ncores ))
  JAX_PLATFORMS=cpu OMP_NUM_THREADS=1 timeout "$COV_LIMIT" taskset -c "$core" \
    $PY experiments/study_coverage.py --config "$cfg" --out "$W/parts/p$k" > "$W/logs/cov$k.log" 2>&1 &
done

cores_fit=0-$((FIRST_CORE - 1))
[ "$FIRST_CORE" -le 1 ] && cores_fit=0
TOFJAX_PROGRAM_STORE=0 TOFJAX_COMPILATION_CACHE=0 timeout "$FIT_LIMIT" taskset -c "$cores_fit" \
  $PY experiments/bench_fit.py --worker --out "$OUT/fit_gpu.json" --captures 1 --repeats 3 --no-stages --no-compile \
  --batch "$BATCH" --separate "$SEPARATE" --batch-data "$BATCH_DATA" > "$W/logs/fit.log" 2>&1
echo "fit bench exit $?"; cat "$W/logs/fit.log" | grep "bench_fit worker"
wait
echo "coverage parts done: $(ls "$W"/parts/p*/coverage.json 2>/dev/null | wc -l) of $PARTS"
$PY experiments/study_coverage.py --merge "$W"/parts/p*/coverage.json --out "$W/merged" \
  --note "Issue 16 item 4: $((PARTS * PER)) replicates (seeds $SEED0-$((SEED0 + PARTS * PER - 1))) as $PARTS parts of $PER, side by side on a lent device machine's CPU (one core per part, JAX_PLATFORMS=cpu; experiments/device_run.sh). Settings: configs/studies/coverage.toml. Simulated." \
  > "$W/logs/merge.log" 2>&1
echo "merge exit $?"; tail -5 "$W/logs/merge.log"
cp "$W"/merged/coverage.json "$W"/merged/coverage.md "$OUT/" 2>/dev/null
cat "$OUT/coverage.md" 2>/dev/null
tar czf "$OUT/coverage_parts.tar.gz" -C "$W" parts 2>/dev/null
tar czf "$OUT/logs.tar.gz" -C "$W" logs 2>/dev/null
ls -la "$OUT"
