"""Scaling of one environment step + one graph build with the number of agents.

Two series, N = 64 ... 4096:
  (a) fixed density: the arena grows with N so that N / l^3 = 1 agent per m^3;
  (b) fixed area l = 4 m: the density grows with N (up to 64 agents per m^3), and so does the number of edges.
Obstacles keep a density of 1/8 per m^3 (8 spheres in the 4 m cube, the paper's Figure 3 setting).

Reported: median wall time over repeats of ``env.step`` (dynamics + collision/unsafe/reached masks) and of
``build_graph`` (LiDAR + cell-list neighbour search + features), the number of edges, and the fitted exponent
``b`` of ``time ~ N^b`` (least squares in log-log over N >= 256). Near-linear growth (b close to 1) at fixed
density is the acceptance criterion; at fixed area the edges grow as N^2 and so must the time, eventually.

    python benchmarks/env_scaling.py                  # CPU, float32, writes docs/benchmarks.md
    python benchmarks/env_scaling.py --device cuda --no-write
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.io.report import replace_section
from egcbf.robots.quadrotor import dynamics as dyn

BEGIN, END = "<!-- env-scaling:begin -->", "<!-- env-scaling:end -->"
SIZES = (64, 128, 256, 512, 1024, 2048, 4096)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn, device, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        out = fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def measure(n: int, area: float, device: torch.device, dtype: torch.dtype, repeats: int, seed: int = 0) -> dict:
    k = max(0, round(area**3 / 8))
    cfg = EnvConfig(num_agents=n, area_size=area, num_obstacles=k, num_envs=1)
    env = SwarmEnv(cfg, device=device, dtype=dtype)
    state = env.reset(seed)
    u = dyn.hover_control(cfg.params, 1, n, dtype=dtype, device=device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t_step, _ = _time(lambda: env.step(state, u), device, repeats)
    t_graph, graph = _time(lambda: build_graph(state, cfg), device, repeats)
    row = {
        "N": n,
        "l": area,
        "obstacles": k,
        "density": n / area**3,
        "edges": graph.num_edges,
        "agent_edges": int((graph.edge_kind == 0).sum()),
        "step_ms": 1e3 * t_step,
        "graph_ms": 1e3 * t_graph,
        "total_ms": 1e3 * (t_step + t_graph),
    }
    if device.type == "cuda":
        row["peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return row


def fit_exponent(rows: list[dict], key: str, n_min: int = 256) -> float:
    pts = [(math.log(r["N"]), math.log(r[key])) for r in rows if r["N"] >= n_min]
    if len(pts) < 2:
        return float("nan")
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sum((x - mx) ** 2 for x, _ in pts)


def table(title: str, rows: list[dict]) -> str:
    cuda = "peak_mb" in rows[0]
    head = "| N | l (m) | N/l^3 | obstacles | edges (agent-agent) | step (ms) | graph (ms) | total (ms) |"
    sep = "|---|---|---|---|---|---|---|---|"
    if cuda:
        head += " peak GPU memory (MiB) |"
        sep += "---|"
    lines = [f"**{title}**", "", head, sep]
    for r in rows:
        line = (
            f"| {r['N']} | {r['l']:.2f} | {r['density']:.2f} | {r['obstacles']} | {r['edges']} ({r['agent_edges']}) "
            f"| {r['step_ms']:.2f} | {r['graph_ms']:.2f} | {r['total_ms']:.2f} |"
        )
        if cuda:
            line += f" {r['peak_mb']:.0f} |"
        lines.append(line)
    if sum(r["N"] >= 256 for r in rows) >= 2:
        fits = ", ".join(
            f"{k.split('_')[0]} N^{fit_exponent(rows, k):.2f}" for k in ("step_ms", "graph_ms", "total_ms")
        )
        lines += ["", f"Fitted growth over N >= 256: {fits}; edges N^{fit_exponent(rows, 'edges'):.2f}."]
    return "\n".join(lines)


def write_section(path: Path, body: str) -> None:
    replace_section(path, "env-scaling", body, heading="## Environment scaling")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", nargs="+", default=["cpu"], help="one or more devices, e.g. cpu cuda")
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: leave as is)")
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--area", type=float, default=4.0, help="side of the fixed-area series")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"))
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)

    sections = []
    for dev_name in args.device:
        device = torch.device(dev_name)
        series = {}
        for name, area_of in (
            ("(a) fixed density, N / l^3 = 1", lambda n: n ** (1 / 3)),
            (f"(b) fixed area, l = {args.area:g}", lambda n: args.area),
        ):
            rows = []
            for n in args.sizes:
                r = measure(n, area_of(n), device, dtype, args.repeats)
                print(
                    f"{device.type} {name}: N={n} edges={r['edges']} step={r['step_ms']:.2f} ms "
                    f"graph={r['graph_ms']:.2f} ms",
                    flush=True,
                )
                rows.append(r)
            series[f"{device.type}: {name}"] = rows
        if device.type == "cuda":
            what = torch.cuda.get_device_name(device)
        else:
            what = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} thread(s)"
        header = (
            f"### {device.type} ({what})\n\n`python benchmarks/env_scaling.py --device {dev_name}"
            f"{' --threads ' + str(args.threads) if args.threads else ''}`: {args.dtype}, torch {torch.__version__}, "
            f"one environment, median of {args.repeats} repeats after a warm-up."
        )
        sections.append(header + "\n\n" + "\n\n".join(table(k, v) for k, v in series.items()))
    intro = (
        "`step` = `SwarmEnv.step` (dynamics with sub-steps + collision/unsafe/reached masks); "
        "`graph` = `build_graph` (LiDAR + cell-list neighbour search + features and edges). "
        "Obstacles at 1/8 per m^3 (8 in the 4 m cube)."
    )
    body = intro + "\n\n" + "\n\n".join(sections)
    print("\n" + body)
    if not args.no_write:
        write_section(Path(args.out), body)
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
