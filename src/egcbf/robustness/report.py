"""docs/robustness.md from the committed cells of ``egcbf robustness``: the faults and their units, the default
field conditions against the perfect world (with paired 95 % intervals), the agent-side fixes
(:mod:`~egcbf.robustness.fixes`), which controller to choose (:mod:`~egcbf.robustness.advice`), the level where
each controller drops below 99 % and 95 % safe, one figure per fault axis (:mod:`~egcbf.robustness.figures`),
and where the cells were computed. Only what is computed is drawn or written; missing cells are named. The README
beside the report's folder quotes the pick at the default field conditions in its ``robustness-headline`` block,
rewritten with the report."""

from __future__ import annotations

from pathlib import Path

from ..faults import parse_faults
from ..io.atomic import write_text_atomic
from ..io.report import quote_section, relative_link
from ..reproduce.paper import LABELS
from .advice import advice, headline
from .cells import before_after, code_list, computed_where, load_records, rate_band, stale_records, stored_cell
from .figures import axis_figure
from .fixes import fix_rows, fix_sections
from .plan import CORRELATED, RobustnessConfig, axis

__all__ = ["write_report"]

THRESHOLDS = (0.99, 0.95)

#: the fault reference of the report: (field, spec alias, unit, where it acts)
_FAULTS_TABLE = (
    ("pos_noise", "pos", "m (std per axis)", "each agent's position estimate, fresh every step (also broadcast)"),
    ("vel_noise", "vel", "m/s (std per axis)", "each agent's velocity estimate, likewise"),
    ("noise_tau", "", "s", "not a level, the estimation errors' memory: 0 white, else a Gauss-Markov process with this "
     "time constant and the same std"),
    ("lidar_noise", "lidar", "m (std)", "each LiDAR ray's range (cast from the true pose, placed around the estimate)"),
    ("lidar_drop", "", "probability", "each LiDAR ray's return lost, each step, before the closest are kept"),
    ("msg_loss", "loss", "probability", "each directed message (receiver <- sender) lost, each step"),
    ("msg_burst", "burst", "control steps", "not a level, how losses come: 0 independent, else each link loses whole "
     "blocks of this many steps (the same rate, in runs)"),
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
    ("noncoop", "", "fraction", "agents that ignore their controller and fly on their autopilot (true state; "
     "noncoop_mode: hover in place, or fly straight to their goal at the nominal cruise speed as if alone, then hover "
     "there); they still broadcast; the metrics count the others"),
)  # fmt: skip


