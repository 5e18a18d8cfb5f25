"""The cost of one training update (rollout, QP target, fit), this tree against an earlier commit, in one run.

Each measurement is a fresh process with one torch thread (the training default) that builds the learner of a
preset, runs one warm-up update and then ``--updates`` more, and reports the median of each phase
(``time/rollout_s``, ``time/reference_s``, ``time/fit_s``, ``time/update_s``) and the loss terms of the first update.
Processes for the baseline commit (checked out with ``git worktree`` into a temporary directory) and for this tree
alternate for ``--rounds`` rounds, so machine load drifts over both alike. Compared:

* the previous CPU recipe, ``cpu`` at the baseline commit and ``cpu-torque`` here (the same configuration): the
  speed-up of the code, and the largest relative difference of the first update's loss terms (the results must
  agree to float tolerance);
* the current ``cpu`` recipe here (acceleration commands, 32 agents per scene), for reference.

    python benchmarks/update_cost.py                       # writes the section of docs/benchmarks.md
    python benchmarks/update_cost.py --baseline 30c0011 --updates 4 --rounds 2 --no-write
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from egcbf.io.report import cpu_name, replace_section

ROOT = Path(__file__).resolve().parents[1]
BASELINE = "30c0011"  # the last commit before the command interface and the update optimizations

CHILD = r"""
import json, sys, torch
from egcbf.algo.config import TrainConfig
from egcbf.algo import GraphCBFLearner
algo, preset, updates = sys.argv[1], sys.argv[2], int(sys.argv[3])
torch.set_num_threads(1)
torch.use_deterministic_algorithms(True)
cfg = TrainConfig.preset(algo, preset, max_wall_minutes=None)
learner = GraphCBFLearner(cfg)
first = learner.update()
rows = [learner.update() for _ in range(updates)]
keys = ("time/rollout_s", "time/reference_s", "time/fit_s", "time/update_s")
print(json.dumps({"first": {k: v for k, v in first.items() if k.startswith("loss/")},
                  "times": {k: [r[k] for r in rows] for k in keys}}))
"""


def _run(src: Path, algo: str, preset: str, updates: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", CHILD, algo, preset, str(updates)], env=env, capture_output=True, text=True, check=False
    )
    if out.returncode != 0:
        raise RuntimeError(f"benchmark child failed ({src}, {preset}):\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", default=BASELINE, help="git commit of the 'before' measurement")
    ap.add_argument("--algo", default="egcbf+")
    ap.add_argument("--updates", type=int, default=4, help="measured updates per process (after one warm-up)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds of all processes")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/benchmarks.md")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.baseline],
                       check=True, capture_output=True)  # fmt: skip
        try:
            cases = {
                "before: cpu recipe of " + args.baseline: (old / "src", "cpu"),
                "after: the same recipe (cpu-torque)": (ROOT / "src", "cpu-torque"),
                "after: cpu recipe (acceleration, 32 agents)": (ROOT / "src", "cpu"),
            }
            results: dict[str, list[dict]] = {k: [] for k in cases}
            for r in range(args.rounds):
                for name, (src, preset) in cases.items():
                    print(f"round {r + 1}/{args.rounds}: {name}", flush=True)
                    results[name].append(_run(src, args.algo, preset, args.updates))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)

    def med(name: str, key: str) -> float:
        return statistics.median(v for res in results[name] for v in res["times"][key])

    names = list(cases)
    lines = [
        f"`python benchmarks/update_cost.py` ({cpu_name()}, {os.cpu_count()} cores, one torch thread per process, "
        f"`{args.algo}`; median over {args.rounds} x {args.updates} updates after a warm-up, processes alternating).",
        "",
        "| case | rollout (s) | QP target (s) | fit (s) | update (s) | updates per hour |",
        "|---|---|---|---|---|---|",
    ]
    for name in names:
        t = [med(name, k) for k in ("time/rollout_s", "time/reference_s", "time/fit_s", "time/update_s")]
        lines.append(f"| {name} | {t[0]:.2f} | {t[1]:.2f} | {t[2]:.2f} | {t[3]:.2f} | {3600 / t[3]:.0f} |")
    before, after = names[0], names[1]
    speedup = med(before, "time/update_s") / med(after, "time/update_s")
    a, b = results[before][0]["first"], results[after][0]["first"]
    diff = max(abs(a[k] - b[k]) / max(1e-12, abs(a[k])) for k in a if k in b and not k.startswith("loss/grad"))
    lines += [
        "",
        f"Same recipe, before / after: **{speedup:.2f}x** per update. First update's loss terms agree to a largest "
        f"relative difference of {diff:.1e} (float32; the order of some reductions changed).",
    ]
    body = "\n".join(lines)
    print(body)
    if not args.no_write:
        replace_section(ROOT / "docs" / "benchmarks.md", "update-cost", body, heading="## Cost of one training update")


if __name__ == "__main__":
    main()
