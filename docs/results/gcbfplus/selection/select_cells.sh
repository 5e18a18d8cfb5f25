#!/bin/bash
# usage: CELLS="N:l:obstacles:steps:episodes ..." [SEED=777] select_cells.sh <out file> <checkpoint dir> ...
# One line per checkpoint: "<dir> <update>" then "<safe %> <reach %>" per cell, from `egcbf eval` on validation seed
# ${SEED:-777} (never an evaluation seed).
out=$1; shift
for c in "$@"; do
  step=$(python3 -c "import json;print(json.load(open('$c/state.json'))['step'])")
  line="$c $step"
  for cell in $CELLS; do
    IFS=: read -r n l obs steps eps <<< "$cell"
    o=/tmp/selc_$(echo $c | tr '/+' '__')_${n}_${l}_${obs}_${steps}; rm -rf $o
    r=$(.venv/bin/egcbf eval --checkpoint $c --num-agents $n --area $l --obstacles $obs --episodes $eps --max-steps $steps --seed ${SEED:-777} --threads 1 --out $o --no-progress 2>&1 | grep "^ *$n " | awk '{print $2, $3}')
    line="$line $r"
  done
  echo "$line" >> $out
done
