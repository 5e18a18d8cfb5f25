"""Three changes to the learned-CBF filter, each aimed at one suspected cause of its condition failures, measured on
validation episodes for docs/learning.md (validation seed 777, never an evaluation seed).

EGCBF+ (training seed 0), N = 512, l = 4, no obstacles, one episode per filter, every step scored
(:mod:`egcbf.certify.rates`, window 32, stride 1) against several barriers:

* **shipped**: the ``cbf`` filter as shipped (the reference row).
* **look-ahead**: the filter's per-edge rows read at the state ``T = 0.05`` s ahead under the accelerations the
  agents realized over the last step (the ``dcbf`` filter's predictor for the attitude loop's lag): is the lag the
  cause?
* **continuous entry**: every edge's barrier faded, in value, to above the free value over the last ``WIDTH`` m
  inside the sensing radius, ``b' = c + (b - c) w(|dp|)`` with ``w`` a smoothstep and ``c = 1 - D + LIFT tau``
  (an edge entering the neighbourhood changes the soft-min by < tau e^-LIFT), used by the filter's rows and by the
  barrier: is the entering edge the cause?
* **prior**: the ``prior`` filter (the correction zeroed): is the failure learned?

Barriers scored on every rollout: the shipped soft-min ``h``, the continuous-entry soft-min, the hard minimum
``min(b_free, min_j b_ij)`` of the per-edge barriers (what the filter's per-edge rows certify: a soft-min's
weighted mean of the edge values exceeds the soft-min by ``tau`` times the weights' entropy, so per-edge
conditions do not imply the soft-min's), and the prior's soft-min and hard minimum. Writes
``docs/results/learned_filter_variants.json`` and the ``learned-filter-variants`` block of docs/learning.md:

    .venv/bin/python docs/gen_learned_filter_variants.py            # run the episodes (~7 min), then write both
    .venv/bin/python docs/gen_learned_filter_variants.py --report   # the block from the committed JSON
"""

import argparse
import copy
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch
from gen_certificate_diagnosis import _prior

import egcbf.algo.edge_qp as edge_qp
from egcbf.certify import LearnedBarrier, count_rates
from egcbf.certify.rollout import Trajectory
from egcbf.control.filters import FilterConfig, FilteredController
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import KIND_AGENT, KIND_GOAL
from egcbf.evaluate.episodes import concat_states, episode_seed
from egcbf.io.report import cpu_name, md_table, replace_section
from egcbf.nn.models import frames_for
from egcbf.train.checkpoint import load_network

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "results" / "learned_filter_variants.json"
DOC = ROOT / "docs" / "learning.md"
SEED = 777
CHECKPOINT = ROOT / "checkpoints" / "egcbf+"
#: (s) the look-ahead of the look-ahead rows (the dcbf filter's default)
LOOKAHEAD = 0.05
#: (m) the band inside the sensing radius over which a continuous-entry edge fades in
WIDTH = 0.2
#: the continuous-entry cap above the free value, in soft-min temperatures
LIFT = 6.0
KEYS = ("states", "unsafe", "unsafe_claimed", "preceding", "missed", "claims", "violated", "filter_bad",
        "negatives_known", "cautious")  # fmt: skip


def _continuous_entry(cbf):
    """The CBF whose per-edge barriers fade in value to above the free value at the sensing radius (module doc)."""
    net = copy.deepcopy(cbf)
    head = net.head
    edge_values = head.edge_values

    def faded(graph, z, frames, dp=None, dv=None):
        b, dst = edge_values(graph, z, frames, dp, dv)
        d = (dp if dp is not None else graph.edge_attr[graph.edge_kind != KIND_GOAL]).norm(dim=-1).to(b.dtype)
        s = ((graph.comm_radius - d) / WIDTH).clamp(0, 1)
        cap = (1.0 - head.distance) + LIFT * head.temperature
        return cap + (b - cap) * (s * s * (3 - 2 * s)), dst

    head.edge_values = faded
    return net


