"""The report of ``egcbf reproduce``: Table I beside the paper, the scalability study, figures, provenance.

Every number in the report is read from the sweep's cell records (:mod:`egcbf.reproduce.store`); a method evaluated
over several training seeds shows their mean with the min and max over the seeds (``92.7 (90.6-95.3)``), in the
tables, the summary and the figures (a band) alike. The report's sections live between ``<!-- name:begin/end -->``
markers of the markdown file, so text written around them survives a regeneration.
"""

from __future__ import annotations

import json
import os
import statistics
from collections import Counter
from pathlib import Path

from ..dynamics.quadrotor import DEFAULT_DT
from .paper import LABELS, LEARNED, METHODS, PAPER_TABLE_I, PaperRow
from .plan import Cell, SweepConfig
from .store import find_method_checkpoint, read_invocations

__all__ = [
    "Stat",
    "provenance_markdown",
    "scalability_figure",
    "seed_rows",
    "summary_markdown",
    "table_markdown",
    "write_report",
]


# ---------------------------------------------------------------------------------------------------- statistics
class Stat:
    """A metric over training seeds: ``mean``, ``lo`` and ``hi`` (min and max), ``n`` seeds."""

    def __init__(self, values: list[float]):
        if not values:
            raise ValueError("Stat needs at least one value")
        self.values = list(values)
        self.n = len(values)
        self.mean = statistics.fmean(values)
        self.lo, self.hi = min(values), max(values)

    def text(self, scale: float = 100.0, digits: int = 1) -> str:
        """``92.7`` (one seed) or ``92.7 (90.6-95.3)`` (mean, min-max over the seeds), values times ``scale``."""
        f = f"{{:.{digits}f}}"
        if self.n == 1:
            return f.format(scale * self.mean)
        return f"{f.format(scale * self.mean)} ({f.format(scale * self.lo)}-{f.format(scale * self.hi)})"


def seed_rows(records: dict[Cell, dict], method: str, obstacles: int, num_agents: int, scale: bool) -> list[dict]:
    """The metrics rows of ``method`` at one setting, one per training seed (seed order)."""
    cells = sorted(
        (
            c
            for c in records
            if (c.method, c.obstacles, c.num_agents, c.scale) == (method, obstacles, num_agents, scale)
        ),
        key=lambda c: -1 if c.train_seed is None else c.train_seed,
    )
    return [records[c]["row"] for c in cells]


def _stat(rows: list[dict], metric: str) -> Stat | None:
    return Stat([float(r[metric]) for r in rows]) if rows else None


def _label(cfg: SweepConfig, method: str) -> str:
    seeds = cfg.seeds_for(method)
    return LABELS[method] + (f" ({len(seeds)} seeds)" if len(seeds) > 1 else "")


# ---------------------------------------------------------------------------------------------------- tables
def _md_table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _partial(rows: list[dict], planned: int) -> str:
    """`` [1 of 3 seeds]`` while some of a method's training seeds are still pending, else ``""``."""
    return f" [{len(rows)} of {planned} seeds]" if 0 < len(rows) < planned else ""


def _fmt_ours(rows: list[dict], planned: int = 1) -> list[str]:
    if not rows:
        return ["pending"] + [""] * 5
    cost, lo, hi = _stat(rows, "cost"), min(r["cost_min"] for r in rows), max(r["cost_max"] for r in rows)
    return [
        _stat(rows, "safe_rate").text() + _partial(rows, planned),
        _stat(rows, "reach_rate").text(),
        _stat(rows, "success_rate").text(),
        f"{cost.mean:.3f} ({lo:.2f}/{hi:.2f})",
        f"{_stat(rows, 'reward').mean:.4g}",
        f"{_stat(rows, 'step_ms_median').mean:.2f}",
    ]


def _fmt_paper(p: PaperRow | None) -> list[str]:
    if p is None:
        return ["-"] * 5
    safe, reach, succ, cost, lo, hi, rew = p
    return [f"{safe:g}", f"{reach:g}", f"{succ:g}", f"{cost:g} ({lo:g}/{hi:g})", f"{rew:g}"]


_OURS = ["Safe %", "Reach %", "Succ %", "Cost (min/max)", "Rew", "step ms"]
_PAPER = ["paper Safe", "paper Reach", "paper Succ", "paper Cost (min/max)", "paper Rew"]


