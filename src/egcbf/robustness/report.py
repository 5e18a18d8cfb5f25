"""docs/robustness.md from the committed cells of ``egcbf robustness``: the default field conditions against the
perfect world (with paired 95 % intervals), one figure per fault axis (safety and success against the level, one
line per controller, 95 % bands over episodes), the level where each controller drops below 99 % and 95 % safe, and
which controller to choose. Only what is computed is drawn or written; missing cells are named."""

from __future__ import annotations

from pathlib import Path

from ..bootstrap import mean_ci
from ..reproduce.paper import BASELINES, LABELS, base_method
from ..reproduce.plan import Cell
from ..reproduce.store import read_json
from .plan import RECEIVER_HOLD, RobustnessConfig, axis

__all__ = ["load_cells", "write_report"]

COLORS = {"nominal": "tab:gray", "ccbf": "tab:brown", "dcbf": "tab:purple", "gcbf+": "tab:orange",
          "egcbf+": "tab:blue", "egcbf+:dcbf": "tab:green"}  # fmt: skip
THRESHOLDS = (0.99, 0.95)

#: the fault reference of the report: (field, spec alias, unit, where it acts)
_FAULTS_TABLE = (
    ("pos_noise", "pos", "m (std per axis)", "each agent's position estimate, fresh every step (also broadcast)"),
    ("vel_noise", "vel", "m/s (std per axis)", "each agent's velocity estimate, likewise"),
    ("lidar_noise", "lidar", "m (std)", "each LiDAR range (rays cast from the true pose, placed around the estimate)"),
    ("lidar_drop", "", "probability", "each LiDAR return lost, each step"),
    ("msg_loss", "loss", "probability", "each directed message (receiver <- sender) lost, each step"),
    ("msg_delay", "delay", "control steps", "every message carries the sender's estimate of that many steps ago"),
    ("msg_hold", "hold", "control steps", "not a fault, the receivers' handling: a lost message is replaced by the "
     "link's newest message of that many steps before"),
    ("msg_predict", "predict", "0 or 1", "not a fault, the receivers' handling: each message is moved on at the "
     "velocity it carries over its age"),
    ("gain", "", "+- fraction", "per agent and channel, drawn once per episode: every control channel"),
    ("thrust_gain", "", "+- fraction", "the same on the collective thrust (quadrotor)"),
    ("torque_gain", "", "+- fraction", "the same on the body torques (quadrotor)"),
    ("torque_bias", "", "N m", "a constant body-torque bias per agent and axis, uniform in +-value"),
    ("act_delay", "", "control steps", "every command acts that many steps late (hover commands before)"),
    ("act_predict", "", "0 or 1", "not a fault, the agents' handling: each commands for its state predicted over "
     "the actuation delay (its dynamics, its commands in flight) and broadcasts that prediction"),
    ("dist_obs", "", "0 or 1", "not a fault, the agents' handling: each estimates the acceleration acting on it "
     "beyond its model (its velocity estimates against its model's prediction, low-passed over 0.25 s) and "
     "cancels it in its command (wind, gusts, thrust errors)"),
    ("wind", "", "m/s^2 (a vector)", "a constant world acceleration on every agent (wind force over mass)"),
    ("gust", "", "m/s^2 (std per axis)", "an Ornstein-Uhlenbeck gust per environment (time constant gust_tau, s)"),
    ("noncoop", "", "fraction", "agents that ignore their controller (noncoop_mode: hover in place or fly straight "
     "to their goal); the metrics count the others"),
)  # fmt: skip


def _cell(method: str, spec: str, n: int, obstacles: int) -> Cell:
    return Cell(method, obstacles, n, None if base_method(method) in BASELINES else 0, None, spec)


