"""What ``egcbf eval --record`` costs: one episode's wall time at N = 128 with and without the MCAP recording.

Each controller runs the same episode (one environment, the evaluation's first seed, ``--steps`` steps, l = 4 m,
8 obstacles, float32, one torch thread) twice in a row through :func:`egcbf.evaluate.episodes.run_episodes`: without
``on_step``, then with an :class:`egcbf.ros.record.EpisodeRecorder` (poses, goals, states, obstacle markers, the
LiDAR cloud, the filter's activity: what ``--record`` writes), ``close()`` included, after a warm-up that pays the
recorder's imports once (reported apart); the row ``egcbf+ --record-cbf`` also records the checkpoint's CBF value
``h`` (one CBF forward per step). One episode per run is the recording's worst case; a last row runs the nominal
controller as ``egcbf eval`` does at this size, 32 episodes together (of which the recorder writes environment 0).
One run each, paired, so the ratio is the meaningful number on a shared machine.

    python benchmarks/record_cost.py                  # writes its section of docs/benchmarks.md
    python benchmarks/record_cost.py --steps 20 --no-write
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

from egcbf.control.filters import FilterConfig
from egcbf.control.resolve import resolve
from egcbf.env import EnvConfig
from egcbf.evaluate.episodes import episode_batch, episode_seed, run_episodes
from egcbf.io.report import cpu_name, replace_section
from egcbf.ros.record import EpisodeRecorder

ROOT = Path(__file__).resolve().parents[1]
#: ``(controller, with the CBF's values (--record-cbf), episodes together)`` of each row (``None``: ``egcbf eval``'s
#: batch at the size)
ROWS = (("nominal", False, 1), ("egcbf+", False, 1), ("egcbf+", True, 1), ("egcbf+:dcbf", False, 1),
        ("nominal", False, None))  # fmt: skip


def _build(name: str, with_cbf: bool = False):
    """The controller and the learned CBF whose values the recording holds (``None``: none, as without
    ``--record-cbf``)."""
    if name == "nominal":
        return resolve(name).controller, None
    kind = name.partition(":")[2] or "none"
    built = resolve(name, ROOT / "checkpoints" / "egcbf+", with_cbf=with_cbf,
                    filter_config=None if kind == "none" else FilterConfig.for_kind(kind))  # fmt: skip
    return built.controller, built.cbf


def measure(name: str, n: int, steps: int, episodes: int = 1, seed: int = 0, with_cbf: bool = False) -> dict:
    """Seconds of ``episodes`` episodes of ``name`` simulated together, without and with the recording (of the
    first), and the recording's size."""
    cfg = EnvConfig.for_robot("quadrotor", num_agents=n, area_size=4.0, num_obstacles=8, max_steps=steps)
    seeds = [episode_seed(seed, n, e) for e in range(episodes)]
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "episode.mcap"
        for recorded in (False, True):
            ctrl, cbf = _build(name, with_cbf)  # a fresh controller per run (the dcbf filter keeps the last velocities)
            rec = EpisodeRecorder(path, cbf=cbf) if recorded else None
            t0 = time.perf_counter()
            run_episodes(ctrl, cfg, seeds, on_step=rec)
            if rec is not None:
                rec.close()
            times[recorded] = time.perf_counter() - t0
        size = path.stat().st_size
    return {"plain_s": times[False], "recorded_s": times[True], "ratio": times[True] / times[False], "mb": size / 1e6}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num-agents", type=int, default=128)
    parser.add_argument("--steps", type=int, default=256, help="episode length (the quadrotor's default: 256)")
    parser.add_argument("--out", default=str(ROOT / "docs" / "benchmarks.md"))
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()  # the recorder's one-time set-up (imports, the typestore), paid once per process
    with tempfile.TemporaryDirectory() as tmp:
        rec = EpisodeRecorder(Path(tmp) / "warm.mcap")
        run_episodes(_build("nominal")[0], EnvConfig(num_agents=2, max_steps=2), [0], on_step=rec)
        rec.close()
    setup = time.perf_counter() - t0
    print(f"set-up (a 2-step recorded episode, imports included): {setup:.2f} s")
    rows = []
    batch = episode_batch(args.num_agents, 50)  # egcbf eval's batch at this size (50 episodes by default)
    for name, with_cbf, episodes in ROWS:
        episodes = episodes or batch
        r = measure(name, args.num_agents, args.steps, episodes, with_cbf=with_cbf)
        name = f"{name} --record-cbf" if with_cbf else name
        rows.append((name, episodes, r))
        print(f"{name:27s} x{episodes:<3d} plain {r['plain_s']:7.2f} s  recorded {r['recorded_s']:7.2f} s  "
              f"ratio {r['ratio']:.2f}  {r['mb']:.1f} MB", flush=True)  # fmt: skip
    lines = [
        f"One episode of N = {args.num_agents} quadrotors, {args.steps} steps, l = 4 m, 8 obstacles, one "
        f"environment (the last row: `egcbf eval`'s {batch} together), float32, one torch thread, {cpu_name()}; "
        "`python benchmarks/record_cost.py` (one run each, paired: without, then with `--record`'s recorder; timed "
        "beside other jobs on a shared machine, so the ratio is the number to read).",
        "",
        "| controller (recording) | episodes together | plain (s) | recorded (s) | ratio | file (MB) |",
        "|---|---|---|---|---|---|",
        *(
            f"| `{name}` | {e} | {r['plain_s']:.2f} | {r['recorded_s']:.2f} | {r['ratio']:.2f}x | {r['mb']:.1f} |"
            for name, e, r in rows
        ),
        "",
        f"Before these, the recorder's one-time set-up (its imports, the typestore: a 2-step recorded episode of 2 "
        f"agents) took {setup:.2f} s.",
    ]
    body = "\n".join(lines)
    if not args.no_write:
        replace_section(Path(args.out), "record-cost", body, heading="## Recording an episode (`egcbf eval --record`)")
        print(f"wrote {args.out}")
    else:
        print(body)


if __name__ == "__main__":
    sys.exit(main())
