"""The tables of the report of ``egcbf reproduce``: every cell's metrics, beside the paper's Table I where it has them.

* **At a glance** (safety rate, success rate): one row per method and one column per N without obstacles (Table I's
  N, then the scalability study's N with their ``l``); below a method's row the paper's value where Table I has one.
  A value made of only some of the method's training seeds ends in ``[2 of 3 seeds]``.
* **Per N, beside Table I** (no obstacles): one table per Table I N, one row per method: our Safe/Reach/Succ % (mean
  over training seeds with its 95 % interval, :class:`~egcbf.reproduce.stats.Stat`), Cost (collision events per agent
  per episode, mean; min/max over episodes and seeds), ``coll. steps`` (steps in collision per agent per episode, mean:
  the other reading of the paper's cost), Rew, ``step ms`` (``†``: an imported cell, timed elsewhere), ``QP slack /
  failed`` (tables with a CBF-QP or run-time filter row; a filter's row adds the share of agent-steps whose command it
  changed), then the paper's five columns (``-`` for the rows not in the paper, such as the run-time filters').
* **With obstacles** (not in Table I) and **scalability past Table I**: the same columns as ours above, one row per
  (N, method).

A row label says ``(2 of 3 seeds)`` while some training seeds of its method are pending at that setting.
"""

from __future__ import annotations

from ..io.report import md_table, number
from .paper import FILTERED, LABELS, METHODS, PAPER_TABLE_I, PaperRow, base_method, method_filter
from .plan import Cell, SweepConfig
from .provenance import timing_text
from .stats import SeedRow, episodes_text, label, partial, scale_text, seed_rows, stat

__all__ = ["table_markdown"]

_OURS = ["Safe %", "Reach %", "Succ %", "Cost (min/max)", "coll. steps", "Rew", "step ms"]
_QP = ["QP slack / failed"]
_PAPER = ["paper Safe", "paper Reach", "paper Succ", "paper Cost (min/max)", "paper Rew"]


def _has_qp(rows: list[list[SeedRow]]) -> bool:
    return any("qp_slack_steps" in r.row for rs in rows for r in rs)


def _fmt_ours(rows: list[SeedRow], qp: bool) -> list[str]:
    """Our columns (``_OURS``, plus ``_QP`` if ``qp``) of one setting's cells; ``pending`` if there are none."""
    width = len(_OURS) + len(_QP) * qp
    if not rows:
        return ["pending"] + [""] * (width - 1)
    cost = stat(rows, "cost")
    lo, hi = min(r.row["cost_min"] for r in rows), max(r.row["cost_max"] for r in rows)
    steps = stat(rows, "collision_steps")
    dagger = "†" if any(r.imported for r in rows) else ""
    cells = [
        stat(rows, "safe_rate").text(),
        stat(rows, "reach_rate").text(),
        stat(rows, "success_rate").text(),
        f"{number(cost.mean)} ({number(lo, 2)}/{number(hi, 2)})",
        "-" if steps is None else number(steps.mean),
        f"{stat(rows, 'reward').mean:.4g}",
        f"{stat(rows, 'step_ms_median').mean:.2f}{dagger}",
    ]
    if qp:
        has = [r for r in rows if "qp_slack_steps" in r.row]
        slack, failed = sum(r.row["qp_slack_steps"] for r in has), sum(r.row.get("qp_failed", 0) for r in has)
        active = stat(rows, "filter_active")  # a run-time filter: the agent-steps whose command it changed
        changed = "" if active is None else f" ({active.text()} % changed)"
        cells.append(f"{slack} / {failed}{changed}" if has else "")
    return cells


def _fmt_paper(p: PaperRow | None) -> list[str]:
    if p is None:
        return ["-"] * 5
    safe, reach, succ, cost, lo, hi, rew = p
    return [f"{safe:g}", f"{reach:g}", f"{succ:g}", f"{cost:g} ({lo:g}/{hi:g})", f"{rew:g}"]


