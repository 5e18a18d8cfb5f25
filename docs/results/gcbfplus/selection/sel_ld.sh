#!/bin/bash
# usage: sel_ld.sh <out> <ckpt>...: safe/reach at N=16 l=2 (32 eps), N=16 l=4 (32 eps), N=64 l=4 (8 eps); 256 steps, seed ${SEED:-777}
out=$1; shift
for c in "$@"; do
  step=$(python3 -c "import json;print(json.load(open('$c/state.json'))['step'])")
  line="$c $step"
  for cell in "16 2 32" "16 4 32" "64 4 8"; do
    set -- $cell
    o=/tmp/selld_$(echo $c | tr '/+' '__')_$1_$2; rm -rf $o
    r=$(.venv/bin/egcbf eval --checkpoint $c --num-agents $1 --area $2 --obstacles 0 --episodes $3 --max-steps 256 --seed ${SEED:-777} --threads 1 --out $o --no-progress 2>&1 | grep "^ *$1 " | awk '{print $2, $3}')
    line="$line $r"
  done
  echo "$line" >> $out
done
