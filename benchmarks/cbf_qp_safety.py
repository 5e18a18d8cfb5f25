"""Closed-loop safety of the hand-crafted CBF-QP baselines (the numbers quoted in ``docs/baselines.md``).

Runs full episodes (seeded resets) with each controller and barrier variant and prints one row per setting:
safe / reach / success rate (``egcbf.evaluate.metrics``), the smallest agent–agent distance seen, the steps whose QPs
needed slack, failed solves and the median controller time.

    .venv/bin/python benchmarks/cbf_qp_safety.py                           # the docs' sweep (~10 min, 2 cores)
    .venv/bin/python benchmarks/cbf_qp_safety.py --agents 16 --area 2 --episodes 1 --steps 100
    .venv/bin/python benchmarks/cbf_qp_safety.py --variants wang hocbf hocbf-cull0.5 hocbf-knn3 --agents 64 --area 2
    .venv/bin/python benchmarks/cbf_qp_safety.py --head-on        # two agents swapping places at full speed
"""

from __future__ import annotations

import argparse
import statistics
import sys

import torch

from egcbf.control.controllers import make_controller
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.evaluate.metrics import EpisodeStats, summarize

VARIANTS = {
    "nominal": ("nominal", {}),
    "wang": ("ccbf", {}),
    "hocbf": ("ccbf", {"kind": "hocbf"}),
    "hocbf-cull0.5": ("ccbf", {"kind": "hocbf", "cull_radius": 0.5}),
    "hocbf-knn3": ("ccbf", {"kind": "hocbf", "max_neighbors": 3}),
    "hocbf-knn6": ("ccbf", {"kind": "hocbf", "max_neighbors": 6}),
    "wang-knn3": ("ccbf", {"max_neighbors": 3}),
    "dcbf-wang": ("dcbf", {}),
    "dcbf-hocbf": ("dcbf", {"kind": "hocbf"}),
}


def run(variant: str, n: int, area: float, obstacles: int, steps: int, episodes: int, seed: int) -> dict:
    name, kw = VARIANTS[variant]
    cfg = EnvConfig(num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=1, max_steps=steps)
    env = SwarmEnv(cfg, dtype=torch.float64)
    nominal = make_controller("nominal")
    per_ep, ms, slack, failed, dmin = [], [], 0, 0, float("inf")
    for ep in range(episodes):
        ctrl = make_controller(name, **kw)
        state = env.reset(seed + ep)
        stats = EpisodeStats(1, n)
        for _ in range(steps):
            u, info = ctrl(state, cfg)
            u_ref, _ = nominal(state, cfg)
            ms.append(info["qp_ms"])
            slack += info["num_slack"] > 0
            failed += info["num_failed"]
            state, si = env.step(state, u)
            stats.update(si, u=u, u_ref=u_ref)
            p = state.positions[0]
            d = torch.cdist(p, p) + torch.eye(n, dtype=p.dtype) * 1e9
            dmin = min(dmin, float(d.min()))
        per_ep.append(stats.per_episode())
    row = summarize({k: torch.cat([e[k] for e in per_ep]) for k in per_ep[0]}, n)
    row.update(variant=variant, dmin=dmin, slack_steps=slack, failed=failed, ms=statistics.median(ms))
    return row


def head_on(name: str, kw: dict, distance: float, offset: float = 0.01) -> float:
    """Smallest distance of two agents that start ``distance`` apart and swap places (goal line offset)."""
    from egcbf.env import Obstacles, SwarmState
    from egcbf.robots.quadrotor import dynamics as dyn

    f64 = torch.float64
    p0 = torch.tensor([[0.2, 2.0, 2.0], [0.2 + distance, 2.0 + offset, 2.0]], dtype=f64)
    x = dyn.hover_state(p0, torch.tensor([0.0, 2.5], dtype=f64))[None]
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=f64), torch.zeros(1, 0, dtype=f64))
    state = SwarmState(x, p0.flip(0)[None].clone(), obs, 0)
    cfg = EnvConfig(num_agents=2, area_size=4.0, num_obstacles=0, max_steps=int(60 + 60 * distance))
    env, ctrl, dmin = SwarmEnv(cfg, dtype=f64), make_controller(name, **kw), float("inf")
    for _ in range(cfg.max_steps):
        u, _ = ctrl(state, cfg)
        state, _ = env.step(state, u)
        dmin = min(dmin, float((state.positions[0, 0] - state.positions[0, 1]).norm()))
    return dmin


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", nargs="+", default=["nominal", "wang", "hocbf", "dcbf-wang", "dcbf-hocbf"])
    ap.add_argument("--agents", type=int, default=64)
    ap.add_argument("--area", type=float, default=2.0)
    ap.add_argument("--obstacles", type=int, default=0)
    ap.add_argument("--steps", type=int, default=256)
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head-on", action="store_true", help="the two-agent head-on table instead")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.head_on:
        print("| barrier | ccbf, 1.6 m | dcbf, 1.6 m | ccbf, 3.6 m | dcbf, 3.6 m |\n|---|---|---|---|---|")
        for label, kw in (("Wang", {}), ("Wang, margin 0.1", {"margin": 0.1}), ("HOCBF", {"kind": "hocbf"})):
            cells = [head_on(c, kw, dist) for dist in (1.6, 3.6) for c in ("ccbf", "dcbf")]
            print(f"| {label} | " + " | ".join(f"{v:.3f}" for v in cells) + " |", flush=True)
        return 0
    print(
        f"N = {args.agents}, l = {args.area:g}, {args.obstacles} obstacles, {args.steps} steps, "
        f"{args.episodes} episode(s) from seed {args.seed}\n"
    )
    print("| variant | safe | reach | success | min distance (m) | slack steps | failed | median ms |")
    print("|---|---|---|---|---|---|---|---|")
    for v in args.variants:
        r = run(v, args.agents, args.area, args.obstacles, args.steps, args.episodes, args.seed)
        print(
            f"| {v} | {r['safe_rate']:.3f} | {r['reach_rate']:.3f} | {r['success_rate']:.3f} | {r['dmin']:.3f} | "
            f"{r['slack_steps']} | {r['failed']} | {r['ms']:.1f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
