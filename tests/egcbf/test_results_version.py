"""What the simulation computes, pinned: a tiny evaluation of every controller of the robustness sweep under every
fault family (float64, 8 agents, 20 steps), against ``tests/egcbf/data/results_pinned.json``.

Stored sweep cells (``egcbf reproduce``, ``egcbf robustness``) are reused by their key, which cannot see the code.
So a change that changes results must bump :data:`egcbf.reproduce.plan.RESULTS_VERSION` (the stored cells are then
recomputed); this test is what says so. If it fails and the change is intended, bump the version and regenerate:

    .venv/bin/python tests/egcbf/test_results_version.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from egcbf.reproduce.plan import RESULTS_VERSION

ROOT = Path(__file__).resolve().parents[2]
PINNED = Path(__file__).resolve().parent / "data" / "results_pinned.json"
CONTROLLERS = ("nominal", "ccbf", "dcbf", "gcbf+", "egcbf+", "egcbf+:dcbf")
FAULTS = (
    "none",
    "default",
    "default,hold=5,predict=1,dist_obs=1",
    "pos=0.05,vel=0.1,act_delay=2,act_predict=1",
    "lidar=0.1,lidar_drop=0.3",
    "wind=1/0/0,gust=0.5,thrust_gain=0.2,torque_bias=0.0001",
    "noncoop=0.25,noncoop_mode=straight",
)


def _factory(method: str):
    from egcbf.control.controllers import make_controller
    from egcbf.control.resolve import resolve
    from egcbf.reproduce.paper import base_method

    base = base_method(method)
    if base in ("nominal", "ccbf", "dcbf"):
        return lambda cfg: make_controller(base)
    ctrl = resolve(method, ROOT / "checkpoints" / base, dtype=torch.float64).controller
    return lambda cfg: ctrl


def compute() -> dict[str, list[float]]:
    """``{"method | spec": [safe, reach, cost, reward, sum of final positions, sum of their squares]}``."""
    from egcbf.evaluate.episodes import evaluate
    from egcbf.faults import parse_faults
    from egcbf.robustness.plan import perceived

    out = {}
    for method in CONTROLLERS:
        factory = _factory(method)
        for spec in FAULTS:
            run = perceived(method, parse_faults(spec).spec())
            rows, records = evaluate(
                factory, [8], area_size=1.5, num_obstacles=2, episodes=1, seed=3, max_steps=20,
                dtype=torch.float64, record=True, show_progress=False, faults=parse_faults(run),
            )  # fmt: skip
            r, p = rows[0], records[8].positions[-1].to(torch.float64)
            out[f"{method} | {spec}"] = [r["safe_rate"], r["reach_rate"], r["cost"], r["reward"],
                                         float(p.sum()), float(p.square().sum())]  # fmt: skip
    return out


def test_the_simulation_computes_what_the_stored_cells_were_made_with():
    pinned = json.loads(PINNED.read_text())
    assert pinned["results_version"] == RESULTS_VERSION, (
        f"RESULTS_VERSION is {RESULTS_VERSION} but {PINNED.name} was made at {pinned['results_version']}: "
        f"regenerate it (python {Path(__file__).relative_to(ROOT)})"
    )
    got = compute()
    assert sorted(got) == sorted(pinned["values"])
    changed = [k for k, v in got.items() if v != pytest.approx(pinned["values"][k], rel=1e-7, abs=1e-9)]
    assert not changed, (
        f"the simulation's results changed for {changed}: if intended, bump egcbf.reproduce.plan.RESULTS_VERSION "
        f"(stored cells are then recomputed) and regenerate (python {Path(__file__).relative_to(ROOT)})"
    )


if __name__ == "__main__":
    torch.set_num_threads(1)
    PINNED.write_text(json.dumps({"results_version": RESULTS_VERSION, "values": compute()}, indent=1) + "\n")
    sys.stdout.write(f"wrote {PINNED}\n")
