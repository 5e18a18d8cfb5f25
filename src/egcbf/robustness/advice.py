"""The report's advice, "What to choose": the controller for the default field conditions, each agent-side fix
with the recommended controller's numbers without and with it, and per fault axis the most severe level some
controller keeps 99 % safe and the one to choose there."""

from __future__ import annotations

from ..control.names import FILTER_LABELS
from ..faults import parse_faults
from ..faults.sensing import unread_fields
from ..reproduce.paper import LABELS, method_filter
from .cells import code_list, paired_change, paired_interval, pct
from .plan import AXES, Axis, RobustnessConfig, axis

__all__ = ["advice", "headline", "recommended"]


def recommended(
    cfg: RobustnessConfig, cells: dict, n: int, k: int, field: str = "field"
) -> tuple[str, dict, bool] | None:
    """The controller for the default field conditions (level 1 of axis ``field``) at ``n`` agents and ``k``
    obstacles: the most successful of those >= 99 % safe (``(method, row, True)``), else the safest (``(method, row,
    False)``); ``None`` while a controller's cell is missing (a choice among some would be no choice)."""
    spec = axis(field).specs()[1]
    if any((m, spec, n, k) not in cells for m in cfg.controllers):
        return None
    order, ok = _ranked(cfg, cells, spec, n, k)
    return order[0], cells[(order[0], spec, n, k)], ok


def _ranked(cfg: RobustnessConfig, cells: dict, spec: str, n: int, k: int) -> tuple[list[str], bool]:
    """The candidates for level ``spec`` at ``n`` agents and ``k`` obstacles, best first: those >= 99 % safe by
    success (then safety), or, when none is, every controller by safety (then success); and whether some is
    >= 99 % safe. Ties keep ``cfg.controllers``' order."""
    rows = {m: cells[(m, spec, n, k)] for m in cfg.controllers}
    safe = [m for m in cfg.controllers if rows[m]["safe_rate"] >= 0.99]
    if safe:
        return sorted(safe, key=lambda m: (rows[m]["success_rate"], rows[m]["safe_rate"]), reverse=True), True
    return sorted(cfg.controllers, key=lambda m: (rows[m]["safe_rate"], rows[m]["success_rate"]), reverse=True), False


def _recommendation(cfg: RobustnessConfig, cells: dict, n: int, field: str = "field") -> list[str]:
    """The pick at the default field conditions of axis ``field`` (level 1) for each obstacle setting; for a variant
    of them (``field_correlated``) also what it costs the plain conditions' pick (paired)."""
    a = axis(field)
    spec = a.specs()[1]
    lines = []
    for k in (0, cfg.obstacles):
        choice = recommended(cfg, cells, n, k, field)
        if choice is None:
            missing = [LABELS.get(m, m) for m in cfg.controllers if (m, spec, n, k) not in cells]
            lines.append(f"- {a.title}, N = {n}, {k} obstacles: pending (not computed yet: "
                         f"{', '.join(missing)}).")  # fmt: skip
            continue
        pick, row, ok = choice
        why = "the most successful of those >= 99 % safe" if ok else "none reaches 99 % safe; the safest"
        spared = _spared(cfg, pick, spec)
        lines.append(
            f"- {a.title}, N = {n}, {k} obstacles: **{LABELS.get(pick, pick)}** "
            f"({100 * row['safe_rate']:.2f} % safe, {100 * row['success_rate']:.2f} % success; {why}"
            f"{'; ' + spared if spared else ''})."
            + _runner_up(cfg, cells, spec, n, k)
            + (_variant_cost(cfg, cells, field, n, k) if field != "field" else "")
        )
    return lines  # fmt: skip


def _variant_cost(cfg: RobustnessConfig, cells: dict, field: str, n: int, k: int) -> str:
    """`` The plain conditions' pick, X: ...``: what the variant ``field`` of the default field conditions costs the
    controller picked for the plain ones (variant minus plain, paired over the same scenes)."""
    plain = recommended(cfg, cells, n, k)
    if plain is None:
        return ""
    m = plain[0]
    before, after = cells[(m, axis("field").specs()[1], n, k)], cells[(m, axis(field).specs()[1], n, k)]
    safe = paired_interval(before, after, "safe_rate")
    change = f"{100 * (after['safe_rate'] - before['safe_rate']):+.2f}" if safe is None else safe.text(100, 2)
    return (f" The plain conditions' pick, {LABELS.get(m, m)}: {pct(before, 'safe_rate')} -> "
            f"{pct(after, 'safe_rate')} % safe ({change} points, paired 95 % CI).")  # fmt: skip


