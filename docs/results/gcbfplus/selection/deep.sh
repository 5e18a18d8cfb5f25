#!/bin/bash
# deep.sh out ckpt... : N=16 l=4, 160 episodes each of validation seeds 779 780 781
out=$1; shift
for c in "$@"; do
  line="$c"
  for s in 779 780 781; do line="$line $s:$(.venv/bin/python docs/results/gcbfplus/selection/collisions.py $c 16 4 160 $s | head -1 | awk '{print $6}')"; done
  echo "$line" >> $out
done
