"""Hot paths of this checkout against another commit, measured in alternation on the same machine.

Three paths, each timed as the median of repeated calls (one torch thread):

* ``canonicalize``: ``Canonicalize(SE2xR)`` around ``TransformerConv(64, 64)``, forward + backward, 4096 nodes of
  in-degree 16 (groupcanon's per-call input checks are on this path);
* ``policy_step``: the EGCBF+ ``cpu`` preset's policy's command for 512 agents at l = 4 (graph, networks,
  interface; untrained weights, so that any commit can run it);
* ``env_step``: one environment step of 512 agents with the nominal controller.

``--base REV`` checks REV out into a temporary git worktree and runs the same measurement there, alternating
base / this checkout ``--rounds`` times (each round a fresh process per side, each side first in every other
round: process-to-process spread on a 2-core VM is about 10 %, so take several rounds), and reports the ratio of medians
(this / base; > 1: slower); ``canonicalize`` also in one process with both versions of groupcanon, calls
interleaved (no process-to-process spread). Results go to ``docs/benchmarks.md`` (section ``hot-paths``) unless
``--no-write``.

    .venv/bin/python benchmarks/hot_paths.py --base daa1b7c --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _median_ms(fn, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def measure(repeats: int) -> dict[str, float]:
    """The three medians (ms) in this process, for the code on ``sys.path``; ``canonicalize`` first, before egcbf
    is imported (groupcanon alone)."""
    import torch
    from torch_geometric.nn import TransformerConv

    from groupcanon import Canonicalize, FieldType, groups
    from groupcanon.features import Scalar, Vector

    torch.set_num_threads(1)
    torch.manual_seed(0)
    g = groups.SE2xR()
    ft = FieldType(g, [Scalar()] * 16 + [Vector(3)] * 16)
    layer = Canonicalize(g, in_type=ft, out_type=ft)(TransformerConv(64, 64))
    n, deg = 4096, 16
    x = torch.randn(n, 64, requires_grad=True)
    src = torch.randint(0, n, (n * deg,))
    edge_index = torch.stack([src, torch.arange(n).repeat_interleave(deg)])
    frames = g.sample(n, generator=torch.Generator().manual_seed(1))

    def canon():
        layer(x, edge_index, frames=frames).square().sum().backward()

    out = {"canonicalize": _median_ms(canon, repeats)}

    from egcbf.algo.config import TrainConfig
    from egcbf.algo.learner import LearnedController
    from egcbf.env import EnvConfig, SwarmEnv
    from egcbf.nn import PolicyNet
    from egcbf.robots.quadrotor.nominal import nominal_control

    torch.manual_seed(2)  # the cpu preset's policy, untrained: the same cost as a trained one, on any commit
    model = TrainConfig.preset("egcbf+", "cpu").model
    ctrl = LearnedController(PolicyNet(model).eval(), model)
    env_cfg = EnvConfig.for_robot("quadrotor", num_agents=512, area_size=4.0, num_obstacles=0, num_envs=1)
    env = SwarmEnv(env_cfg)
    state = env.reset(123)
    for _ in range(30):  # a moving swarm
        state, _ = env.step(state, nominal_control(state.x, state.goals, env_cfg.params))

    def policy():
        with torch.no_grad():
            ctrl(state, env_cfg)

    u = nominal_control(state.x, state.goals, env_cfg.params)

    def step():
        env.step(state, u)

    out["policy_step"] = _median_ms(policy, repeats)
    out["env_step"] = _median_ms(step, repeats)
    return out


def canonicalize_ab(base_pkg_dir: str, repeats: int) -> dict[str, float]:
    """``canonicalize`` of this checkout's groupcanon and of the base's (imported as ``groupcanon_base`` from a copy
    in ``base_pkg_dir``) in one process, the same wrapped layer and inputs, calls interleaved in alternating order:
    no process-to-process spread (groupcanon imports itself relatively, so a renamed copy is the base's code)."""
    import importlib

    import torch
    from torch_geometric.nn import TransformerConv

    sys.path.insert(0, base_pkg_dir)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    conv = TransformerConv(64, 64)
    layers, frames = {}, None
    for side, name in (("this", "groupcanon"), ("base", "groupcanon_base")):
        gc = importlib.import_module(name)
        feats = importlib.import_module(f"{name}.features")
        g = gc.groups.SE2xR()
        ft = gc.FieldType(g, [feats.Scalar()] * 16 + [feats.Vector(3)] * 16)
        layers[side] = gc.Canonicalize(g, in_type=ft, out_type=ft)(conv)
        frames = g.sample(4096, generator=torch.Generator().manual_seed(1)) if frames is None else frames
    n, deg = 4096, 16
    x = torch.randn(n, 64, requires_grad=True)
    edge_index = torch.stack([torch.randint(0, n, (n * deg,)), torch.arange(n).repeat_interleave(deg)])
    times: dict[str, list[float]] = {"this": [], "base": []}
    for i in range(repeats + 2):
        for side in ("this", "base") if i % 2 else ("base", "this"):
            t = time.perf_counter()
            layers[side](x, edge_index, frames=frames).square().sum().backward()
            if i >= 2:  # warm-up
                times[side].append(1e3 * (time.perf_counter() - t))
    return {side: statistics.median(v) for side, v in times.items()}


def _run_side(src: Path, repeats: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(src / "src"), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--repeats", str(repeats)]
    out = subprocess.run(cmd, env=env, cwd=src, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", default=None, help="the commit to compare against (a git revision)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-ab", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.repeats)))
        return
    if args.child_ab:
        print(json.dumps(canonicalize_ab(args.child_ab, args.repeats)))
        return
    if args.base is None:
        print(json.dumps(_run_side(ROOT, args.repeats), indent=2))
        return
    rev = subprocess.run(["git", "rev-parse", "--short", args.base], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()  # fmt: skip
    head = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, check=True, capture_output=True,
                          text=True).stdout.strip()  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        base_dir = Path(tmp) / "base"
        subprocess.run(["git", "worktree", "add", "--detach", str(base_dir), rev], cwd=ROOT, check=True,
                       capture_output=True)  # fmt: skip
        try:
            runs: dict[str, list[dict[str, float]]] = {"base": [], "this": []}
            for r in range(args.rounds):
                order = (("base", base_dir), ("this", ROOT))
                for side, src in order if r % 2 == 0 else order[::-1]:  # each side first in every other round
                    runs[side].append(_run_side(src, args.repeats))
                print(f"round {r + 1}/{args.rounds}: base {runs['base'][-1]}  this {runs['this'][-1]}", flush=True)
            pkg = Path(tmp) / "pkg"
            shutil.copytree(base_dir / "src" / "groupcanon", pkg / "groupcanon_base")
            cmd = [
                sys.executable,
                str(Path(__file__).resolve()),
                "--child-ab",
                str(pkg),
                "--repeats",
                str(args.repeats),
            ]
            env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
            ab = json.loads(subprocess.run(cmd, env=env, cwd=ROOT, check=True, capture_output=True, text=True)
                            .stdout.strip().splitlines()[-1])  # fmt: skip
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base_dir)], cwd=ROOT, check=False)
    lines = [
        f"`.venv/bin/python benchmarks/hot_paths.py --base {args.base} --rounds {args.rounds}`: this checkout "
        f"(`{head}`) against `{rev}`, {args.rounds} rounds of {args.repeats} calls each (a fresh process per side "
        "and round, sides in alternating order), one thread; median over rounds of each round's median.",
        "",
        "| path | base (ms) | this (ms) | this / base |",
        "|---|---|---|---|",
    ]
    for key in runs["base"][0]:
        b = statistics.median(r[key] for r in runs["base"])
        t = statistics.median(r[key] for r in runs["this"])
        lines.append(f"| `{key}` | {b:.2f} | {t:.2f} | {t / b:.3f} |")
    lines += [
        "",
        "The same `canonicalize` call with both versions of groupcanon in one process (the base's imported from a "
        f"renamed copy), {args.repeats} interleaved calls each: the layer's own cost without the process-to-process "
        "spread above (which comes from the rest of the process: the same code measured in two fresh processes "
        "differs by up to ~10 % here).",
        "",
        "| path | base (ms) | this (ms) | this / base |",
        "|---|---|---|---|",
        f"| `canonicalize`, one process | {ab['base']:.2f} | {ab['this']:.2f} | {ab['this'] / ab['base']:.3f} |",
    ]
    body = "\n".join(lines) + "\n"
    print(body)
    if not args.no_write:
        from egcbf.io.report import replace_section

        replace_section(
            ROOT / "docs" / "benchmarks.md", "hot-paths", body, heading="## Hot paths against a base commit"
        )


if __name__ == "__main__":
    main()
