#!/bin/bash
# swap_sel.sh out_prefix ckpt... : copies each checkpoint with model.base_law = $LAW (default brisk_isolated) and
# model.brisk_weight = $WEIGHT (default 1.0), then sel_park.sh (the base-law swap of docs/robots.md, "The Dubins car,
# session 41")
pre=$1; shift
law=${LAW:-brisk_isolated}; weight=${WEIGHT:-1.0}
for c in "$@"; do
  d=/tmp/swapc/$(echo $c | tr '/+' '__')_${law}_${weight}; mkdir -p $d; cp $c/config.json $c/model.safetensors $c/state.json $d/
  python3 - $d $law $weight <<'PY'
import json,sys
p=sys.argv[1]+'/config.json'; c=json.load(open(p))
c['model']['base_law']=sys.argv[2]; c['model']['brisk_weight']=float(sys.argv[3]); json.dump(c,open(p,'w'),indent=2)
PY
  docs/results/gcbfplus/selection/sel_park.sh $pre $d
done