def _glance(cfg: SweepConfig, records: dict[Cell, dict], metric: str) -> str:
    """One table: ``metric`` of every method at every N without obstacles (Table I's and the scalability study's),
    the paper's row below ours where Table I has the method."""
    sizes = [(int(n), False) for n in cfg.num_agents] + [(int(n), True) for n in cfg.scale_sizes]
    main = cfg.table_cells() + cfg.scale_cells()  # (the long horizon has its own section)
    sizes = [(n, s) for n, s in sizes if any(c.num_agents == n and c.scale == s for c in main)]
    head = ["method"] + [f"N = {n}" + (f" (l = {cfg.scale_area(n):g} m)" if s else "") for n, s in sizes]
    index = {"safe_rate": 0, "success_rate": 2}[metric]
    rows = []
    for m in (m for m in METHODS if m in cfg.methods):
        cells = []
        for n, s in sizes:
            rows_ = seed_rows(records, m, 0, n, s)
            st = stat(rows_, metric)
            planned = sum(c.method == m and c.num_agents == n and c.scale == s and not c.obstacles for c in main)
            cells.append(st.text() + partial(len(rows_), planned) if st else ("pending" if planned else ""))
        rows.append([label(cfg, m), *cells])
        paper = [PAPER_TABLE_I.get(m, {}).get(n) if not s else None for n, s in sizes]
        if any(p is not None for p in paper):
            rows.append([f"{LABELS[m]}, paper", *("-" if p is None else f"{p[index]:g}" for p in paper)])
    return md_table(head, rows)


def _paper_qp_limit() -> int | None:
    """The largest N at which the paper's Table I has a CBF-QP row."""
    sizes = [n for m in ("dcbf", "ccbf") for n, row in PAPER_TABLE_I[m].items() if row is not None]
    return max(sizes, default=None)