def _runner_up(cfg: RobustnessConfig, cells: dict, spec: str, n: int, k: int) -> str:
    """`` Minus the runner-up ...``: the pick minus the next candidate (:func:`_ranked`), paired over the same
    scenes, so a reader sees whether the choice is settled or a tie (``""`` when there is none)."""
    order, _ = _ranked(cfg, cells, spec, n, k)
    if len(order) < 2:
        return ""
    pick, other = order[:2]
    mine, theirs = cells[(pick, spec, n, k)], cells[(other, spec, n, k)]
    intervals = [paired_interval(theirs, mine, rate) for rate in ("safe_rate", "success_rate")]
    if None in intervals:
        return ""
    tie = "" if any(x.excludes_zero() for x in intervals) else "; not distinguishable within these episodes"
    spared = _spared(cfg, other, spec)
    return (
        f" Minus the runner-up, {LABELS.get(other, other)}{f' ({spared})' if spared else ''}: safe "
        f"{intervals[0].text(100, 2)}, success {intervals[1].text(100, 2)} points (paired 95 % CI{tie})."
    )


def _spared(cfg: RobustnessConfig, m: str, spec: str) -> str:
    """``"ran without ..."`` when controller ``m`` does not perceive some of level ``spec``'s faults (a centralized
    QP reads no messages: its result at this level is not like for like with those that do), else ``""``."""
    spared = cfg.unperceived(m, spec)
    if not spared:
        return ""
    return f"ran without {code_list(spared)}, which it does not perceive: not like for like"


def _filter_spared(m: str, spec: str) -> str:
    """``" ..."`` when ``m`` is a policy behind a filter that itself does not read some of ``spec``'s faults (the
    dCBF filter's obstacle rows come from the map, not the LiDAR): those reach only the policy, which a reader
    choosing for that fault must know. ``""`` otherwise."""
    kind = method_filter(m)
    if kind == "none":
        return ""
    from ..control.filters import filter_reads_sensing

    unread = unread_fields(filter_reads_sensing(kind, has_policy=False), parse_faults(spec))
    if not unread:
        return ""
    label = FILTER_LABELS.get(kind, f"{kind} filter")
    return f" Its {label} does not read {code_list(unread)}: those faults reach only its policy."


def _fault_axes(cfg: RobustnessConfig) -> list[Axis]:
    """The swept fault axes proper: neither the default field conditions nor a fix's repeat."""
    return [axis(x) for x in cfg.axes if axis(x).fixes is None and not x.startswith("field")]


def _fix_effect(cfg: RobustnessConfig, cells: dict, m: str, before: str, after: str, sizes) -> tuple[str, str]:
    """What the fix that turns level ``before`` into ``after`` does for controller ``m``, judged by the paired 95 %
    intervals (after minus before, the same scenes) at the largest of ``sizes`` where both cells are computed (each
    obstacle setting there): ``("on", evidence)`` when it makes ``m`` safer or more successful and no less safe,
    ``("off", ...)`` when it costs safety, ``("none", ...)`` when no interval excludes 0, or ``("unreached", ...)``,
    ``("pending", ...)``."""
    name = LABELS.get(m, m)
    if cfg.cell_spec(m, before) == cfg.cell_spec(m, after):
        return "unreached", f"it does not change {name}, which does not perceive what it handles"
    for n in sorted(sizes, reverse=True):
        ks = [k for k in (0, cfg.obstacles) if all((m, sp, n, k) in cells for sp in (before, after))]
        if ks:
            break
    else:
        return "pending", f"measured for {name}: pending"
    parts, verdicts = [], []
    for k in ks:
        b, f = cells[(m, before, n, k)], cells[(m, after, n, k)]
        safe, success = paired_interval(b, f, "safe_rate"), paired_interval(b, f, "success_rate")
        if safe is None or success is None:  # rows without episodes: the point estimates only
            verdicts.append("unjudged")
        else:
            verdicts.append("off" if safe.high < 0 else "on" if safe.low > 0 or success.low > 0 else "none")
        parts.append(f"{k} obstacles: {pct(b, 'safe_rate')} -> {pct(f, 'safe_rate')} % safe{_ci(safe)}, "
                     f"{pct(b, 'success_rate')} -> {pct(f, 'success_rate')} % success{_ci(success)}")  # fmt: skip
    verdict = next((v for v in ("off", "on", "unjudged") if v in verdicts), "none")
    larger = [x for x in sizes if x > n]
    note = f" (N = {', '.join(map(str, larger))} pending)" if larger else ""
    return verdict, f"measured at N = {n}{note}: " + "; ".join(parts)


