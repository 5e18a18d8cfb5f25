"""Hot paths of this checkout against another commit, measured in alternation on the same machine.

Three paths, each timed as the median of repeated calls (one torch thread):

* ``canonicalize``: ``Canonicalize(SE2xR)`` around ``TransformerConv(64, 64)``, forward + backward, 4096 nodes of
  in-degree 16 (groupcanon's per-call input checks are on this path);
* ``policy_step``: the EGCBF+ ``cpu`` preset's policy's command for 512 agents at l = 4 (graph, networks,
  interface; untrained weights, so that any commit can run it);
* ``env_step``: one environment step of 512 agents with the nominal controller.

``--base REV`` checks REV out into a temporary git worktree and runs the same measurement there, alternating
base / this checkout ``--rounds`` times (each round a fresh process per side), and reports the ratio of medians
(this / base; > 1: slower). Results go to ``docs/benchmarks.md`` (section ``hot-paths``) unless ``--no-write``.

    .venv/bin/python benchmarks/hot_paths.py --base daa1b7c --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
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
    """The three medians (ms) in this process, for the code on ``sys.path``."""
    import torch
    from torch_geometric.nn import TransformerConv

    from egcbf.algo.learner import LearnedController
    from egcbf.config import TrainConfig
    from egcbf.control.nominal import nominal_control
    from egcbf.env import EnvConfig, SwarmEnv
    from egcbf.nn import PolicyNet
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

    return {
        "canonicalize": _median_ms(canon, repeats),
        "policy_step": _median_ms(policy, repeats),
        "env_step": _median_ms(step, repeats),
    }


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
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.repeats)))
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
                runs["base"].append(_run_side(base_dir, args.repeats))
                runs["this"].append(_run_side(ROOT, args.repeats))
                print(f"round {r + 1}/{args.rounds}: base {runs['base'][-1]}  this {runs['this'][-1]}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base_dir)], cwd=ROOT, check=False)
    lines = [
        f"`.venv/bin/python benchmarks/hot_paths.py --base {args.base} --rounds {args.rounds}`: this checkout "
        f"(`{head}`) against `{rev}`, {args.rounds} alternating rounds of {args.repeats} calls each, one thread; "
        "median over rounds of each round's median.",
        "",
        "| path | base (ms) | this (ms) | this / base |",
        "|---|---|---|---|",
    ]
    for key in runs["base"][0]:
        b = statistics.median(r[key] for r in runs["base"])
        t = statistics.median(r[key] for r in runs["this"])
        lines.append(f"| `{key}` | {b:.2f} | {t:.2f} | {t / b:.3f} |")
    body = "\n".join(lines) + "\n"
    print(body)
    if not args.no_write:
        from egcbf.report import replace_section

        replace_section(
            ROOT / "docs" / "benchmarks.md", "hot-paths", body, heading="## Hot paths against a base commit"
        )


if __name__ == "__main__":
    main()
