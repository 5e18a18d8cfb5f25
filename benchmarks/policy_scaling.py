"""Step time and memory of the nominal controller, GCBF+ and EGCBF+ from 512 to 4096 agents, and one training update.

Every measurement is a fresh process that runs the CLI's own evaluation (``egcbf.evaluate.episodes.evaluate``: the
controller builds its graph, casts LiDAR and acts, then the environment steps) with the CLI's process defaults
(:func:`egcbf.io.allocator.keep_freed_memory`, threads from :func:`egcbf.io.threads.choose_threads` unless
``--threads``) and reports the median ms per environment step over ``--steps`` steps of one episode, and its peak
resident memory above what the process held before the first step (``ru_maxrss``; on CUDA the peak allocation). Cases:

* fixed density (8 agents per m^3, the paper's N = 512 at l = 4): N = 512, 1024, 2048, 4096 at l = 4 (N / 512)^(1/3);
* fixed area l = 4: N = 512, 1024 (denser than any evaluation);
* batched: 4 environments of 512 agents at l = 4 (ms per environment step);
* ``--load``: N = 512 at l = 4 again while one other CPU-bound process runs (a Python busy loop), as a user's
  other job would; the ratio to the quiet run is reported;
* ``--update``: one training update of EGCBF+ and GCBF+ (rollout, QP target, fit) with the ``cpu`` preset, one
  thread (the training default), median of 2 after a warm-up.

The learned controllers are the shipped checkpoints. The EGCBF+ / GCBF+ ratio is taken within this run.

    python benchmarks/policy_scaling.py                      # all cases; writes docs/benchmarks.md and the figure
    python benchmarks/policy_scaling.py --quick --no-write   # 512 and 1024 only
    python benchmarks/policy_scaling.py --device cuda --sizes 512,4096,32768   # on a GPU
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from egcbf.io.report import cpu_name, replace_section

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "docs" / "results" / "bench" / "policy_scaling.json"
FIGURE = ROOT / "docs" / "figures" / "policy_scaling.png"
CONTROLLERS = ("nominal", "gcbf+", "egcbf+")
DENSITY_AREA = 4.0  # l at N = 512

STEP_CHILD = r"""
import json, resource, sys, time, torch
try:
    from egcbf.io.allocator import keep_freed_memory
    keep_freed_memory()
except ImportError:  # a baseline commit from before the allocator setting
    pass
from egcbf.io.threads import choose_threads
name, n, area, envs, steps, device, threads = sys.argv[1:8]
n, area, envs, steps = int(n), float(area), int(envs), int(steps)
th, reason = choose_threads(int(threads) if threads != "auto" else None)
torch.set_num_threads(th)
from egcbf.evaluate.episodes import evaluate
from egcbf.control.controllers import make_controller
overrides = {}
if name == "nominal":
    ctrl = make_controller("nominal")
else:
    from egcbf.train.checkpoint import load_controller
    ctrl, cfg = load_controller(sys.argv[8], device=device)
    overrides = dict(cfg.env_overrides)
def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20
base = rss_mb()
if device.startswith("cuda"):
    torch.cuda.reset_peak_memory_stats()
t0 = time.perf_counter()
rows, _ = evaluate(lambda cfg: ctrl, [n], area_size=area, episodes=envs, batch=envs, max_steps=steps,
                   device=device, show_progress=False, env_overrides=overrides)
