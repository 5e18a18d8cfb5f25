"""Average the weights of two checkpoints of the same model (``lam`` of A plus ``1 - lam`` of B), written as a
``best/`` checkpoint: the diagnostic behind docs/learning.md, "The fine-tuned policy is slower at scale" (A the
fine-tuned policy, B the policy it started from; weight-space ensembling of a fine-tuned model with its start,
as in WiSE-FT, Wortsman et al. 2022).

    python benchmarks/weight_average.py --a checkpoints/egcbf+ --b checkpoints/paper-target/egcbf+ --lam 0.5 \\
        --out out/wise/l0.5
    egcbf eval --checkpoint out/wise/l0.5 --num-agents 4096 --area 8 --episodes 1 --seed 777

Refuses checkpoints of different methods, groups or tensor layouts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from egcbf.checkpoint import load_learner, read_config, read_tensors, save_best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", required=True, type=Path)
    ap.add_argument("--b", required=True, type=Path)
    ap.add_argument("--lam", type=float, default=0.5, help="weight of A (0..1)")
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args(argv)
    if not 0.0 <= args.lam <= 1.0:
        ap.error(f"--lam must be in [0, 1], got {args.lam}")
    ca, cb = read_config(args.a), read_config(args.b)
    if (ca.algo, ca.group, ca.model) != (cb.algo, cb.group, cb.model):
        ap.error(f"{args.a} and {args.b} are not the same model ({ca.algo}/{ca.group} and {cb.algo}/{cb.group})")
    a, b = read_tensors(args.a / "model.safetensors"), read_tensors(args.b / "model.safetensors")
    if a.keys() != b.keys() or any(a[k].shape != b[k].shape for k in a):
        ap.error("the two checkpoints' tensors differ in names or shapes")
    learner = load_learner(args.a)
    for name in ("policy", "cbf", "cbf_target"):
        prefix = name + "."
        mixed = {k[len(prefix) :]: args.lam * a[k] + (1 - args.lam) * b[k] for k in a if k.startswith(prefix)}
        getattr(learner, name).load_state_dict(mixed)
    note = f"weights: {args.lam:g} x {args.a} + {1 - args.lam:g} x {args.b} (benchmarks/weight_average.py)"
    print(save_best(learner, args.out, 0.0, {"note": note}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
