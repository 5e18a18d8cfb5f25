#!/bin/bash
# usage: [SEED=778] [OBS="0 32 128"] select3.sh <out file> <checkpoint dir> ...: safe/reach per rectangle count (N=256, l=16, 1024 steps,
# one episode each); seed 777 unless SEED is set; one line per checkpoint
out=$1; shift
for c in "$@"; do
  step=$(python3 -c "import json;print(json.load(open('$c/state.json'))['step'])")
  line="$c $step"
  for obs in ${OBS:-0 32 128}; do  # OBS: the rectangle counts
    o=/tmp/sel_$(echo $c | tr '/+' '__')_$obs; rm -rf $o
    r=$(.venv/bin/egcbf eval --checkpoint $c --num-agents 256 --area 16 --obstacles $obs --episodes 1 --max-steps 1024 --seed ${SEED:-777} --threads 1 --out $o --no-progress 2>&1 | grep "^ *256 " | awk '{print $2, $3}')
    line="$line $r"
  done
  echo "$line" >> $out
done
