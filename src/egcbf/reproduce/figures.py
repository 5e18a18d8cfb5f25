"""The figures of the report of ``egcbf reproduce`` and the sections that show them: the rates against N
(:func:`scalability_figure`), the training curves of the learned checkpoints and the CBF contour of EGCBF+ and
GCBF+. A figure that cannot be drawn leaves a sentence saying why, never a lost report."""

from __future__ import annotations

import json
from pathlib import Path

from ..io.report import relative_link
from .paper import LABELS, LEARNED, METHODS, base_method, method_filter
from .plan import Cell, SweepConfig
from .stats import episodes_text, label, scale_text, seed_rows, stat
from .store import find_method_checkpoint

__all__ = ["contour_section", "convergence_section", "scalability_figure", "scalability_section"]


def _panels(cfg: SweepConfig) -> list[tuple[int, str, str]]:
    """``(obstacles, metric, title)`` of each panel: safety and success without obstacles, safety with obstacles
    when the sweep has an obstacle setting."""
    panels = [(0, "safe_rate", "safety rate, no obstacles"), (0, "success_rate", "success rate, no obstacles")]
    if any(c.obstacles for c in cfg.table_cells()):
        panels.append((cfg.obstacles, "safe_rate", f"safety rate, {cfg.obstacles} obstacles"))
    return panels


#: the marker of each run-time filter's line (a method alone: a circle)
_MARKERS = {"none": "o", "dcbf": "s", "cbf": "^", "prior": "v"}


def _style(m: str) -> tuple[str, str]:
    """``(colour, marker)`` of a method's lines: a method alone keeps its colour of the paper's methods (the
    nominal controller black); behind a run-time filter, its base method's colour with the filter's marker."""
    base = base_method(m)
    color = "k" if base == "nominal" else f"C{METHODS.index(base)}"
    return color, _MARKERS.get(method_filter(m), "o")


def _join(cfg: SweepConfig) -> int | None:
    """The Table I N that the fixed-density line starts from: ``scale_reference`` (the same density), if Table I
    has it."""
    return cfg.scale_reference if cfg.scale_reference in {int(n) for n in cfg.num_agents} else None


