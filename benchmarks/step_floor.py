"""The arithmetic floor of the simulated step at N = 512, l = 4: how fast the shipped networks could run here at best.

Issue 28 asks for EGCBF+'s step at N = 512, l = 4 in <= 10 ms on the 2-core CPU. This benchmark says whether that is
reachable without changing what the networks compute. In one process with the CLI's thread choice
(:func:`egcbf.io.threads.choose_threads`) it measures, on the states of the episode the CLI-step benchmark
(``benchmarks/policy_scaling.py``) times (evaluation seed 0, episode 0, no obstacles, each method's own closed
loop; every ``--every``-th of its first ``--steps`` steps):

* the policy's floating-point operations (``torch.utils.flop_counter``: the matrix products, which are nearly all
  of the arithmetic) for the shipped EGCBF+ and GCBF+;
* this CPU's rate on the products that dominate them: ``addmm`` of ``(E, 64) @ (64, 64)`` with ``E`` the median
  state's edge rows, the shape of the per-edge layers (median of ``--repeats`` calls, best of three blocks);
* the policy's own time as it runs today (eager PyTorch, median of ``--repeats`` calls), and the controller's
  (graph, policy, command and attitude loop, casts: what ``egcbf eval`` calls);
* the environment step (dynamics, collisions), median of ``--repeats`` calls.

The floor is ``FLOPs / rate + (controller - policy) + environment step``: the step with every matrix product of
the policy at the CPU's dense rate, every other operation of the network (activations, gathers, scatters,
normalizations, group actions) free, and everything outside the network as it runs. The table gives each column's
median over the states. A target below the floor needs fewer operations (a smaller network, fewer edges), not
faster code.

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

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.evaluate.episodes import episode_seed
from egcbf.io.allocator import keep_freed_memory
from egcbf.io.report import cpu_name, replace_section
from egcbf.io.threads import busy_cpus, choose_threads
from egcbf.train.checkpoint import load_controller

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "docs" / "results" / "bench" / "step_floor.json"
TARGET_MS = 10.0
NUM_AGENTS, AREA = 512, 4.0


def median_ms(fn, repeats: int) -> float:
    """Median wall time (ms) of ``repeats`` calls of ``fn`` after two warm-up calls."""
    fn(), fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def episode_states(method: str, steps: list[int]) -> tuple[list, EnvConfig, object]:
    """The states at ``steps`` of the CLI-step benchmark's episode (evaluation seed 0, episode 0, N = 512, l = 4,
    no obstacles) under ``method``'s own closed loop, with the environment config and the controller (also used by
    ``benchmarks/policy_variants.py``)."""
    controller, config = load_controller(ROOT / "checkpoints" / method)
    cfg = EnvConfig.for_robot("quadrotor", num_agents=NUM_AGENTS, area_size=AREA, num_obstacles=0,
                              **dict(config.env_overrides))  # fmt: skip
    env = SwarmEnv(cfg)
    state = env.reset(episode_seed(0, NUM_AGENTS, 0))
    states = []
    with torch.no_grad():
        for k in range(max(steps) + 1):
            if k in steps:
                states.append(state)
            u, _ = controller(state, cfg)
            state, _ = env.step(state, u)
    return states, cfg, controller


def measure_state(policy, controller, env: SwarmEnv, cfg: EnvConfig, state, repeats: int) -> dict:
    """One state's edge rows, policy FLOPs and the medians of policy, controller and environment step (ms; the
    environment steps with the nominal control, which costs it the same as any other)."""
    graph = build_graph(state, cfg)
    u = cfg.make_robot().nominal_control(state.x, state.goals)
    with FlopCounterMode(display=False) as counter:
        policy(graph)
    return {
        "edge_rows": int(graph.edge_kind.numel()),
        "flops": counter.get_total_flops(),
        "policy_ms": median_ms(lambda: policy(graph), repeats),
        "controller_ms": median_ms(lambda: controller(state, cfg), repeats),
        "env_ms": median_ms(lambda: env.step(state, u), repeats),
    }


def measure(repeats: int, steps: int, every: int) -> dict:
    per_state, rows_all = {}, []
    with torch.no_grad():
        for method in ("egcbf+", "gcbf+"):
            states, cfg, controller = episode_states(method, list(range(0, steps, every)))
            env, policy = SwarmEnv(cfg), controller.policy
            out = [measure_state(policy, controller, env, cfg, state, repeats) for state in states]
            per_state[method] = out
            rows_all += [o["edge_rows"] for o in out]
        rows = int(statistics.median(rows_all))
        a, w, b = torch.randn(rows, 64), torch.randn(64, 64), torch.randn(rows, 64)
        mm_ms = min(median_ms(lambda: torch.addmm(b, a, w), repeats) for _ in range(3))
    rate = 2 * rows * 64 * 64 / (mm_ms * 1e-3)  # FLOP/s
    return {"steps": steps, "every": every, "rate_rows": rows, "addmm_ms": mm_ms, "rate_gflops": rate / 1e9,
            "per_state": per_state}  # fmt: skip


def summary(r: dict, method: str) -> dict:
    """Per-state floor and step of ``method``, and the medians over the states (ms; GFLOP)."""
    floor, now = [], []
    for o in r["per_state"][method]:
        ideal = o["flops"] / (r["rate_gflops"] * 1e9) * 1e3
        outside = o["controller_ms"] - o["policy_ms"] + o["env_ms"]
        floor.append(ideal + outside)
        now.append(o["controller_ms"] + o["env_ms"])
    med = {k: statistics.median(o[k] for o in r["per_state"][method]) for k in r["per_state"][method][0]}
    med["gflop"] = med.pop("flops") / 1e9
    med["ideal_ms"] = med["gflop"] / r["rate_gflops"] * 1e3
    med["floor_ms"], med["step_ms"] = statistics.median(floor), statistics.median(now)
    return med


def markdown(r: dict) -> str:
    rows = [o["edge_rows"] for m in r["per_state"] for o in r["per_state"][m]]
    n = len(next(iter(r["per_state"].values())))
    lines = [
        f"`python benchmarks/step_floor.py` ({r['cpu']}, {r['threads']} torch threads (the CLI's choice), torch "
        f"{r['torch']}; CPUs kept busy by other work at start: {r['busy_cpus']}; {r['date']}). N = {NUM_AGENTS}, "
        f"l = {AREA:g}, no obstacles: {n} states of the episode the CLI-step benchmark times (steps 0, "
        f"{r['every']}, ..., < {r['steps']}; each method's own closed loop), {min(rows):,} to {max(rows):,} edge rows; "
        f"medians over the states. Rate: `addmm` ({r['rate_rows']}, 64) @ (64, 64), {r['addmm_ms']:.3f} ms, "
        f"{r['rate_gflops']:.1f} GFLOP/s.",
        "",
        "| method | edge rows | policy GFLOP per step | policy at the dense rate (ms) | policy as it runs (ms) | "
        "controller outside the policy: graph, command, casts (ms) | environment step (ms) | floor (ms) | "
        "step as it runs (ms) | target (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method in r["per_state"]:
        s = summary(r, method)
        cells = (f"{s['edge_rows']:,.0f}", f"{s['gflop']:.3f}", f"{s['ideal_ms']:.2f}", f"{s['policy_ms']:.2f}",
                 f"{s['controller_ms'] - s['policy_ms']:.2f}", f"{s['env_ms']:.2f}", f"{s['floor_ms']:.2f}",
                 f"{s['step_ms']:.2f}")  # fmt: skip
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {TARGET_MS:.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=30, help="calls per median")
    ap.add_argument("--steps", type=int, default=48, help="the episode's steps the states come from")
    ap.add_argument("--every", type=int, default=4, help="take every this-many-th step's state")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the CLI's choice)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/")
    args = ap.parse_args()
    keep_freed_memory()
    busy = busy_cpus()
    busy = None if busy is None else round(busy, 2)
    threads, _ = choose_threads(args.threads)
    torch.set_num_threads(threads)
    r = measure(args.repeats, args.steps, args.every)
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
