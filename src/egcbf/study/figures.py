"""The equivariance study's figures: zero-shot safety against N, validation curves against updates, agent-steps and
wall time, and the rotated-world test's rates against the rotation angle. Each draws only what is computed."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from ..reproduce.paper import LABELS
from .plan import Arm, Run

__all__ = ["curves_figure", "rotated_figure", "zero_shot_figure"]

COLORS = {"egcbf+": "tab:blue", "gcbf+": "tab:orange", "egcbf": "tab:green", "gcbf": "tab:red"}


def _seeds_label(algo: str, k: int) -> str:
    return f"{LABELS[algo]} ({k} seed{'s' if k > 1 else ''})"


def _save(fig, out_png: Path) -> Path:
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    return out_png


def zero_shot_figure(arms: Sequence[Arm], cells: Mapping[str, dict], out_png: str | Path) -> Path:
    """Safe rate (%) against N, one panel per arm; lines are means over training seeds, bands their min-max."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.2 * len(arms), 3.2))
    axes = fig.subplots(1, len(arms), squeeze=False)[0]
    for ax, arm in zip(axes, arms):
        c = cells[arm.name]
        for algo in arm.algos():
            sizes = sorted({(n, sc) for (a, _, n, sc) in c if a == algo}, key=lambda t: t[0])
            xs, mean, lo, hi = [], [], [], []
            for n, sc in sizes:
                vals = [100 * c[(algo, s, n, sc)]["safe_rate"] for s in arm.seeds(algo) if (algo, s, n, sc) in c]
                if len(vals) == len(arm.seeds(algo)):
                    xs.append(n), mean.append(sum(vals) / len(vals)), lo.append(min(vals)), hi.append(max(vals))
            if xs:
                ax.plot(xs, mean, "o-", color=COLORS[algo], label=_seeds_label(algo, len(arm.seeds(algo))))
                ax.fill_between(xs, lo, hi, color=COLORS[algo], alpha=0.2)
        ax.set_xscale("log", base=2)
        ax.set_title(arm.name)
        ax.set_xlabel("N (l = 4 m to 512, then fixed density)")
        ax.set_ylabel("safe %")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, Path(out_png))


def curves_figure(
    runs: Mapping[str, Sequence[tuple[Run, dict]]], out_png: str | Path, key: str = "success_rate"
) -> Path:
    """Validation ``key`` (%) of each arm's runs against update, agent-steps and wall minutes (columns), one row per
    arm; per method the mean over seeds (at the updates every seed validated) with a min-max band."""
    from matplotlib.figure import Figure

    arms = list(runs)
    fig = Figure(figsize=(13, 2.8 * len(arms)))
    grid = fig.subplots(len(arms), 3, squeeze=False)
    for row, name in zip(grid, arms):
        by_algo: dict[str, list[dict]] = {}
        for run, c in runs[name]:
            by_algo.setdefault(run.algo, []).append(c)
        for algo, cs in by_algo.items():
            steps = sorted(set.intersection(*(set(c["step"]) for c in cs)))
            if not steps:
                continue
            at = [[c[key][c["step"].index(s)] * 100 for c in cs] for s in steps]
            for ax, xkey, scale in ((row[0], "step", 1), (row[1], "agent_steps", 1e-6), (row[2], "wall_s", 1 / 60)):
                x = [sum(c[xkey][c["step"].index(s)] for c in cs) / len(cs) * scale for s in steps]
                ax.plot(x, [sum(v) / len(v) for v in at], color=COLORS[algo], label=f"{LABELS[algo]} ({len(cs)})")
                ax.fill_between(x, [min(v) for v in at], [max(v) for v in at], color=COLORS[algo], alpha=0.2)
        for ax, xl in zip(row, ("update", "agent-steps (millions)", "wall time (min)")):
            ax.set_xlabel(xl)
            ax.set_ylabel(f"{name}: val. {key.split('_')[0]} %")
            ax.grid(alpha=0.3)
        row[0].legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, Path(out_png))


def rotated_figure(
    panels: Mapping[tuple[str, int], Mapping[str, list[tuple[float, float, float, float]]]], out_png: str | Path
) -> Path:
    """Safety and success (%) against the rotation of the training scenes: one panel per ``(metric, N)`` key of
    ``panels`` (metric ``"safe_rate"`` or ``"success_rate"``; rows by metric, columns by N), one line per run (run
    label -> ``(yaw, estimate, low, high)`` of its 95 % interval)."""
    from matplotlib.figure import Figure

    metrics = sorted({m for m, _ in panels}, key=lambda m: m != "safe_rate")
    sizes = sorted({n for _, n in panels})
    fig = Figure(figsize=(4.2 * len(sizes), 2.8 * len(metrics)))
    axes = fig.subplots(len(metrics), len(sizes), squeeze=False)
    for (metric, n), points in panels.items():
        ax = axes[metrics.index(metric)][sizes.index(n)]
        for label, pts in points.items():
            algo = label.split("-s")[0]
            pts = sorted(pts)
            ax.errorbar(
                [p[0] for p in pts], [100 * p[1] for p in pts],
                yerr=[[100 * (p[1] - p[2]) for p in pts], [100 * (p[3] - p[1]) for p in pts]],
                marker="o", capsize=3, color=COLORS.get(algo), label=label,
                linestyle="-" if label.endswith("s0") else "--",
            )  # fmt: skip
        ax.set_xticks([0, 90, 180])
        ax.set_title(f"N = {n}", fontsize=9)
        ax.set_xlabel("rotation of the training scenes (degrees)")
        ax.set_ylabel(("safe" if metric == "safe_rate" else "success") + " % (95 % CI)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, Path(out_png))
