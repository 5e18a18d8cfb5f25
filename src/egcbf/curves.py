"""Training curves: safety, reach and success of the evaluation rollouts of training runs, against update and wall time.

    from egcbf.curves import training_curves
    training_curves({"EGCBF+": "checkpoints/egcbf+", "GCBF+": "checkpoints/gcbf+"}, "docs/figures/training_curves.png")

Each run is a directory holding the ``metrics.csv`` that :func:`egcbf.train.train` writes (one row per evaluation:
``step, wall_s, safe_rate, reach_rate, success_rate, ...``); a shipped checkpoint directory keeps a copy of it.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from pathlib import Path

__all__ = ["load_metrics", "training_curves"]

_COLUMNS = ("safe_rate", "reach_rate", "success_rate")
_TITLES = {"safe_rate": "safe", "reach_rate": "reach", "success_rate": "success (safe and reached)"}


def load_metrics(run: str | Path) -> dict[str, list[float]]:
    """The columns of ``run/metrics.csv`` (or of ``run`` if it is the CSV file) as lists of floats, sorted by step."""
    path = Path(run)
    if path.is_dir():
        path = path / "metrics.csv"
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist (a training run writes it: egcbf train --out DIR)")
    with open(path, newline="") as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["step"]))
    if not rows:
        raise ValueError(f"{path} holds no evaluation rows")
    return {k: [float(r[k]) for r in rows] for k in rows[0] if k in ("step", "wall_s", *_COLUMNS)}


def _best_step(run: Path) -> int | None:
    state = run / "state.json"
    if run.is_dir() and state.exists():
        return int(json.loads(state.read_text()).get("step", -1))
    return None


def training_curves(runs: Mapping[str, str | Path], out_png: str | Path, *, title: str | None = None) -> Path:
    """Plot safe / reach / success rates (%) of each run against training update (top row) and wall time in
    minutes (bottom row); one colour per run. A run directory that holds a ``state.json`` (a shipped checkpoint)
    gets a marker at the update it was selected at. Returns ``out_png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not runs:
        raise ValueError("training_curves needs at least one run")
    data = {name: load_metrics(path) for name, path in runs.items()}
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharey=True)
    for i, (name, m) in enumerate(data.items()):
        color = f"C{i}"
        best = _best_step(Path(runs[name]))
        for j, col in enumerate(_COLUMNS):
            y = [100 * v for v in m[col]]
            axes[0, j].plot(m["step"], y, color=color, label=name, lw=1.6)
            axes[1, j].plot([w / 60 for w in m["wall_s"]], y, color=color, label=name, lw=1.6)
            if best is not None and best in m["step"]:
                k = m["step"].index(best)
                axes[0, j].plot(m["step"][k], y[k], "o", color=color, ms=7, mfc="none", mew=1.8)
                axes[1, j].plot(m["wall_s"][k] / 60, y[k], "o", color=color, ms=7, mfc="none", mew=1.8)
    for j, col in enumerate(_COLUMNS):
        axes[0, j].set_title(_TITLES[col])
        axes[0, j].set_xlabel("training update")
        axes[1, j].set_xlabel("wall time (min)")
        for ax in axes[:, j]:
            ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("rate of evaluation rollouts (%)")
    axes[1, 0].set_ylabel("rate of evaluation rollouts (%)")
    axes[0, 0].legend(loc="lower left", fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