def _ci(interval) -> str:
    return "" if interval is None else f" ({interval.text(100, 2)})"


_VERDICTS = {
    "on": "turn on {h} for {name}: safer or more successful with it, and not measurably less safe",
    "off": "leave {h} off for {name}: it costs safety",
    "none": "{h}: no change measurable within these episodes for {name} (every 95 % interval includes 0)",
    "unjudged": "{h} for {name}: not judged (no per-episode results to pair)",
}


def _fix_line(cfg: RobustnessConfig, cells: dict, m: str, fix: Axis, before: str, after: str, sizes) -> str:
    """``fix``'s verdict for controller ``m`` with its evidence (after minus before, points, paired 95 % CI)."""
    verdict, evidence = _fix_effect(cfg, cells, m, before, after, sizes)
    h = f"`{fix.handling()}`"
    if verdict in ("unreached", "pending"):
        return f"{h}: {evidence}"
    return _VERDICTS[verdict].format(h=h, name=LABELS.get(m, m)) + f"; {evidence}"


def _fix_hint(cfg: RobustnessConfig, cells: dict, name: str, m: str, level: int, n: int, why: str) -> str:
    """`` The agents' fix, at ...: ...`` for the fault axis ``name`` at level index ``level`` (``why`` says what
    that level is to ``m``): what the fix whose axis repeats it does for the chosen controller ``m`` there (at ``n``
    agents), or ``""`` when no fix repeats it."""
    fixes = [a for a in AXES if a.fixes == name and a.name in cfg.axes]
    if not fixes or level == 0:
        return ""
    fix, a = fixes[0], axis(name)
    before, after = a.specs()[level], fix.specs()[level]
    line = _fix_line(cfg, cells, m, fix, before, after, (n,))
    return f" The agents' fix, at {a.levels[level]:g} ({a.unit}), {why}: {line}."


def _fix_level(first_fail: int, held: int, count: int) -> tuple[int, str]:
    """Where to measure a fix for a controller that first drops below 99 % safe at level index ``first_fail`` (``count``
    levels) and is chosen up to level index ``held``: where it breaks, the level the fix is for; at its last level
    when it never breaks."""
    if first_fail < count:
        return first_fail, "where it first drops below 99 % safe"
    return held, "the last level"


