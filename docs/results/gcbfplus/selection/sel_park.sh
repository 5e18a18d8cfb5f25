#!/bin/bash
# usage: sel_park.sh <out prefix> <checkpoint>... -> "<ckpt> 777:<safe %> 778:<safe %> l22.6:<safe %> <reach %>" per line
# in <out prefix>.txt: N = 16, l = 4, 160 episodes each of validation seeds 777 and 778 (collisions.py); N = 256,
# l = 22.6, 256 steps, 4 episodes of seed 777 (egcbf eval). Never an evaluation seed.
pre=$1; shift
for c in "$@"; do
  s=$(basename $c)
  a=$(.venv/bin/python docs/results/gcbfplus/selection/collisions.py $c 16 4 160 777 | head -1 | awk '{print $6}')
  b=$(.venv/bin/python docs/results/gcbfplus/selection/collisions.py $c 16 4 160 778 | head -1 | awk '{print $6}')
  r=$(.venv/bin/egcbf eval --checkpoint $c --num-agents 256 --area 22.6 --episodes 4 --max-steps 256 --seed 777 --threads 1 --out /tmp/e256_$$ --no-progress --overwrite 2>&1 | grep "^ *256 " | awk '{print $2, $3}')
  echo "$c 777:$a 778:$b l22.6:$r" >> $pre.txt
done
