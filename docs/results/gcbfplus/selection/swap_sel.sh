#!/bin/bash
# swap_sel.sh out_prefix ckpt... : copies each checkpoint with model.base_law = brisk_isolated, then sel_park.sh (the base-law swap of docs/robots.md, "The Dubins car, session 41")
pre=$1; shift
for c in "$@"; do
  d=/tmp/swapc/$(echo $c | tr '/+' '__'); mkdir -p $d; cp $c/config.json $c/model.safetensors $c/state.json $d/
  python3 - $d <<'PY'
import json,sys
p=sys.argv[1]+'/config.json'; c=json.load(open(p)); c['model']['base_law']='brisk_isolated'; json.dump(c,open(p,'w'),indent=2)
PY
  docs/results/gcbfplus/selection/sel_park.sh $pre $d
done