def _intro(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    seeds = ", ".join(LABELS[m] for m in cfg.seed_methods if m in cfg.methods and len(cfg.seeds_for(m)) > 1)
    qps = [LABELS[m] for m in ("dcbf", "ccbf") if m in cfg.methods]
    limit = _paper_qp_limit()
    text = (
        f"Table I: l = {cfg.area:g} m, {episodes_text(cfg)}, evaluation seed {cfg.seed}. Scalability past Table I: "
        f"{scale_text(cfg)}. "
    )
    if seeds:
        text += (
            f"{seeds}: mean over the training seeds {list(cfg.train_seeds)}; a row or value made of only some of them "
            "says so (`2 of 3 seeds`). "
        )
    text += (
        "`[low, high]`: the 95 % interval of the mean, a two-level bootstrap over training seeds and then episodes "
        "(10 000 resamples, `egcbf.evaluate.bootstrap.mean_ci`; over episodes alone for one training seed and the "
        "hand-crafted controllers); `(low-high)`: the min-max over training seeds of a row whose cells kept no "
        "per-episode values (computed before they were recorded), which have no interval. "
        "Rates in %, with more decimals wherever one decimal would print a rate below 100 % as 100.0 (or above 0 "
        "as 0.0). Cost = collision events per agent per episode (mean over episodes, min/max over episodes and "
        "seeds); `coll. steps` = steps in collision per agent per episode (mean over episodes). The paper does not "
        "say which of the two its Cost counts (`docs/metrics.md`), so compare its Cost with both. A cost above 0 "
        "that would print as 0.000 shows two significant digits. Our Rew is -sum_t ||u - u_nom||^2 in SI units "
        "(`docs/metrics.md`), so its scale differs from the paper's; compare it between methods, not with the "
        "paper. "
    )
    if qps and limit is not None:
        text += (
            f"The paper's {'/'.join(qps)} rows stop at N = {limit} (its QPs did not scale); ours run to the largest "
            "N. `QP slack / failed`: QPs solved with a slack above its tolerance (a CBF constraint relaxed) / QPs not "
            "solved (their agents brake), summed over every step of every episode (cCBF-QP: one QP per environment "
            "and step; dCBF-QP: one per agent and step; `docs/baselines.md`). "
        )
    filtered = [m for m in FILTERED if m in cfg.methods]
    if filtered:
        text += _filters_text(filtered)
    text += (
        "`step ms`: median wall time of one environment step (controller + simulation; batched steps divided by "
        "their number of environments); it depends on the machine and on what ran beside the cell. "
    )
    timing = timing_text(cfg, records)
    if timing:
        text += timing + " "
    return text + "`pending`: the cell has not been computed yet.\n"


def _filters_text(filtered: list[str]) -> str:
    """What the rows of the controllers behind a run-time filter are (not in the paper)."""
    what = []
    for m in filtered:
        base, kind = base_method(m), method_filter(m)
        who = "the nominal controller's command" if base == "nominal" else f"the {LABELS[base]} policy"
        seeds = "" if base == "nominal" else f", over {LABELS[base]}'s training seeds and checkpoints"
        what.append(f"{LABELS[m]}: {who} behind the `{kind}` filter (`egcbf eval --filter {kind}`{seeds})")
    return (
        "Run-time safety filters (not in the paper; `docs/safety_filters.md`, `egcbf eval --filter`, its default "
        "settings, recorded in each cell): "
        + "; ".join(what)
        + ". Every agent solves one small QP per step over its own acceleration (`dcbf`: the dCBF-QP's hand-crafted "
        "barriers with the filter's own settings; `cbf`: the checkpoint's learned per-edge barriers; `prior`: the "
        "untrained barrier, the ablation that shows what the learned CBF adds; `nominal + ...`: the ablation that "
        "shows what the learned policy adds); their `QP slack / failed` count those agent QPs, and `% changed` is "
        "the share of agent-steps whose command the filter changed (mean over training seeds). "
    )


def _setting_table(cfg: SweepConfig, records: dict[Cell, dict], settings: list[tuple[int, int, bool]]) -> str:
    """One row per (N, method) of ``settings`` ``(obstacles, N, scale)``: N, method and our columns."""
    found = {
        (k, n, s, m): seed_rows(records, m, k, n, s)
        for k, n, s in settings
        for m in METHODS
        if any(c.method == m for c in _cells_at(cfg, k, n, s))
    }
    qp = _has_qp(list(found.values()))
    rows = [
        [
            str(n) + (f" (l = {cfg.scale_area(n):g} m)" if s else ""),
            label(cfg, m, len(rs)),
            *_fmt_ours(rs, qp),
        ]
        for (k, n, s, m), rs in found.items()
    ]
    return md_table(["N", "method", *_OURS, *_QP * qp], rows)


def _cells_at(cfg: SweepConfig, obstacles: int, num_agents: int, scale: bool) -> list[Cell]:
    main = cfg.table_cells() + cfg.scale_cells()  # (the long horizon has its own section)
    return [c for c in main if (c.obstacles, c.num_agents, c.scale) == (obstacles, num_agents, scale)]


def table_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """The tables (module doc): safe and success % at a glance, our metrics beside the paper's Table I per swarm
    size (no obstacles), the obstacle setting, and the scalability study's cells; an introduction says what every
    column means and where the timings come from."""
    parts = [
        _intro(cfg, records),
        "### Safety rate at a glance (no obstacles)\n",
        _glance(cfg, records, "safe_rate") + "\n",
        "### Success rate at a glance (no obstacles)\n",
        _glance(cfg, records, "success_rate") + "\n",
        "### Without obstacles, beside the paper's Table I\n",
    ]
    for n in cfg.num_agents:
        found = {m: seed_rows(records, m, 0, int(n), False) for m in METHODS if m in cfg.methods}
        qp = _has_qp(list(found.values()))
        rows = [
            [label(cfg, m, len(rs)), *_fmt_ours(rs, qp), *_fmt_paper(PAPER_TABLE_I.get(m, {}).get(int(n)))]
            for m, rs in found.items()
        ]
        parts.append(f"**N = {n}**\n\n" + md_table(["method", *_OURS, *_QP * qp, *_PAPER], rows) + "\n")
    obstacle_cells = [c for c in cfg.table_cells() if c.obstacles]
    if obstacle_cells:
        parts.append(f"### With {cfg.obstacles} obstacles (not in Table I)\n")
        parts.append(_setting_table(cfg, records, [(cfg.obstacles, int(n), False) for n in cfg.num_agents]) + "\n")
    if cfg.scale_cells():
        parts.append("### Scalability past Table I (fixed density, no obstacles)\n")
        parts.append(f"Setting: {scale_text(cfg)}.\n")
        parts.append(_setting_table(cfg, records, [(0, int(n), True) for n in cfg.scale_sizes]) + "\n")
    return "\n".join(parts)