def _glance(cfg: SweepConfig, records: dict[Cell, dict], metric: str) -> str:
    """One table: ``metric`` of every method at every N (Table I's and the scalability study's), paper below ours."""
    sizes = [(int(n), False) for n in cfg.num_agents] + [(int(n), True) for n in cfg.scale_sizes]
    sizes = [(n, s) for n, s in sizes if any(c.num_agents == n and c.scale == s for c in cfg.cells())]
    head = ["method"] + [f"N = {n}" + (f" (l = {cfg.scale_area(n):g})" if s else "") for n, s in sizes]
    index = {"safe_rate": 0, "success_rate": 2}[metric]
    rows = []
    for m in (m for m in METHODS if m in cfg.methods):
        cells = []
        for n, s in sizes:
            rows_ = seed_rows(records, m, 0, n, s)
            st = _stat(rows_, metric)
            planned = sum(c.method == m and c.num_agents == n and c.scale == s and not c.obstacles for c in cfg.cells())
            cells.append(st.text() + _partial(rows_, planned) if st else ("pending" if planned else ""))
        rows.append([_label(cfg, m), *cells])
        paper = [PAPER_TABLE_I[m].get(n) if not s else None for n, s in sizes]
        if any(p is not None for p in paper):
            rows.append([f"{LABELS[m]}, paper", *("-" if p is None else f"{p[index]:g}" for p in paper)])
    return _md_table(head, rows)


def table_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """The tables: safe and success % at a glance, our metrics beside the paper's Table I per swarm size (no
    obstacles), the obstacle setting, and the scalability study's cells."""
    seeds = ", ".join(LABELS[m] for m in cfg.seed_methods if m in cfg.methods and len(cfg.seeds_for(m)) > 1)
    parts = [
        f"Table I: l = {cfg.area:g} m, {cfg.episodes_text()}, evaluation seed {cfg.seed}. Scalability past Table I: "
        f"{cfg.scale_text()}. "
        + (f"{seeds}: mean over the training seeds {list(cfg.train_seeds)} (min-max over the seeds). " if seeds else "")
        + "Rates in %, Cost = collision events per agent per episode (mean over episodes, min/max over episodes and "
        "seeds). Our Rew is -sum_t ||u - u_nom||^2 in SI units (`docs/metrics.md`), so its scale differs from the "
        "paper's; compare it between methods, not with the paper. The paper's dCBF/cCBF columns stop at N = 16 (its "
        "QPs did not scale); ours run to the largest N. `step ms`: median wall time of one environment step "
        "(controller + simulation; batched steps divided by their number of environments; one torch thread, two "
        "cells at once on the 2-core CPU). `pending`: the cell has not been computed yet.\n",
        "### Safety rate at a glance (no obstacles)\n",
        _glance(cfg, records, "safe_rate") + "\n",
        "### Success rate at a glance (no obstacles)\n",
        _glance(cfg, records, "success_rate") + "\n",
        "### Without obstacles, beside the paper's Table I\n",
    ]
    for n in cfg.num_agents:
        rows = [
            [
                _label(cfg, m),
                *_fmt_ours(seed_rows(records, m, 0, int(n), False)),
                *_fmt_paper(PAPER_TABLE_I[m].get(int(n))),
            ]
            for m in METHODS
            if m in cfg.methods
        ]
        parts.append(f"**N = {n}**\n\n" + _md_table(["method", *_OURS, *_PAPER], rows) + "\n")
    if cfg.obstacles > 0 and cfg.obstacle_methods:
        parts.append(f"### With {cfg.obstacles} obstacles (not in Table I)\n")
        rows = [
            [
                str(n),
                _label(cfg, m),
                *_fmt_ours(seed_rows(records, m, cfg.obstacles, int(n), False), len(cfg.seeds_for(m))),
            ]
            for n in cfg.num_agents
            for m in METHODS
            if m in cfg.methods and m in cfg.obstacle_methods
        ]
        parts.append(_md_table(["N", "method", *_OURS], rows) + "\n")
    if any(c.scale for c in cfg.cells()):
        parts.append(f"### Scalability past Table I ({cfg.scale_text()}; no obstacles)\n")
        rows = [
            [
                f"{n} (l = {cfg.scale_area(int(n)):g})",
                _label(cfg, m),
                *_fmt_ours(seed_rows(records, m, 0, int(n), True)),
            ]
            for n in cfg.scale_sizes
            for m in METHODS
            if m in cfg.methods and m in cfg.scale_methods
        ]
        parts.append(_md_table(["N", "method", *_OURS], rows) + "\n")
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------------- summary
def _pct(rate: float) -> str:
    """A rate in % with one decimal, or as many more (up to four) as keep a rate below 1 from reading 100."""
    digits = 1
    while rate < 1 and round(100 * rate, digits) == 100 and digits < 4:
        digits += 1
    return f"{100 * rate:.{digits}f}"