def load_cells(cfg: RobustnessConfig) -> dict[tuple[str, str, int, int], dict]:
    """``{(method, axis-level spec, N, obstacles): row}`` of every computed cell (the level spec as the axis names it;
    a controller that does not read messages is looked up under the level's state-level spec)."""
    out = {}
    for a in (axis(n) for n in cfg.axes):
        for spec in a.specs():
            for m in cfg.controllers:
                run = cfg.cell_spec(m, spec)
                if run is None:
                    continue
                for n in cfg.num_agents:
                    for k in (0, cfg.obstacles):
                        rec = read_json(_cell(m, run, n, k).path(cfg.out))
                        if isinstance(rec, dict) and "row" in rec:
                            out[(m, spec, n, k)] = rec["row"]
    return out


def _episodes(row: dict, key: str) -> list[float]:
    return list(row.get("per_episode", {}).get(key, [])) or [row[key]]


def _pct(row: dict | None, key: str) -> str:
    return "-" if row is None else f"{100 * row[key]:.2f}"


def _loss_text(clean: dict, faulty: dict) -> str:
    """Safe-rate change (points) with its paired 95 % interval (the same scenes, episode by episode)."""
    a, b = _episodes(faulty, "safe_rate"), _episodes(clean, "safe_rate")
    if len(a) != len(b) or len(a) < 2:
        return f"{100 * (faulty['safe_rate'] - clean['safe_rate']):+.2f}"
    return mean_ci([[x - y for x, y in zip(a, b)]], resamples=2000).text(100, 2)


def _before_after(before: dict | None, after: dict | None) -> str:
    """The table cells ``safe before | safe after | change [95 % CI] | success before | success after``."""
    change = "-" if before is None or after is None else _loss_text(before, after)
    return (f"{_pct(before, 'safe_rate')} | {_pct(after, 'safe_rate')} | {change} | {_pct(before, 'success_rate')} | "
            f"{_pct(after, 'success_rate')}")  # fmt: skip


