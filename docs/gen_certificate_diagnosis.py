"""Why does the learned CBF fail its decrease condition? A diagnosis on validation episodes, for docs/learning.md.

EGCBF+ (training seed 0) behind its own learned-CBF filter, N = 512, l = 4, without and with 8 obstacles, one
episode each on validation seed 777 (never an evaluation seed: this diagnosis informs the next barrier's design).
Every agent-state with ``h >= 0`` whose condition ``h(x_{t+1}) - h(x_t) >= -dt alpha h(x_t)`` fails
(:mod:`egcbf.certify.rates`, stride 1) is classified by whether the agent's neighbour set (agents within the
communication radius) or its set of obstacles within LiDAR range changed over that step (the graph CBF is
discontinuous there), and by the size of the failure. Two variants of the barrier are scored on the same rollouts
(the filter's rows, hence the rollouts, are unchanged): the head's untrained prior (the learned correction zeroed:
is the failure learned?), and each edge's term of the soft-min weighted by a smoothstep of its distance that
vanishes at the sensing radius (``ENTRY_WIDTH``: is it the edges entering the neighbourhood?). Writes
``docs/results/certificate_diagnosis.json`` and the ``certificate-diagnosis`` block of docs/learning.md:

    .venv/bin/python docs/gen_certificate_diagnosis.py            # run the episodes, then write both
    .venv/bin/python docs/gen_certificate_diagnosis.py --report   # the block from the committed JSON
"""

import argparse
import copy
import json
from pathlib import Path

import torch

from egcbf.certify import LearnedBarrier, count_rates, roll_out
from egcbf.control.resolve import resolve
from egcbf.env import EnvConfig
from egcbf.env.graph import KIND_GOAL
from egcbf.evaluate.episodes import episode_seed
from egcbf.io.report import md_table, replace_section
from egcbf.nn.edge_min import segment_logsumexp
from egcbf.train.checkpoint import load_network

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "results" / "certificate_diagnosis.json"
DOC = ROOT / "docs" / "learning.md"
SEED = 777
CHECKPOINT = ROOT / "checkpoints" / "egcbf+"
#: (m) the width of the smoothstep that fades an edge's soft-min term in from the sensing radius
ENTRY_WIDTH = 0.25


def _prior(cbf):
    """The CBF with its learned correction zeroed: the head's untrained closest-approach prior."""
    net = copy.deepcopy(cbf)
    with torch.no_grad():
        net.head.edge_mlp[-1].weight.zero_()
        net.head.edge_mlp[-1].bias.zero_()
    return net


def _faded(cbf, width: float = ENTRY_WIDTH):
    """The CBF whose soft-min weights each edge's term by ``w = smoothstep((R - |dp|) / width)`` (0 at the
    sensing radius R: an entering edge changes h continuously)."""
    net = copy.deepcopy(cbf)
    head = net.head

    def forward(graph, z, frames):
        b, dst = head.edge_values(graph, z, frames)
        d = graph.edge_attr[graph.edge_kind != KIND_GOAL].norm(dim=-1)
        s = ((graph.comm_radius - d) / width).clamp(0, 1)
        w = s * s * (3 - 2 * s)
        logw = torch.where(w > 0, w.clamp_min(1e-30).log(), torch.full_like(w, -1e4))
        tau = head.temperature
        return -tau * segment_logsumexp(-b / tau + logw, dst, graph.num_dst, -(1.0 - head.distance) / tau)

    head.forward = forward
    return net


class _Recorder:
    """A 'barrier' that records every state's positions and obstacles (its values are zeros)."""

    def __init__(self):
        self.positions, self.obstacles = [], None

    def values(self, state, config):
        self.positions.append(state.positions.detach().to(torch.float64).cpu().clone())
        self.obstacles = state.obstacles
        return torch.zeros(state.x.shape[:2], dtype=torch.float64)


def _sets_changed(pos: torch.Tensor, radius: float, centers, radii, agent_radius: float) -> torch.Tensor:
    """``(T, N)`` bool: agent i's set of neighbours within ``radius`` (or of obstacles whose surface is within it:
    the LiDAR's range is the communication radius) differs between t and t + 1; ``pos`` ``(T + 1, N, 3)``."""
    d = torch.cdist(pos, pos)
    near = d < radius
    changed = (near[1:] != near[:-1]).any(-1)
    if centers is not None and centers.shape[0]:
        surface = torch.cdist(pos, centers) - radii - agent_radius
        close = surface < radius
        changed |= (close[1:] != close[:-1]).any(-1)
    return changed


