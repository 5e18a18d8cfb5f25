"""Agent-steps per second of the swarm through each interface, at B x N = 4096 agents, in one run.

Paths, each stepping the nominal controller (its command computed from the current state in every path, the same
small cost everywhere, so that the swarm moves as in an episode and the neighbour lists age as they would):

* ``SwarmEnv.step``: the simulator alone (dynamics with sub-steps, collision / unsafe / reached masks);
* ``SwarmEnv.step + build_graph``: what the repository's own learners read each step (LiDAR, neighbour search,
  graph features);
* ``SwarmTask.step``: the simulator plus the per-agent observations, rewards and costs as plain tensors (the
  native batched path of a multi-agent learner: ``egcbf.env.task``);
* ``TorchRL``: ``egcbf.env.torchrl.SwarmTorchRLEnv.step`` (the same work, in a TensorDict, with TorchRL's checks);
* ``PettingZoo``: ``egcbf.env.pettingzoo`` (one scene; per-agent NumPy dictionaries), only where ``B = 1``.

A second table splits ``SwarmTask.step`` into its parts, timed inside the same steps (mean per step): the
simulator's step (dynamics and masks: ``SwarmEnv.transition`` and ``SwarmEnv.info``, whose agent pairs are the
neighbour search's), the LiDAR scan and the neighbour rows of the observation (the Verlet list's
searches amortized over the steps they serve), and the rest (nominal command, reward, cost, the gathers). It says
what bounds the ratio of any path that builds these observations to the bare simulator; a note after it gives
the share of the neighbour rows that the Verlet list's k-d tree searches take (their count over the timed steps).

Settings: ``8 x 512`` at Table I's density (l = 4 m) without and with 8 obstacles, and ``1 x 4096`` at the same
density (l = 8 m). Each path's time per step is the median over ``--rounds`` rounds of the mean of a block of
``--steps`` steps (the rate a run sees: the neighbour list's searches, every few steps, included), after
``--warmup`` steps; within a round the paths run their blocks in turn, each path's episode going on from round to
round, so that a slow spell of the machine falls on every path alike and their ratios share its state. float32,
one torch thread.

    python benchmarks/marl_env_speed.py            # writes its section of docs/benchmarks.md and docs/marl.md
    python benchmarks/marl_env_speed.py --rounds 1 --steps 3 --warmup 1 --no-write
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from egcbf.env import EnvConfig, SwarmEnv, observations
from egcbf.env.graph import build_graph
from egcbf.env.task import SwarmTask
from egcbf.io.report import cpu_name, quote_section, replace_section

SETTINGS = ((8, 512, 4.0, 0), (8, 512, 4.0, 8), (1, 4096, 8.0, 0))


def _interleaved(paths: dict, rounds: int, steps: int, warmup: int) -> dict[str, float]:
    """Seconds per step of each of ``paths`` (name -> a function making one step): the median over ``rounds`` of
    the mean of a block of ``steps`` steps, the paths' blocks run in turn within each round (module doc)."""
    for step in paths.values():
        for _ in range(warmup):
            step()
    blocks = {name: [] for name in paths}
    for _ in range(rounds):
        for name, step in paths.items():
            t0 = time.perf_counter()
            for _ in range(steps):
                step()
            blocks[name].append((time.perf_counter() - t0) / steps)  # the Verlet searches of the block included
    return {name: statistics.median(times) for name, times in blocks.items()}