def _field_table(cfg: RobustnessConfig, cells: dict) -> list[str]:
    spec = axis("field").specs()[1]
    lines = ["| controller | N | obstacles | safe % (none) | safe % (default) | change, points [95 % CI] | "
             "success % (none) | success % (default) | faults it sees |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in cfg.controllers:
        for n in cfg.num_agents:
            for k in (0, cfg.obstacles):
                sees = cfg.cell_spec(m, spec)
                note = "all" if sees == spec else f"state-level only (`{sees}`)"
                pair = _before_after(cells.get((m, "none", n, k)), cells.get((m, spec, n, k)))
                lines.append(f"| {LABELS.get(m, m)} | {n} | {k} | {pair} | {note} |")
    return lines


def _fix_rows(cfg: RobustnessConfig, cells: dict, before: str, after: str, what: str) -> list[str]:
    """The table of a fix: every controller the fix reaches, level ``before`` against ``after`` (the same level
    with the fix; paired over the same scenes), ``what`` naming the level in the header."""
    lines = [
        f"| controller | N | obstacles | safe % ({what}) | safe % ({what}, with the fix) | change, points "
        f"[95 % CI] | success % ({what}) | success % (with the fix) |",
        "|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for m in cfg.controllers:
        if cfg.cell_spec(m, after) == cfg.cell_spec(m, before):
            continue  # perceives none of what the fix handles: it changes nothing for it
        for n in cfg.num_agents:
            for k in (0, cfg.obstacles):
                pair = _before_after(cells.get((m, before, n, k)), cells.get((m, after, n, k)))
                lines.append(f"| {LABELS.get(m, m)} | {n} | {k} | {pair} |")
    return lines


def _receivers_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of the message faults (issue 27, item 4): the default field conditions with the receivers holding a
    lost neighbour's last message and predicting every message over its age, against the same conditions without,
    for every controller that reads messages (paired over the same scenes)."""
    if "field_receivers" not in cfg.axes or "field" not in cfg.axes:
        return []
    before, after = axis("field").specs()[1], axis("field_receivers").specs()[1]
    return [
        "## Fixes: what the receivers do about lost and late messages",
        "",
        "A lost message removes a neighbour from the receiver's graph (and from its QP rows) for that step, and a "
        "late one shows it where it was. Neither needs a new controller: each receiver can keep using a "
        f"neighbour's last message for a few steps (`msg_hold`, here {RECEIVER_HOLD} steps) and move every "
        "message on at the velocity it carries over its age (`msg_predict`: constant-velocity dead reckoning, "
        "`p + v age dt`). The receivers' axes (`field_receivers`, `loss_receivers`, "
        "`delay_receivers`) repeat the message axes with both; the table is the default field conditions without "
        "and with them (the same scenes; the change is the paired difference, after minus before).",
        "",
        *_fix_rows(cfg, cells, before, after, "default"),
        "",
    ]  # fmt: skip


def _actuation_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of actuation delay (issue 27, item 4): two steps of delay with every agent commanding for its state
    predicted over the delay, against the same delay without (every controller; paired over the same scenes)."""
    if "act_delay" not in cfg.axes or "act_delay_predict" not in cfg.axes:
        return []
    before, after = axis("act_delay").specs()[2], axis("act_delay_predict").specs()[2]
    return [
        "## Fixes: commanding for the state the command will act on",
        "",
        "A command that acts `act_delay` control steps late was computed for a state the agent has left: the "
        "attitude loop then fights its own past commands (the actuation-delay figure below shows where each "
        "controller breaks). The agent knows its delay and the commands it has sent, so it can roll its estimate "
        "forward through its own dynamics over them and command for that predicted state (`act_predict`: a Smith "
        "predictor; it knows neither gain errors nor wind; it broadcasts the prediction, so the whole swarm acts "
        "on the same future). The `act_delay_predict` axis repeats the actuation-delay axis with it; the table "
        "is two steps of delay without and with it (the same scenes; after minus before). With the delay the only "
        "fault the prediction is exact, so this axis is the fix's ceiling; under noise, gain errors or wind as well "
        "it is approximate (`egcbf eval --faults default,act_delay=2,act_predict=1` measures that case).",
        "",
        *_fix_rows(cfg, cells, before, after, f"`{before}`"),
        "",
    ]  # fmt: skip


def _disturbance_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The fix of wind and thrust gain errors (issue 27, item 4): 1 m/s^2 of wind and +-30 % thrust gain with every
    agent's disturbance observer, against the same faults without (every controller; paired over the same
    scenes)."""
    tables = []
    for name, level in (("wind", 2), ("thrust", 4)):
        if name in cfg.axes and f"{name}_observer" in cfg.axes:
            before, after = axis(name).specs()[level], axis(f"{name}_observer").specs()[level]
            tables += [*_fix_rows(cfg, cells, before, after, f"`{before}`"), ""]
    if not tables:
        return []
    if "field" in cfg.axes and "field_fixes" in cfg.axes:
        before, after = axis("field").specs()[1], axis("field_fixes").specs()[1]
        tables += [
            "The default field conditions' fixes at once (the receivers' hold and prediction, and the disturbance "
            "observer against their +-10 % thrust), against the same conditions without (`field_fixes`; the "
            "observer differentiates noisy velocity estimates, so this is where it could cost safety):",
            "",
            *_fix_rows(cfg, cells, before, after, "default"),
            "",
        ]  # fmt: skip
    return [
        "## Fixes: cancelling the wind and the thrust errors",
        "",
        "Wind and a thrust gain error leave every controller safe but slow: each controller's position loop is "
        "proportional, so a steady push leaves a steady offset, and an agent held off its goal by more than the "
        "goal radius never arrives (the wind and thrust figures below). The agent can measure what pushes it: "
        "its velocity estimate against what its own model predicts from its previous estimate under the command "
        "it knows acted, low-passed over 0.25 s, is the acceleration acting on it beyond its model; it then "
        "cancels that in its command (`dist_obs`: a disturbance observer; `Robot.reject_disturbance` turns the "
        "quadrotor's thrust vector by `-m d`, the attitude loop's own answer to the lowered target, to first "
        "order). The `wind_observer` and `thrust_observer` axes repeat those axes with it; the tables are 1 m/s^2 "
        "of wind (with gusts of half that) and +-30 % thrust gain, without and with it (the same scenes; after "
        "minus before). It reads velocity estimates, so sensing noise enters it (about `vel_noise / 0.25 s`: "
        "0.08 m/s^2 at the default field's 2 cm/s).",
        "",
        *tables,
    ]  # fmt: skip


def _breaking_levels(cfg: RobustnessConfig, cells: dict, n: int, k: int) -> list[str]:
    """Per axis and controller: the first level whose safe rate drops below each threshold ('>' the last level
    when it never does; '?' where a level is missing)."""
    head = "| axis (unit) | " + " | ".join(LABELS.get(m, m) for m in cfg.controllers) + " |"
    lines = [head, "|---|" + "---|" * len(cfg.controllers)]
    for a in (axis(x) for x in cfg.axes if not x.startswith("field")):
        row = [f"{a.title} ({a.unit})"]
        for m in cfg.controllers:
            parts = []
            for thr in THRESHOLDS:
                found = None
                for level, spec in zip(a.levels, a.specs()):
                    r = cells.get((m, spec, n, k))
                    if r is None:
                        found = "?" if cfg.cell_spec(m, spec) is not None else "n/a"
                        break
                    if r["safe_rate"] < thr:
                        found = f"{level:g}"
                        break
                parts.append(found or f">{a.levels[-1]:g}")
            row.append(" / ".join(parts))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def _axis_figure(cfg: RobustnessConfig, cells: dict, name: str, out_png: Path) -> Path | None:
    """Safe and success % against the level (columns: without and with obstacles), one colour per controller, one
    line style per swarm size (the largest solid), 95 % bands over episodes; ``None`` if nothing is drawable."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    a = axis(name)
    specs = a.specs()
    sizes = sorted(cfg.num_agents, reverse=True)
    styles = ("-", "--", ":", "-.")
    fig = Figure(figsize=(8.4, 5.6))
    panels = fig.subplots(2, 2, squeeze=False)
    drawn = False
    for col, k in enumerate((0, cfg.obstacles)):
        for row, key in enumerate(("safe_rate", "success_rate")):
            ax = panels[row][col]
            for m in cfg.controllers:
                for n, style in zip(sizes, styles):
                    xs, mid, lo, hi = [], [], [], []
                    for i, spec in enumerate(specs):  # levels equally spaced: they grow by factors
                        r = cells.get((m, spec, n, k))
                        if r is None:
                            continue
                        values = _episodes(r, key)
                        ci = mean_ci([values], resamples=2000) if len(values) > 1 else None
                        xs.append(i)
                        mid.append(100 * r[key])
                        lo.append(100 * (ci.low if ci else r[key]))
                        hi.append(100 * (ci.high if ci else r[key]))
                    if len(xs) < 2:
                        continue
                    drawn = True
                    ax.plot(xs, mid, marker="o", ls=style, color=COLORS.get(m), ms=3)
                    ax.fill_between(xs, lo, hi, color=COLORS.get(m), alpha=0.12, lw=0)
            ax.set_title(f"{'safe' if key == 'safe_rate' else 'success'} %, {k} obstacles", fontsize=9)
            ax.set_xticks(range(len(a.levels)), [f"{x:g}" for x in a.levels], fontsize=8)
            ax.set_xlabel(a.unit, fontsize=8)
            ax.grid(alpha=0.3)
    if not drawn:
        return None
    handles = [Line2D([], [], color=COLORS.get(m), marker="o", ms=3, label=LABELS.get(m, m)) for m in cfg.controllers]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=7, frameon=False)
    fig.subplots_adjust(bottom=0.16, hspace=0.45)
    sizes_text = ", ".join(f"N = {n} {'solid' if i == 0 else 'dashed' if i == 1 else 'dotted'}"
                           for i, n in enumerate(sizes[:3]))  # fmt: skip
    fig.suptitle(f"{a.title} ({sizes_text})", fontsize=10)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90, bbox_inches="tight")
    return out_png