def _hard_min(cbf):
    """The CBF whose soft-min is replaced by the hard minimum of its per-edge barriers and the free value."""
    net = copy.deepcopy(cbf)
    head = net.head

    def forward(graph, z, frames):
        b, dst = head.edge_values(graph, z, frames)
        free = torch.full((graph.num_dst,), 1.0 - head.distance, dtype=b.dtype, device=b.device)
        return free.scatter_reduce(0, dst, b, "amin", include_self=True)

    head.forward = forward
    return net


class _LookAhead:
    """``edge_qp.edge_barriers`` with every agent and hit edge read ``LOOKAHEAD`` s ahead under the realized
    accelerations ``accel`` ``(M, 3)`` (set per step; ``None``: the current state)."""

    def __init__(self):
        self.accel = None
        self.plain = edge_qp.edge_barriers

    def __call__(self, graph, cbf=None, distance=0.25, horizon=1.0):
        if self.accel is None or cbf is None:
            return self.plain(graph, cbf, distance, horizon)
        sel = graph.edge_kind != KIND_GOAL
        ei, kind = graph.edge_index[:, sel], graph.edge_kind[sel]
        a = torch.as_tensor(self.accel, dtype=torch.float64).reshape(-1, 3)
        recv, send = ei[1], ei[0].clamp(max=a.shape[0] - 1)  # agents are the first M senders
        da = torch.where((kind == KIND_AGENT)[:, None], a[send] - a[recv], -a[recv])  # hits are static
        dp0 = graph.edge_attr[sel].detach().to(torch.float64)
        dv0 = graph.relative_velocity(ei).detach().to(torch.float64)
        dp = (dp0 + LOOKAHEAD * dv0 + 0.5 * LOOKAHEAD**2 * da).requires_grad_(True)
        dv = (dv0 + LOOKAHEAD * da).requires_grad_(True)
        with torch.enable_grad():
            with torch.no_grad():
                z = cbf.encoder(graph)
            b, _ = cbf.head.edge_values(graph, z, frames_for(cbf.encoder.group, graph), dp.to(z.dtype), dv.to(z.dtype))
            b = b.to(torch.float64)
            gp, gv = torch.autograd.grad(b.sum(), (dp, dv))
        return edge_qp.EdgeBarriers(recv, kind, b.detach(), gp, gv, dv.detach())


def _episode(ctrl, barriers: dict, env_cfg: EnvConfig, look: _LookAhead | None) -> dict:
    seed = episode_seed(SEED, env_cfg.num_agents, 0)
    env = SwarmEnv(dataclasses.replace(env_cfg, num_envs=1))
    state = concat_states([env.reset(seed)])
    h = {n: [b.values(state, env.config)] for n, b in barriers.items()}
    coll, bad, ms = [torch.zeros(state.x.shape[:2], dtype=torch.bool)], [], []
    reached = torch.zeros(state.x.shape[:2], dtype=torch.bool)
    for _ in range(env_cfg.max_steps):
        if look is not None:
            look.accel = ctrl._realized_acceleration(state, env.config)
        t0 = time.perf_counter()
        u, info = ctrl(state, env.config)
        ms.append(1e3 * (time.perf_counter() - t0))
        bad.append(torch.from_numpy(np.asarray(info["slack_mask"]) | np.asarray(info["failed_mask"])))
        state, step = env.step(state, u)
        coll.append(step.collision.cpu())
        reached |= step.reached.cpu()
        for n, b in barriers.items():
            h[n].append(b.values(state, env.config))
    traj = Trajectory(h={n: torch.stack(v) for n, v in h.items()}, collision=torch.stack(coll),
                      filter_bad=torch.stack(bad), dt=float(env.config.dt))  # fmt: skip
    collided = traj.collision.any(0)
    success = float((~collided & reached).double().mean())
    out = {"safe_rate": float((~collided).double().mean()), "success_rate": success,
           "step_ms_median": float(np.median(ms)), "barriers": {}}  # fmt: skip
    for n, b in barriers.items():
        c = count_rates(traj, n, b.kappa, window=32, stride=1)
        out["barriers"][n] = {k: c[k] for k in KEYS}
    return out