def measure(b: int, n: int, area: float, obstacles: int, rounds: int, steps: int, warmup: int, seed: int = 0) -> dict:
    """Seconds per step of every path (module doc) for ``b`` scenes of ``n`` agents."""
    horizon = 10**6  # no truncation inside the timed steps
    cfg = EnvConfig(num_agents=n, num_envs=b, area_size=area, num_obstacles=obstacles, max_steps=horizon)
    env = SwarmEnv(cfg, dtype=torch.float32)
    start = env.reset(seed)
    robot = env.robot
    paths = {}
    simulator = {"state": start}

    def env_step():
        s = simulator["state"]
        simulator["state"], _ = env.step(s, robot.nominal_control(s.x, s.goals))

    paths["SwarmEnv.step"] = env_step
    graphed = {"state": start}

    def env_graph_step():
        s = graphed["state"]
        graphed["state"], _ = env.step(s, robot.nominal_control(s.x, s.goals))
        build_graph(graphed["state"], cfg)

    paths["SwarmEnv.step + build_graph"] = env_graph_step
    task = SwarmTask(cfg, dtype=torch.float32)
    task.reset(seed)
    paths["SwarmTask.step"] = lambda: task.step(robot.nominal_control(task.state.x, task.state.goals))
    try:
        from egcbf.env.torchrl import SwarmTorchRLEnv
    except ImportError:
        SwarmTorchRLEnv = None
    if SwarmTorchRLEnv is not None:
        tenv = SwarmTorchRLEnv(cfg, dtype=torch.float32, seed=seed)
        box = {"td": tenv.reset()}

        def torchrl_step():
            td = box["td"]
            obs = td["agents", "observation"]
            td["agents", "action"] = robot.nominal_control(obs["state"], obs["goal"])
            box["td"] = tenv.step(td)["next"]

        paths["TorchRL"] = torchrl_step
    if b == 1:
        try:
            from egcbf.env.pettingzoo import parallel_env
        except ImportError:
            parallel_env = None
        if parallel_env is not None:
            penv = parallel_env(num_agents=n, area_size=area, num_obstacles=obstacles, max_steps=horizon)
            penv.reset(seed=seed)

            def pettingzoo_step():
                s = penv.task.state
                u = robot.nominal_control(s.x, s.goals)[0].numpy()
                penv.step({a: u[i] for i, a in enumerate(penv.possible_agents)})

            paths["PettingZoo"] = pettingzoo_step
    times = _interleaved(paths, rounds, steps, warmup)
    parts, searches = _task_parts(cfg, seed, rounds * steps, warmup)
    return {"B": b, "N": n, "l": area, "obstacles": obstacles, "seconds": times, "parts": parts, "searches": searches}


