#!/bin/bash
# si.sh out ckpt... : the single integrator's reference cells on validation seed 777 (safe reach per cell)
out=$1; shift
for c in "$@"; do
  line="$c"
  for cell in 16:4:160 64:11.3:40 256:22.6:10; do IFS=: read n l e <<< $cell
    r=$(.venv/bin/egcbf eval --checkpoint $c --num-agents $n --area $l --episodes $e --max-steps 256 --seed 777 --threads 1 --out /tmp/si_$$_$n --no-progress --overwrite 2>&1 | grep "^ *$n " | awk '{print $2, $3}')
    line="$line $r"; done
  echo "$line" >> $out
done
