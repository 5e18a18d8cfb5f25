"""Cost of a run-time safety filter against the policy alone, per control step, from N = 64 to 4096 agents.

At the density of Table I's N = 512 (8 agents per m^3: ``l = 4 (N / 512)^(1/3)``), one environment, a closed-loop
rollout of ``--steps`` steps of the policy alone from a seeded reset (float32, one torch thread): at every
``--stride``-th state, each controller (the policy alone, the policy behind each filter of ``--filters``) is
called on the same state, in turn, and its wall time recorded. Reported: the median controller time per step
(graph, LiDAR, policy, and for a filter its rows, solve, check and attitude loop; not the simulator), its ratio to
the policy alone measured on the same states in the same run, and the fitted growth exponent over N >= 512.

    .venv/bin/python benchmarks/filter_cost.py               # writes docs/benchmarks.md (minutes, one core)
    .venv/bin/python benchmarks/filter_cost.py --sizes 64 512 --steps 8 --no-write

Results go to ``docs/benchmarks.md`` between ``<!-- filter-cost:begin -->`` and ``<!-- filter-cost:end -->``.
Run it alone on the machine: timings taken beside other jobs are not comparable.
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from datetime import date
from pathlib import Path

import numpy as np
import torch

from egcbf.control.resolve import resolve
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.io.report import replace_section
from egcbf.train.checkpoint import load_controller

ROOT = Path(__file__).resolve().parents[1]
SIZES = (64, 256, 512, 1024, 2048, 4096)


def _area(n: int) -> float:
    return round(4.0 * (n / 512) ** (1 / 3), 3)


def measure(checkpoint: Path, filters: list[str], n: int, steps: int, stride: int, seed: int) -> dict[str, float]:
    """Median controller ms per step ``{name: ms}`` over the sampled states of one rollout."""
    policy, train_cfg = load_controller(checkpoint)
    controllers = {"policy": policy}
    for kind in filters:
        controllers[kind] = resolve(f"policy:{kind}", checkpoint).controller
    cfg = EnvConfig(num_agents=n, area_size=_area(n), num_obstacles=0, num_envs=1, max_steps=steps,
                    **train_cfg.env_overrides)  # fmt: skip
    env = SwarmEnv(cfg)
    state = env.reset(seed)
    times: dict[str, list[float]] = {k: [] for k in controllers}
    for t in range(steps):
        if t % stride == 0:
            for name, ctrl in controllers.items():
                t0 = time.perf_counter()
                ctrl(state, cfg)
                times[name].append(1e3 * (time.perf_counter() - t0))
        u, _ = policy(state, cfg)
        state, _ = env.step(state, u)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", type=Path, default=ROOT / "checkpoints" / "egcbf+")
    ap.add_argument("--filters", nargs="+", default=["dcbf", "cbf"])
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--steps", type=int, default=64)
    ap.add_argument("--stride", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for n in args.sizes:
        ms = measure(args.checkpoint, args.filters, n, args.steps, args.stride, args.seed)
        rows.append((n, ms))
        print(f"N={n:>5} l={_area(n):<6g} " + "  ".join(f"{k} {v:8.1f} ms" for k, v in ms.items()), flush=True)
    names = ["policy", *args.filters]
    head = " | ".join(f"{k} ms" if k == "policy" else f"{k} ms (x policy)" for k in names)
    lines = [
        f"Measured {date.today()} on {platform.machine()}, {platform.python_version()}, torch {torch.__version__}, "
        f"one torch thread, float32; `{args.checkpoint.relative_to(ROOT)}`; one environment at 8 agents per m^3 "
        f"(l = 4 (N / 512)^(1/3)), no obstacles; median controller time over the states every {args.stride} steps "
        f"of a {args.steps}-step rollout of the policy alone (seed {args.seed}); every controller timed on the "
        "same states in turn.",
        "",
        f"| N | l (m) | {head} |",
        "|---|---|" + "---|" * len(names),
    ]
    for n, ms in rows:
        cells = [f"{ms['policy']:.1f}"] + [f"{ms[k]:.1f} ({ms[k] / ms['policy']:.2f}x)" for k in args.filters]
        lines.append(f"| {n} | {_area(n):g} | " + " | ".join(cells) + " |")
    big = [(n, ms) for n, ms in rows if n >= 512]
    if len(big) >= 2:
        x = np.log([n for n, _ in big])
        fits = ", ".join(
            f"{k} N^{np.polyfit(x, np.log([ms[k] for _, ms in big]), 1)[0]:.2f}" for k in names
        )  # fmt: skip
        lines += ["", f"Fitted growth over N >= 512: {fits}."]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        replace_section(ROOT / "docs" / "benchmarks.md", "filter-cost", text,
                        heading="## Run-time safety filters: cost per step")  # fmt: skip
        print("wrote docs/benchmarks.md")
    assert all(math.isfinite(v) for _, ms in rows for v in ms.values())


if __name__ == "__main__":
    main()