def _task_parts(cfg: EnvConfig, seed: int, steps: int, warmup: int) -> tuple[dict[str, float], tuple[float, int]]:
    """Mean seconds per step of ``SwarmTask.step``'s parts (module doc), each part timed where the step calls it;
    and, inside the neighbour rows, the Verlet list's searches: their mean seconds per step and their count."""
    task = SwarmTask(cfg, dtype=torch.float32)
    task.reset(seed)
    robot = task.robot
    spent = {"simulator step": [], "LiDAR scan": [], "neighbour rows": []}
    searched = []

    def timed(name, fn):
        def run(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            spent[name].append(time.perf_counter() - t0)
            return out

        return run

    task.env.transition = timed("simulator step", task.env.transition)  # the step's dynamics, then its masks
    task.env.info = timed("simulator step", task.env.info)
    task.env.lidar = timed("LiDAR scan", task.env.lidar)
    task.neighbours.nearest = timed("neighbour rows", task.neighbours.nearest)
    search = observations.radius_pairs

    def timed_search(*args, **kwargs):
        t0 = time.perf_counter()
        out = search(*args, **kwargs)
        searched.append(time.perf_counter() - t0)
        return out

    observations.radius_pairs = timed_search  # the neighbour list's searches (module global), for these steps only
    try:
        for _ in range(warmup):
            task.step(robot.nominal_control(task.state.x, task.state.goals))
        for v in (*spent.values(), searched):
            v.clear()
        total = []
        for _ in range(steps):
            t0 = time.perf_counter()
            task.step(robot.nominal_control(task.state.x, task.state.goals))
            total.append(time.perf_counter() - t0)
    finally:
        observations.radius_pairs = search
    out = {name: sum(v) / steps for name, v in spent.items()}
    out["rest"] = statistics.fmean(total) - sum(out.values())
    return out, (sum(searched) / steps, len(searched))


def parts_table(rows: list[dict]) -> str:
    names = list(rows[0]["parts"])
    head = "| B x N | l (m) | obstacles | " + " | ".join(f"{p} (ms)" for p in names) + " | observation / simulator |"
    lines = [head, "|" + "---|" * (4 + len(names))]
    for r in rows:
        p = r["parts"]
        ratio = (p["LiDAR scan"] + p["neighbour rows"]) / p["simulator step"]
        cells = " | ".join(f"{1e3 * p[k]:.1f}" for k in names)
        lines.append(f"| {r['B']} x {r['N']} | {r['l']:g} | {r['obstacles']} | {cells} | {ratio:.2f} |")
    return "\n".join(lines)


def searches_note(rows: list[dict], steps: int) -> str:
    """One sentence: the share of the neighbour rows that their Verlet list's k-d tree searches take."""
    cells = []
    for r in rows:
        (seconds, count), where = r["searches"], f"{r['B']} x {r['N']}{', obstacles' if r['obstacles'] else ''}"
        cells.append(f"{where}: {count} search{'' if count == 1 else 'es'}, {1e3 * seconds:.1f} ms per step")
    return (f"Of the neighbour rows, the Verlet list's searches (a k-d tree's pairs within the radius plus the skin, "
            f"around anchors that lead the agents; over the {steps} steps): " + "; ".join(cells) + ".")  # fmt: skip


def table(rows: list[dict]) -> str:
    paths = list(dict.fromkeys(p for r in rows for p in r["seconds"]))
    head = "| B x N | l (m) | obstacles | " + " | ".join(f"{p} (agent-steps/s)" for p in paths) + " |"
    lines = [head, "|" + "---|" * (3 + len(paths))]
    for r in rows:
        agents = r["B"] * r["N"]
        base = r["seconds"]["SwarmEnv.step"]
        cells = []
        for p in paths:
            t = r["seconds"].get(p)
            cells.append("-" if t is None else f"{agents / t:,.0f} ({base / t:.2f}x)")
        lines.append(f"| {r['B']} x {r['N']} | {r['l']:g} | {r['obstacles']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--steps", type=int, default=10, help="steps per path in each round")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"))
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for b, n, area, obstacles in SETTINGS:
        row = measure(b, n, area, obstacles, args.rounds, args.steps, args.warmup)
        print(f"{b} x {n}, l = {area:g}, {obstacles} obstacles: "
              + ", ".join(f"{p} {1e3 * t:.1f} ms" for p, t in row["seconds"].items()), flush=True)  # fmt: skip
        rows.append(row)
    body = (
        f"`python benchmarks/marl_env_speed.py`: {cpu_name()}, 1 thread, torch {torch.__version__}, float32; per path "
        f"the median over {args.rounds} rounds of a {args.steps}-step block's mean, the paths' blocks in turn within "
        f"each round, after {args.warmup} steps; each cell agent-steps per second and, in brackets, its ratio to "
        "`SwarmEnv.step` alone measured in the same run. Paths (the script's docstring): the simulator alone; with "
        "the graph the repository's learners build; `SwarmTask` (observations, rewards, costs as tensors); the "
        "TorchRL environment; the PettingZoo environment (one scene only).\n\n" + table(rows) + "\n\n"
        "Where `SwarmTask.step`'s time goes (mean per step; the neighbour rows' Verlet searches amortized; `rest`: "
        "nominal command, reward, cost, the gathers; the simulator step's masks test the neighbour search's pairs, "
        "so it costs less than `SwarmEnv.step` alone, which searches). The last column is the observation's cost "
        "over that simulator step's.\n\n" + parts_table(rows) + "\n\n" + searches_note(rows, args.rounds * args.steps)
    )
    print("\n" + body)
    if not args.no_write:
        replace_section(Path(args.out), "marl-env-speed", body, heading="## Multi-agent RL interfaces")
        quoted = quote_section(Path(args.out).parent / "marl.md", "marl-env-speed", body)  # the page's copy
        print(f"\nwrote {args.out}" + (" and marl.md beside it" if quoted else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
