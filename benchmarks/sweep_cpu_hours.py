"""CPU-hours of the whole `make reproduce` sweep: what its computed cells took, and what its pending cells will take.

Reads the committed cells of ``docs/results/reproduction/`` (each records its wall time, ``meta.wall_s``, with one
torch thread per cell) and the sweep's plan (``egcbf.reproduce.SweepConfig()``, the defaults of `egcbf reproduce`),
and tabulates per group of controllers: cells computed and their summed CPU-hours, cells pending and an estimate of
theirs. The estimate scales, per controller, its computed cells' seconds per agent-step to the pending cell's
agent-steps (episodes x N x steps): from the same controller at the same N where there is one (another training
seed, or the other horizon), else from its cells at the largest computed N. Imported cells (timed by an earlier
`egcbf eval` run, not by the sweep, which kept only the median step time) count that step time times their steps.

**Before and after the learned filters' exact QP solver.** The ``cbf`` and ``prior`` filters solved their per-agent
QPs by the interior-point method until ``FilterConfig.qp_solver`` made the exact dual active-set method their
default; their cells computed before are kept in ``docs/results/reproduction-ipm/``. The whole sweep (every cell of
the plan) is then counted twice: *before*, each learned-filter cell at its interior-point time (its archived cell's
wall time, else that filter's archived seconds per agent-step as above) and every other cell as in the table; *after*,
the same with each learned-filter cell's interior-point time divided by the episode ratio measured side by side for
its filter and obstacle setting (``docs/results/bench/edge_filter_solver.json``, ``benchmarks/edge_filter_solver.py``:
N = 512; the scalability study's cells take the no-obstacle ratio), and a learned-filter cell already computed with
the active set at its own wall time. The pending learned-filter cells of the table are estimated the same way.

The cells were computed over many sessions on two kinds of 2-core machines, one or two cells at a time, so the
sums are an account of what the sweep cost, not a benchmark; a speed-up is measured as a per-cell ratio, side by
side on one machine (docs/benchmarks.md says which).

    .venv/bin/python benchmarks/sweep_cpu_hours.py            # writes the block sweep-cpu-hours of docs/benchmarks.md
    .venv/bin/python benchmarks/sweep_cpu_hours.py --no-write
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

from egcbf.io.report import md_table, replace_section
from egcbf.reproduce import SweepConfig
from egcbf.reproduce.paper import LABELS
from egcbf.reproduce.plan import Cell
from egcbf.reproduce.store import load_cells, read_json
from egcbf.robots.quadrotor.dynamics import DEFAULT_MAX_STEPS

ROOT = Path(__file__).resolve().parents[1]
#: the learned-filter cells computed with the interior-point QP solver (module doc)
IPM_CELLS = ROOT / "docs" / "results" / "reproduction-ipm"
#: the measured episode ratios of the interior-point method over the active set, per filter and obstacle count
SOLVER_RATIOS = ROOT / "docs" / "results" / "bench" / "edge_filter_solver.json"
LEARNED_FILTERS = ("cbf", "prior")


def _filter_kind(cell: Cell) -> str | None:
    kind = cell.method.partition(":")[2]
    return kind if kind in LEARNED_FILTERS else None


def _ipm_records(cfg: SweepConfig) -> dict[Cell, dict]:
    """The archived interior-point cells of the plan's learned-filter cells (module doc)."""
    out = {}
    for cell in cfg.cells():
        if _filter_kind(cell) is not None:
            rec = read_json(cell.path(IPM_CELLS))
            if isinstance(rec, dict) and "meta" in rec:
                out[cell] = rec
    return out


def _solver_ratio(cell: Cell) -> float:
    """The measured interior-point / active-set episode ratio for ``cell``'s filter and obstacle setting."""
    ratios = json.loads(SOLVER_RATIOS.read_text())["episode_ratio"][_filter_kind(cell)]
    return float(ratios[str(cell.obstacles if not cell.scale else 0)])


def _agent_steps(cfg: SweepConfig, cell: Cell) -> int:
    return cfg.episodes_for(cell) * cell.num_agents * (cfg.steps_for(cell) or DEFAULT_MAX_STEPS)


def _wall(cfg: SweepConfig, cell: Cell, record: dict) -> float:
    """A computed cell's seconds: its own wall time, or for an imported cell (timed by the `egcbf eval` run it comes
    from, which kept only its step time) the median step time times its steps and episodes."""
    wall = record.get("meta", {}).get("wall_s")
    if wall is not None:
        return float(wall)
    return record["row"]["step_ms_median"] / 1e3 * (cfg.steps_for(cell) or DEFAULT_MAX_STEPS) * cfg.episodes_for(cell)


def _group(cell: Cell) -> str:
    where = "Table I" if not cell.scale else ("scalability, long horizon" if cell.steps else "scalability")
    return f"{where}: {LABELS[cell.method]}"


def _rate(cfg: SweepConfig, records: dict[Cell, dict], cell: Cell) -> float | None:
    """Seconds per agent-step for ``cell``, from the computed cells of its method (module doc)."""
    same = [c for c in records if c.method == cell.method and c.obstacles == cell.obstacles]
    near = [c for c in same if c.num_agents == cell.num_agents and c.scale == cell.scale] or [
        c for c in same if c.num_agents == max(x.num_agents for x in same)
    ]
    if not near:
        return None
    return sum(_wall(cfg, c, records[c]) for c in near) / sum(_agent_steps(cfg, c) for c in near)