wall = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base
out = {"ms": rows[0]["step_ms_median"], "mem_mb": peak, "threads": th, "threads_reason": reason, "wall_s": wall}
if device.startswith("cuda"):
    out["mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
print(json.dumps(out))
"""

PROFILE_CHILD = r"""
import collections, json, sys, time, torch
from egcbf.io.allocator import keep_freed_memory
keep_freed_memory()
torch.set_num_threads(1)
import egcbf.algo.learner as learner_mod, egcbf.env.graph as graph_mod
from groupcanon.field_type import FieldType
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.train.checkpoint import load_learner
name, n, area, steps, ckpt = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
acc, active = collections.defaultdict(float), [True]
def timed(label, fn):
    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            if active[0]:
                acc[label] += time.perf_counter() - t0
    return wrapper
learner = load_learner(ckpt)
layer = learner.policy.encoder.layer.layer
for label, mod in (("node encoder", layer.node_enc), ("edge encoder", layer.edge_enc), ("attention", layer.attn),
                   ("feed-forward and heads", layer.ff), ("feed-forward and heads", learner.policy.head)):
    mod.forward = timed(label, mod.forward)
if learner.policy.edge_head is not None:
    learner.policy.edge_head.forward = timed("feed-forward and heads", learner.policy.edge_head.forward)
learner.policy.forward = timed("policy network", learner.policy.forward)
graph_mod.cast_lidar = timed("LiDAR", graph_mod.cast_lidar)
graph_mod.radius_neighbors = timed("neighbour search", graph_mod.radius_neighbors)
learner_mod.build_graph = timed("graph (total)", learner_mod.build_graph)
FieldType.act = timed("canonicalization (group actions)", FieldType.act)
FieldType.act_gathered = timed("canonicalization (group actions)", FieldType.act_gathered)
cfg = EnvConfig(num_agents=n, area_size=area, num_obstacles=0, num_envs=1, **learner.config.env_overrides)
env = SwarmEnv(cfg)
state = env.reset(0)
ctrl = learner.controller()
call = timed("controller (total)", type(ctrl).__call__)
env_step = timed("environment step", env.step)
active[0] = False
for _ in range(5):
    u, _ = call(ctrl, state, cfg)
    state, _ = env_step(state, u)
active[0] = True
t0 = time.perf_counter()
for _ in range(steps):
    u, _ = call(ctrl, state, cfg)
    state, _ = env_step(state, u)
total = time.perf_counter() - t0
print(json.dumps({"total_ms": 1e3 * total / steps, **{k: 1e3 * v / steps for k, v in acc.items()}}))
"""

UPDATE_CHILD = r"""
import json, statistics, sys, torch
from egcbf.io.allocator import keep_freed_memory
keep_freed_memory()
from egcbf.algo.config import TrainConfig
from egcbf.algo import GraphCBFLearner
torch.set_num_threads(1)
cfg = TrainConfig.preset(sys.argv[1], "cpu", max_wall_minutes=None)
learner = GraphCBFLearner(cfg)
learner.update()
rows = [learner.update() for _ in range(2)]
keys = ("time/rollout_s", "time/reference_s", "time/fit_s", "time/update_s")
print(json.dumps({k: statistics.median(r[k] for r in rows) for k in keys}))
"""


def _child(code: str, *args: str, src: Path | None = None, env_vars: dict | None = None) -> dict:
    env = dict(os.environ, **(env_vars or {}))
    if src is not None:
        env["PYTHONPATH"] = str(src)
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark child failed ({' '.join(args)}):\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


PROFILE_ROWS = (
    ("LiDAR", "LiDAR"),
    ("neighbour search", "neighbour search"),
    ("graph (total, with the two above)", "graph (total)"),
    ("canonicalization (group actions)", "canonicalization (group actions)"),
    ("node encoder", "node encoder"),
    ("edge encoder", "edge encoder"),
    ("attention", "attention"),
    ("feed-forward and policy heads", "feed-forward and heads"),
    ("policy network (total, with the five above)", "policy network"),
)


def profile_table(sizes: list[int]) -> list[str]:
    """Stage times (ms per step, one thread) of EGCBF+ and GCBF+ at each size of ``sizes`` (fixed density)."""
    cols, res = [], {}
    for n in sizes:
        for algo in ("egcbf+", "gcbf+"):
            r = _child(PROFILE_CHILD, algo, str(n), str(_area(n)), "20", str(ROOT / "checkpoints" / algo))
            res[(algo, n)] = r
            cols.append((algo, n))
            print(f"profile {algo} N={n}: {r['total_ms']:.1f} ms", flush=True)
    lines = [
        "| stage (ms per step) | " + " | ".join(f"{a} N={n}" for a, n in cols) + " |",
        "|---" * (1 + len(cols)) + "|",
    ]
    for label, key in PROFILE_ROWS:
        lines.append(f"| {label} | " + " | ".join(f"{res[c].get(key, 0.0):.2f}" for c in cols) + " |")
    rest = [res[c]["controller (total)"] - res[c]["graph (total)"] - res[c]["policy network"] for c in cols]
    lines.append("| command: nominal controller, attitude loop, casts | " + " | ".join(f"{v:.2f}" for v in rest) + " |")
    lines.append("| environment step (dynamics, collisions) | "
                 + " | ".join(f"{res[c]['environment step']:.2f}" for c in cols) + " |")  # fmt: skip
    lines.append("| **total** | " + " | ".join(f"**{res[c]['total_ms']:.2f}**" for c in cols) + " |")
    return lines


def _area(n: int) -> float:
    return round(DENSITY_AREA * (n / 512) ** (1 / 3), 3)


def measure_step(
    name: str, n: int, area: float, envs: int, args, src: Path | None = None, env_vars: dict | None = None
) -> dict:
    ckpt = "" if name == "nominal" else str(ROOT / "checkpoints" / name)
    cmd = (name, str(n), str(area), str(envs), str(args.steps), args.device, args.threads, ckpt)
    res = _child(STEP_CHILD, *cmd, src=src, env_vars=env_vars)
    res.update(controller=name, n=n, area=area, envs=envs)
    print(
        f"{'baseline ' if src else ''}{name:>7} N={n:>5} l={area:<6g} envs={envs}: {res['ms']:8.2f} ms/step  "
        f"{res['mem_mb']:8.1f} MB  threads {res['threads']} ({res['threads_reason']})",
        flush=True,
    )
    return res


def measure_rounds(specs: list[tuple], args, repeats: int, **kw) -> list[dict]:
    """``measure_step(*spec)`` for every spec, ``repeats`` rounds interleaved (spec 1, 2, ..., then again), so that
    a slow spell of a noisy machine hits every controller alike; each row holds the median ms over the rounds (and
    every round's ms in ``ms_rounds``) and the largest memory."""
    rounds = [[measure_step(*spec, args, **kw) for spec in specs] for _ in range(max(1, repeats))]
    out = []
    for i in range(len(specs)):
        runs = [r[i] for r in rounds]
        ms = [r["ms"] for r in runs]
        out.append(dict(runs[-1], ms=statistics.median(ms), ms_rounds=ms, mem_mb=max(r["mem_mb"] for r in runs)))
    if repeats > 1:
        for row in out:
            print(f"  median of {len(row['ms_rounds'])}: {row['controller']:>7} N={row['n']}: {row['ms']:.2f} ms "
                  f"(rounds {', '.join(f'{m:.1f}' for m in row['ms_rounds'])})", flush=True)  # fmt: skip
    return out


class BusyProcess:
    """One CPU-bound process (a Python busy loop) for the duration of a ``with`` block."""

    def __enter__(self):
        self.proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        time.sleep(65)  # let the 1-minute load average see it, as it would see a user's running job
        return self

    def __exit__(self, *exc):
        self.proc.kill()
        self.proc.wait()


def _table(rows: list[dict], title: str) -> list[str]:
    ms_cols = " | ".join(f"{c} ms" for c in CONTROLLERS)
    mb_cols = " | ".join(f"{c} MB" for c in CONTROLLERS)
    header = f"| N | l | envs | {ms_cols} | EGCBF+/GCBF+ | {mb_cols} |"
    lines = [title, "", header, "|---" * (4 + 2 * len(CONTROLLERS)) + "|"]
    keys = sorted({(r["n"], r["area"], r["envs"]) for r in rows})
    for key in keys:
        cell = {r["controller"]: r for r in rows if (r["n"], r["area"], r["envs"]) == key}
        ms = " | ".join(f"{cell[c]['ms']:.1f}" if c in cell else "" for c in CONTROLLERS)
        mb = " | ".join(f"{cell[c]['mem_mb']:.0f}" if c in cell else "" for c in CONTROLLERS)
        ratio = cell["egcbf+"]["ms"] / cell["gcbf+"]["ms"] if {"egcbf+", "gcbf+"} <= cell.keys() else float("nan")
        lines.append(f"| {key[0]} | {key[1]:g} | {key[2]} | {ms} | {ratio:.2f}x | {mb} |")
    used = sorted({r["threads"] for r in rows})
    lines += ["", f"Torch threads chosen in these rows: {', '.join(map(str, used))}."]
    return lines


def _figure(density_rows: list[dict], device: str) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6))
    ax_t, ax_m = fig.subplots(1, 2)
    for c in CONTROLLERS:
        pts = sorted((r["n"], r["ms"], r["mem_mb"]) for r in density_rows if r["controller"] == c)
        if not pts:
            continue
        ns = [p[0] for p in pts]
        ax_t.plot(ns, [p[1] for p in pts], "o-", label=c)
        ax_m.plot(ns, [max(p[2], 1e-1) for p in pts], "o-", label=c)
    n0 = min(r["n"] for r in density_rows)
    for ax, what in ((ax_t, "ms per step"), (ax_m, "peak memory above start (MB)")):
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("agents N (8 agents / m^3)")
        ax.set_ylabel(what)
        ax.grid(True, which="both", alpha=0.3)
    egcbf = sorted((r["n"], r["ms"]) for r in density_rows if r["controller"] == "egcbf+")
    if egcbf:
        ax_t.plot([n0, egcbf[-1][0]], [egcbf[0][1], egcbf[0][1] * egcbf[-1][0] / n0], "k:", label="linear in N")
    ax_t.legend(fontsize=8)
    ax_t.set_title(f"one environment step ({device})", fontsize=10)
    ax_m.set_title("memory of one episode", fontsize=10)
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=110)


