"""Benchmarks of groupcanon: the cost of canonicalizing a layer, and the speed of batched group actions.

    .venv/bin/python benchmarks/run.py            # full run (a few minutes on 2 cores), writes docs/benchmarks.md
    .venv/bin/python benchmarks/run.py --quick    # smoke run (seconds)
    .venv/bin/python benchmarks/run.py --quick --no-write

(a) ``TransformerConv(64, 64, heads=1)`` raw against the same layer wrapped by ``Canonicalize(SE2xR, ...)``, on random
    graphs with in-degree 16, forward (no grad) and forward + backward, interleaved, median over repeats.
    Memory: the bytes of the tensors autograd saves for backward (the activation memory of a training step),
    counted once per storage with ``torch.autograd.graph.saved_tensors_hooks``; on CUDA also the peak allocation.
(b) Group-action throughput (elements per second) of SE(3) acting on points and composing, groupcanon against
    roma (``roma.Rigid``: rotation matrix + translation, ``roma.RigidUnitQuat``: unit quaternion + translation).

Results go to ``docs/benchmarks.md`` between ``<!-- groupcanon:begin -->`` and ``<!-- groupcanon:end -->`` (the
rest of the file is kept).
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import roma
import torch
import torch_geometric
from torch_geometric.nn import TransformerConv

from egcbf.io.report import cpu_name
from groupcanon import Canonicalize, FieldType, groups
from groupcanon.features import Point, Scalar, Vector

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"


# ----------------------------------------------------------------------------------------------------- utilities
def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: torch.device) -> float:
    """Seconds for one call of ``fn``."""
    sync(device)
    t0 = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - t0


def per_call(fn: Callable[[], object], device: torch.device, block_s: float, repeats: int) -> list[float]:
    """Seconds per call of a fast ``fn``: blocks of ``k`` calls lasting >= ``block_s``, ``repeats`` blocks."""
    fn()
    k = 1
    while True:
        t = timed(lambda k=k: [fn() for _ in range(k)], device)
        if t >= block_s or k >= 1 << 20:
            break
        k = min(max(2 * k, int(1.2 * k * block_s / max(t, 1e-9)) + 1), 1 << 20)
    return [timed(lambda k=k: [fn() for _ in range(k)], device) / k for _ in range(repeats)]


def saved_bytes(fn: Callable[[], torch.Tensor]) -> int:
    """Bytes of the tensors autograd saves for backward while ``fn`` runs (each storage counted once)."""
    storages: dict[int, int] = {}

    def pack(t: torch.Tensor):
        s = t.untyped_storage()
        storages[s.data_ptr()] = s.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = fn()
    del out
    return sum(storages.values())


def random_graph(n: int, degree: int, generator: torch.Generator, device) -> torch.Tensor:
    """Every node receives ``degree`` edges from uniformly random sources (duplicates and self loops possible)."""
    src = torch.randint(0, n, (n * degree,), generator=generator)
    dst = torch.arange(n).repeat_interleave(degree)
    return torch.stack((src, dst)).to(device)


def machine(device: torch.device) -> dict[str, str]:
    cpu = cpu_name()
    info = {
        "CPU": cpu,
        "cores (os.cpu_count)": str(os.cpu_count()),
        "torch threads": str(torch.get_num_threads()),
        "load average at start (1 min)": f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "n/a",
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_geometric": torch_geometric.__version__,
        "roma": roma.__version__,
    }
    if device.type == "cuda":
        info["GPU"] = torch.cuda.get_device_name(device)
    return info


# ------------------------------------------------------------------------------------------- (a) layer cost
def bench_layer(sizes, degree: int, repeats: int, device: torch.device, log) -> tuple[list[dict], list[dict]]:
    G = groups.SE2xR()
    t_in = FieldType(G, [Scalar(58), Vector(3), Point(3)])
    t_out = FieldType(G, [Scalar(58), Vector(3, n=2)])
    rows, breakdown = [], []
    for n in sizes:
        gen = torch.Generator().manual_seed(n)
        edge_index = random_graph(n, degree, gen, device)
        x = torch.randn(n, t_in.dim, generator=gen).to(device)
        frames = G.sample(n, generator=gen).to(device)
        torch.manual_seed(0)
        raw = TransformerConv(t_in.dim, t_out.dim, heads=1).to(device)
        wrapped = Canonicalize(G, t_in, t_out)(raw)  # the same parameters
        times, mem, peak = _time_layer(raw, wrapped, x, edge_index, frames, repeats, device)
        for mode in ("forward", "forward+backward"):
            r = statistics.median(times[(mode, "raw")])
            w = statistics.median(times[(mode, "wrapped")])
            row = {
                "N": n,
                "E": edge_index.shape[1],
                "mode": mode,
                "raw_ms": 1e3 * r,
                "wrapped_ms": 1e3 * w,
                "raw_min_ms": 1e3 * min(times[(mode, "raw")]),
                "wrapped_min_ms": 1e3 * min(times[(mode, "wrapped")]),
                "ratio": w / r,
                "raw_saved_mb": mem["raw"] / 2**20,
                "wrapped_saved_mb": mem["wrapped"] / 2**20,
            }
            if peak:
                row["raw_peak_mb"] = peak["raw"] / 2**20
                row["wrapped_peak_mb"] = peak["wrapped"] / 2**20
            rows.append(row)
            log(
                f"  N={n:6d} {mode:17s} raw {row['raw_ms']:9.2f} ms  wrapped {row['wrapped_ms']:9.2f} ms  "
                f"ratio {row['ratio']:.2f}"
            )
        if n == max(sizes):
            breakdown = _breakdown(G, t_in, t_out, raw, x, edge_index, frames, repeats, device)
            for b in breakdown:
                log(f"    {b['part']:55s} {b['ms']:9.2f} ms")
    return rows, breakdown


def _time_layer(raw, wrapped, x, edge_index, frames, repeats, device):
    """Interleaved timings of the four variants, saved-for-backward bytes, and (CUDA) peak memory."""

    def fwd_raw():
        return raw(x, edge_index)

    def fwd_wrapped():
        return wrapped(x, edge_index, frames=frames)

    def train_step(f):
        def step():
            raw.zero_grad(set_to_none=True)
            f().square().mean().backward()

        return step

    variants = {
        ("forward", "raw"): lambda: _no_grad(fwd_raw),
        ("forward", "wrapped"): lambda: _no_grad(fwd_wrapped),
        ("forward+backward", "raw"): train_step(fwd_raw),
        ("forward+backward", "wrapped"): train_step(fwd_wrapped),
    }
    times: dict[tuple[str, str], list[float]] = {k: [] for k in variants}
    for f in variants.values():  # warm-up
        timed(f, device)
    for _ in range(repeats):  # interleaved, so that load from other processes hits both alike
        for key, f in variants.items():
            times[key].append(timed(f, device))
    mem = {"raw": saved_bytes(fwd_raw), "wrapped": saved_bytes(fwd_wrapped)}
    peak = {}
    if device.type == "cuda":
        for name in ("raw", "wrapped"):
            torch.cuda.reset_peak_memory_stats(device)
            base = torch.cuda.memory_allocated(device)
            variants[("forward+backward", name)]()
            peak[name] = torch.cuda.max_memory_allocated(device) - base
    return times, mem, peak


def _no_grad(f):
    with torch.no_grad():
        return f()


def _breakdown(G, t_in, t_out, raw, x, edge_index, frames, repeats, device) -> list[dict]:
    """Forward (no grad) time of the pieces of the wrapped layer, at one size."""
    src, dst = edge_index
    e = src.shape[0]
    with torch.no_grad():
        inv = G.inverse(frames)
        inv_e = inv[dst]
        xs = t_in.act(inv_e, x[src])
        xd = t_in.act(inv, x)
        expanded = torch.stack((torch.arange(e, device=device), dst))
        out = raw((xs, xd), expanded)
        wrapped = Canonicalize(G, t_in, t_out)(raw)
        parts = {
            "raw layer on the original graph": lambda: raw(x, edge_index),
            "wrapped layer, total": lambda: wrapped(x, edge_index, frames=frames),
            "of which: gather sources `x[src]` (E rows)": lambda: x[src],
            "of which: gather + localize sources (E rows, `act_gathered`)": lambda: t_in.act_gathered(inv[dst], x, src),
            "for comparison: naive `act(g, x[src])` (E rows)": lambda: t_in.act(inv[dst], x[src]),
            "of which: localize targets (N rows)": lambda: t_in.act(G.inverse(frames), x),
            "of which: unmodified layer on the expanded graph": lambda: raw((xs, xd), expanded),
            "of which: globalize outputs (N rows)": lambda: t_out.act(frames, out),
        }
        times = {k: [] for k in parts}
        for f in parts.values():
            timed(f, device)
        for _ in range(repeats):
            for k, f in parts.items():
                times[k].append(timed(f, device))
    return [{"part": k, "ms": 1e3 * statistics.median(v)} for k, v in times.items()]


def _action_cases(G, point_type, g, h, p, rig_g, rig_h, q_g, q_h) -> dict:
    return {
        ("transform points", "groupcanon SE3().transform(g, p)"): lambda: G.transform(g, p),
        ("transform points", "groupcanon FieldType(SE3(), [Point(3)]).act(g, p)"): lambda: point_type.act(g, p),
        ("transform points", "roma Rigid(R, t).apply(p)"): lambda: rig_g.apply(p),
        ("transform points", "roma RigidUnitQuat(q, t).apply(p)"): lambda: q_g.apply(p),
        ("compose", "groupcanon SE3().compose(g, h)"): lambda: G.compose(g, h),
        ("compose", "roma Rigid.compose"): lambda: rig_g.compose(rig_h),
        ("compose", "roma RigidUnitQuat.compose"): lambda: q_g.compose(q_h),
        ("inverse", "groupcanon SE3().inverse(g)"): lambda: G.inverse(g),
        ("inverse", "roma Rigid.inverse"): lambda: rig_g.inverse(),
        ("inverse", "roma RigidUnitQuat.inverse"): lambda: q_g.inverse(),
    }


# ------------------------------------------------------------------------------------ (b) action throughput
def bench_actions(batches, repeats: int, block_s: float, device: torch.device, log) -> list[dict]:
    G = groups.SE3()
    point_type = FieldType(G, [Point(3)])
    rows = []
    for b in batches:
        gen = torch.Generator().manual_seed(b)
        g = G.sample(b, generator=gen).to(device)
        h = G.sample(b, generator=gen).to(device)
        p = torch.randn(b, 3, generator=gen).to(device)
        rig_g = roma.Rigid(g[..., :3].contiguous(), g[..., 3].contiguous())
        rig_h = roma.Rigid(h[..., :3].contiguous(), h[..., 3].contiguous())
        q_g = roma.RigidUnitQuat(roma.rotmat_to_unitquat(g[..., :3]), g[..., 3].contiguous())
        q_h = roma.RigidUnitQuat(roma.rotmat_to_unitquat(h[..., :3]), h[..., 3].contiguous())
        # the implementations agree (to float32 rounding)
        ref = G.transform(g, p)
        for other in (point_type.act(g, p), rig_g.apply(p), q_g.apply(p)):
            assert torch.allclose(other, ref, atol=1e-4), "implementations disagree on transform"
        gh = G.compose(g, h)
        assert torch.allclose(rig_g.compose(rig_h).linear, gh[..., :3], atol=1e-5)
        assert torch.allclose(q_g.compose(q_h).translation, gh[..., 3], atol=1e-4)
        cases = _action_cases(G, point_type, g, h, p, rig_g, rig_h, q_g, q_h)
        with torch.no_grad():
            for (op, impl), f in cases.items():
                t = statistics.median(per_call(f, device, block_s, repeats))
                rows.append({"op": op, "impl": impl, "batch": b, "us": 1e6 * t, "per_s": b / t})
                log(f"  {op:17s} B={b:8d} {impl:52s} {1e6 * t:10.1f} us  {b / t:10.3e} el/s")
    return rows


# ------------------------------------------------------------------------------------------------- report
def _fmt_batch(b: int) -> str:
    e = len(str(b)) - 1
    return f"1e{e}" if b == 10**e else str(b)


def render(info, command, date, layer_rows, breakdown, action_rows, degree, repeats, device, title) -> str:
    out = [
        f"## {title}",
        "",
        f"Measured {date} with `{command}` on {device.type.upper()}.",
        "",
        "| machine | |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in info.items()],
        "",
        "The machine may be shared with other processes: the variants are interleaved (raw, wrapped, raw, ...) so that",
        "load hits both alike, and the tables give medians (minimum in brackets).",
        "",
        *_load_warning(info),
        "### Cost of canonicalizing a layer",
        "",
        "`TransformerConv(64, 64, heads=1)` raw against `Canonicalize(SE2xR(), in_type, out_type)` around the",
        "same layer, with `in_type = Scalar(58) + Vector(3) + Point(3)` and `out_type = Scalar(58) + Vector(3, n=2)`,",
        f"float32, random graphs in which every node receives {degree} edges from uniformly random sources (duplicates",
        "and self loops possible); random SE2xR frames.",
        f"Median of {repeats} interleaved repeats after one warm-up. Forward runs under `torch.no_grad()`;",
        "forward+backward is `zero_grad`, forward, `out.square().mean().backward()`.",
        "Saved MB: bytes of the tensors autograd saves for backward during the forward (the activation memory of a",
        "training step; each storage counted once, via `torch.autograd.graph.saved_tensors_hooks`); parameters and",
        "transient buffers are not included. (tracemalloc does not see torch's allocations.)",
        "",
    ]
    has_peak = any("raw_peak_mb" in r for r in layer_rows)
    head = "| N | E | pass | raw ms | wrapped ms | wrapped / raw | raw saved MB | wrapped saved MB |"
    sep = "|---:|---:|---|---:|---:|---:|---:|---:|"
    if has_peak:
        head += " raw peak MB | wrapped peak MB |"
        sep += "---:|---:|"
    out += [head, sep]
    for r in layer_rows:
        line = (
            f"| {r['N']} | {r['E']} | {r['mode']} | {r['raw_ms']:.2f} ({r['raw_min_ms']:.2f}) | "
            f"{r['wrapped_ms']:.2f} ({r['wrapped_min_ms']:.2f}) | **{r['ratio']:.2f}** | "
            f"{r['raw_saved_mb']:.1f} | {r['wrapped_saved_mb']:.1f} |"
        )
        if has_peak:
            line += f" {r.get('raw_peak_mb', float('nan')):.1f} | {r.get('wrapped_peak_mb', float('nan')):.1f} |"
        out.append(line)
    if breakdown:
        n = max(r["N"] for r in layer_rows)
        out += [
            "",
            f"Where the forward time goes at N = {n} (median ms, pieces timed separately, no grad):",
            "",
            "| piece | ms |",
            "|---|---:|",
            *[f"| {b['part']} | {b['ms']:.2f} |" for b in breakdown],
            "",
            "The wrapped layer runs the unmodified layer on the edge-expanded bipartite graph: its source-side linear",
            "maps (key and value) see E rows instead of N, which is inherent to canonicalization; localizing the E",
            "source rows is the wrapper's own overhead: `FieldType.act_gathered` gathers all channels once and",
            "only the non-invariant ones again (the naive gather-then-act row is shown for comparison).",
        ]
    out += [
        "",
        "### Group-action throughput: SE(3)",
        "",
        "Elements per second (higher is better) for a batch of B elements (one element per point), float32,",
        "no grad; median over blocks of calls lasting at least a few milliseconds each. groupcanon stores SE(3)",
        "as `[R | t]` `(B, 3, 4)`; roma's objects are built once outside the timing (`Rigid`: rotation matrix +",
        "translation, `RigidUnitQuat`: unit quaternion + translation). All implementations are checked to agree.",
        "",
    ]
    batches = sorted({r["batch"] for r in action_rows})
    out += [
        "| operation | implementation | " + " | ".join(f"B = {_fmt_batch(b)}" for b in batches) + " |",
        "|---|---|" + "---:|" * len(batches),
    ]
    seen = []
    for r in action_rows:
        key = (r["op"], r["impl"])
        if key not in seen:
            seen.append(key)
    for op, impl in seen:
        cells = []
        for b in batches:
            m = [r for r in action_rows if r["op"] == op and r["impl"] == impl and r["batch"] == b]
            cells.append(f"{m[0]['per_s']:.3g}" if m else "")
        out.append(f"| {op} | `{impl}` | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def _load_warning(info: dict[str, str]) -> list[str]:
    """A warning paragraph if other processes kept the CPU busy (load average above the core count)."""
    try:
        cores = int(info["cores (os.cpu_count)"])
        loads = [float(v) for k, v in info.items() if k.startswith("load average")]
    except (KeyError, ValueError):
        return []
    if not loads or max(loads) <= cores:
        return []
    return [
        f"**Contended run**: the load average reached {max(loads):.1f} on {cores} cores, i.e. other processes were",
        "running: absolute times are inflated and noisy; the interleaved wrapped/raw ratios are the meaningful part.",
        "",
    ]


def write_section(text: str, marker: str, path: Path = DOC) -> None:
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    block = f"{begin}\n{text}{end}\n"
    if path.exists():
        doc = path.read_text()
        if begin in doc and end in doc:
            head, rest = doc.split(begin, 1)
            tail = rest.split(end, 1)[1].lstrip("\n")
            doc = head + block + ("\n" + tail if tail else "")
        else:
            doc = doc.rstrip("\n") + "\n\n" + block
    else:
        doc = "# Benchmarks\n\nRegenerate with `make bench` (`.venv/bin/python benchmarks/run.py`).\n\n" + block
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="groupcanon benchmarks")
    parser.add_argument("--quick", action="store_true", help="small sizes and few repeats (smoke test, seconds)")
    parser.add_argument("--no-write", action="store_true", help=f"do not write {DOC.relative_to(ROOT)}")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per variant (default 7; quick 1)")
    parser.add_argument("--output", type=Path, default=DOC, help="markdown file to update")
    parser.add_argument(
        "--marker",
        default=None,
        help="section marker name (default: groupcanon on CPU, groupcanon-<device type> otherwise)",
    )
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    repeats = args.repeats or (1 if args.quick else 7)
    sizes = (128, 512) if args.quick else (512, 4096, 32768)
    batches = (10**3, 10**4) if args.quick else (10**3, 10**5, 10**6)
    block_s = 0.001 if args.quick else 0.02
    degree = 16
    exe = Path(sys.executable)
    exe_name = exe.relative_to(ROOT).as_posix() if exe.is_relative_to(ROOT) else "python"
    command = f"{exe_name} benchmarks/run.py" + "".join(f" {a}" for a in (argv or sys.argv[1:]))
    date = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    info = machine(device)
    t0 = time.perf_counter()
    print(
        f"groupcanon benchmarks on {device} ({info['CPU']}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads)"
    )
    print("(a) TransformerConv raw vs Canonicalize(SE2xR)")
    layer_rows, breakdown = bench_layer(sizes, degree, repeats, device, print)
    print("(b) SE(3) action throughput, groupcanon vs roma")
    action_rows = bench_actions(batches, max(repeats, 3), block_s, device, print)
    marker = args.marker or ("groupcanon" if device.type == "cpu" else f"groupcanon-{device.type}")
    title = f"groupcanon ({device.type.upper()}, {info['cores (os.cpu_count)']} cores)"
    if device.type == "cuda":
        title = f"groupcanon ({info['GPU']})"
    if hasattr(os, "getloadavg"):
        info["load average at end (1 min)"] = f"{os.getloadavg()[0]:.2f}"
    text = render(info, command, date, layer_rows, breakdown, action_rows, degree, repeats, device, title)
    worst = max(r["ratio"] for r in layer_rows)
    print(f"worst wrapped/raw ratio: {worst:.2f}; total {time.perf_counter() - t0:.0f} s")
    if not args.no_write:
        write_section(text, marker, args.output)
        print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
