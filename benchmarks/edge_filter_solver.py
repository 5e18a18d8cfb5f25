"""The ``cbf`` filter's per-agent QPs by the interior-point method and by the exact dual active-set method, on the
same QPs, and the ``egcbf+:cbf`` episode with either (``FilterConfig.qp_solver``).

The QPs are recorded along a closed-loop rollout of ``egcbf+:cbf`` (``checkpoints/egcbf+``, quadrotor, N = 512,
l = 4 m, float32 states as in the evaluation, ``--steps`` steps from a seeded reset), without obstacles and with 8.
On every recorded step's QPs the two batched solvers (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`,
:func:`egcbf.qp.dense_active_set.solve_dense_batch_active_set`) are timed in turn (order alternating), as is the
whole filtered controller (graph, policy, rows, solve, check, attitude loop) with either setting on the same
states. Reported: median ms per filter step, the agents solved (those whose reference violates a row), failures,
``max |dz|`` between the solvers, and the ratios. Then ``--episode-steps`` steps of
:func:`egcbf.evaluate.episodes.run_episodes` with either setting, interleaved, ``--repeats`` times each (and how far
apart the two trajectories end up). Under load the absolute times are noisy; the ratios are the numbers.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/edge_filter_solver.py            # writes docs/benchmarks.md
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/edge_filter_solver.py --steps 8 --episode-steps 8 --no-write

The episode ratios also go to ``docs/results/bench/edge_filter_solver.json`` (``benchmarks/sweep_cpu_hours.py``
applies them to the sweep's learned-filter cells). Results go to ``docs/benchmarks.md`` between
``<!-- edge-filter-solver:begin -->`` and
``<!-- edge-filter-solver:end -->``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import statistics
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

from egcbf.algo import edge_qp
from egcbf.algo.edge_qp import SLACK_TOL
from egcbf.control.filters import FilterConfig
from egcbf.control.resolve import resolve
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.evaluate.episodes import run_episodes
from egcbf.io.report import replace_section
from egcbf.qp.dense_active_set import solve_dense_batch_active_set
from egcbf.qp.dense_qp import solve_dense_batch_ipm, verified

ROOT = Path(__file__).resolve().parents[1]
SOLVERS = ("ipm", "active_set")
#: the measured episode ratios (IPM seconds over active-set seconds) per filter and obstacle count, which
#: benchmarks/sweep_cpu_hours.py applies to the sweep's learned-filter cells
RATIOS = ROOT / "docs" / "results" / "bench" / "edge_filter_solver.json"


def controllers(checkpoint: Path, kind: str = "cbf") -> dict:
    """``egcbf+:KIND`` (``cbf`` or ``prior``) with either QP solver."""
    return {
        s: resolve(f"egcbf+:{kind}", checkpoint, filter_config=FilterConfig.for_kind(kind, qp_solver=s)).controller
        for s in SOLVERS
    }


def record(ctrl, cfg: EnvConfig, steps: int, seed: int) -> tuple[list, list]:
    """The states and the per-agent QPs (:class:`~egcbf.qp.dense_qp.DenseBatchQP`) of a rollout of ``ctrl``."""
    env = SwarmEnv(cfg)
    state = env.reset(seed)
    states, qps = [], []
    solve = edge_qp.SOLVERS[ctrl.config.qp_solver]

    def recording(q, **kw):
        qps.append(q)
        return solve(q, **kw)

    edge_qp.SOLVERS[ctrl.config.qp_solver] = recording
    try:
        for _ in range(steps):
            states.append(state)
            u, _ = ctrl(state, cfg)
            state, _ = env.step(state, u)
    finally:
        edge_qp.SOLVERS[ctrl.config.qp_solver] = solve
    return states, qps


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return 1e3 * (time.perf_counter() - t0), out


def measure_qps(qps: list) -> dict:
    """Both solvers on every QP batch of ``qps``, in turn (order alternating)."""
    ms = {s: [] for s in SOLVERS}
    solved, failed, dz = [], {s: 0 for s in SOLVERS}, 0.0
    fns = {"ipm": solve_dense_batch_ipm, "active_set": solve_dense_batch_active_set}
    for i, q in enumerate(qps):
        out = {}
        for s in SOLVERS if i % 2 == 0 else SOLVERS[::-1]:
            t, out[s] = _timed(fns[s], q)
            ms[s].append(t)
        (z_i, ok_i, it_i), (z_a, ok_a, _) = out["ipm"], out["active_set"]
        solved.append(int((it_i > 0).sum()))
        failed["ipm"] += int((~verified(q, z_i, ok_i, SLACK_TOL)).sum())  # (the agents that brake)
        failed["active_set"] += int((~verified(q, z_a, ok_a, SLACK_TOL)).sum())
        both = ok_i & ok_a
        dz = max(dz, float(np.abs(z_i[both] - z_a[both]).max(initial=0.0)))
    return {"ms": {s: statistics.median(v) for s, v in ms.items()}, "solved": statistics.median(solved),
            "failed": failed, "dz": dz}  # fmt: skip


def measure_steps(ctrls: dict, states: list, cfg: EnvConfig) -> dict:
    """The filtered controller with either solver on the same states, in turn: median controller ms and its
    ``qp_ms`` (rows, solve, check), and the largest difference of their commands."""
    ms = {s: [] for s in SOLVERS}
    qp = {s: [] for s in SOLVERS}
    da = 0.0
    for i, state in enumerate(states):
        out = {}
        for s in SOLVERS if i % 2 == 0 else SOLVERS[::-1]:
            t, (_, info) = _timed(ctrls[s], state, cfg)
            ms[s].append(t)
            qp[s].append(info["qp_ms"])
            out[s] = info["a_safe"]
        da = max(da, float((out["ipm"] - out["active_set"]).abs().max()))
    med = statistics.median
    return {"ms": {s: med(v) for s, v in ms.items()}, "qp_ms": {s: med(v) for s, v in qp.items()}, "da": da}


def measure_episodes(ctrls: dict, cfg: EnvConfig, repeats: int, seed: int) -> dict:
    """``run_episodes`` with either solver, interleaved: the best wall seconds of ``repeats`` runs (the least
    disturbed by other jobs), the agent-steps given the braking fallback, and the largest distance between the two
    trajectories' positions (m) at the last step and over the episode."""
    sec = {s: [] for s in SOLVERS}
    pos, failed = {}, {}
    for r in range(repeats):
        for s in SOLVERS if r % 2 == 0 else SOLVERS[::-1]:
            t0 = time.perf_counter()
            _, timing, rec = run_episodes(ctrls[s], cfg, [seed], record=True)
            sec[s].append(time.perf_counter() - t0)
            pos[s], failed[s] = torch.stack(rec.positions).to(torch.float64), timing["num_failed"]
    d = (pos["ipm"] - pos["active_set"]).norm(dim=-1).amax(-1)  # (T,)
    return {"s": {s: min(v) for s, v in sec.items()}, "failed": failed, "dp_end": float(d[-1]),
            "dp_max": float(d.max())}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", type=Path, default=ROOT / "checkpoints" / "egcbf+")
    ap.add_argument("--num-agents", type=int, default=512)
    ap.add_argument("--area", type=float, default=4.0)
    ap.add_argument("--obstacles", type=int, nargs="+", default=[0, 8])
    ap.add_argument("--steps", type=int, default=32, help="recorded steps per scene")
    ap.add_argument("--episode-steps", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=3, help="episode runs per solver")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--filters", nargs="+", default=["cbf", "prior"], choices=["cbf", "prior"])
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines = [
        f"Measured {date.today()} on {platform.machine()}, {platform.python_version()}, torch {torch.__version__}, "
        f"numpy {np.__version__}, one thread, beside other jobs (ratios of interleaved timings in one process); "
        f"`egcbf+:cbf` and `egcbf+:prior` of `{args.checkpoint.relative_to(ROOT)}`, N = {args.num_agents}, "
        f"l = {args.area:g} m, "
        f"float32 states; the QPs of the first {args.steps} steps of a rollout (seed {args.seed}) and "
        f"{args.episode_steps}-step episodes (`run_episodes`, best of {args.repeats} runs per solver).",
        "",
        "| filter | obstacles | agents solved / step | IPM ms / step | active set ms / step | QP ratio | "
        "max \\|dz\\| | failed (IPM, AS) | controller ms (IPM, AS) | step ratio | episode s (IPM, AS) | "
        "episode ratio | episode brakings (IPM, AS) | max \\|dp\\| (m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ratios: dict[str, dict[str, float]] = {}
    for kind, n_obs in ((k, o) for k in args.filters for o in args.obstacles):
        ctrls = controllers(args.checkpoint, kind)
        cfg = EnvConfig(num_agents=args.num_agents, area_size=args.area, num_obstacles=n_obs, num_envs=1,
                        max_steps=max(args.steps, args.episode_steps))  # fmt: skip
        states, qps = record(ctrls["ipm"], cfg, args.steps, args.seed)
        q = measure_qps(qps)
        st = measure_steps(ctrls, states, cfg)
        ep = measure_episodes(ctrls, dataclasses.replace(cfg, max_steps=args.episode_steps), args.repeats, args.seed)
        qi, qa = q["ms"]["ipm"], q["ms"]["active_set"]
        si, sa = st["ms"]["ipm"], st["ms"]["active_set"]
        ei, ea = ep["s"]["ipm"], ep["s"]["active_set"]
        qp_i, qp_a = st["qp_ms"]["ipm"], st["qp_ms"]["active_set"]
        ratios.setdefault(kind, {})[str(n_obs)] = ei / ea
        print(f"{kind}, obstacles {n_obs}: solved {q['solved']:.0f}/step, QP ipm {qi:.2f} ms, active set {qa:.2f} ms "
              f"({qi / qa:.2f}x), max |dz| {q['dz']:.1e}, failed {q['failed']}; controller ipm {si:.1f} ms "
              f"(qp_ms {qp_i:.1f}), active set {sa:.1f} ms (qp_ms {qp_a:.1f}) ({si / sa:.2f}x), max |da| "
              f"{st['da']:.1e}; episode ipm {ei:.1f} s, active set {ea:.1f} s ({ei / ea:.2f}x), max |dp| "
              f"{ep['dp_max']:.1e} m (last step {ep['dp_end']:.1e}), brakings {ep['failed']}", flush=True)  # fmt: skip
        lines.append(
            f"| `{kind}` | {n_obs} | {q['solved']:.0f} | {qi:.2f} | {qa:.2f} | {qi / qa:.2f}x | {q['dz']:.0e} | "
            f"{q['failed']['ipm']}, {q['failed']['active_set']} | {si:.0f}, {sa:.0f} | {si / sa:.2f}x | "
            f"{ei:.1f}, {ea:.1f} | {ei / ea:.2f}x | {ep['failed']['ipm']}, {ep['failed']['active_set']} | "
            f"{ep['dp_max']:.0e} |"
        )
    lines += [
        "",
        "QP ratio: the batched interior-point method's median time per filter step over the exact dual active-set "
        "method's (`FilterConfig.qp_solver`, default `active_set`), on the same QPs; step ratio: the whole filtered "
        "controller's (same states, in turn); episode ratio: whole `run_episodes` runs. max |dz|: the largest "
        "difference of the two solutions (the IPM's inaccuracy: the active set's are exact); failed: QPs a solver "
        "reported unsolved (the agent brakes); max |dp|: the largest distance between an agent's positions in the "
        "two episodes (an IPM failure on a degenerate QP that the active set solves makes the trajectories part).",
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        RATIOS.parent.mkdir(parents=True, exist_ok=True)
        RATIOS.write_text(json.dumps({"episode_ratio": ratios, "num_agents": args.num_agents, "area": args.area,
                                      "episode_steps": args.episode_steps, "measured": str(date.today())},
                                     indent=1) + "\n")  # fmt: skip
        replace_section(ROOT / "docs" / "benchmarks.md", "edge-filter-solver", text,
                        heading="## Per-edge filter QP: interior point vs. active set")  # fmt: skip
        print("wrote docs/benchmarks.md")


if __name__ == "__main__":
    main()