def _ipm_seconds(cfg: SweepConfig, ipm: dict[Cell, dict], cell: Cell) -> float | None:
    """A learned-filter cell's seconds with the interior-point solver: its archived cell's, else estimated from the
    archived cells of its method (:func:`_rate`)."""
    if cell in ipm:
        return _wall(cfg, cell, ipm[cell])
    rate = _rate(cfg, ipm, cell)
    return None if rate is None else rate * _agent_steps(cfg, cell)


def before_after(cfg: SweepConfig) -> dict[str, float]:
    """CPU-hours of the whole sweep before and after the learned filters' active-set solver (module doc), and the
    learned-filter cells' share of each."""
    records, ipm = load_cells(cfg), _ipm_records(cfg)
    out = defaultdict(float)
    for cell in cfg.cells():
        if _filter_kind(cell) is None:
            sec = _wall(cfg, cell, records[cell]) if cell in records else (_rate(cfg, records, cell) or 0.0) * (
                _agent_steps(cfg, cell))  # fmt: skip
            out["before"] += sec
            out["after"] += sec
            continue
        before = _ipm_seconds(cfg, ipm, cell) or 0.0
        after = _wall(cfg, cell, records[cell]) if cell in records else before / _solver_ratio(cell)
        out["before"] += before
        out["after"] += after
        out["filters_before"] += before
        out["filters_after"] += after
    return {k: v / 3600 for k, v in out.items()}


def _pending_seconds(cfg: SweepConfig, records: dict, ipm: dict, cell: Cell) -> float | None:
    """A pending cell's estimated seconds: from its method's computed cells (:func:`_rate`), or for a learned-filter
    cell without any computed with the active set, its interior-point seconds over the measured ratio."""
    rate = _rate(cfg, records, cell)
    if rate is not None:
        return rate * _agent_steps(cfg, cell)
    if _filter_kind(cell) is None:
        return None
    before = _ipm_seconds(cfg, ipm, cell)
    return None if before is None else before / _solver_ratio(cell)


def account(cfg: SweepConfig) -> tuple[list[list[str]], dict[str, float]]:
    """The table's rows (one per group) and the totals: computed and pending cells, CPU-hours of each."""
    records, ipm = load_cells(cfg), _ipm_records(cfg)
    done, todo = defaultdict(list), defaultdict(list)
    for cell in cfg.cells():
        (done if cell in records else todo)[_group(cell)].append(cell)
    rows, total = [], defaultdict(float)
    for group in dict.fromkeys([_group(c) for c in cfg.cells()]):
        spent = sum(_wall(cfg, c, records[c]) for c in done[group]) / 3600
        secs = [_pending_seconds(cfg, records, ipm, c) for c in todo[group]]
        estimate = sum(x for x in secs if x is not None) / 3600
        unknown = sum(x is None for x in secs)
        total["computed"] += len(done[group])
        total["computed_h"] += spent
        total["pending"] += len(todo[group])
        total["pending_h"] += estimate
        left = (f"{estimate:.2f}" if todo[group] else "-") + (f" (+{unknown} not estimated)" if unknown else "")
        rows.append([group, str(len(done[group])), f"{spent:.2f}", str(len(todo[group])), left])
    return rows, dict(total)


def markdown(cfg: SweepConfig) -> str:
    rows, total = account(cfg)
    ba = before_after(cfg)
    rows.append(["**all**", str(int(total["computed"])), f"**{total['computed_h']:.1f}**", str(int(total["pending"])),
                 f"**{total['pending_h']:.1f}**"])  # fmt: skip
    head = ["cells", "computed", "CPU-hours", "pending", "CPU-hours (estimate)"]
    return (
        "`python benchmarks/sweep_cpu_hours.py`, from the committed cells of `docs/results/reproduction/` and the "
        "plan of `egcbf reproduce`'s defaults: each computed cell's own wall time (one torch thread; an imported "
        "cell's median step time times its steps), summed; each "
        "pending cell estimated from its controller's computed cells (seconds per agent-step; the script's "
        "docstring). The cells ran over many sessions on 2-core Intel Xeon and AMD EPYC machines, one or two at a "
        "time, so this is an account, not a benchmark.\n\n" + md_table(head, rows) + "\n\n"
        f"The whole sweep, every cell of the plan, computed or estimated: **{ba['before']:.1f} CPU-hours before** the "
        f"learned filters' exact active-set QP solver (their cells at the interior-point method's time, "
        f"{ba['filters_before']:.1f} of them) and **{ba['after']:.1f} after** ({ba['filters_after']:.1f}; each "
        "learned-filter cell's interior-point time over the episode ratio measured side by side for its filter and "
        "obstacle setting, `docs/results/bench/edge_filter_solver.json`; the script's docstring). The learned-filter "
        "cells computed with the interior-point method are kept in `docs/results/reproduction-ipm/`.\n"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-write", action="store_true", help="print the table; do not touch docs/benchmarks.md")
    args = parser.parse_args(argv)
    cfg = SweepConfig(out=ROOT / "docs" / "results" / "reproduction", checkpoints=ROOT / "checkpoints")
    text = markdown(cfg)
    print(text)
    if not args.no_write:
        replace_section(
            ROOT / "docs" / "benchmarks.md", "sweep-cpu-hours", text, heading="## The whole sweep's CPU-hours"
        )


if __name__ == "__main__":
    main()