def scalability_figure(cfg: SweepConfig, records: dict[Cell, dict], out_png: str | Path) -> Path:
    """Safety rate without obstacles, success rate without obstacles and (with an obstacle setting) safety rate
    with obstacles, in %, against N (log2 axis); one colour per method (behind a run-time filter: its base method's
    colour, a marker per filter), a band for the min-max over training seeds.
    Table I's cells (l fixed, the density grows) are joined by solid lines; the scalability study's (fixed density)
    by dotted lines from Table I's ``scale_reference`` N on (the same density). Returns ``out_png``."""
    from matplotlib.figure import Figure

    panels = _panels(cfg)
    fig = Figure(figsize=(5 * len(panels), 4.4))
    axes = fig.subplots(1, len(panels), sharey=True)
    big, join = max(int(n) for n in cfg.num_agents), _join(cfg)
    for ax, (k, metric, title) in zip(axes, panels):
        for m in METHODS:
            color, marker = _style(m)
            for scale, style in ((False, "-" + marker), (True, ":" + marker)):
                sizes = cfg.scale_sizes if scale else cfg.num_agents
                pts = [(int(n), stat(seed_rows(records, m, k, int(n), scale), metric)) for n in sizes]
                pts = [(n, st) for n, st in pts if st is not None]
                if scale and k == 0 and pts and join is not None:
                    first = stat(seed_rows(records, m, 0, join, False), metric)
                    pts = ([(join, first)] if first is not None else []) + pts
                if not pts:
                    continue
                xs = [n for n, _ in pts]
                name = None if scale else label(cfg, m)
                ax.plot(xs, [100 * st.mean for _, st in pts], style, color=color, ms=4, lw=1.5, label=name)
                if any(st.n > 1 for _, st in pts):
                    ax.fill_between(xs, [100 * st.lo for _, st in pts], [100 * st.hi for _, st in pts],
                                    color=color, alpha=0.15, lw=0)  # fmt: skip
        ticks = sorted({int(n) for n in cfg.num_agents} | ({int(n) for n in cfg.scale_sizes} if k == 0 else set()))
        ax.set_xscale("log", base=2)
        ax.set_xticks(ticks, [str(n) for n in ticks], fontsize=8)
        if k == 0 and cfg.scale_sizes:
            ax.axvline(big, color="0.6", lw=0.8, ls="--")
        ax.set_xlabel("number of agents N")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("%")
    axes[0].set_ylim(-3, 103)
    handles, labels = axes[0].get_legend_handles_labels()  # the no-obstacle panel has every method
    axes[-1].legend(handles, labels, fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    note = f"solid: l = {cfg.area:g} m ({episodes_text(cfg)}); bands: min-max over training seeds"
    if cfg.scale_sizes:
        start = f", from N = {join}" if join is not None else ""
        note += f"\ndotted (Table I ends at the dashed line){start}: {scale_text(cfg)}"
    fig.suptitle(note, fontsize=8)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    return out


def scalability_section(cfg: SweepConfig, records: dict[Cell, dict], report: Path, figures: Path) -> str:
    """The rates-against-N figure and its caption."""
    if not records:
        return "No cells computed yet."
    png = scalability_figure(cfg, records, figures / f"{report.stem}_scalability.png")
    text = (
        f"![safety and success rate against N]({relative_link(png, report)})\n\n"
        "Safety and success rates against the number "
        f"of agents: at l = {cfg.area:g} m up to N = {max(cfg.num_agents)} (the density grows with N, Table I)"
    )
    if cfg.scale_cells():
        join = _join(cfg)
        start = f" from N = {join}" if join is not None else ""
        text += f", then at fixed density{start} to N = {max(cfg.scale_sizes)} (dotted)"
    if len(_panels(cfg)) > 2:
        text += f"; right: with {cfg.obstacles} obstacles"
    return text + ". Lines are means over training seeds, bands their min-max."


def _fine_tuned_from(path: Path) -> Path | None:
    """The checkpoint a fine-tuned checkpoint started from (its config's ``init_from``, relative to the working
    directory), if it names one that still has its ``metrics.csv``; else ``None``."""
    try:
        start = json.loads((path / "config.json").read_text()).get("init_from")
    except (OSError, ValueError):
        return None
    return Path(start) if start and (Path(start) / "metrics.csv").exists() else None


def convergence_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    """The training curves of every learned checkpoint under ``cfg.checkpoints`` that has its ``metrics.csv``."""
    from ..viz.curves import training_curves

    runs, started = {}, set()
    for m in LEARNED:
        dirs = []
        for s in cfg.seeds_for(m):
            try:
                path = find_method_checkpoint(cfg.checkpoints, m, s).path
            except (FileNotFoundError, ValueError):
                continue
            start = _fine_tuned_from(path)
            if start is not None:  # a fine-tuned policy: the whole training run is the one it started from
                path = start
                started.add(LABELS[m])
            if (path / "metrics.csv").exists():
                dirs.append(path)
        if dirs:
            runs[LABELS[m]] = dirs  # training_curves says "mean of k seeds" itself
    if not runs:
        return f"Training curves: no `{cfg.checkpoints}/<method>/metrics.csv` (copy each run's metrics.csv there)."
    try:
        png = training_curves(runs, figures / f"{report.stem}_convergence.png")
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"Training curves failed: `{type(err).__name__}: {err}`."
    return (
        f"![training curves]({relative_link(png, report)})\n\nSafe, reach and success rates of the validation rollouts "
        "during training, against update (top) and wall time (bottom); several training seeds are drawn as their "
        "mean with a min-max band, a single run with a circle at the shipped checkpoint."
        + (
            f" {', '.join(sorted(started))}: the runs the shipped policies were fine-tuned from (their configs' "
            "`init_from`); the fine-tuning's own validations are in their checkpoints' metrics.csv."
            if started
            else ""
        )
    )


#: a float64 gap below this is round-off, whose last digits differ between CPUs: printed as the bound alone
ROUND_OFF = 1e-12


def _gap(value: float) -> str:
    """``4.38e-02``, or ``< 1e-12 (round-off)`` for a gap below :data:`ROUND_OFF` (the same text on every machine)."""
    return f"< {ROUND_OFF:.0e} (round-off)" if value < ROUND_OFF else f"{value:.2e}"


def contour_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    """The learned CBF of EGCBF+ and GCBF+ (training seed 0) over a plane, in a scene and in its transformed copy."""
    from ..viz.contour import cbf_contour_figure

    ckpts = {}
    for m in ("egcbf+", "gcbf+"):
        try:
            ckpts[LABELS[m]] = find_method_checkpoint(cfg.checkpoints, m).path
        except (FileNotFoundError, ValueError):
            continue
    if not ckpts:
        return f"CBF contour figure: no EGCBF+ or GCBF+ checkpoint under `{cfg.checkpoints}`."
    png = figures / f"{report.stem}_contour.png"
    try:
        diffs = cbf_contour_figure(ckpts, png)
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"CBF contour figure failed: `{type(err).__name__}: {err}`."
    gaps = ", ".join(f"{k}: {_gap(v)}" for k, v in (diffs or {}).items())
    return (
        f"![CBF contour]({relative_link(png, report)})\n\n"
        "The learned CBF of one agent (training seed 0) over the horizontal "
        f"plane in a scene G and in its transformed copy phi_g(G) (`egcbf.viz.contour`); max |h(g . G) - h(G)|: {gaps}."
    )
