"""One agent's step of the exported filtered controller (``egcbf export --controller egcbf+:dcbf``) on one core:
the standalone runtime (``egcbf_runtime.Controller.step``: the ONNX policy under onnxruntime with one intra-op
thread, the numpy dcbf filter and attitude loop), and its parts.

The observation is :mod:`agent_latency`'s (agent 0 of a seeded scene with ``--neighbours`` neighbours in range
(20) and ``--hits`` LiDAR hits (32), all rows valid, exported with exactly that many rows), plus three sphere
obstacles within the filter's range and random realized accelerations; the scene is crowded, so the filter's QP
has rows and, in its ``--active`` variant, the policy's command is replaced by one the QP must change (the
filter's worst case: the active-set solve runs). Timed: ``--steps`` single steps (median, 90th and 99th
percentiles), after ``--warmup``; the parts (policy, filter and attitude loop, the same with the QP active)
likewise, in interleaved blocks of 100 calls.

    .venv/bin/python benchmarks/export_latency.py                 # writes docs/benchmarks.md (about a minute)
    .venv/bin/python benchmarks/export_latency.py --no-write --steps 200

Results go to ``docs/benchmarks.md`` and ``docs/deploy.md`` between ``<!-- export-latency:begin -->`` and
``<!-- export-latency:end -->``, and to ``docs/results/export_latency.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from agent_latency import observation

from egcbf.deploy.agent import AgentFilteredController
from egcbf.deploy.controller_export import export_filtered_controller, load_runtime
from egcbf.io.report import cpu_name, replace_section
from egcbf.io.threads import busy_cpus

ROOT = Path(__file__).resolve().parents[1]


def _times_us(fn, steps: int, warmup: int) -> np.ndarray:
    for _ in range(warmup):
        fn()
    out = np.empty(steps)
    for k in range(steps):
        t0 = time.perf_counter()
        fn()
        out[k] = time.perf_counter() - t0
    return 1e6 * out


def measure(checkpoint: Path, neighbours: int, hits: int, steps: int, warmup: int, seed: int = 0) -> dict:
    import onnxruntime

    torch.set_num_threads(1)
    busy = busy_cpus()
    ctrl = AgentFilteredController.from_checkpoint(checkpoint, max_neighbours=neighbours, max_hits=hits)
    state, goal, nbr, pts = (t.double().numpy() for t in observation(ctrl.controller, neighbours, hits, seed))
    rng = np.random.default_rng(seed)
    p = state[:3]
    obstacles = (p + np.array([[0.22, 0.0, 0.0], [-0.2, -0.3, 0.05], [0.0, 0.35, -0.1]]), np.array([0.1, 0.15, 0.1]))
    acc = rng.normal(scale=0.5, size=(1 + neighbours, 3))
    with tempfile.TemporaryDirectory() as d:
        out = export_filtered_controller(ctrl, Path(d) / "ctrl", checkpoint)
        mod = load_runtime(out)
        rt = mod.Controller.load(out, threads=1)
        size_kb = (out / mod.POLICY_FILE).stat().st_size / 1024
    mask, hmask = np.ones(neighbours, dtype=bool), np.ones(hits, dtype=bool)
    command, _ = rt.policy(state, goal, nbr, mask, pts, hmask)
    # a command toward the nearest neighbour at full scale: the QP must change it (its active-set solve runs)
    nearest = nbr[np.argmin(((nbr[:, :3] - p) ** 2).sum(-1)), :3]
    push = 1.4 * (nearest - p) / np.linalg.norm(nearest - p)
    _, info = rt.step(state, goal, nbr, mask, pts, hmask, acc, obstacles)
    _, active = rt.filter(state, push, nbr, mask, acc, obstacles)
    changed = float(np.abs(active["command"] - push).max())
    runs = {
        "step (policy + filter + attitude loop)": lambda: rt.step(state, goal, nbr, mask, pts, hmask, acc, obstacles),
        "policy (onnxruntime, with row selection)": lambda: rt.policy(state, goal, nbr, mask, pts, hmask),
        "filter + attitude loop (numpy)": lambda: rt.filter(state, command, nbr, mask, acc, obstacles),
        "filter + attitude loop, QP active": lambda: rt.filter(state, push, nbr, mask, acc, obstacles),
    }
    for fn in runs.values():
        _times_us(fn, warmup, 0)
    blocks = max(1, steps // 100)  # interleaved blocks of 100 calls: drift on a shared machine hits every part alike
    times = {k: np.zeros(0) for k in runs}
    for _ in range(blocks):
        for k, fn in runs.items():
            times[k] = np.concatenate((times[k], _times_us(fn, steps // blocks, 0)))
    summary = {
        k: {
            "median_us": float(np.median(t)),
            "p90_us": float(np.percentile(t, 90)),
            "p99_us": float(np.percentile(t, 99)),
        }
        for k, t in times.items()
    }
    return {
        "checkpoint": str(checkpoint),
        "neighbours": neighbours,
        "hits": hits,
        "obstacles": 3,
        "steps": steps,
        "filter_rows": info["num_rows"],
        "filter_changed_policy_command": bool(np.abs(info["command"] - info["policy_command"]).max() > 1e-9),
        "active_variant_change": changed,
        "times": summary,
        "onnx_kb": round(size_kb, 1),
        "machine": {
            "cpu": cpu_name(),
            "cores": os.cpu_count(),
            "threads": 1,
            "numpy": np.__version__,
            "onnxruntime": onnxruntime.__version__,
            "python": platform.python_version(),
            "busy_cpus_at_start": None if busy is None else round(busy, 2),
        },
        "date": date.today().isoformat(),
    }


def markdown(r: dict) -> str:
    m = r["machine"]
    lines = [
        "Generated by `.venv/bin/python benchmarks/export_latency.py` (results: `docs/results/export_latency.json`). "
        f"{m['cpu']}, one core (onnxruntime `intra_op_num_threads=1`), numpy {m['numpy']}, onnxruntime "
        f"{m['onnxruntime']}; CPUs kept busy by other work at start: {m['busy_cpus_at_start']} (sampled over 0.2 s); "
        f"{r['date']}. `egcbf_runtime.Controller.step` of `{r['checkpoint']}` behind the dcbf filter, exported with "
        f"{r['neighbours']} neighbour and {r['hits']} hit rows: one agent with {r['neighbours']} neighbours in range, "
        f"{r['hits']} LiDAR hits and {r['obstacles']} sphere obstacles ({r['filter_rows']} CBF rows in its QP); "
        f"{r['steps']} single calls each, float64 inputs. The QP-active variant feeds the filter a command toward the "
        f"nearest neighbour, which the QP changes by {r['active_variant_change']:.2f} (command units).",
        "",
        "| part | median | 90th percentile | 99th percentile |",
        "|---|---|---|---|",
    ]
    for k, t in r["times"].items():
        lines.append(f"| {k} | {t['median_us']:.0f} us | {t['p90_us']:.0f} us | {t['p99_us']:.0f} us |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=ROOT / "checkpoints/egcbf+")
    ap.add_argument("--neighbours", type=int, default=20)
    ap.add_argument("--hits", type=int, default=32)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    r = measure(args.checkpoint, args.neighbours, args.hits, args.steps, args.warmup)
    ck = args.checkpoint.resolve()
    r["checkpoint"] = str(ck.relative_to(ROOT)) if ck.is_relative_to(ROOT) else str(args.checkpoint)
    text = markdown(r)
    print(text)
    if not args.no_write:
        (ROOT / "docs" / "results" / "export_latency.json").write_text(json.dumps(r, indent=2) + "\n")
        replace_section(ROOT / "docs" / "benchmarks.md", "export-latency", text,
                        heading="## The exported filtered controller's step (deployment)")  # fmt: skip
        replace_section(ROOT / "docs" / "deploy.md", "export-latency", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