def _recommendation(cfg: RobustnessConfig, cells: dict, n: int) -> list[str]:
    spec = axis("field").specs()[1]
    lines = []
    for k in (0, cfg.obstacles):
        done = [(cells[(m, spec, n, k)]["safe_rate"], cells[(m, spec, n, k)]["success_rate"], m)
                for m in cfg.controllers if (m, spec, n, k) in cells]  # fmt: skip
        missing = [LABELS.get(m, m) for m in cfg.controllers if (m, spec, n, k) not in cells]
        if missing:  # a choice among some controllers would be no choice: say what is missing
            lines.append(f"- default field conditions, N = {n}, {k} obstacles: pending (not computed yet: "
                         f"{', '.join(missing)}).")  # fmt: skip
            continue
        safe = [d for d in done if d[0] >= 0.99]
        pick = max(safe, key=lambda d: (d[1], d[0])) if safe else max(done)
        why = "the most successful of those >= 99 % safe" if safe else "none reaches 99 % safe; the safest"
        lines.append(f"- default field conditions, N = {n}, {k} obstacles: **{LABELS.get(pick[2], pick[2])}** "
                     f"({100 * pick[0]:.2f} % safe, {100 * pick[1]:.2f} % success; {why}).")  # fmt: skip
    return lines


#: the agents' fixes the report advises on: (what a user has, the handling to turn on, the axis without it and
#: with it, the level compared)
_FIXES = (
    ("lost and late messages", "`hold=5,predict=1`", "field", "field_receivers", 1),
    ("actuation latency", "`act_predict=1`", "act_delay", "act_delay_predict", 2),
    ("wind", "`dist_obs=1`", "wind", "wind_observer", 2),
    ("uneven motors", "`dist_obs=1`", "thrust", "thrust_observer", 4),
)


