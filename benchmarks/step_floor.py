"""The arithmetic floor of the simulated step at N = 512, l = 4: how fast the shipped networks could run here at best.

Issue 28 asks for EGCBF+'s step at N = 512, l = 4 in <= 10 ms on the 2-core CPU. This benchmark says whether that is
reachable without changing what the networks compute. In one process with the CLI's thread choice
(:func:`egcbf.threads.choose_threads`) it measures, on the state of a fresh episode (seed 0, no obstacles):

* the policy's floating-point operations (``torch.utils.flop_counter``: the matrix products, which are nearly all
  of the arithmetic) for the shipped EGCBF+ and GCBF+;
* this CPU's rate on the products that dominate them: ``addmm`` of ``(E, 64) @ (64, 64)`` with ``E`` the graph's
  edge rows, the shape of the per-edge layers (median of ``--repeats`` calls, best of three blocks);
* the policy's own time as it runs today (eager PyTorch, median of ``--repeats`` calls);
* the stages outside the networks, the neighbour search and graph (``build_graph``) and the environment step,
  medians of ``--repeats`` calls.

The floor is ``FLOPs / rate + graph + environment step``: the step with every matrix product at the CPU's dense rate
and every other network operation (activations, gathers, scatters, normalizations, group actions) free. A target
below it needs fewer operations (a smaller network, fewer edges), not faster code.

    python benchmarks/step_floor.py            # writes docs/results/bench/step_floor.json and docs/benchmarks.md
    python benchmarks/step_floor.py --no-write
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from datetime import date
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from egcbf.allocator import keep_freed_memory
from egcbf.checkpoint import load_learner
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.graph import build_graph
from egcbf.report import cpu_name, replace_section
from egcbf.threads import busy_cpus, choose_threads

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "docs" / "results" / "bench" / "step_floor.json"
TARGET_MS = 10.0


def median_ms(fn, repeats: int) -> float:
    """Median wall time (ms) of ``repeats`` calls of ``fn`` after two warm-up calls."""
    fn(), fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def measure(repeats: int, num_agents: int, area: float) -> dict:
    cfg = EnvConfig.for_robot("quadrotor", num_agents=num_agents, num_obstacles=0, num_envs=1, area_size=area)
    env = SwarmEnv(cfg)
    state = env.reset(0)
    graph = build_graph(state, cfg)
    rows = int(graph.edge_kind.numel())
    flops, policy_ms = {}, {}
    with torch.no_grad():
        for method in ("egcbf+", "gcbf+"):
            policy = load_learner(ROOT / "checkpoints" / method).policy
            with FlopCounterMode(display=False) as counter:
                policy(graph)
            flops[method] = counter.get_total_flops()
            policy_ms[method] = median_ms(lambda p=policy: p(graph), repeats)
        a, w, b = torch.randn(rows, 64), torch.randn(64, 64), torch.randn(rows, 64)
        mm_ms = min(median_ms(lambda: torch.addmm(b, a, w), repeats) for _ in range(3))
        rate = 2 * rows * 64 * 64 / (mm_ms * 1e-3)  # FLOP/s
        graph_ms = median_ms(lambda: build_graph(state, cfg), repeats)
        u = cfg.make_robot().nominal_control(state.x, state.goals)
        env_ms = median_ms(lambda: env.step(state, u), repeats)
    return {"edge_rows": rows, "flops": flops, "policy_ms": policy_ms, "addmm_ms": mm_ms, "rate_gflops": rate / 1e9,
            "graph_ms": graph_ms, "env_ms": env_ms}  # fmt: skip


def markdown(r: dict) -> str:
    lines = [
        f"`python benchmarks/step_floor.py` ({r['cpu']}, {r['threads']} torch threads (the CLI's choice), torch "
        f"{r['torch']}; CPUs kept busy by other work at start: {r['busy_cpus']}; {r['date']}). N = 512, l = 4, "
        f"no obstacles, the state of a fresh episode (seed 0): {r['edge_rows']:,} edge rows. Rate: `addmm` "
        f"({r['edge_rows']}, 64) @ (64, 64), {r['addmm_ms']:.3f} ms, {r['rate_gflops']:.1f} GFLOP/s; graph "
        f"(neighbour search, LiDAR, edges) {r['graph_ms']:.2f} ms; environment step {r['env_ms']:.2f} ms.",
        "",
        "| method | policy GFLOP per step | policy at the dense rate (ms) | policy as it runs (ms) | floor: "
        "+ graph + environment (ms) | as it runs: + graph + environment (ms) | target (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for method, flops in r["flops"].items():
        ideal = flops / (r["rate_gflops"] * 1e9) * 1e3
        rest = r["graph_ms"] + r["env_ms"]
        now = r["policy_ms"][method]
        cells = (f"{flops / 1e9:.3f}", f"{ideal:.2f}", f"{now:.2f}", f"{ideal + rest:.2f}", f"{now + rest:.2f}")
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {TARGET_MS:.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30, help="calls per median")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the CLI's choice)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/")
    args = ap.parse_args()
    keep_freed_memory()
    busy = busy_cpus()
    busy = None if busy is None else round(busy, 2)
    threads, _ = choose_threads(args.threads)
    torch.set_num_threads(threads)
    r = measure(args.repeats, 512, 4.0)
    r.update(cpu=cpu_name(), cores=os.cpu_count(), threads=threads, torch=torch.__version__, busy_cpus=busy,
             date=date.today().isoformat())  # fmt: skip
    body = markdown(r)
    print(body)
    if args.no_write:
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(r, indent=1) + "\n")
    replace_section(DOC, "step-floor", body, heading="## The arithmetic floor of the N = 512 step (issue 28)")
    print(f"wrote {DOC}, {RESULTS}")


if __name__ == "__main__":
    main()