def run() -> dict:
    torch.set_num_threads(1)
    policy, tc = load_network(CHECKPOINT, "policy")
    cbf = load_network(CHECKPOINT, "cbf")[0]
    prior = _prior(cbf)
    barriers = {"shipped": cbf, "continuous entry": _continuous_entry(cbf), "hard min": _hard_min(cbf),
                "prior": prior, "prior, hard min": _hard_min(prior)}  # fmt: skip
    barriers = {n: LearnedBarrier(net, tc.alpha) for n, net in barriers.items()}
    env_cfg = EnvConfig.for_robot("quadrotor", num_agents=512, area_size=4.0, num_obstacles=0)
    look = _LookAhead()
    out = {"checkpoint": "checkpoints/egcbf+", "seed": SEED, "cpu": cpu_name(), "lookahead": LOOKAHEAD, "width": WIDTH,
           "lift": LIFT, "filters": {}}  # fmt: skip
    filters = {
        "shipped": (FilterConfig.for_kind("cbf"), cbf, None),
        "look-ahead": (dataclasses.replace(FilterConfig.for_kind("cbf"), lookahead=LOOKAHEAD), cbf, look),
        "continuous entry": (FilterConfig.for_kind("cbf"), _continuous_entry(cbf), None),
        "prior": (FilterConfig.for_kind("prior"), None, None),
    }
    edge_qp.edge_barriers = look  # falls through to the plain rows unless look.accel is set
    try:
        for name, (fc, net, lk) in filters.items():
            ctrl = FilteredController(policy, tc.model, fc, net)
            look.accel = None
            out["filters"][name] = _episode(ctrl, barriers, env_cfg, lk)
            look.accel = None
            print(name, json.dumps(out["filters"][name]), flush=True)
    finally:
        edge_qp.edge_barriers = look.plain
    return out


def _r(c: dict, k: str, n: str) -> str:
    return f"{c[k]:,} / {c[n]:,} ({100 * c[k] / max(c[n], 1):.1f} %)"


def block(res: dict) -> str:
    rows, brows = [], []
    for name, f in res["filters"].items():
        s = f["barriers"]["shipped"]
        rows.append([name, f"{100 * f['safe_rate']:.2f}", f"{100 * f['success_rate']:.2f}",
                     _r(s, "filter_bad", "states"), f"{f['step_ms_median']:.0f}"])  # fmt: skip
        for bname, c in f["barriers"].items():
            brows.append([name, bname, _r(c, "violated", "claims"), _r(c, "missed", "preceding"),
                          _r(c, "unsafe_claimed", "unsafe"), _r(c, "cautious", "negatives_known")])  # fmt: skip
    return (f"Generated by `.venv/bin/python docs/gen_learned_filter_variants.py` from "
            f"`docs/results/learned_filter_variants.json`: EGCBF+ (training seed 0) behind four variants of the "
            f"learned-CBF filter, N = 512, l = 4, no obstacles, one episode each on validation seed {res['seed']}, "
            f"every step scored (look-ahead {res['lookahead']:g} s; continuous entry over the last {res['width']:g} m "
            f"of the sensing radius, cap {res['lift']:g} tau above the free value; one torch thread, {res['cpu']}, "
            "beside one other job).\n\n"
            + md_table(["filter", "safe %", "success %", "agent-steps with QP slack / braked", "step ms"], rows)
            + "\n\nEach rollout scored against the barriers:\n\n"
            + md_table(["filter", "barrier", "condition fails among h ≥ 0", "misses among states preceding a "
                        "collision", "unsafe states with h ≥ 0", "h < 0 yet safe for 32 steps"], brows))  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--report", action="store_true", help="only rewrite the block from the committed JSON")
    args = ap.parse_args()
    if not args.report:
        OUT.write_text(json.dumps(run(), indent=1) + "\n")
    replace_section(DOC, "learned-filter-variants", block(json.loads(OUT.read_text())))
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