def run() -> dict:
    torch.set_num_threads(1)
    cbf, train_cfg = load_network(CHECKPOINT, "cbf")
    barrier = LearnedBarrier(cbf, train_cfg.alpha)
    variants = {"shipped": barrier, "prior": LearnedBarrier(_prior(cbf), train_cfg.alpha),
                "shipped, faded entry": LearnedBarrier(_faded(cbf), train_cfg.alpha),
                "prior, faded entry": LearnedBarrier(_faded(_prior(cbf)), train_cfg.alpha)}  # fmt: skip
    out = {"checkpoint": "checkpoints/egcbf+", "seed": SEED, "settings": []}
    for k in (0, 8):
        env = EnvConfig.for_robot("quadrotor", num_agents=512, area_size=4.0, num_obstacles=k)
        ctrl = resolve("policy:cbf", CHECKPOINT).controller
        rec = _Recorder()
        traj = roll_out(ctrl, {**variants, "rec": rec}, env, [episode_seed(SEED, 512, 0)])
        traj.h["h"] = traj.h["shipped"]
        h = traj.h["h"][:, 0]  # (T + 1, N)
        pos = torch.stack(rec.positions)[:, 0]
        obs = rec.obstacles
        centers = obs.centers[0].to(torch.float64) if obs.centers.shape[1] else None
        radii = obs.radii[0].to(torch.float64) if obs.centers.shape[1] else None
        changed = _sets_changed(pos, env.comm_radius, centers, radii, env.agent_radius)
        ht, hn = h[:-1], h[1:]
        claim = ht >= 0
        excess = -traj.dt * barrier.alpha * ht - (hn - ht)  # > 0: the condition fails by this much
        fail = claim & (excess > 0)
        bad = traj.filter_bad[:, 0]
        out["settings"].append({
            "obstacles": k,
            "claims": int(claim.sum()),
            "failures": int(fail.sum()),
            "claims_with_set_change": int((claim & changed).sum()),
            "failures_with_set_change": int((fail & changed).sum()),
            "failures_with_filter_bad": int((fail & bad).sum()),
            "failures_without_change_or_bad": int((fail & ~changed & ~bad).sum()),
            "excess_median": float(excess[fail].median()) if fail.any() else 0.0,
            "excess_small": int((fail & (excess < 1e-3)).sum()),
            "h_median_at_failure": float(ht[fail].median()) if fail.any() else 0.0,
            "safe_rate": float(1 - traj.collision.any(0).double().mean()),
            "variants": {n: count_rates(traj, n, b.kappa, window=32, stride=1) for n, b in variants.items()},
        })  # fmt: skip
        for c in out["settings"][-1]["variants"].values():
            c.pop("histogram")
        print(out["settings"][-1], flush=True)
    return out


def block(res: dict) -> str:
    rows = []
    for s in res["settings"]:
        f = max(s["failures"], 1)
        rows.append([str(s["obstacles"]), f"{100 * s['safe_rate']:.2f}", f"{s['claims']:,}",
                     f"{s['failures']:,} ({100 * s['failures'] / max(s['claims'], 1):.1f} %)",
                     f"{100 * s['claims_with_set_change'] / max(s['claims'], 1):.1f} %",
                     f"{100 * s['failures_with_set_change'] / f:.1f} %",
                     f"{100 * s['failures_with_filter_bad'] / f:.1f} %",
                     f"{100 * s['failures_without_change_or_bad'] / f:.1f} %",
                     f"{100 * s['excess_small'] / f:.1f} %", f"{s['excess_median']:.4f}",
                     f"{s['h_median_at_failure']:.3f}"])  # fmt: skip
    head = ["obstacles", "safe %", "states with h ≥ 0", "condition fails", "of h ≥ 0: neighbour or obstacle set "
            "changes over the step", "of failures: set changes", "of failures: filter QP slack / braked",
            "of failures: neither", "of failures: by < 1e-3", "median failure size",
            "median h at a failure"]  # fmt: skip
    vrows = []
    for s in res["settings"]:
        for n, c in s["variants"].items():
            vrows.append([str(s["obstacles"]), n, _r(c, "violated", "claims"), _r(c, "missed", "preceding"),
                          _r(c, "unsafe_claimed", "unsafe"), _r(c, "cautious", "negatives_known")])  # fmt: skip
    return (f"Generated by `.venv/bin/python docs/gen_certificate_diagnosis.py` from "
            f"`docs/results/certificate_diagnosis.json`: EGCBF+ (training seed 0) behind its own learned-CBF filter, "
            f"N = 512, l = 4, one episode per row on validation seed {res['seed']}, every step (no thinning).\n\n"
            + md_table(head, rows) + "\n\nThe same rollouts scored against variants of the barrier (the untrained "
            f"prior: the correction zeroed; faded entry: each edge's soft-min term weighted by a smoothstep over the "
            f"last {ENTRY_WIDTH:g} m inside the sensing radius):\n\n"
            + md_table(["obstacles", "barrier", "condition fails among h ≥ 0", "misses among states preceding a "
                        "collision", "unsafe states with h ≥ 0", "h < 0 yet safe for 32 steps"], vrows))  # fmt: skip


def _r(c: dict, k: str, n: str) -> str:
    return f"{c[k]:,} / {c[n]:,} ({100 * c[k] / max(c[n], 1):.1f} %)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--report", action="store_true", help="only rewrite the block from the committed JSON")
    args = ap.parse_args()
    if not args.report:
        OUT.write_text(json.dumps(run(), indent=1) + "\n")
    replace_section(DOC, "certificate-diagnosis", block(json.loads(OUT.read_text())))
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
