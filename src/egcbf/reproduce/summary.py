"""The summary of the report of ``egcbf reproduce``: what the tables say, in sentences written from the cells.

Nothing here is typed in by hand: every number, N and verdict is computed from the cell records (and the paper's
Table I, :mod:`~egcbf.reproduce.paper`). The bullets, each present only when its cells are:

* **Progress**: cells computed, per group (Table I seed 0 and hand-crafted, further training seeds, scalability).
* **Against the paper**: each learned method's safe rate at Table I's largest N against the paper's (above, below,
  or around it when its 95 % interval holds it).
* **The hand-crafted CBF-QPs**: their lowest safe and success rate over Table I's N (no obstacles), and the nominal
  controller's safe rate at the largest N.
* **At fixed density**: each method's safe rate from Table I's ``scale_reference`` N to the largest fixed-density N.
* **<E-method> minus <plain method>**: the difference of safe-rate points per N (where either is below 100 %), with
  its 95 % interval (two-level bootstrap over training seeds and episodes, :func:`egcbf.evaluate.bootstrap.
  difference_ci`), or how the training seeds' ranges bear on it where a cell kept no per-episode values.
* **<method>'s seeds**: each training seed's safe rate at Table I's largest N, labelled with its own seed.
* **Behind run-time filters**: each filtered controller's safe and success rate at Table I's largest N (no
  obstacles) beside those of the same controller alone, and the difference with its 95 % interval.
* **Learned minus nominal behind the same filter**: each learned policy behind a filter against the nominal
  controller behind that filter, safe and success points with 95 % intervals, at Table I's largest N and at the
  largest fixed-density N.

Every interval is a percentile interval of 10 000 resamples with seed 0, so the text is the same at every run.
"""

from __future__ import annotations

from ..evaluate.bootstrap import Interval, difference_ci
from ..io.report import pct
from .paper import FILTERED, LABELS, LEARNED, METHODS, PAPER_TABLE_I, base_method
from .plan import Cell, SweepConfig
from .stats import Stat, seed_rows, setting_text, so_far, stat

__all__ = ["summary_markdown"]


def _at(records: dict[Cell, dict], m: str, n: int, scale: bool = False, metric: str = "safe_rate") -> Stat | None:
    """``metric`` of ``m`` at ``n`` without obstacles over its training seeds."""
    return stat(seed_rows(records, m, 0, n, scale), metric)


