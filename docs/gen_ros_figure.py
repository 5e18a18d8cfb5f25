"""Draw docs/figures/recording.png: a 3-D picture of one ``egcbf eval --record`` recording, read back from its MCAP.

    .venv/bin/python docs/gen_ros_figure.py                 # records the episode below, then draws it
    .venv/bin/python docs/gen_ros_figure.py FILE.mcap       # draws an existing recording

Without a file it runs (about a minute on one core)::

    egcbf eval --checkpoint checkpoints/egcbf+ --filter dcbf --num-agents 16 --obstacles 8 --episodes 1 \\
        --max-steps 200 --seed 0 --no-progress --out OUT --record OUT/episode.mcap

and draws what :func:`egcbf.ros.record.read_recording` reads back: every agent's path (its ``/egcbf/poses``), its
start and goal, the obstacles (``/egcbf/obstacles`` markers), the LiDAR hits of every fifth step
(``/egcbf/lidar``) and the positions where the ``dcbf`` filter changed the agent's command
(``/egcbf/filter_active``). Headless (matplotlib's Agg backend).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "figures" / "recording.png"
COMMAND = ["eval", "--checkpoint", str(ROOT / "checkpoints" / "egcbf+"), "--filter", "dcbf", "--num-agents", "16",
           "--obstacles", "8", "--episodes", "1", "--max-steps", "200", "--seed", "0", "--no-progress"]  # fmt: skip


def record(directory: Path) -> Path:
    """Run the module doc's command into ``directory``; the recording's path."""
    path = directory / "episode.mcap"
    egcbf = Path(sys.executable).with_name("egcbf")
    cmd = [str(egcbf)] if egcbf.exists() else [sys.executable, "-m", "egcbf"]
    subprocess.run([*cmd, *COMMAND, "--out", str(directory / "eval"), "--record", str(path)], check=True)
    return path


def draw(path: Path, out: Path) -> Path:
    from egcbf.ros.record import read_recording

    rec = read_recording(path)
    n = rec.positions.shape[1]
    fig = plt.figure(figsize=(7.5, 6.5))
    ax = fig.add_subplot(projection="3d")
    u, v = np.mgrid[0 : 2 * np.pi : 24j, 0 : np.pi : 12j]
    for c, r in zip(rec.centers, rec.radii, strict=True):
        ax.plot_surface(c[0] + r * np.cos(u) * np.sin(v), c[1] + r * np.sin(u) * np.sin(v), c[2] + r * np.cos(v),
                        color="0.6", alpha=0.35, linewidth=0)  # fmt: skip
    hits = np.concatenate([h for h in rec.hits[::5] if len(h)] or [np.zeros((0, 3))])
    ax.scatter(*hits.T, s=1, c="tab:red", alpha=0.25, label="LiDAR hits (every 5th step)")
    colours = plt.get_cmap("viridis")(np.linspace(0, 1, n))
    for i in range(n):
        p = rec.positions[:, i]
        ax.plot(*p.T, color=colours[i], linewidth=1.2)
        ax.scatter(*p[0], color=colours[i], s=12, marker="o")
        ax.scatter(*rec.goals[0, i], color=colours[i], s=30, marker="x")
    if rec.filter_active is not None:
        active = rec.positions[:-1][rec.filter_active]
        ax.scatter(*active.T, s=6, c="black", label="dcbf filter changed the command")
    lim = (0, float(np.ceil(max(rec.positions.max(), rec.goals.max()))))
    ax.set(xlim=lim, ylim=lim, zlim=lim, xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    steps, dt = len(rec.stamps) - 1, float(rec.metadata.get("dt", "nan"))
    ax.set_title(f"{rec.metadata.get('controller', '')}: N = {n}, {steps} steps of {dt * 1e3:g} ms, read back from "
                 f"{path.name}", fontsize=9)  # fmt: skip
    ax.legend(loc="upper left", fontsize=8)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", nargs="?", type=Path, help="an MCAP recording (default: record one)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.recording is not None:
        print(f"wrote {draw(args.recording, args.out)}")
        return
    with tempfile.TemporaryDirectory() as tmp:
        print(f"wrote {draw(record(Path(tmp)), args.out)}")


if __name__ == "__main__":
    main()