def _field_table(cfg: RobustnessConfig, cells: dict) -> list[str]:
    spec = axis("field").specs()[1]
    lines = ["| controller | N | obstacles | safe % (none) | safe % (default) | change, points [95 % CI] | "
             "success % (none) | success % (default) | faults it sees |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for m in cfg.controllers:
        for n in cfg.num_agents:
            for k in (0, cfg.obstacles):
                sees, unseen = cfg.cell_spec(m, spec), code_list(cfg.unperceived(m, spec))
                note = "all" if sees == spec else "none" if sees is None else f"not {unseen} (`{sees}`)"
                pair = before_after(cells.get((m, "none", n, k)), cells.get((m, spec, n, k)))
                lines.append(f"| {LABELS.get(m, m)} | {n} | {k} | {pair} | {note} |")
    return lines


def _correlated_section(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The default field conditions with their errors correlated in time and their losses in bursts, against the
    same conditions drawn white and independent (every controller; paired over the same scenes)."""
    if "field_correlated" not in cfg.axes:
        return []
    before, after = axis("field").specs()[1], axis("field_correlated").specs()[1]
    shaped = parse_faults(CORRELATED)
    return [
        "Every random fault of the axes is drawn afresh each step and link (white estimation noise, independent "
        "losses). A real estimator's errors are correlated in time and a radio loses messages in bursts; the "
        f"`field_correlated` axis is the default field conditions so shaped (`{CORRELATED}`: each estimation "
        f"error a Gauss-Markov process with a {shaped.noise_tau:g} s time constant and the same std, each link "
        f"losing whole blocks of {shaped.msg_burst} steps, the same rate; `egcbf.faults.FaultConfig`), against the "
        "same levels drawn white (the same scenes; after minus before):",
        "",
        *fix_rows(cfg, cells, before, after, "default", "correlated and bursty"),
        "",
        *_correlated_fix(cfg, cells),
    ]


def _correlated_fix(cfg: RobustnessConfig, cells: dict) -> list[str]:
    """The receivers' fix (hold and predict) under the correlated and bursty default field conditions, for every
    controller that reads messages (``field_correlated_receivers``; paired over the same scenes)."""
    fix = axis("field_correlated_receivers")
    if fix.name not in cfg.axes:
        return []
    before, after = fix.compared()
    return [
        f"A burst outlasts a single lost message; the receivers' fix (`{fix.handling()}`, section \"Fixes: what the "
        'receivers do about lost and late messages") against the same correlated and bursty conditions without it:',
        "",
        *fix_rows(cfg, cells, before, after, "correlated and bursty"),
        "",
    ]


def _breaking_levels(cfg: RobustnessConfig, cells: dict, n: int, k: int) -> list[str]:
    """Per axis and controller: the first level whose safe rate drops below each threshold ('>' the last level
    when it never does; '?' where a level is missing; '*' where that level's 95 % band over episodes still
    reaches the threshold, so the break is not distinguishable from it)."""
    head = "| axis (unit) | " + " | ".join(LABELS.get(m, m) for m in cfg.controllers) + " |"
    lines = [head, "|---|" + "---|" * len(cfg.controllers)]
    for a in (axis(x) for x in cfg.axes if not x.startswith("field")):
        row = [f"{a.title} ({a.unit})"]
        for m in cfg.controllers:
            if all(cfg.cell_spec(m, spec) is None for spec in a.specs()[1:]):
                row.append("n/a")  # it perceives none of the axis' faults
                continue
            parts = []
            for thr in THRESHOLDS:
                found = None
                for level, spec in zip(a.levels, a.specs()):
                    r = cells.get((m, spec, n, k))
                    if r is None:
                        found = "?" if cfg.cell_spec(m, spec) is not None else "n/a"
                        break
                    if r["safe_rate"] < thr:
                        found = f"{level:g}" + ("*" if rate_band(r, "safe_rate")[1] >= thr else "")
                        break
                parts.append(found or f">{a.levels[-1]:g}")
            row.append(" / ".join(parts))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def _coverage(computed: int, planned: int, stale: int = 0, checkpoints: Path | None = None) -> str:
    """How much of the planned sweep the report stands on (``stale``: cells of an older checkpoint, left out)."""
    old = (f"; {stale} more computed with a checkpoint other than the one now in `{checkpoints}`, left out as stale: "
           "rerun `egcbf robustness` to recompute them") if stale else ""  # fmt: skip
    if computed >= planned:
        return f"all {planned} cells computed"
    return f"{computed} of {planned} cells computed{old}; rerun `egcbf robustness` to compute the rest"


def _provenance(cfg: RobustnessConfig, records: dict) -> list[str]:
    where = computed_where(cfg, records)
    if not where:
        return ["No cell computed yet."]
    return [
        f"Each cell's file records the machine, torch build, device and code version that computed it (`meta`), and "
        f"`{cfg.out / 'sweep.json'}` every invocation of the sweep. Cells computed with different torch builds or "
        "CPUs agree in distribution, not necessarily bit for bit; to recompute a cell on your machine, delete its "
        "file and rerun `egcbf robustness`.",
        "",
        "| cells | computed on |",
        "|---|---|",
        *(f"| {count} | {text} |" for text, count in where),
    ]


def write_report(cfg: RobustnessConfig, path: str | Path = "docs/robustness.md",
                 figures: str | Path = "docs/figures") -> Path:  # fmt: skip
    """Write the report from the cells under ``cfg.out`` (module doc); returns its path."""
    records = load_records(cfg)
    stale = stale_records(cfg, records)
    n_stale = len({stored_cell(cfg, key) for key in stale})
    records = {key: rec for key, rec in records.items() if key not in stale}
    cells = {key: rec["row"] for key, rec in records.items()}
    path, figures = Path(path), Path(figures)
    runs = {(m, cfg.cell_spec(m, s)) for a in (axis(x) for x in cfg.axes) for s in a.specs() for m in cfg.controllers}
    planned = len([r for r in runs if r[1] is not None]) * len(cfg.num_agents) * 2
    computed = len({stored_cell(cfg, key) for key in records})
    lines = [
        "# Robustness to real-world faults",
        "",
        "Generated by `egcbf robustness --report-only` from the cells in "
        f"`{cfg.out}` ({_coverage(computed, planned, n_stale, cfg.checkpoints)}). "
        f"Every cell: {cfg.episodes} episodes on evaluation seed {cfg.seed}, l = {cfg.area:g}, without obstacles "
        f"and with {cfg.obstacles}; the learned controllers are the shipped checkpoints (`{cfg.checkpoints}`, "
        "training seed 0). The faults, their units and where they act are in `egcbf.faults` "
        "(`egcbf eval --faults`); the controller sees corrupted perception and sends corrupted commands, the "
        "metrics read the true states and count the cooperative agents only. Safe: an agent touched no other "
        "agent and no obstacle in the episode; success: safe and at its goal once (docs/metrics.md). Neither "
        "counts an agent that loses its attitude or leaves the arena (it has no walls) as failed, so read a safe "
        "rate with its success rate.",
        "",
        "A controller runs the faults of a level it perceives: the learned policies all of them (filtered or not: "
        "the policy reads the messages and the LiDAR through its graph), the dCBF-QP the messages but not the "
        "LiDAR (its obstacle rows come from the map, as do the dCBF filter's), the centralized CBF-QP and the "
        "nominal controller neither (state-level faults only); a level it perceives nothing of is n/a for it "
        "(`egcbf.faults.sensing.unread_faults`).",
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
        "message one control step (25 ms) late, +-10 % collective thrust gain per agent, 5 % of the agents "
        "hovering in place without cooperating. Why these: 1 cm is a motion-capture-grade estimate (a UWB-aided "
        "one is typically at 5 to 10 cm, which the state-estimate noise axis covers up to "
        f"{axis('sensing').levels[-1]:g} m); a crowded "
        "2.4 GHz mesh loses messages at this rate, and one control period of latency is the least a radio round "
        "adds; a battery's sag and the spread of motors and propellers change the thrust an agent gets for a "
        "command by about 10 % (lumped into one collective gain; a per-motor spread shows mostly as torque error, "
        "`torque_gain` and `torque_bias`, which the default leaves at 0); a swarm in the field always has an agent "
        "whose planner has failed or been told to wait, which holds position on its autopilot (it still "
        "broadcasts its state: the others know of it only through its messages).",

        "",
        "The change is the paired difference (the same scenes, episode by episode) with its bootstrap 95 % "
        f"interval over the {cfg.episodes} episodes (an interval of [+0.00, +0.00] means that no episode "
        "differed, e.g. no collision in either run: not that the rate is known exactly).",
        "",
        *_field_table(cfg, cells),
        "",
        *_correlated_section(cfg, cells),
        *fix_sections(cfg, cells),
        "## What to choose",
        "",
        *advice(cfg, cells),
        "",
        "## Where each controller breaks",
        "",
        "The first level at which the safe rate drops below 99 % / 95 % ('>x': never up to the last level x; "
        "'?': not computed yet; 'n/a': the controller does not perceive this fault; '0': already below it without "
        "faults). These are point estimates over the episodes: '*' marks a level whose 95 % band over episodes still "
        "reaches the threshold: below it in these episodes, but not distinguishably so (e.g. one agent-episode "
        "short of it).",
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
        png = axis_figure(cfg, cells, name, figures / f"robustness_{name}.png")
        lines.append(f"### {a.title}")
        lines.append("")
        lines.append(f"Levels: {', '.join(f'{x:g}' for x in a.levels)} ({a.unit}); specs: "
                     + code_list(a.specs()[1:]) + ".")  # fmt: skip
        lines.append("")
        if png is None:
            lines.append("Not computed yet.")
        else:
            rel = png.relative_to(path.parent) if png.is_relative_to(path.parent) else png
            lines.append(f"![{a.title}]({rel})")
        lines.append("")
    lines += ["## Where the cells were computed", "", *_provenance(cfg, records), ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, "\n".join(lines).rstrip() + "\n")
    _quote_headline(path, cfg, cells)
    return path


def _quote_headline(report: Path, cfg: RobustnessConfig, cells: dict) -> None:
    """Rewrite the ``robustness-headline`` block of the README beside the report's folder (only where it has the
    markers: a report written elsewhere quotes into nothing), so no page restates the result by hand."""
    readme = report.parent.parent / "README.md"
    link = relative_link(report, readme)
    body = headline(cfg, cells) or "pending: the default field conditions are not computed yet for every controller."
    quote_section(readme, "robustness-headline", f"Robustness ([{link}]({link}), generated by `egcbf robustness "
                                                 f"--report-only`): {body}")  # fmt: skip
