#!/usr/bin/env bash
# The CUDA path in one call: egcbf's device tests, 10 training updates of EGCBF+, and `egcbf eval` of the shipped
# EGCBF+ (alone and behind the dcbf filter) at N = 512 and 4096, on the device and on the CPU from the same seed,
# with their step times; then a summary (benchmarks/gpu_check_summary.py).
#
#   benchmarks/gpu_check.sh OUT_DIR [--device cuda|cuda:N|cpu] [--smoke]
#
# Made for a machine with no network and its own torch + torch-geometric: run from the repository root; the
# project is read from src/ (not installed), and its other dependencies come from wheels in $WHEELS (default .whl,
# made here with benchmarks/gpu_wheels.sh) installed with `pip install --no-index --no-deps` when that folder
# exists. Every job runs under `timeout -s KILL`, within a budget of $GPU_CHECK_BUDGET_S seconds (default 480: the
# whole script ends within 8 minutes); from the start, every minute, what is done is packed into
# OUT_DIR/gpu_check.tgz (and OUT_DIR/summary.md rewritten), so a run cut short keeps what it did.
# --smoke: N = 16, 2 updates, egcbf's device tests only (CI runs it with --device cpu, tests/test_gpu_check.py).
set -uo pipefail

usage() { echo "usage: $0 OUT_DIR [--device cuda|cuda:N|cpu] [--smoke]" >&2; exit 2; }
[ $# -ge 1 ] || usage
OUT=$1; shift
DEVICE=cuda; SMOKE=0
while [ $# -gt 0 ]; do
  case "$1" in
    --device) [ $# -ge 2 ] || usage; DEVICE=$2; shift 2 ;;
    --smoke) SMOKE=1; shift ;;
    *) usage ;;
  esac
done
cd "$(dirname "$0")/.." || exit 2
mkdir -p "$OUT" || exit 2
OUT=$(cd "$OUT" && pwd)
PY=${PYTHON:-python3}
BUDGET=${GPU_CHECK_BUDGET_S:-480}
START=$(date +%s)
WORK=$(mktemp -d)
RES=$WORK/gpu_check
mkdir -p "$RES"
echo -e "job\trc\tseconds\tlimit_s" > "$RES/jobs.tsv"

save() {  # pack what is done into OUT (atomically) and rewrite the summary
  "$PY" benchmarks/gpu_check_summary.py "$RES" --device "$DEVICE" > "$RES/summary.md" 2> "$RES/summary.err" || true
  cp "$RES/summary.md" "$OUT/summary.md.tmp" && mv "$OUT/summary.md.tmp" "$OUT/summary.md"
  tar czf "$OUT/gpu_check.tgz.tmp" -C "$WORK" gpu_check && mv "$OUT/gpu_check.tgz.tmp" "$OUT/gpu_check.tgz"
}
( while sleep 60; do save; done ) &
SAVER=$!
trap 'kill $SAVER 2>/dev/null; save; rm -rf "$WORK"' EXIT

remaining() { echo $(( BUDGET - ($(date +%s) - START) )); }
job() {  # job NAME LIMIT_S COMMAND...: under timeout -s KILL, at most the budget left; log in RES/NAME.log
  local name=$1 limit=$2; shift 2
  local left; left=$(remaining)
  [ "$left" -lt "$limit" ] && limit=$left
  if [ "$limit" -le 5 ]; then echo -e "$name\tskipped\t0\t$limit" >> "$RES/jobs.tsv"; return; fi
  local t0; t0=$(date +%s)
  timeout -s KILL "$limit" "$@" > "$RES/$name.log" 2>&1
  local rc=$?
  echo -e "$name\t$rc\t$(( $(date +%s) - t0 ))\t$limit" >> "$RES/jobs.tsv"
}

WHEELS=${WHEELS:-.whl}
if [ -d "$WHEELS" ] && ls "$WHEELS"/*.whl > /dev/null 2>&1; then
  job wheels 120 "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$WORK/site" "$WHEELS"/*.whl
  export PYTHONPATH="$WORK/site${PYTHONPATH:+:$PYTHONPATH}"
  for d in "$WORK"/site/cmeel.prefix/lib/python3*/site-packages; do  # proxsuite's layout (cmeel): --target
    [ -d "$d" ] && export PYTHONPATH="$d:$PYTHONPATH" LD_LIBRARY_PATH="$WORK/site/cmeel.prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  done  # installs skip the .pth file that would add it
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
job info 60 "$PY" -c "
import json, platform, torch, torch_geometric, egcbf
cuda = torch.cuda.is_available()
print(json.dumps({'python': platform.python_version(), 'torch': torch.__version__,
                  'torch_geometric': torch_geometric.__version__, 'egcbf': egcbf.__version__,
                  'cuda_available': cuda, 'cuda': torch.version.cuda,
                  'gpu': torch.cuda.get_device_name(0) if cuda else None, 'cpu': platform.processor() or platform.machine(),
                  'device': '$DEVICE', 'smoke': bool($SMOKE)}))"
cp "$RES/info.log" "$RES/info.json" 2>/dev/null

if [ "$SMOKE" = 1 ]; then
  SIZES="16:2"; STEPS=20; PRESET=tiny; UPDATES=2; TEST_LIMIT=120; TESTS=tests/egcbf/test_egcbf_on_device.py
else
  SIZES="512:4 4096:8"; STEPS=200; PRESET=cpu; UPDATES=10; TEST_LIMIT=150; TESTS=tests
fi
job tests "$TEST_LIMIT" "$PY" -m pytest -q -m device --device "$DEVICE" -p no:cacheprovider $TESTS
job train 150 "$PY" -m egcbf train --algo egcbf+ --preset "$PRESET" --steps "$UPDATES" --device "$DEVICE" \
  --seed 0 --no-progress --out "$WORK/train"
cp "$WORK/train/metrics.csv" "$RES/train_metrics.csv" 2>/dev/null

evals() {  # evals DEVICE THREADS: the shipped EGCBF+ alone and behind dcbf at every size (one lane)
  local dev=$1 threads=$2 spec n area steps filter name
  for spec in $SIZES; do
    n=${spec%%:*}; area=${spec##*:}; steps=$STEPS
    [ "$n" -ge 4096 ] && steps=$(( STEPS / 2 ))
    for filter in none dcbf; do
      name=eval-${dev//:/}-n$n-$filter
      job "$name" 240 "$PY" -m egcbf eval --checkpoint checkpoints/egcbf+ --filter "$filter" --num-agents "$n" \
        --area "$area" --episodes 1 --seed 0 --max-steps "$steps" --device "$dev" --threads "$threads" \
        --no-progress --out "$RES/$name"
    done
  done
}
if [ "$DEVICE" = cpu ]; then
  evals cpu 1
else  # the device's lane and the CPU's lane side by side (the CPU one needs no GPU)
  evals cpu 4 &
  CPU_LANE=$!
  evals "$DEVICE" 4
  wait "$CPU_LANE"
fi
echo "done in $(( $(date +%s) - START )) s" > "$RES/done"