def _baseline(args, commit: str) -> list[dict]:
    """N = 512 at l = 4 with the source tree of ``commit`` (a temporary ``git worktree``)."""
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), commit],
                       check=True, capture_output=True)  # fmt: skip
        try:
            rows = measure_rounds([(c, 512, DENSITY_AREA, 1) for c in CONTROLLERS], args, args.repeats, src=old / "src")
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], check=False)
    return [dict(r, commit=commit) for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="512,1024,2048,4096", help="agent counts of the fixed-density series")
    ap.add_argument("--steps", type=int, default=48, help="environment steps per measurement (median; the issue's 48)")
    ap.add_argument("--threads", default="auto", help="torch threads per process: auto (the CLI's default) or an int")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="sizes 512,1024; no load, batched or update cases")
    ap.add_argument("--load", action=argparse.BooleanOptionalAction, default=True, help="the under-load case")
    ap.add_argument("--update", action=argparse.BooleanOptionalAction, default=True, help="one training update")
    ap.add_argument("--profile", action=argparse.BooleanOptionalAction, default=True, help="stage times (CPU)")
    ap.add_argument("--baseline", default=None, help="also measure N = 512 with the code of these git commits (a,b)")
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the N = 512, one-environment cases (median)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/")
    args = ap.parse_args()
    sizes = [512, 1024] if args.quick else [int(s) for s in args.sizes.split(",")]
    quick = args.quick or args.device != "cpu"

    t_start = time.time()
    commits = args.baseline.split(",") if args.baseline else []
    baseline = [r for commit in commits for r in _baseline(args, commit)]
    density = [
        r
        for n in sizes
        for r in measure_rounds([(c, n, _area(n), 1) for c in CONTROLLERS], args, args.repeats if n == 512 else 1)
    ]
    fixed = [] if quick else [measure_step(c, 1024, DENSITY_AREA, 1, args) for c in CONTROLLERS]
    batched = [] if quick else [measure_step(c, 512, DENSITY_AREA, 4, args) for c in CONTROLLERS]
    no_keep = []
    if not quick:  # the allocator setting's share: the same step with glibc's defaults
        no_keep = measure_rounds([(c, 512, DENSITY_AREA, 1) for c in CONTROLLERS], args, args.repeats,
                                 env_vars={"EGCBF_KEEP_FREED_MEMORY": "0"})  # fmt: skip
    loaded = []
    if args.load and not quick:
        with BusyProcess():
            loaded = measure_rounds([(c, 512, DENSITY_AREA, 1) for c in CONTROLLERS], args, args.repeats)
    profile = profile_table([sizes[0], sizes[-1]]) if args.profile and not quick else []
    updates = {}
    if args.update and not quick:
        for algo in ("gcbf+", "egcbf+"):
            updates[algo] = _child(UPDATE_CHILD, algo)
            print(f"update {algo}: {updates[algo]}", flush=True)
    wall = time.time() - t_start

    def cell(rows, c, n):
        return next(r for r in rows if r["controller"] == c and r["n"] == n)

    base = {c: cell(density, c, sizes[0]) for c in CONTROLLERS}
    lines = [
        f"`python benchmarks/policy_scaling.py` ({cpu_name() if args.device == 'cpu' else args.device}, "
        f"{os.cpu_count()} cores; threads: {args.threads} (the CLI's default policy unless a number); the CLI's "
        f"allocator setting; median ms per environment step over {args.steps} steps of one episode, shipped "
        f"checkpoints, no obstacles; the one-environment N = 512 rows (quiet, under load, allocator, before/after): "
        f"median over {args.repeats} interleaved rounds of fresh processes; memory: peak resident memory above the "
        f"process's before the first step; {wall / 60:.0f} min).",
        "",
        *_table(density, "**Fixed density** (8 agents per m^3):"),
    ]
    last = sizes[-1]
    growth = {c: cell(density, c, last)["ms"] / base[c]["ms"] for c in CONTROLLERS}
    mem_growth = cell(density, "egcbf+", last)["mem_mb"] / max(base["egcbf+"]["mem_mb"], 1e-9)
    lines += [
        "",
        f"From N = {sizes[0]} to {last} ({last // sizes[0]}x the agents): step time x{growth['egcbf+']:.1f} for "
        f"EGCBF+, x{growth['gcbf+']:.1f} for GCBF+, x{growth['nominal']:.1f} for the nominal controller; EGCBF+'s "
        f"memory x{mem_growth:.1f}.",
    ]
    if fixed or batched:
        at_l4 = fixed + batched + [r for r in density if r["n"] == 512]
        lines += ["", *_table(at_l4, "**At l = 4** (one and four environments; batched: ms per environment):")]
    if loaded:
        lines += ["", *_table(loaded, "**N = 512, l = 4 while one other CPU-bound process runs:**"), ""]
        lines.append(
            "Under load / quiet: "
            + ", ".join(f"{c} x{cell(loaded, c, 512)['ms'] / base[c]['ms']:.2f}" for c in CONTROLLERS)
            + f" (threads chosen under load: {cell(loaded, 'egcbf+', 512)['threads']})."
        )
    for commit in commits:
        rows = [r for r in baseline if r["commit"] == commit]
        pairs = [(c, cell(rows, c, 512)["ms"], base[c]["ms"]) for c in CONTROLLERS]
        change = ", ".join(f"{c} {old:.1f} -> {new:.1f} ms (x{old / new:.2f})" for c, old, new in pairs)
        lines += ["", f"**Before / after** (N = 512, l = 4, the code of commit `{commit}` -> this tree, same "
                  f"checkpoints, same run; x = speed-up): {change}."]  # fmt: skip
    if no_keep:
        pairs = [(c, cell(no_keep, c, 512)["ms"], base[c]["ms"]) for c in CONTROLLERS]
        change = ", ".join(f"{c} {off:.1f} -> {on:.1f} ms" for c, off, on in pairs)
        lines += ["", f"**Allocator** (N = 512, l = 4; `EGCBF_KEEP_FREED_MEMORY=0`, glibc's defaults -> the CLI's "
                  f"setting): {change}."]  # fmt: skip
    if profile:
        intro = (
            "**Where the time goes** (one thread, fixed density; wall time of each stage per step, averaged over "
            "steps 5-25 of an episode, where the graph is sparser than later in the episode as agents converge; nested "
            "stages are included in their totals):"
        )
        lines += ["", intro, "", *profile]
    if updates:
        lines += ["", "**One training update** (`cpu` preset, one thread; median of 2 after a warm-up):", "",
                  "| method | rollout (s) | QP target (s) | fit (s) | update (s) | updates per hour |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for algo, t in updates.items():
            v = [t[k] for k in ("time/rollout_s", "time/reference_s", "time/fit_s", "time/update_s")]
            lines.append(f"| {algo} | {v[0]:.2f} | {v[1]:.2f} | {v[2]:.2f} | {v[3]:.2f} | {3600 / v[3]:.0f} |")
    if not args.no_write:
        lines += ["", f"![step time and memory against N]({FIGURE.relative_to(DOC.parent)})"]
    body = "\n".join(lines)
    print(body)
    if args.no_write:
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    record = {"baseline": baseline, "allocator_off": no_keep, "density": density, "fixed_area": fixed,
              "batched": batched, "loaded": loaded, "updates": updates, "args": vars(args), "cpu": cpu_name(),
              "wall_s": wall}  # fmt: skip
    RESULTS.write_text(json.dumps(record, indent=1) + "\n")
    _figure(density, args.device)
    replace_section(DOC, "policy-scaling", body, heading="## Learned policy at scale")
    print(f"wrote {DOC}, {RESULTS}, {FIGURE}")


if __name__ == "__main__":
    main()
