"""Per-step solve time of the hand-crafted CBF-QP baselines (cCBF-QP, dCBF-QP) against the number of agents.

For each N (default 8, 16, 64, 128, 256, 512) in the fixed arena l = 4 m without obstacles (density N / 64 per m^3,
8 per m^3 at N = 512), a closed-loop rollout of ``--steps`` control steps from a seeded reset is run with each
controller; the controller's own wall time per step (``info["qp_ms"]``: nominal acceleration, neighbour search,
constraint and QP assembly, solve, checks; not the attitude loop or the simulator) is recorded and the median
reported, with the number of CBF rows, the steps whose QP needed slack and the failed solves.

Solver comparison (centralized QP): on ``--snapshots`` states of the cCBF-QP rollout, the same assembled sparse QP
is solved by every installed solver egcbf tests (``egcbf.qp.sparse_qp.SOLVERS``, through qpsolvers, same tolerance
1e-7, no warm start) and the median solve time (conversion + setup + solve) is reported, with the largest distance
to PIQP's solution. With ``--direct`` the solvers egcbf had before qpsolvers are also called through their old
hand-written adapters (``benchmarks/qp_direct.py``), alternating with the qpsolvers call on the same QP, and the
ratio of the medians is qpsolvers' overhead. The per-agent QPs are solved by the batched interior-point method
(torch, on the CPU) and by proxsuite's ``dense.BatchQP`` + ``solve_in_parallel`` on the same states.

    .venv/bin/python benchmarks/qp_scaling.py                 # writes docs/benchmarks.md (a few minutes, 2 cores)
    .venv/bin/python benchmarks/qp_scaling.py --sizes 8 64 --steps 10 --no-write

Results go to ``docs/benchmarks.md`` between ``<!-- qp-scaling:begin -->`` and ``<!-- qp-scaling:end -->``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.io.report import replace_section
from egcbf.qp.dense_qp import assemble_decentralized, solve_dense_batch, solve_dense_batch_ipm
from egcbf.qp.sparse_qp import SOLVERS, assemble_centralized, solve_sparse
from egcbf.qp.sparse_solvers import available_solvers
from egcbf.robots.quadrotor.barriers import build_constraints, split_for_agents
from egcbf.robots.quadrotor.cbf_qp import CentralizedCBFQP
from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP

sys.path.insert(0, str(Path(__file__).resolve().parent))
from qp_direct import DIRECT, solve_direct  # the pre-qpsolvers adapters, for --direct

BEGIN, END = "<!-- qp-scaling:begin -->", "<!-- qp-scaling:end -->"
SIZES = (8, 16, 64, 128, 256, 512)


def rollout(ctrl, n: int, area: float, steps: int, seed: int, snapshots: int):
    cfg = EnvConfig(num_agents=n, area_size=area, num_obstacles=0, num_envs=1, max_steps=steps)
    env = SwarmEnv(cfg, dtype=torch.float64)
    state = env.reset(seed)
    ms, cpu, rows, slack, failed, coll = [], [], [], 0, 0, torch.zeros(1, n, dtype=torch.bool)
    keep = set(np.linspace(steps // 4, steps - 1, snapshots).astype(int).tolist()) if snapshots else set()
    snaps = []
    for t in range(steps):
        if t in keep:
            snaps.append(state)
        u, info = ctrl(state, cfg)
        ms.append(info["qp_ms"])
        cpu.append(info["qp_cpu_ms"])
        rows.append(info["num_constraints"])
        slack += info["num_slack"] > 0
        failed += info["num_failed"]
        state, si = env.step(state, u)
        coll |= si.collision
    return (
        {
            "ms": statistics.median(ms),
            "p90": float(np.percentile(ms, 90)),
            "cpu": statistics.median(cpu),
            "rows": statistics.median(rows),
            "slack_steps": slack,
            "failed": failed,
            "collided": int(coll.sum()),
        },
        snaps,
        cfg,
    )


def solver_comparison(ctrl: CentralizedCBFQP, snaps, cfg, solvers, direct: bool = False, repeats: int = 3) -> dict:
    """Median solve time per solver on the centralized QPs of ``snaps`` (and the dense per-agent solvers); with
    ``direct``, also ``"<solver>:direct"`` (the pre-qpsolvers adapter) and ``"<solver>:qpsolvers"``, each call
    timed ``repeats`` times, alternating the two."""
    times = {s: [] for s in solvers}
    dev = {s: 0.0 for s in solvers}
    dense = {"ipm": [], "proxsuite-batch": []}
    pairs = {f"{s}:{k}": [] for s in solvers if direct and s in DIRECT for k in ("direct", "qpsolvers")}
    for state in snaps:
        prep = ctrl._prepare(state, cfg)
        cons = build_constraints(prep.p[0], prep.v[0], prep.barrier, bounds=prep.bounds)
        qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0], ctrl.config.penalty)
        ref = None
        for s in solvers:
            t0 = time.perf_counter()
            res = solve_sparse(qp, s, eps_abs=1e-7, max_iter=1000)
            times[s].append(1e3 * (time.perf_counter() - t0) if res.ok else float("nan"))
            for _ in range(repeats if f"{s}:direct" in pairs else 0):
                pairs[f"{s}:direct"].append(solve_direct(qp, s, eps_abs=1e-7, max_iter=1000)[2])
                t0 = time.perf_counter()
                solve_sparse(qp, s, eps_abs=1e-7, max_iter=1000)
                pairs[f"{s}:qpsolvers"].append(1e3 * (time.perf_counter() - t0))
            if ref is None and res.ok:
                ref = res.x
            elif res.ok:
                dev[s] = max(dev[s], float(np.abs(res.x - ref).max()))
        owner, normal, rhs = split_for_agents(cons)
        n = prep.p.shape[1]
        dq = assemble_decentralized(
            prep.a_nom[0], owner, normal, rhs, prep.bC[0], prep.blo[0], prep.bhi[0], ctrl.config.penalty
        )
        t0 = time.perf_counter()
        solve_dense_batch_ipm(dq)
        dense["ipm"].append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        solve_dense_batch(dq, eps_abs=1e-9)
        dense["proxsuite-batch"].append(1e3 * (time.perf_counter() - t0))
        del n
    out = {s: (statistics.median(v) if v else float("nan"), dev[s]) for s, v in times.items()}
    out.update({k: (statistics.median(v), 0.0) for k, v in dense.items() if v})
    out.update({k: (statistics.median(v), 0.0) for k, v in pairs.items() if v})
    return out


def _adapter_solve(qp, solver, eps_abs=1e-6, max_iter=1000, x0=None):
    """``solve_sparse`` through the pre-qpsolvers adapter (``benchmarks/qp_direct.py``), as a SolveResult."""
    from egcbf.qp.sparse_qp import SolveResult

    t0 = time.perf_counter()
    try:
        x, ok, status, it = DIRECT[solver](qp, eps_abs, max_iter, x0)
    except Exception as exc:
        x, ok, status, it = None, False, f"error: {exc}", 0
    ms = 1e3 * (time.perf_counter() - t0)
    if x is None or not np.all(np.isfinite(x)):
        return SolveResult(np.full(qp.H.shape[0], np.nan), False, status, it, ms)
    return SolveResult(x, ok, status, it, ms)


def rollout_with_adapters(n: int, args) -> dict:
    """The cCBF-QP rollout of :func:`rollout` with its solves through the pre-qpsolvers adapters."""
    import egcbf.robots.quadrotor.cbf_qp as ccbf_module

    saved = ccbf_module.solve_sparse
    ccbf_module.solve_sparse = _adapter_solve
    try:
        return rollout(CentralizedCBFQP(), n, args.area, args.steps, args.seed, 0)[0]
    finally:
        ccbf_module.solve_sparse = saved


def installed_solvers() -> list[str]:
    installed = available_solvers()
    return [s for s in SOLVERS if s in installed]


def render(rows: list[dict], comp: dict[int, dict], args, solvers) -> str:
    cpu = platform.processor() or platform.machine()
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {cpu}, {os.cpu_count()} CPU cores (shared with other jobs, so "
        f"expect noise), Python {platform.python_version()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} torch thread(s). Arena l = {args.area:g} m, no obstacles, {args.steps} "
        f"closed-loop steps from reset (seed {args.seed}), float64. Time = the controller's wall time per step "
        "(nominal acceleration, neighbour search, rows, assembly, solve, checks).",
        "",
        "| N | density (1/m^3) | cCBF-QP median ms | p90 ms | CPU ms | CBF rows | slack steps | failed | "
        "dCBF-QP median ms | p90 ms | CPU ms | slack steps | failed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        c, d = r["ccbf"], r["dcbf"]
        lines.append(
            f"| {r['N']} | {r['N'] / args.area**3:.3g} | {c['ms']:.1f} | {c['p90']:.1f} | {c['cpu']:.1f} | "
            f"{c['rows']:.0f} | {c['slack_steps']} | {c['failed']} | {d['ms']:.1f} | {d['p90']:.1f} | "
            f"{d['cpu']:.1f} | {d['slack_steps']} | {d['failed']} |"
        )
    if any("ccbf_direct" in r for r in rows):
        lines += [
            "",
            "cCBF-QP per step through qpsolvers against the same rollout through the hand-written adapters egcbf had "
            "before it (`--direct`, `benchmarks/qp_direct.py`; PIQP, falling back to ProxQP):",
            "",
            "| N | adapters median ms | qpsolvers median ms | qpsolvers / adapters |",
            "|---|---|---|---|",
        ]
        for r in rows:
            if "ccbf_direct" in r:
                a, q = r["ccbf_direct"]["ms"], r["ccbf"]["ms"]
                lines.append(f"| {r['N']} | {a:.1f} | {q:.1f} | {q / a:.2f} |")
    if comp:
        names = [*solvers, "ipm", "proxsuite-batch"]
        lines += [
            "",
            f"Solver comparison (median ms per solve over {args.snapshots} states of the cCBF-QP rollout; sparse "
            "solvers on the centralized QP, setup + solve, tolerance 1e-7, in brackets the largest difference from "
            "PIQP's solution; the last two columns: all per-agent QPs of the decentralized split, one batch):",
            "",
            "| N | " + " | ".join(names) + " |",
            "|---|" + "---|" * len(names),
        ]
        for n, c in comp.items():
            cells = []
            for s in names:
                t, dv = c.get(s, (float("nan"), 0.0))
                cells.append(f"{t:.1f}" + (f" ({dv:.0e})" if s in solvers and s != solvers[0] else ""))
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        direct = [s for s in solvers if any(f"{s}:direct" in c for c in comp.values())]
        if direct:
            lines += [
                "",
                "qpsolvers' overhead (`--direct`): median ms per solve through qpsolvers and through the hand-written "
                "adapter egcbf had before it (`benchmarks/qp_direct.py`), the two calls alternating on the same QPs "
                "(conversion + setup + solve):",
                "",
                "| N | solver | adapter ms | qpsolvers ms | qpsolvers / adapter |",
                "|---|---|---|---|---|",
            ]
            for n, c in comp.items():
                for s in direct:
                    a, q = c[f"{s}:direct"][0], c[f"{s}:qpsolvers"][0]
                    lines.append(f"| {n} | {s} | {a:.1f} | {q:.1f} | {q / a:.2f} |")
        missing = [s for s in SOLVERS if s not in solvers]
        if missing:
            lines += ["", f"Not installed here, so not compared: {', '.join(missing)} (`pip install -e '.[solvers]'`)."]
    return "\n".join(lines)


def write_section(path: Path, body: str) -> None:
    replace_section(path, "qp-scaling", body, heading="## CBF-QP baselines: solve time")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--area", type=float, default=4.0)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--snapshots", type=int, default=3, help="states per N for the solver comparison (0: skip)")
    ap.add_argument("--compare-sizes", type=int, nargs="+", default=[64, 256, 512])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--direct", action="store_true", help="also time the pre-qpsolvers adapters (the overhead)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"))
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    solvers = installed_solvers()
    rows, comp = [], {}
    for n in args.sizes:
        snapshots = args.snapshots if n in args.compare_sizes else 0
        cc = CentralizedCBFQP()
        c, snaps, cfg = rollout(cc, n, args.area, args.steps, args.seed, snapshots)
        d, _, _ = rollout(DecentralizedCBFQP(), n, args.area, args.steps, args.seed, 0)
        rows.append({"N": n, "ccbf": c, "dcbf": d})
        if args.direct:  # the same rollout with the pre-qpsolvers adapters (same run: the ratio is the overhead)
            rows[-1]["ccbf_direct"] = rollout_with_adapters(n, args)
        print(f"N={n}: ccbf {c}  dcbf {d}", flush=True)
        if snaps:
            comp[n] = solver_comparison(cc, snaps, cfg, solvers, direct=args.direct)
            print(f"  solvers: {comp[n]}", flush=True)
    body = render(rows, comp, args, solvers)
    print(body)
    if not args.no_write:
        write_section(Path(args.out), body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
