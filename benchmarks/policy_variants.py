"""Ways to run the shipped EGCBF+ policy's forward at N = 512, l = 4, timed against each other (issue 28).

The step-floor benchmark (``benchmarks/step_floor.py``) says how fast the policy could run at the CPU's dense matrix
rate; this one measures what restructurings of the same computation give on this CPU, in one process, on graphs
captured from the episode the CLI-step benchmark times (evaluation seed 0, episode 0, no obstacles, the shipped
EGCBF+'s closed loop; the graphs of steps ``--steps``). Every variant computes the same outputs (checked: float32
within 1e-5 of the shipped forward). Variants:

* ``eager``: the shipped forward (``PolicyNet.raw``);
* ``fused``: every ``Linear`` of the MLPs, with the ``SiLU`` after it, as one oneDNN call with bias and activation
  fused into the product (``torch.ops.mkldnn._linear_pointwise``; skipped where oneDNN is missing);
* ``blocks``: the receivers in two halves (``SwarmGraph.with_receivers``), so that each half's per-edge tensors
  stay in cache; exact, since an agent's output reads only its incoming edges;
* ``threads``: the two halves at once in two Python threads with one torch thread each (2 or more threads only);
* ``compile`` (``--compile``): ``torch.compile(dynamic=True)`` over the per-edge attention path (the receiver-side
  path's sparse products do not trace); compile time reported separately.

Median ms per forward over ``--repeats`` rounds of the graphs, best of ``--rounds`` interleaved rounds.

    python benchmarks/policy_variants.py --compile          # writes docs/results/bench/policy_variants.json + docs
    python benchmarks/policy_variants.py --threads 1 --no-write
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import date
from pathlib import Path

import torch
from step_floor import episode_states  # the same episode as the step-floor and CLI-step benchmarks
from torch import Tensor, nn

from egcbf.env.graph import SwarmGraph, build_graph
from egcbf.io.allocator import keep_freed_memory
from egcbf.io.report import cpu_name, replace_section
from egcbf.io.threads import busy_cpus, choose_threads
from egcbf.nn.attention import EdgeAttention
from egcbf.nn.layers import SiLU

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = ROOT / "docs" / "results" / "bench" / "policy_variants.json"
LABELS = {
    "eager": "eager PyTorch (shipped)",
    "fused": "bias and SiLU fused into the product (`torch.ops.mkldnn._linear_pointwise`, every MLP)",
    "blocks": "receivers in two blocks (each block's edges stay in cache; exact)",
    "threads": "two Python threads, one receiver half each (one torch thread each)",
    "compile": "`torch.compile(dynamic=True)` on the per-edge attention path",
}


def capture_graphs(steps: list[int]) -> tuple[list[SwarmGraph], nn.Module]:
    """The graphs the shipped EGCBF+ builds at ``steps`` of the CLI-step benchmark's episode, and its policy."""
    states, cfg, controller = episode_states("egcbf+", steps)
    return [build_graph(s, cfg) for s in states], controller.policy.eval()


def fused_mlp_forward(self: nn.Sequential, x: Tensor) -> Tensor:
    """``nn.Sequential.forward`` with each ``Linear`` (and the ``SiLU`` after it) as one oneDNN call (float32)."""
    mods, i = list(self), 0
    while i < len(mods):
        m = mods[i]
        if isinstance(m, nn.Linear) and x.dtype == torch.float32:
            act = i + 1 < len(mods) and isinstance(mods[i + 1], SiLU)
            x = torch.ops.mkldnn._linear_pointwise(x, m.weight, m.bias, "swish" if act else "none", [], "")
            i += 2 if act else 1
        else:
            x, i = m(x), i + 1
    return x