def _progress(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    groups = {
        "Table I, training seed 0 and hand-crafted": [c for c in cfg.table_cells() if not c.train_seed],
        "Table I, further training seeds": [c for c in cfg.table_cells() if c.train_seed],
        "scalability": cfg.scale_cells(),
        "scalability at the long horizon": cfg.long_cells(),
    }
    done = ", ".join(f"{k}: {sum(c in records for c in v)} of {len(v)}" for k, v in groups.items() if v)
    total = len(cfg.cells())
    return f"- **Progress:** {sum(c in records for c in cfg.cells())} of {total} cells computed ({done})."


def _against_paper(cfg: SweepConfig, records: dict[Cell, dict], big: int) -> list[str]:
    verdicts = []
    for m in (m for m in LEARNED if m in cfg.methods):
        ours, paper = _at(records, m, big), PAPER_TABLE_I[m].get(big)
        if ours is None or paper is None:
            continue
        iv = ours.interval
        if iv is not None:  # the 95 % interval over training seeds and episodes
            word = "above" if iv.low * 100 > paper[0] else ("below" if iv.high * 100 < paper[0] else "around")
            spread = " (its 95 % interval holds it)" if word == "around" else ""
        else:
            word = "above" if ours.lo * 100 > paper[0] else ("below" if ours.hi * 100 < paper[0] else "around")
            spread = "" if ours.n == 1 else f" (every seed {word})" if word != "around" else " (the seeds straddle it)"
        verdicts.append(f"{LABELS[m]} {ours.text()} % against the paper's {paper[0]:g} %: {word}{spread}"
                        + so_far(ours, cfg, m))  # fmt: skip
    if not verdicts:
        return []
    return [f"- **Against the paper** (safe rate at N = {big}, no obstacles): " + "; ".join(verdicts) + "."]


def _lowest(pts: list[tuple[int, dict]], metric: str, word: str) -> str:
    """``100 % safe at every N`` or ``at least 99.98 % safe (lowest at N = 512)`` over ``pts`` ``(N, row)``."""
    n, row = min(pts, key=lambda p: p[1][metric])
    if row[metric] == 1:
        return f"100 % {word} at every N"
    return f"at least {pct(row[metric])} % {word} (lowest at N = {n})"


def _qps(cfg: SweepConfig, records: dict[Cell, dict], big: int) -> list[str]:
    """The CBF-QPs over Table I's N without obstacles (the fixed-density cells have their own bullet)."""
    qps = []
    for m in (m for m in ("dcbf", "ccbf") if m in cfg.methods):
        pts = [(int(n), rows[0].row) for n in cfg.num_agents if (rows := seed_rows(records, m, 0, int(n), False))]
        if not pts:
            continue
        sizes = [n for n, _ in pts]
        pending = len(cfg.num_agents) - len(pts)
        span = f"N = {min(sizes)} to {max(sizes)}" + (f" ({pending} N pending)" if pending else "")
        qps.append(
            f"{LABELS[m]} over Table I's {span}: {_lowest(pts, 'safe_rate', 'safe')}, "
            f"{_lowest(pts, 'success_rate', 'successful')}"
        )
    if not qps:
        return []
    nominal = _at(records, "nominal", big)
    nom = f"; the nominal controller alone is {nominal.text()} % safe at N = {big}" if nominal else ""
    return ["- **The hand-crafted CBF-QPs** (no obstacles): " + "; ".join(qps) + nom + "."]


def _fixed_density(cfg: SweepConfig, records: dict[Cell, dict]) -> list[str]:
    """Each method from Table I's ``scale_reference`` N (the same density) to the largest fixed-density N."""
    if not cfg.scale_sizes:
        return []
    moves = []
    for m in (m for m in METHODS if m in cfg.methods and m in cfg.scale_methods):
        sized = [(int(n), _at(records, m, int(n), scale=True)) for n in cfg.scale_sizes]
        sized = [(n, st) for n, st in sized if st is not None]
        if not sized:
            continue
        n, st = max(sized, key=lambda p: p[0])
        ref = _at(records, m, cfg.scale_reference)
        start = f"{ref.text()} % at N = {cfg.scale_reference} to " if ref is not None else ""
        moves.append(f"{LABELS[m]} {start}{st.text()} % at {setting_text(cfg, n, True)}{so_far(st, cfg, m)}")
    if not moves:
        return []
    return [
        f"- **At fixed density** (the density of N = {cfg.scale_reference} at l = {cfg.area:g} m, no obstacles), "
        "safe rate: " + "; ".join(moves) + "."
    ]


def _spread_note(cfg: SweepConfig, records: dict[Cell, dict], equi: str, plain: str, a: Stat, b: Stat,
                 n: int, scale: bool) -> str:  # fmt: skip
    """How the training seeds bear on ``a - b`` (``equi`` minus ``plain``) at one setting."""
    if a.n > 1 and b.n > 1:
        return " (seed ranges overlap)" if a.lo <= b.hi and b.lo <= a.hi else " (seed ranges apart)"
    if a.n > 1 or b.n > 1:
        (one, single), (many, multi) = ((plain, b), (equi, a)) if a.n > 1 else ((equi, a), (plain, b))
        where = "inside" if multi.lo <= single.mean <= multi.hi else "outside"
        return (
            f" ({LABELS[one]}: one training seed, {where} {LABELS[many]}'s seed range {pct(multi.lo)}-{pct(multi.hi)})"
        )
    spreads = [
        f"{LABELS[m]} {100 * (st.hi - st.lo):.1f}"
        for m in cfg.seed_methods
        if m in cfg.methods and m not in (equi, plain)
        and (st := _at(records, m, n, scale)) is not None and st.n > 1
    ]  # fmt: skip
    return f" (seed spread here: {', '.join(spreads)} points)" if spreads else ""


def _difference(a: Stat, b: Stat) -> Interval | None:
    """``a - b`` with its 95 % two-level bootstrap interval, or ``None`` if a side kept no per-episode values."""
    return None if a.runs is None or b.runs is None else difference_ci(a.runs, b.runs)


def _differences(cfg: SweepConfig, records: dict[Cell, dict]) -> list[str]:
    """E-method minus plain method in safe-rate points, per N (Table I's, then the fixed-density ones) where either
    is below 100 %."""
    settings = [(int(n), False) for n in cfg.num_agents] + [(int(n), True) for n in cfg.scale_sizes]
    lines = []
    for plain, equi in (("gcbf+", "egcbf+"), ("gcbf", "egcbf")):
        diffs, seeds = [], set()
        for n, s in settings:
            a, b = _at(records, equi, n, s), _at(records, plain, n, s)
            if a is None or b is None or (a.lo == 1 and b.lo == 1):
                continue
            seeds.add((a.n, b.n))
            diff = _difference(a, b)
            diffs.append(
                f"{setting_text(cfg, n, s)}: "
                + (f"{100 * (a.mean - b.mean):+.1f}" + _spread_note(cfg, records, equi, plain, a, b, n, s)
                   if diff is None else diff.text(scale=100))
                + so_far(a, cfg, equi, (b, plain))
            )  # fmt: skip
        if diffs:
            each = "; one training seed each" if seeds == {(1, 1)} else ""
            lines.append(
                f"- **{LABELS[equi]} minus {LABELS[plain]}** (safe-rate points, no obstacles{each}): "
                + "; ".join(diffs)
                + "."
            )
    return lines


def _seeds(cfg: SweepConfig, records: dict[Cell, dict], big: int) -> list[str]:
    """Each training seed's safe rate at Table I's largest N, best first, each value with its own seed."""
    lines = []
    for m in (m for m in cfg.seed_methods if m in cfg.methods and len(cfg.seeds_for(m)) > 1):
        st = _at(records, m, big)
        if st is None or st.n < 2:
            continue
        order = sorted(zip(st.values, st.seeds), key=lambda p: -p[0])
        lines.append(
            f"- **{LABELS[m]}'s seeds** at N = {big}: {', '.join(f'seed {s} {pct(v)} %' for v, s in order)} "
            f"(spread {100 * (st.hi - st.lo):.1f} points){so_far(st, cfg, m)}."
        )
    return lines


def _filters(cfg: SweepConfig, records: dict[Cell, dict], big: int) -> list[str]:
    """Each filtered controller against its base controller alone, at Table I's largest N without obstacles."""
    parts = []
    for m in (m for m in FILTERED if m in cfg.methods):
        safe, succ = _at(records, m, big), _at(records, m, big, metric="success_rate")
        if safe is None or succ is None:
            continue
        base = base_method(m)
        alone = (_at(records, base, big), _at(records, base, big, metric="success_rate"))
        name = LABELS[base].split(" (")[0]  # "nominal", not "nominal (no CBF)"
        beside = "" if None in alone else f" ({name} alone: {alone[0].text()} / {alone[1].text()} %"
        gains = [] if None in alone else [_difference(safe, alone[0]), _difference(succ, alone[1])]
        if gains and None not in gains:
            beside += f"; filtered minus alone: {gains[0].text(scale=100)} / {gains[1].text(scale=100)} points"
        beside += ")" if beside else ""
        parts.append(f"{LABELS[m]} {safe.text()} / {succ.text()} %{beside}{so_far(safe, cfg, m)}")
    if not parts:
        return []
    return [f"- **Behind run-time filters** (safe / success rate at N = {big}, no obstacles): " + "; ".join(parts)
            + "."]  # fmt: skip


def _against_nominal(cfg: SweepConfig, records: dict[Cell, dict], big: int) -> list[str]:
    """Each learned policy behind a filter minus the nominal controller behind the same filter, at Table I's
    largest N and at the largest fixed-density N (no obstacles), in safe and success points."""
    settings = [(big, False)] + ([(max(int(n) for n in cfg.scale_sizes), True)] if cfg.scale_sizes else [])
    parts = []
    for m in (m for m in FILTERED if m in cfg.methods and base_method(m) != "nominal"):
        ref = "nominal:" + m.split(":", 1)[1]
        if ref not in cfg.methods:
            continue
        for n, s in settings:
            pairs = [(_at(records, m, n, s, k), _at(records, ref, n, s, k)) for k in ("safe_rate", "success_rate")]
            if any(a is None or b is None for a, b in pairs):
                continue
            diffs = [_difference(a, b) for a, b in pairs]
            text = " / ".join(
                f"{100 * (a.mean - b.mean):+.1f}" if d is None else d.text(scale=100) for d, (a, b) in zip(diffs, pairs)
            )
            parts.append(f"{LABELS[m]} minus {LABELS[ref]} at {setting_text(cfg, n, s)}: {text}"
                         + so_far(pairs[0][0], cfg, m))  # fmt: skip
    if not parts:
        return []
    return ["- **Learned minus nominal behind the same filter** (safe / success points, no obstacles, 95 % "
            "intervals): " + "; ".join(parts) + "."]  # fmt: skip


def summary_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """What the tables say, in sentences written from the cells (module doc)."""
    lines = [_progress(cfg, records)]
    if not records:
        return lines[0]
    big = max(int(n) for n in cfg.num_agents)
    lines += _against_paper(cfg, records, big)
    lines += _qps(cfg, records, big)
    lines += _fixed_density(cfg, records)
    lines += _differences(cfg, records)
    lines += _seeds(cfg, records, big)
    lines += _filters(cfg, records, big)
    lines += _against_nominal(cfg, records, big)
    return "\n".join(lines)