def _so_far(st: Stat, cfg: SweepConfig, method: str) -> str:
    """`` (1 of 3 seeds of EGCBF+ so far)`` while some of ``method``'s training seeds are pending, else ``""``."""
    planned = len(cfg.seeds_for(method))
    return f" ({st.n} of {planned} seeds of {LABELS[method]} so far)" if st.n < planned else ""


def _at(records, cfg, m, n, k=0, scale=False, metric="safe_rate") -> Stat | None:
    return _stat(seed_rows(records, m, k, n, scale), metric)


def summary_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """What the tables say, in sentences written from the cells (nothing here is typed in by hand)."""
    groups = {
        "Table I, training seed 0 and hand-crafted": [c for c in cfg.table_cells() if not c.train_seed],
        "Table I, further training seeds": [c for c in cfg.table_cells() if c.train_seed],
        "scalability": cfg.scale_cells(),
    }
    done = ", ".join(f"{k}: {sum(c in records for c in v)} of {len(v)}" for k, v in groups.items() if v)
    total = len(cfg.cells())
    lines = [f"- **Progress:** {sum(c in records for c in cfg.cells())} of {total} cells computed ({done})."]
    if not records:
        return lines[0]
    big = max(int(n) for n in cfg.num_agents)
    # where we beat or miss the paper (Table I's largest N)
    verdicts = []
    for m in (m for m in LEARNED if m in cfg.methods):
        ours, paper = _at(records, cfg, m, big), PAPER_TABLE_I[m].get(big)
        if ours is None or paper is None:
            continue
        word = "above" if ours.lo * 100 > paper[0] else ("below" if ours.hi * 100 < paper[0] else "around")
        spread = "" if ours.n == 1 else f" (every seed {word})" if word != "around" else " (the seeds straddle it)"
        spread += _so_far(ours, cfg, m)
        verdicts.append(f"{LABELS[m]} {ours.text()} % against the paper's {paper[0]:g} %: {word}{spread}")
    if verdicts:
        lines.append(f"- **Against the paper** (safe rate at N = {big}, no obstacles): " + "; ".join(verdicts) + ".")
    # the hand-crafted QPs
    qps = []
    for m in ("dcbf", "ccbf"):
        pts = [(c.num_agents, r["row"]) for c, r in records.items() if c.method == m and c.obstacles == 0]
        if pts:
            worst = min(pts, key=lambda p: p[1]["safe_rate"])
            succ = min(pts, key=lambda p: p[1]["success_rate"])
            lowest = "" if worst[1]["safe_rate"] == 1 else f"; lowest at N = {worst[0]}"
            qps.append(
                f"{LABELS[m]} is at least {_pct(worst[1]['safe_rate'])} % safe at every N it ran (up to "
                f"{max(n for n, _ in pts)}{lowest}), success at least "
                f"{_pct(succ[1]['success_rate'])} % (lowest at N = {succ[0]})"
            )
    nominal = _at(records, cfg, "nominal", big)
    if qps:
        nom = f"; the nominal controller alone is {nominal.text()} % safe at N = {big}" if nominal else ""
        lines.append("- **The hand-crafted CBF-QPs:** " + "; ".join(qps) + nom + ".")
    # the scalability study: from Table I's largest N to the largest N at the same density
    if cfg.scale_sizes:
        moves = []
        for m in (m for m in METHODS if m in cfg.methods and m in cfg.scale_methods):
            sized = [(int(n), _at(records, cfg, m, int(n), scale=True)) for n in cfg.scale_sizes]
            sized = [(n, st) for n, st in sized if st is not None]
            if not sized:
                continue
            n, st = max(sized, key=lambda p: p[0])
            ref = _at(records, cfg, m, cfg.scale_reference)
            start = f"{ref.text()} % at N = {cfg.scale_reference} to " if ref is not None else ""
            moves.append(f"{LABELS[m]} {start}{st.text()} % at N = {n}{_so_far(st, cfg, m)}")
        if moves:
            lines.append(
                f"- **At fixed density** (the density of N = {cfg.scale_reference} at l = {cfg.area:g} m, no "
                "obstacles), safe rate: " + "; ".join(moves) + "."
            )
    # what equivariance buys: E-method minus plain method, per N, with the seed ranges
    for plain, equi in (("gcbf+", "egcbf+"), ("gcbf", "egcbf")):
        diffs = []
        for n, s in [(int(n), False) for n in cfg.num_agents] + [(int(n), True) for n in cfg.scale_sizes]:
            a, b = _at(records, cfg, equi, n, scale=s), _at(records, cfg, plain, n, scale=s)
            if a is None or b is None or n < 64:
                continue
            overlap = a.lo <= b.hi and b.lo <= a.hi
            diffs.append(
                f"N = {n}: {100 * (a.mean - b.mean):+.1f}"
                + (" (seed ranges overlap)" if overlap and a.n > 1 else "")
                + _so_far(a, cfg, equi)
                + _so_far(b, cfg, plain)
            )
        if diffs:
            lines.append(
                f"- **What equivariance buys** ({LABELS[equi]} minus {LABELS[plain]}, safe-rate points, no "
                "obstacles): " + "; ".join(diffs) + "."
            )
    # the seeds
    for m in (m for m in cfg.seed_methods if m in cfg.methods and len(cfg.seeds_for(m)) > 1):
        st = _at(records, cfg, m, big)
        if st is None or st.n < 2:
            continue
        order = sorted(zip(st.values, cfg.seeds_for(m)), reverse=True)
        lines.append(
            f"- **{LABELS[m]}'s seeds** at N = {big}: {', '.join(f'seed {s} {100 * v:.1f} %' for v, s in order)} "
            f"(spread {100 * (st.hi - st.lo):.1f} points)."
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- figures
def scalability_figure(cfg: SweepConfig, records: dict[Cell, dict], out_png: str | Path) -> Path:
    """Safety rate without obstacles, success rate without obstacles and safety rate with obstacles (%) against N
    (log2 axis); one colour per method, a band for the min-max over training seeds. Table I's cells (l fixed, the
    density grows) are joined by solid lines; the scalability study's (fixed density) by dotted lines from
    Table I's largest N on. Returns ``out_png``."""
    from matplotlib.figure import Figure

    panels = [(0, "safe_rate", "safety rate, no obstacles"), (0, "success_rate", "success rate, no obstacles")]
    if cfg.obstacles > 0 and cfg.obstacle_methods:
        panels.append((cfg.obstacles, "safe_rate", f"safety rate, {cfg.obstacles} obstacles"))
    fig = Figure(figsize=(5 * len(panels), 4.4))
    axes = fig.subplots(1, len(panels), sharey=True)
    big = max(int(n) for n in cfg.num_agents)
    for ax, (k, metric, title) in zip(axes, panels):
        for i, m in enumerate(METHODS):
            color = "k" if m == "nominal" else f"C{i}"
            for scale, style in ((False, "-o"), (True, ":o")):
                sizes = cfg.scale_sizes if scale else cfg.num_agents
                pts = [(int(n), _stat(seed_rows(records, m, k, int(n), scale), metric)) for n in sizes]
                pts = [(n, st) for n, st in pts if st is not None]
                if scale and k == 0 and pts:  # join the fixed-density points to Table I's largest N
                    first = _stat(seed_rows(records, m, 0, big, False), metric)
                    pts = ([(big, first)] if first is not None else []) + pts
                if not pts:
                    continue
                xs = [n for n, _ in pts]
                label = None if scale else _label(cfg, m)
                ax.plot(xs, [100 * st.mean for _, st in pts], style, color=color, ms=4, lw=1.5, label=label)
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
    note = f"solid: l = {cfg.area:g} m ({cfg.episodes_text()}); bands: min-max over training seeds"
    if cfg.scale_sizes:
        note += f"\ndotted, right of the dashed line: {cfg.scale_text()}"
    fig.suptitle(note, fontsize=8)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    return out


def _rel(path: Path, report: Path) -> str:
    return Path(os.path.relpath(path, report.parent)).as_posix()


def _scalability_section(cfg: SweepConfig, records: dict[Cell, dict], report: Path, figures: Path) -> str:
    if not records:
        return "No cells computed yet."
    png = scalability_figure(cfg, records, figures / "reproduction_scalability.png")
    return (
        f"![safety and success rate against N]({_rel(png, report)})\n\nSafety and success rates against the number "
        f"of agents: at l = {cfg.area:g} m up to N = {max(cfg.num_agents)} (the density grows with N, Table I), then "
        f"at fixed density to N = {max(cfg.scale_sizes, default=max(cfg.num_agents))} (dotted); right: with "
        f"{cfg.obstacles} obstacles. Lines are means over training seeds, bands their min-max."
    )


def _convergence_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    from ..curves import training_curves

    runs = {}
    for m in LEARNED:
        dirs = []
        for s in cfg.seeds_for(m):
            try:
                path = find_method_checkpoint(cfg.checkpoints, m, s).path
            except (FileNotFoundError, ValueError):
                continue
            if (path / "metrics.csv").exists():
                dirs.append(path)
        if dirs:
            runs[LABELS[m]] = dirs  # training_curves says "mean of k seeds" itself
    if not runs:
        return f"Training curves: no `{cfg.checkpoints}/<method>/metrics.csv` (copy each run's metrics.csv there)."
    try:
        png = training_curves(runs, figures / "reproduction_convergence.png")
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"Training curves failed: `{type(err).__name__}: {err}`."
    return (
        f"![training curves]({_rel(png, report)})\n\nSafe, reach and success rates of the validation rollouts "
        "during training, against update (top) and wall time (bottom); several training seeds are drawn as their "
        "mean with a min-max band, a single run with a circle at the shipped checkpoint."
    )


def _contour_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    from ..contour import cbf_contour_figure

    ckpts = {}
    for m in ("egcbf+", "gcbf+"):
        try:
            ckpts[LABELS[m]] = find_method_checkpoint(cfg.checkpoints, m).path
        except (FileNotFoundError, ValueError):
            continue
    if not ckpts:
        return f"CBF contour figure: no EGCBF+ or GCBF+ checkpoint under `{cfg.checkpoints}`."
    png = figures / "reproduction_contour.png"
    try:
        diffs = cbf_contour_figure(ckpts, png)
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"CBF contour figure failed: `{type(err).__name__}: {err}`."
    gaps = ", ".join(f"{k}: {v:.2e}" for k, v in (diffs or {}).items())
    return (
        f"![CBF contour]({_rel(png, report)})\n\nThe learned CBF of one agent (training seed 0) over the horizontal "
        f"plane in a scene G and in its transformed copy phi_g(G) (`egcbf.contour`); max |h(g . G) - h(G)|: {gaps}."
    )


# ---------------------------------------------------------------------------------------------------- provenance
def _duration(seconds: float) -> str:
    """``3.25 h``, ``12.5 min`` or ``40 s``."""
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def provenance_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """Commands, seeds, machine, wall times and checkpoints behind the report."""
    invocations = read_invocations(cfg.out)
    commands = list(dict.fromkeys(i.get("command") for i in invocations if i.get("command")))
    lines = ["Commands (every invocation of the sweep into the same results directory, oldest first):", ""]
    lines += [f"    {c}" for c in commands] or ["    (none recorded)"]
    lines += [
        "",
        f"- Results: `{cfg.out}/<method>[-s<seed>]_obs<k>/N<n>.json` (Table I) and `{cfg.out}/scale/...` "
        "(scalability), one file per cell (metrics row + meta).",
        f"- Evaluation seed {cfg.seed}; episode e at size N resets from `episode_seed({cfg.seed}, N, e)` "
        f"(`egcbf.evaluate`); {cfg.episodes_text()}; episode length {cfg.max_steps or 256} steps of "
        f"{1e3 * DEFAULT_DT:g} ms; l = {cfg.area:g} m; obstacle setting: {cfg.obstacles} obstacles; scalability: "
        f"{cfg.scale_text()}.",
    ]
    machines = Counter(
        json.dumps(r["meta"].get("machine"), sort_keys=True) for r in records.values() if r["meta"].get("machine")
    )
    for m, count in sorted(machines.items()):
        d = json.loads(m)
        cores = f"{d['cores']} cores" if d.get("cores") else "core count not recorded"
        lines.append(
            f"- Machine of {count} cell(s): {d.get('cpu')}, {cores}, torch {d.get('torch')}, python "
            f"{d.get('python')}, {d.get('threads')} torch thread(s) per cell."
        )
    total = sum(float(i.get("wall_s") or 0.0) for i in invocations)
    last = invocations[-1] if invocations else {}
    status = [i.get("status", "finished") for i in invocations]
    killed = status.count("running") + status.count("interrupted")
    cut = (
        f", {killed} not recorded as finished (still running, or stopped: counted to their last finished cell)"
        if killed
        else ""
    )
    computed = [r for r in records.values() if not r["meta"].get("imported_from")]
    cell_wall = sum(float(r["meta"].get("wall_s") or 0.0) for r in computed)
    lines += [
        f"- Sweep wall time: {_duration(total)} over {len(invocations)} recorded invocation(s){cut}; last: "
        f"{last.get('workers')} worker(s), backend {last.get('backend')}; paused time, if any, is included.",
        f"- The {len(computed)} computed cells' own wall times sum to {_duration(cell_wall)}; with "
        f"{last.get('workers') or 1} cell(s) at a time that is {_duration(cell_wall / (last.get('workers') or 1))} "
        "of the machine (this counts every cell, including those of invocations killed before they recorded "
        "themselves).",
    ]
    lines += ["", "| run | cells computed | cells imported | sum of cell wall times | checkpoint | step | "
              "train seed |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    by_run: dict[tuple[str, int | None], list[dict]] = {}
    for c, rec in records.items():
        by_run.setdefault((c.method, c.train_seed), []).append(rec)
    order = {m: i for i, m in enumerate(METHODS)}
    for (m, s), recs in sorted(by_run.items(), key=lambda kv: (order[kv[0][0]], kv[0][1] or 0)):
        imported = sum(1 for r in recs if r["meta"].get("imported_from"))
        wall = sum(float(r["meta"].get("wall_s") or 0.0) for r in recs if not r["meta"].get("imported_from"))
        meta, sha = recs[0]["meta"], recs[0]["key"].get("checkpoint_sha256")
        ck = f"`{meta.get('checkpoint')}` (sha256 {sha[:12]})" if sha else "-"
        step = meta.get("checkpoint_step")
        cells = [LABELS[m], str(len(recs) - imported), str(imported), _duration(wall), ck]
        cells += ["-" if step is None else str(step), "-" if s is None else str(s)]
        lines.append("| " + " | ".join(cells) + " |")
    imported = sorted({r["meta"]["imported_from"] for r in records.values() if r["meta"].get("imported_from")})
    if imported:
        lines += ["", "Imported baseline cells (same `evaluate`, seeds and settings) come from:", ""]
        lines += [f"- `{d}`" for d in imported]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- the report
_INTRO = """# Reproducing Table I and the scalability study

Generated by `egcbf reproduce` (`src/egcbf/reproduce/`) from the cell results in `{out}`; the sections between
the `<!-- name:begin/end -->` markers are regenerated, text around them is kept. Regenerate the report alone with
`egcbf reproduce --report-only`.
"""

_SECTIONS = (
    ("summary", "## Summary"),
    ("table", "## Table I: ours beside the paper's"),
    ("scalability", "## Scalability"),
    ("convergence", "## Convergence of training"),
    ("contour", "## CBF contour"),
    ("provenance", "## Provenance"),
)


def write_report(
    cfg: SweepConfig, records: dict[Cell, dict], report: str | Path, figures: str | Path | None = None
) -> Path:
    """Write (or update) the markdown ``report`` and its figures (default: ``<report dir>/figures``)."""
    from ..report import replace_section

    report = Path(report)
    figures = Path(figures) if figures is not None else report.parent / "figures"
    if not report.exists():
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(_INTRO.format(out=cfg.out))
    bodies = {
        "summary": summary_markdown(cfg, records),
        "table": table_markdown(cfg, records),
        "scalability": _scalability_section(cfg, records, report, figures),
        "convergence": _convergence_section(cfg, report, figures),
        "contour": _contour_section(cfg, report, figures),
        "provenance": provenance_markdown(cfg, records),
    }
    for name, heading in _SECTIONS:
        replace_section(report, name, bodies[name], heading=heading)
    return report