def halves(graph: SwarmGraph) -> list[Tensor]:
    """Two boolean masks ``(M,)`` splitting the receivers in half."""
    rows = torch.arange(graph.num_dst)
    return [rows < graph.num_dst // 2, rows >= graph.num_dst // 2]


def variants(policy: nn.Module, compile_: bool) -> dict[str, Callable]:
    """The forwards to time, by key of :data:`LABELS` (each a ``graph -> (M, k)`` callable)."""

    def blocks(g):
        return torch.cat([policy.raw(g.with_receivers(keep))[keep] for keep in halves(g)])

    def fused(g):
        plain = nn.Sequential.forward
        nn.Sequential.forward = fused_mlp_forward
        try:
            return policy.raw(g)
        finally:
            nn.Sequential.forward = plain

    out = {"eager": policy.raw, "blocks": blocks}
    if torch.backends.mkldnn.is_available():
        out["fused"] = fused
    if torch.get_num_threads() > 1:
        pool = ThreadPoolExecutor(2)

        def half(g, keep):
            with torch.no_grad():
                return policy.raw(g.with_receivers(keep))[keep]

        def threads(g):
            n = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                return torch.cat(list(pool.map(lambda keep: half(g, keep), halves(g))))
            finally:
                torch.set_num_threads(n)

        out["threads"] = threads
    if compile_:
        out["compile"] = torch.compile(policy.raw, dynamic=True)
    return out


def median_ms(fn: Callable, graphs: list[SwarmGraph], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        for g in graphs:
            t = time.perf_counter()
            fn(g)
            times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def measure(steps: list[int], repeats: int, rounds: int, compile_: bool) -> dict:
    graphs, policy = capture_graphs(steps)
    runs = variants(policy, compile_)
    ms: dict[str, list[float]] = {k: [] for k in runs}
    max_diff, compile_s = {}, None
    with torch.no_grad():
        ref = [policy.raw(g) for g in graphs]
        if compile_:  # tell the EdgeAttention to take the traceable per-edge path for the compiled variant
            EdgeAttention.receiver_side = False
            t = time.perf_counter()
            [runs["compile"](g) for g in graphs]
            compile_s = time.perf_counter() - t
            EdgeAttention.receiver_side = True
        for key, fn in runs.items():
            if key == "compile":
                EdgeAttention.receiver_side = False
            max_diff[key] = max(float((fn(g) - r).abs().max()) for g, r in zip(graphs, ref))
            EdgeAttention.receiver_side = True
        for _ in range(rounds):
            for key, fn in runs.items():
                EdgeAttention.receiver_side = key != "compile"
                ms[key].append(median_ms(fn, graphs, repeats))
        EdgeAttention.receiver_side = True
    bad = {k: d for k, d in max_diff.items() if d > 1e-5}
    if bad:
        raise SystemExit(f"variants disagree with the shipped forward beyond 1e-5: {bad}")
    return {"edge_rows": [int(g.num_edges) for g in graphs], "steps": steps, "ms": {k: min(v) for k, v in ms.items()},
            "max_abs_diff": max_diff, "compile_s": compile_s}  # fmt: skip


def markdown(r: dict) -> str:
    lines = [
        f"`python benchmarks/policy_variants.py{' --compile' if r['compile_s'] is not None else ''}` ({r['cpu']}, "
        f"{r['threads']} torch threads, torch {r['torch']}; CPUs kept busy by other work at start: {r['busy_cpus']}; "
        f"{r['date']}). The shipped EGCBF+ policy's forward on the graphs of steps {', '.join(map(str, r['steps']))} "
        f"of the CLI-step benchmark's episode ({', '.join(f'{e:,}' for e in r['edge_rows'])} edge rows); median ms "
        f"per forward, best of {r['rounds']} interleaved rounds; every variant within "
        f"{max(r['max_abs_diff'].values()):.1e} of the shipped output (float32).",
        "",
        "| variant | ms per forward | x eager |",
        "|---|---|---|",
    ]
    base = r["ms"]["eager"]
    for key, ms in r["ms"].items():
        label = LABELS[key] + (f" ({r['compile_s']:.0f} s to compile)" if key == "compile" else "")
        lines.append(f"| {label} | {ms:.2f} | {ms / base:.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", default="5,20,40", help="comma list of the episode's steps whose graphs are timed")
    ap.add_argument("--repeats", type=int, default=15, help="rounds of the graphs per median")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of every variant (best is kept)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: the CLI's choice)")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile (tens of seconds to compile)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/")
    args = ap.parse_args()
    keep_freed_memory()
    busy = busy_cpus()
    threads, _ = choose_threads(args.threads)
    torch.set_num_threads(threads)
    steps = sorted({int(s) for s in args.steps.split(",")})
    r = measure(steps, args.repeats, args.rounds, args.compile)
    r.update(cpu=cpu_name(), threads=threads, torch=torch.__version__, rounds=args.rounds,
             busy_cpus=None if busy is None else round(busy, 2), date=date.today().isoformat())  # fmt: skip
    body = markdown(r)
    print(body)
    if args.no_write:
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(r, indent=1) + "\n")
    replace_section(DOC, "policy-variants", body, heading="## Restructured policy forwards (issue 28)")
    print(f"wrote {DOC}, {RESULTS}")


if __name__ == "__main__":
    main()