def _axis_choices(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """Per fault axis, at the largest N computed for every controller and level: the last level before the first
    at which no controller is >= 99 % safe (the worse of without and with obstacles), and the most successful of
    those 99 % safe there. Controllers that do not perceive the axis' faults (n/a) are not candidates."""
    lines = []
    for a in _fault_axes(cfg):
        specs, obstacles = a.specs(), (0, cfg.obstacles)
        methods = [m for m in cfg.controllers if all(cfg.cell_spec(m, sp) is not None for sp in specs)]
        if not methods:  # no controller perceives this axis' faults
            continue
        for n in sorted(cfg.num_agents, reverse=True):
            if not all((m, sp, n, k) in cells for m in methods for sp in specs for k in obstacles):
                continue
            worst = {(m, i): tuple(min(cells[(m, sp, n, k)][key] for k in obstacles)
                                   for key in ("safe_rate", "success_rate"))
                     for m in methods for i, sp in enumerate(specs)}  # fmt: skip
            # each controller's first level below 99 % safe: a controller holds a level only if it held every milder one
            first_fail = {m: next((i for i in range(len(specs)) if worst[(m, i)][0] < 0.99), len(specs))
                          for m in methods}  # fmt: skip
            held = max(first_fail.values())
            names = ", ".join(LABELS.get(m, m) for m in methods)
            larger = [x for x in cfg.num_agents if x > n]
            pending = f" (N = {', '.join(map(str, larger))} pending)" if larger else ""
            where = f"N = {n}{pending}, each rate the worse of {obstacles[0]} and {obstacles[1]} obstacles"
            if held == 0:
                lines.append(f"- {a.title}: none of the controllers that perceive it ({names}) is 99 % safe even "
                             f"without it ({where}).")  # fmt: skip
                break
            i = held - 1  # the most severe level some controller holds, with every milder one
            if i == 0:
                best = max(methods, key=lambda m: worst[(m, 1)])  # the safest at the mildest level
                fix = _fix_hint(cfg, cells, a.name, best, 1, n, f"for {LABELS.get(best, best)}, the safest there")
                lines.append(f"- {a.title}: no controller stays 99 % safe at {a.levels[1]:g} ({a.unit}) already "
                             f"({where}).{fix}")  # fmt: skip
                break
            pick = max((m for m in methods if first_fail[m] > i), key=lambda m: worst[(m, i)][::-1])
            safe, success = worst[(pick, i)]
            beyond = f"; none stays 99 % safe up to {a.levels[held]:g}" if held < len(specs) else ""
            j, why = _fix_level(first_fail[pick], i, len(specs))
            fix = _fix_hint(cfg, cells, a.name, pick, j, n, why)
            few = " Fewer than half of its agents reach their goals there." if success < 0.5 else ""
            lines.append(
                f"- {a.title}, up to {a.levels[i]:g} ({a.unit}): **{LABELS.get(pick, pick)}** "
                f"({100 * safe:.2f} % safe, {100 * success:.2f} % success there, {where}{beyond})."
                f"{_filter_spared(pick, specs[i])}{few}{fix}"
            )
            break
    return lines


def _fix_advice(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """One line per compared fix (:meth:`Axis.compared`): the recommended controller (the largest N's pick without
    obstacles) without and with it, at the largest N where both cells are computed, or pending."""
    choice = recommended(cfg, cells, max(cfg.num_agents), 0)
    if choice is None:
        return []
    pick = choice[0]
    lines = []
    for fix in (axis(x) for x in cfg.axes):
        if fix.compared() is None or fix.fixes not in cfg.axes:
            continue
        before, after = fix.compared()
        lines.append(f"- {fix.title}: {_fix_line(cfg, cells, pick, fix, before, after, cfg.num_agents)}.")
    return lines


def advice(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The "What to choose" section's lines."""
    n_big = max(cfg.num_agents)
    return [
        *(_recommendation(cfg, cells, n_big) or ["- pending: the default field conditions at the largest N are not "
                                                 "computed yet."]),
        *(_recommendation(cfg, cells, n_big, "field_correlated") if "field_correlated" in cfg.axes else []),
        *_fix_advice(cfg, cells),
        "",
        "Under one fault, pushed further (from the axes below; controllers that do not perceive a fault, n/a in the "
        "tables, are not candidates: the centralized QP for messages, the dCBF-QP for LiDAR, whose obstacles come "
        "from the map; a controller holds a level when it is 99 % safe there and at every milder level):",
        "",
        *(_axis_choices(cfg, cells) or ["- pending: no axis is computed for every controller yet."]),
    ]  # fmt: skip


def headline(cfg: RobustnessConfig, cells: dict) -> str | None:
    """One sentence for the pages that quote the report (the README): the pick at the default field conditions at
    the largest N in each obstacle setting, its safe rate with the change against the fault-free run (paired 95 %
    CI), and its safe rate with the agents' fixes on (``field_fixes``, where planned and computed); ``None`` while
    a pick is pending."""
    n, field = max(cfg.num_agents), axis("field").specs()[1]
    fixed = axis("field_fixes") if "field_fixes" in cfg.axes else None
    parts = []
    for k in (0, cfg.obstacles):
        choice = recommended(cfg, cells, n, k)
        if choice is None:
            return None
        pick, row, _ = choice
        clean = cells.get((pick, "none", n, k))
        change = "" if clean is None else f", {paired_change(clean, row)} points against the fault-free run"
        with_fix = cells.get((pick, fixed.specs()[1], n, k)) if fixed else None
        fix = "" if with_fix is None else f"; {pct(with_fix, 'safe_rate')} % with the agents' fixes on"
        parts.append(f"{k} obstacles: **{LABELS.get(pick, pick)}**, {pct(row, 'safe_rate')} % safe{change}{fix}")
    fixes = f" (the fixes: `{fixed.handling()}`)" if fixed else ""
    return (f"under the default field conditions (`--faults default`: `{field}`), N = {n}, l = {cfg.area:g}, the "
            f"controller to choose: " + "; ".join(parts) + f"{fixes}; {cfg.episodes} episodes per cell, evaluation "
            f"seed {cfg.seed}, paired 95 % CIs.")  # fmt: skip
