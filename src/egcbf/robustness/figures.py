"""The report's figure of one fault axis: safety and success against the level, one colour per controller, one
line style per swarm size, 95 % bands over episodes."""

from __future__ import annotations

from pathlib import Path

from ..reproduce.paper import LABELS
from .cells import rate_band
from .plan import RobustnessConfig, axis

__all__ = ["COLORS", "axis_figure"]

COLORS = {"nominal": "tab:gray", "ccbf": "tab:brown", "dcbf": "tab:purple", "gcbf+": "tab:orange",
          "egcbf+": "tab:blue", "egcbf+:dcbf": "tab:green"}  # fmt: skip


#: the report's safety thresholds (%), each with its line style
_THRESHOLDS = ((99, "--"), (95, ":"))


def _series(cells: dict, specs: list[str], m: str, n: int, k: int, key: str) -> tuple[list, ...]:
    """``(xs, mid, lo, hi)`` of controller ``m`` at ``n`` agents and ``k`` obstacles along ``specs``: the level
    index (levels equally spaced: they grow by factors) and the rate in percent with its 95 % band over episodes."""
    xs, mid, lo, hi = [], [], [], []
    for i, spec in enumerate(specs):
        r = cells.get((m, spec, n, k))
        if r is None:
            continue
        low, high = rate_band(r, key)
        xs.append(i)
        mid.append(100 * r[key])
        lo.append(100 * low)
        hi.append(100 * high)
    return xs, mid, lo, hi


def axis_figure(cfg: RobustnessConfig, cells: dict, name: str, out_png: Path) -> Path | None:
    """Safe and success % against the level (columns: without and with obstacles), one colour per controller, one
    line style per swarm size (the largest solid), 95 % bands over episodes; a fix's axis also draws the axis it
    repeats, faint and without bands (before the fix); dashed and dotted lines mark 99 and 95 % safe. Controllers that
    perceive none of the axis' faults are left out (n/a). ``None`` if nothing is drawable."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    a = axis(name)
    before = axis(a.fixes).specs() if a.fixes is not None and a.fixes in cfg.axes else None
    # a controller that perceives none of the axis' faults is n/a there (as in the tables), not a flat line
    methods = [m for m in cfg.controllers if all(cfg.cell_spec(m, sp) is not None for sp in a.specs())]
    sizes = sorted(cfg.num_agents, reverse=True)
    styles = dict(zip(sizes, ("-", "--", ":", "-.")))
    fig = Figure(figsize=(8.4, 5.6))
    panels = fig.subplots(2, 2, squeeze=False)
    drawn: set[int] = set()
    for col, k in enumerate((0, cfg.obstacles)):
        for row, key in enumerate(("safe_rate", "success_rate")):
            ax = panels[row][col]
            for m in methods:
                for n in sizes:
                    color = COLORS.get(m)
                    if before is not None:
                        xs, mid, _, _ = _series(cells, before, m, n, k, key)
                        if len(xs) >= 2:
                            ax.plot(xs, mid, ls=styles[n], color=color, lw=0.8, alpha=0.35)
                    xs, mid, lo, hi = _series(cells, a.specs(), m, n, k, key)
                    if len(xs) < 2:
                        continue
                    drawn.add(n)
                    ax.plot(xs, mid, marker="o", ls=styles[n], color=color, ms=3)
                    ax.fill_between(xs, lo, hi, color=color, alpha=0.12, lw=0)
            if key == "safe_rate":
                for level, ls in _THRESHOLDS:
                    ax.axhline(level, color="black", lw=0.6, ls=ls, alpha=0.5)
            ax.set_title(f"{'safe' if key == 'safe_rate' else 'success'} %, {k} obstacles", fontsize=9)
            ax.set_xticks(range(len(a.levels)), [f"{x:g}" for x in a.levels], fontsize=8)
            ax.set_xlabel(a.unit, fontsize=8)
            ax.grid(alpha=0.3)
    if not drawn:
        return None
    handles = [Line2D([], [], color=COLORS.get(m), marker="o", ms=3, label=LABELS.get(m, m)) for m in methods]
    handles += [Line2D([], [], color="black", lw=0.6, ls=ls, alpha=0.5, label=f"{v} % safe") for v, ls in _THRESHOLDS]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    fig.subplots_adjust(bottom=0.16, hspace=0.45)
    names = {"-": "solid", "--": "dashed", ":": "dotted", "-.": "dash-dotted"}
    sizes_text = ", ".join(f"N = {n} {names[styles[n]]}" for n in sizes if n in drawn)
    faint = f"; faint: without the fix ({a.fixes})" if before is not None else ""
    fig.suptitle(f"{a.title} ({sizes_text}{faint})", fontsize=10)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    return out_png