#: the fault axes proper (not the fixes' repeats), in the order the advice names them, with the agents' fix of each
_FAULT_AXES = {"sensing": None, "loss": "`hold=5,predict=1`", "delay": "`predict=1`", "lidar": None,
               "thrust": "`dist_obs=1`", "act_delay": "`act_predict=1`", "wind": "`dist_obs=1`", "noncoop": None,
               "noncoop_straight": None}  # fmt: skip


def _axis_choices(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """Per fault axis, at the largest N computed for every controller and level: the most severe level some
    controller keeps >= 99 % safe (the worse of without and with obstacles), and the most successful of those
    there. Controllers that do not perceive the axis' faults (n/a) are not candidates."""
    lines = []
    for a in (axis(x) for x in cfg.axes if x in _FAULT_AXES):
        specs, obstacles = a.specs(), (0, cfg.obstacles)
        methods = [m for m in cfg.controllers if all(cfg.cell_spec(m, sp) is not None for sp in specs)]
        for n in sorted(cfg.num_agents, reverse=True):
            if not all((m, sp, n, k) in cells for m in methods for sp in specs for k in obstacles):
                continue
            worst = {(m, i): tuple(min(cells[(m, sp, n, k)][key] for k in obstacles)
                                   for key in ("safe_rate", "success_rate"))
                     for m in methods for i, sp in enumerate(specs)}  # fmt: skip
            fix = f" The agents' fix: {_FAULT_AXES[a.name]}." if _FAULT_AXES[a.name] else ""
            kept = [i for i in range(len(specs)) if any(worst[(m, i)][0] >= 0.99 for m in methods)]
            names = ", ".join(LABELS.get(m, m) for m in methods)
            if 0 not in kept:
                lines.append(f"- {a.title}: none of the controllers that perceive it ({names}) is 99 % safe even "
                             f"without it (N = {n}, the worse of {obstacles[0]} and {obstacles[1]} "
                             f"obstacles).{fix}")  # fmt: skip
                break
            i = max(kept)
            pick = max((m for m in methods if worst[(m, i)][0] >= 0.99), key=lambda m: worst[(m, i)][::-1])
            safe, success = worst[(pick, i)]
            if i == 0:
                lines.append(
                    f"- {a.title}: every controller drops below 99 % safe at {a.levels[1]:g} ({a.unit}) "
                    f"already (N = {n}, the worse of {obstacles[0]} and {obstacles[1]} obstacles).{fix}"
                )
                break  # fmt: skip
            beyond = "" if i == len(specs) - 1 else "; beyond it no controller stays 99 % safe"
            lines.append(f"- {a.title}, up to {a.levels[i]:g} ({a.unit}): **{LABELS.get(pick, pick)}** "
                         f"({100 * safe:.2f} % safe, {100 * success:.2f} % success there, N = {n}, the worse of "
                         f"{obstacles[0]} and {obstacles[1]} obstacles{beyond}).{fix}")  # fmt: skip
            break
    return lines


def _fix_advice(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """One line per fix of :data:`_FIXES`: the recommended controller (the largest N's pick without obstacles)
    without and with it, at the largest N where both cells are computed, or pending."""
    n_big = max(cfg.num_agents)
    spec = axis("field").specs()[1]
    done = [(cells[(m, spec, n_big, 0)]["safe_rate"], cells[(m, spec, n_big, 0)]["success_rate"], m)
            for m in cfg.controllers if (m, spec, n_big, 0) in cells]  # fmt: skip
    if len(done) < len(cfg.controllers):
        return []
    safe = [d for d in done if d[0] >= 0.99]
    pick = (max(safe, key=lambda d: (d[1], d[0])) if safe else max(done))[2]
    lines = []
    for what, handling, name, fixed, level in _FIXES:
        if name not in cfg.axes or fixed not in cfg.axes:
            continue
        before, after = axis(name).specs()[level], axis(fixed).specs()[level]
        runs = (cfg.cell_spec(pick, before), cfg.cell_spec(pick, after))
        pairs = [(n, k) for n in sorted(cfg.num_agents, reverse=True) for k in (0, cfg.obstacles)
                 if all((pick, r, n, k) in cells for r in runs)]  # fmt: skip
        if not pairs:
            lines.append(f"- with {what}: turn on {handling} (measured for {LABELS.get(pick, pick)}: pending).")
            continue
        n, k = pairs[0]
        b, f = cells[(pick, runs[0], n, k)], cells[(pick, runs[1], n, k)]
        where = "the default field conditions" if name == "field" else f"`{before}`"
        lines.append(f"- with {what}: turn on {handling}. {LABELS.get(pick, pick)} at {where}, N = {n}, {k} "
                     f"obstacles: {_pct(b, 'safe_rate')} -> {_pct(f, 'safe_rate')} % safe, "
                     f"{_pct(b, 'success_rate')} -> {_pct(f, 'success_rate')} % success.")  # fmt: skip
    return lines


def write_report(cfg: RobustnessConfig, path: str | Path = "docs/robustness.md",
                 figures: str | Path = "docs/figures") -> Path:  # fmt: skip
    """Write the report from the cells under ``cfg.out`` (module doc); returns its path."""
    cells = load_cells(cfg)
    path, figures = Path(path), Path(figures)
    n_big = max(cfg.num_agents)
    runs = {(m, cfg.cell_spec(m, s)) for a in (axis(x) for x in cfg.axes) for s in a.specs() for m in cfg.controllers}
    planned = len([r for r in runs if r[1] is not None]) * len(cfg.num_agents) * 2
    computed = len({(m, cfg.cell_spec(m, s), n, k) for (m, s, n, k) in cells})
    lines = [
        "# Robustness to real-world faults",
        "",
        "Generated by `egcbf robustness --report-only` from the cells in "
        f"`{cfg.out}` ({computed} of {planned} cells computed; rerun `egcbf robustness` to compute the rest). "
        f"Every cell: {cfg.episodes} episodes on evaluation seed {cfg.seed}, l = {cfg.area:g}, without obstacles "
        f"and with {cfg.obstacles}; the learned controllers are the shipped checkpoints (`{cfg.checkpoints}`, "
        "training seed 0). The faults, their units and where they act are in `egcbf.faults` "
        "(`egcbf eval --faults`); the controller sees corrupted perception and sends corrupted commands, the "
        "metrics read the true states and count the cooperative agents only.",
        "",
        "A controller runs the faults of a level it perceives: the learned policies all of them, the dCBF-QP (alone "
        "or as a filter) the messages but not the LiDAR (its obstacle rows come from the map), the centralized "
        "CBF-QP and the nominal controller neither (state-level faults only); a level it perceives nothing of is "
        "n/a for it (`egcbf.faults.sensing.unread_faults`).",
        "",
        "## The faults",
        "",
        "`egcbf eval --faults SPEC` (and `egcbf robustness`) takes `none`, `default`, comma-separated `key=value` "
        "pairs (after `default` they override it: `default,loss=0.3`; vectors `/`-separated: `wind=1/0/0`) or a "
        "JSON file of these fields (`egcbf.faults.FaultConfig`). Every draw is a pure function of the episode seed, "
        "the step and the agents it concerns, so a result does not depend on batching; a zero level is the perfect "
        "world bit for bit (tests/egcbf/test_faults.py).",
        "",
        "| field | short | unit | acts on |",
        "|---|---|---|---|",
        *(f"| `{f}` | {('`' + a + '`') if a else ''} | {u} | {w} |" for f, a, u, w in _FAULTS_TABLE),
        "",
        "## Default field conditions",
        "",
        "`--faults default`: 1 cm position and 2 cm/s velocity estimation noise, 10 % of messages lost, every "
        "message one control step (25 ms) late, +-10 % thrust gain per motor set, 5 % of the agents hovering in "
        "place without cooperating. Why these: a motion-capture or UWB-aided estimator is good to about a "
        "centimetre, a crowded 2.4 GHz mesh loses messages at this rate, one control period of latency is the "
        "least a radio round adds, and motor and propeller spread is about 10 %; a swarm in the field always has "
        "an agent that lost its link or its estimator and holds position.",
        "",
        "The change is the paired difference (the same scenes, episode by episode) with its bootstrap 95 % "
        "interval.",
        "",
        *_field_table(cfg, cells),
        "",
        *_receivers_section(cfg, cells),
        *_actuation_section(cfg, cells),
        *_disturbance_section(cfg, cells),
        "## What to choose",
        "",
        *(_recommendation(cfg, cells, n_big) or ["- pending: the default field conditions at the largest N are not "
                                                 "computed yet."]),
        *_fix_advice(cfg, cells),
        "",
        "Under one fault, pushed further (from the axes below; controllers that do not perceive a fault, n/a in the "
        "tables, are not candidates: the centralized QP for messages, the dCBF-QP for LiDAR, whose obstacles come "
        "from the map):",
        "",
        *(_axis_choices(cfg, cells) or ["- pending: no axis is computed for every controller yet."]),
        "",
        "## Where each controller breaks",
        "",
        "The first level at which the safe rate drops below 99 % / 95 % ('>x': never up to the last level x; "
        "'?': not computed yet; 'n/a': the controller does not perceive this fault; '0': already below it without "
        "faults).",
        "",
    ]  # fmt: skip
    for n in sorted(cfg.num_agents, reverse=True):
        for k in (0, cfg.obstacles):
            lines += [f"**N = {n}, {k} obstacles**", "", *_breaking_levels(cfg, cells, n, k), ""]
    lines += ["## Each fault axis", ""]
    for name in cfg.axes:
        if name.startswith("field"):
            continue
        a = axis(name)
        png = _axis_figure(cfg, cells, name, figures / f"robustness_{name}.png")
        lines.append(f"### {a.title}")
        lines.append("")
        lines.append(f"Levels: {', '.join(f'{x:g}' for x in a.levels)} ({a.unit}); specs: "
                     + ", ".join(f"`{s}`" for s in a.specs()[1:]) + ".")  # fmt: skip
        lines.append("")
        if png is None:
            lines.append("Not computed yet.")
        else:
            rel = png.relative_to(path.parent) if png.is_relative_to(path.parent) else png
            lines.append(f"![{a.title}]({rel})")
        lines.append("")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path
