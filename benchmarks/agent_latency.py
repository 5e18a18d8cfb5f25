"""One agent's control step on one core: the per-agent controller in PyTorch, its TorchScript file and its ONNX file
under onnxruntime, with the network's parameter count and FLOPs.

The observation is agent 0 of a seeded scene with ``--neighbours`` neighbours in range (20) and ``--hits`` LiDAR
hits (32), all rows valid, exported with exactly that many rows (``egcbf export --max-neighbours 20 --max-hits 32``).
Timed: the fixed-shape module on its padded inputs (PyTorch eager, the TorchScript file, the ONNX file under
onnxruntime with one intra-op thread), interleaved, median of ``--repeats`` blocks of calls; and the whole
:class:`egcbf.deploy.agent.AgentController` call in PyTorch (padding, nearest-row selection and the module).
FLOPs: ``torch.utils.flop_counter`` on the eager module (matrix products and the like; element-wise work is not
counted).

    .venv/bin/python benchmarks/agent_latency.py                 # writes docs/benchmarks.md (about a minute)
    .venv/bin/python benchmarks/agent_latency.py --no-write --repeats 5

Results go to ``docs/benchmarks.md`` and ``docs/deploy.md`` between ``<!-- agent-latency:begin -->`` and
``<!-- agent-latency:end -->``, and to ``docs/results/agent_latency.json``. Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from datetime import date
from pathlib import Path

import torch

from egcbf.deploy.agent import AgentController
from egcbf.deploy.export import INPUT_NAMES, OUTPUT_NAMES, export_controller, exportable
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.io.report import cpu_name, replace_section
from egcbf.io.threads import busy_cpus

ROOT = Path(__file__).resolve().parents[1]


def observation(ctrl: AgentController, neighbours: int, hits: int, seed: int = 0):
    """Agent 0 with ``neighbours`` agents within its radius and ``hits`` LiDAR hits around it (float32)."""
    cfg = EnvConfig.for_robot("quadrotor", num_agents=1 + neighbours, num_envs=1, area_size=0.55, num_obstacles=0)
    state = SwarmEnv(cfg, dtype=torch.float32).reset(seed)
    x, g = state.x[0], torch.Generator().manual_seed(seed)
    p = ctrl.robot.positions(x[0])
    in_range = torch.linalg.vector_norm(ctrl.robot.positions(x[1:]) - p, dim=-1) < ctrl.env_config.comm_radius
    if int(in_range.sum()) != neighbours:
        raise RuntimeError(f"only {int(in_range.sum())} of {neighbours} neighbours are within range: shrink the arena")
    direction = torch.nn.functional.normalize(torch.randn(hits, 3, generator=g), dim=-1)
    return x[0], state.goals[0, 0], x[1:], p + 0.3 * direction


def per_call_ms(fn, block_s: float = 0.2) -> float:
    """Milliseconds per call over a block of calls lasting about ``block_s``."""
    fn()
    k = max(1, int(block_s / max(_once(fn), 1e-6)))
    t0 = time.perf_counter()
    for _ in range(k):
        fn()
    return 1e3 * (time.perf_counter() - t0) / k


def _once(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def measure(checkpoint: Path, neighbours: int, hits: int, repeats: int) -> dict:
    import numpy as np
    import onnxruntime

    torch.set_num_threads(1)
    busy = busy_cpus()
    busy = None if busy is None else round(busy, 2)
    ctrl = AgentController.from_checkpoint(checkpoint, max_neighbours=neighbours, max_hits=hits)
    obs = observation(ctrl, neighbours, hits)
    padded = ctrl.pad(*obs)
    eager = exportable(ctrl.module)
    with tempfile.TemporaryDirectory() as d:
        ts = torch.jit.load(str(export_controller(ctrl, "torchscript", Path(d) / "a.pt")))
        onnx_path = export_controller(ctrl, "onnx", Path(d) / "a.onnx")
        opts = onnxruntime.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        session = onnxruntime.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
        size_kb = onnx_path.stat().st_size / 1024
    feeds = {n: np.asarray(a.numpy()) for n, a in zip(INPUT_NAMES, padded)}
    runs = {
        "pytorch (AgentController call)": lambda: ctrl(*obs),
        "pytorch (fixed-shape module)": lambda: eager(*padded),
        "torchscript": lambda: ts(*padded),
        "onnxruntime": lambda: session.run(list(OUTPUT_NAMES), feeds),
    }
    times: dict[str, list[float]] = {k: [] for k in runs}
    with torch.no_grad():
        for _ in range(repeats):  # interleaved: drift on a shared machine hits every variant alike
            for name, fn in runs.items():
                times[name].append(per_call_ms(fn))
        from torch.utils.flop_counter import FlopCounterMode

        with FlopCounterMode(display=False) as counter:
            eager(*padded)
    params = sum(p.numel() for p in ctrl.module.policy.parameters())
    return {
        "checkpoint": str(checkpoint),
        "neighbours": neighbours,
        "hits": hits,
        "median_ms": {k: statistics.median(v) for k, v in times.items()},
        "min_ms": {k: min(v) for k, v in times.items()},
        "repeats": repeats,
        "policy_parameters": params,
        "flops": counter.get_total_flops(),
        "onnx_kb": round(size_kb, 1),
        "machine": {
            "cpu": cpu_name(),
            "cores": os.cpu_count(),
            "threads": 1,
            "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__,
            "python": platform.python_version(),
            "busy_cpus_at_start": busy,
        },
        "date": date.today().isoformat(),
    }


def markdown(results: list[dict]) -> str:
    m = results[0]["machine"]
    lines = [
        "Generated by `.venv/bin/python benchmarks/agent_latency.py` (results: `docs/results/agent_latency.json`). "
        f"{m['cpu']}, one thread, torch {m['torch']}, onnxruntime {m['onnxruntime']}; CPUs kept busy by other work "
        f"at start: {m['busy_cpus_at_start']} (sampled over 0.2 s); {results[0]['date']}. One agent's step: "
        f"{results[0]['neighbours']} "
        f"neighbours in range and {results[0]['hits']} LiDAR hits, exported with exactly that many rows; median "
        f"(min) of {results[0]['repeats']} interleaved blocks of calls, float32.",
        "",
        "| checkpoint | parameters | FLOPs | ONNX file | PyTorch call (AgentController) | PyTorch module "
        "| TorchScript | onnxruntime |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        t = [f"{r['median_ms'][k]:.3f} ({r['min_ms'][k]:.3f}) ms" for k in r["median_ms"]]
        lines.append(f"| `{r['checkpoint']}` | {r['policy_parameters']:,} | {r['flops'] / 1e6:.2f} M | "
                     f"{r['onnx_kb']:.0f} kB | " + " | ".join(t) + " |")  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--checkpoints", nargs="+", type=Path, default=[ROOT / "checkpoints/egcbf+", ROOT / "checkpoints/gcbf+"]
    )
    ap.add_argument("--neighbours", type=int, default=20)
    ap.add_argument("--hits", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    results = []
    for ck in args.checkpoints:
        r = measure(ck, args.neighbours, args.hits, args.repeats)
        r["checkpoint"] = str(ck.resolve().relative_to(ROOT)) if ck.resolve().is_relative_to(ROOT) else str(ck)
        results.append(r)
    text = markdown(results)
    print(text)
    if not args.no_write:
        (ROOT / "docs" / "results" / "agent_latency.json").write_text(json.dumps(results, indent=2) + "\n")
        replace_section(ROOT / "docs" / "benchmarks.md", "agent-latency", text,
                        heading="## One agent's control step (deployment)")  # fmt: skip
        replace_section(ROOT / "docs" / "deploy.md", "agent-latency", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
