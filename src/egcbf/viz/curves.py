"""Training curves: safety, reach and success of the evaluation rollouts of training runs, against update and wall time.

    from egcbf.viz.curves import training_curves
    training_curves({"EGCBF+": "checkpoints/egcbf+", "GCBF+": "checkpoints/gcbf+"}, "docs/figures/training_curves.png")

Each run is a directory holding the ``metrics.csv`` that :func:`egcbf.train.loop.train` writes (one row per evaluation:
``step, wall_s, safe_rate, reach_rate, success_rate, ...``); a shipped checkpoint directory keeps a copy of it.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping, Sequence
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


def _on_grid(runs: list[dict[str, list[float]]], col: str) -> tuple[list[float], ...]:
    """Steps evaluated by every run, with the mean, min and max of ``col`` there and the mean wall time."""
    common = sorted(set.intersection(*(set(r["step"]) for r in runs)))
    vals = [[r[col][r["step"].index(s)] for r in runs] for s in common]
    wall = [sum(r["wall_s"][r["step"].index(s)] for r in runs) / len(runs) for s in common]
    return common, [sum(v) / len(v) for v in vals], [min(v) for v in vals], [max(v) for v in vals], wall


def training_curves(
    runs: Mapping[str, str | Path | Sequence[str | Path]], out_png: str | Path, *, title: str | None = None
) -> Path:
    """Plot safe / reach / success rates (%) of each method against training update (top row) and wall time in
    minutes (bottom row); one colour per method. A method maps to one run directory or to several (training
    seeds): then the line is the mean over the seeds and the band their min / max, at the updates all of them
    evaluated. A single run directory that holds a ``state.json`` (a shipped checkpoint) gets a marker at the
    update it was selected at. Returns ``out_png``."""
    from matplotlib.figure import Figure

    if not runs:
        raise ValueError("training_curves needs at least one run")
    groups = {name: [paths] if isinstance(paths, (str, Path)) else list(paths) for name, paths in runs.items()}
    if any(not paths for paths in groups.values()):
        raise ValueError("training_curves: every method needs at least one run")
    fig = Figure(figsize=(13, 6.5))
    axes = fig.subplots(2, 3, sharey=True)
    for i, (name, paths) in enumerate(groups.items()):
        color = f"C{i}"
        data = [load_metrics(p) for p in paths]
        label = name if len(data) == 1 else f"{name} (mean of {len(data)} seeds, min-max band)"
        best = _best_step(Path(paths[0])) if len(paths) == 1 else None
        for j, col in enumerate(_COLUMNS):
            steps, mean, lo, hi, wall = _on_grid(data, col)
            minutes = [w / 60 for w in wall]
            y = [100 * v for v in mean]
            axes[0, j].plot(steps, y, color=color, label=label, lw=1.6)
            axes[1, j].plot(minutes, y, color=color, label=label, lw=1.6)
            if len(data) > 1:
                axes[0, j].fill_between(steps, [100 * v for v in lo], [100 * v for v in hi], color=color, alpha=0.2)
                axes[1, j].fill_between(minutes, [100 * v for v in lo], [100 * v for v in hi], color=color, alpha=0.2)
            if best is not None and best in steps:
                k = steps.index(best)
                axes[0, j].plot(steps[k], y[k], "o", color=color, ms=7, mfc="none", mew=1.8)
                axes[1, j].plot(minutes[k], y[k], "o", color=color, ms=7, mfc="none", mew=1.8)
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
    return out
