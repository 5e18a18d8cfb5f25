"""Where the report's numbers come from: the sweep's invocations, machines, wall times and checkpoints, how the
``step ms`` column was timed, and the command that regenerates the report.

Everything here is read from the cell files (their ``meta``), ``OUT/sweep.json`` (one entry per invocation:
command, start, wall time, status, backend, workers, threads per cell, counts) and, where present, the checkpoints
under ``cfg.checkpoints``; the report is written without checkpoints too (``--report-only``).

A computed cell is attributed to the invocation that ran it when its ``finished`` time lies within that invocation's
recorded span (``started`` to ``started + wall_s``); cells of invocations from before ``sweep.json`` existed, or of
another results directory, are attributed to none and said to be so.
"""

from __future__ import annotations

import datetime
import json
import shlex
from collections import Counter
from pathlib import Path

from ..io.report import md_table
from ..robots.quadrotor.dynamics import DEFAULT_DT, DEFAULT_MAX_STEPS
from .paper import LABELS, METHODS
from .plan import Cell, SweepConfig
from .stats import episodes_text, scale_text
from .store import current_sha256, read_invocations

__all__ = ["cell_invocations", "machine_text", "provenance_markdown", "regenerate_command", "timing_text"]

#: slack (s) on an invocation's recorded span: ``finished`` and ``started`` are whole seconds
_SLACK_S = 2.0


# ---------------------------------------------------------------------------------------------------- helpers
def _duration(seconds: float) -> str:
    """``3.25 h``, ``12.5 min`` or ``40 s``."""
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _time(text) -> datetime.datetime | None:
    try:
        t = datetime.datetime.fromisoformat(str(text))
    except ValueError:
        return None
    return t if t.tzinfo else t.replace(tzinfo=datetime.timezone.utc)


def _imported(rec: dict) -> bool:
    return bool(rec.get("meta", {}).get("imported_from"))


def cell_invocations(records: dict[Cell, dict], invocations: list[dict]) -> dict[Cell, int | None]:
    """For every computed cell, the index in ``invocations`` of the invocation that ran it (module doc), or
    ``None`` when no recorded invocation spans its ``finished`` time."""
    spans = []
    for i, inv in enumerate(invocations):
        start = _time(inv.get("started"))
        if start is not None:
            end = start + datetime.timedelta(seconds=float(inv.get("wall_s") or 0.0) + _SLACK_S)
            spans.append((start, end, i))
    owners = {}
    for cell, rec in records.items():
        if _imported(rec):
            continue
        done = _time(rec.get("meta", {}).get("finished"))
        inside = [(s, i) for s, e, i in spans if done is not None and s <= done <= e]
        owners[cell] = max(inside)[1] if inside else None  # the latest one to start, should two overlap
    return owners


def _at_a_time(inv: dict | None) -> str:
    """How many cells an invocation ran at once, in words."""
    if inv is None:
        return "cells at a time not recorded"
    if inv.get("backend") == "ray":
        return "as Ray tasks"
    workers = int(inv.get("workers") or 1)
    return "one cell at a time" if workers == 1 else f"up to {workers} cells at a time"


def machine_text(machine: dict | None) -> str:
    """A cell's recorded machine in words: ``CPU model (K cores)``."""
    machine = machine or {}
    cores = f" ({machine['cores']} cores)" if machine.get("cores") else ""
    return f"{machine.get('cpu') or 'an unrecorded machine'}{cores}"


def _threads(machine: dict | None, each: str = "") -> str:
    """``1 torch thread`` (plus `` per cell`` with ``each``), or that the count was not recorded."""
    threads = (machine or {}).get("threads")
    if threads is None:
        return "torch threads not recorded"
    return f"{threads} torch thread{'s' * (threads != 1)}{each}"


# ---------------------------------------------------------------------------------------------------- timing
def timing_text(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """Where and how the ``step ms`` of the cells were measured, from their meta and ``OUT/sweep.json``: the
    computed cells per machine, torch threads per cell and cells at a time; the imported cells (marked ``†`` in the
    tables) per machine, timed by the ``egcbf eval`` run they come from."""
    invocations = read_invocations(cfg.out)
    owners = cell_invocations(records, invocations)
    computed, imported = Counter(), Counter()
    for cell, rec in records.items():
        meta = rec.get("meta", {})
        machine = meta.get("machine")
        if _imported(rec):
            imported[f"{machine_text(machine)}, {_threads(machine)}"] += 1
            continue
        owner = owners.get(cell)
        device = meta.get("device") or "cpu"
        where = machine_text(machine) + ("" if device == "cpu" else f", device {device}")
        computed[f"{where}, {_threads(machine, ' per cell')}, "
                 f"{_at_a_time(None if owner is None else invocations[owner])}"] += 1  # fmt: skip
    parts = []
    if computed:
        parts.append(
            "Computed cells: " + "; ".join(f"{k} on {w}" for w, k in sorted(computed.items(), key=lambda p: -p[1]))
        )
    if imported:
        parts.append(
            "† imported cells, timed by the `egcbf eval` run they come from (one process, one N at a time): "
            + "; ".join(f"{k} on {w}" for w, k in sorted(imported.items(), key=lambda p: -p[1]))
        )
    return ". ".join(parts) + "." if parts else ""


# ---------------------------------------------------------------------------------------------------- regenerating
#: the fields of :class:`SweepConfig` that decide which cells ``--report-only`` reads and what the report shows,
#: with their ``egcbf reproduce`` flags (``workers``, ``backend``, ``baselines`` and ``threads`` do not matter there)
_FLAGS = (
    ("methods", "--methods"),
    ("num_agents", "--num-agents"),
    ("area", "--area"),
    ("obstacles", "--obstacles"),
    ("obstacle_methods", "--obstacle-methods"),
    ("episodes", "--episodes"),
    ("baseline_episodes", "--baseline-episodes"),
    ("train_seeds", "--train-seeds"),
    ("seed_methods", "--seed-methods"),
    ("scale_sizes", "--scale-sizes"),
    ("scale_methods", "--scale-methods"),
    ("scale_agent_episodes", "--scale-agent-episodes"),
    ("long_steps", "--long-steps"),
    ("long_methods", "--long-methods"),
    ("seed", "--seed"),
    ("max_steps", "--max-steps"),
    ("checkpoints", "--checkpoints"),
    ("device", "--device"),
)
#: fields that change the cells read but have no flag
_NO_FLAG = ("scale_reference",)


def _flag_value(name: str, value) -> str:
    if value is None and name == "long_steps":
        return "none"
    if isinstance(value, tuple | list):
        return ",".join(str(v) for v in value) if value else ("none" if name == "scale_sizes" else "")
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def regenerate_command(cfg: SweepConfig, report: str | Path) -> str:
    """The ``egcbf reproduce ... --report-only`` command that rewrites ``report`` from ``cfg.out``'s cells: ``--out``
    and ``--report`` as given, and every flag whose value differs from the default (quoted for a POSIX shell)."""
    default = SweepConfig()
    args = ["egcbf", "reproduce", "--out", str(cfg.out), "--report", str(report)]
    for name, flag in _FLAGS:
        value = _flag_value(name, getattr(cfg, name))
        if value != _flag_value(name, getattr(default, name)) and (getattr(cfg, name) is not None or value == "none"):
            args += [flag, value]
    return shlex.join([*args, "--report-only"])


def regenerate_caveat(cfg: SweepConfig) -> str:
    """``""``, or a sentence naming the settings of ``cfg`` that :func:`regenerate_command` cannot express."""
    default = SweepConfig()
    odd = [f"{n} = {getattr(cfg, n)}" for n in _NO_FLAG if getattr(cfg, n) != getattr(default, n)]
    if not odd:
        return ""
    return f"The sweep also set {', '.join(odd)}, which has no flag: regenerate from Python with `write_report`."


# ---------------------------------------------------------------------------------------------------- provenance
def _cell(text) -> str:
    """``text`` safe inside a markdown table cell."""
    return str(text).replace("|", "\\|")


def _invocation_table(invocations: list[dict]) -> str:
    rows = []
    for inv in invocations:
        started = _time(inv.get("started"))
        threads = inv.get("threads_per_cell")
        at_once = _at_a_time(inv) + ("" if threads is None else f", {threads} torch thread(s) per cell")
        rows.append(
            [
                "-" if started is None else started.strftime("%Y-%m-%d %H:%M"),
                f"`{_cell(inv.get('command') or '(not recorded)')}`",
                str(inv.get("status", "finished")),
                _duration(float(inv.get("wall_s") or 0.0)),
                at_once,
                " / ".join(str(inv.get(k, "?")) for k in ("reused", "imported", "computed"))
                + (f" ({inv['failed']} failed)" if inv.get("failed") else ""),
                f"`{inv['code']}`" if inv.get("code") else "-",
            ]
        )
    head = ["started (UTC)", "command", "status", "wall time", "cells at a time", "reused / imported / computed",
            "code"]  # fmt: skip
    return md_table(head, rows)


def _runs_table(cfg: SweepConfig, records: dict[Cell, dict]) -> tuple[str, int, list[str]]:
    """The table of runs (method, training seed), the number of cells whose checkpoint differs from the current
    one, and the runs whose current checkpoint was not found."""
    by_run: dict[tuple[str, int | None], list[dict]] = {}
    for c, rec in records.items():
        by_run.setdefault((c.method, c.train_seed), []).append(rec)
    order = {m: i for i, m in enumerate(METHODS)}
    rows, stale, missing = [], 0, []
    for (m, s), recs in sorted(by_run.items(), key=lambda kv: (order[kv[0][0]], kv[0][1] or 0)):
        imported = sum(_imported(r) for r in recs)
        wall = sum(float(r["meta"].get("wall_s") or 0.0) for r in recs if not _imported(r))
        paths = sorted({str(r["meta"]["checkpoint"]) for r in recs if r["meta"].get("checkpoint")})
        steps = sorted({r["meta"]["checkpoint_step"] for r in recs if r["meta"].get("checkpoint_step") is not None})
        shas = Counter(r["key"].get("checkpoint_sha256") for r in recs if r["key"].get("checkpoint_sha256"))
        current = current_sha256(cfg.checkpoints, m, s) if shas else None
        if shas and current is None:
            missing.append(f"{LABELS[m]} seed {s}")
        sha_text = []
        for sha, k in shas.most_common():
            flag = current is not None and sha != current
            stale += k if flag else 0
            sha_text.append(f"{sha[:12]} ({k})" + (" **not the current checkpoint**" if flag else ""))
        rows.append(
            [
                LABELS[m],
                "-" if s is None else str(s),
                str(len(recs) - imported),
                str(imported),
                _duration(wall),
                ", ".join(f"`{p}`" for p in paths) or "-",
                ", ".join(str(x) for x in steps) or "-",
                ", ".join(sha_text) or "-",
            ]
        )
    head = ["run", "train seed", "cells computed", "cells imported", "sum of cell wall times", "checkpoint", "step",
            "sha256 of model.safetensors (cells)"]  # fmt: skip
    return md_table(head, rows), stale, missing


def provenance_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """Invocations, settings, machines, wall times and checkpoints behind the report: a table of the sweep's
    recorded invocations (start, command, status, wall time, cells at a time, cells reused / imported / computed),
    then one row per run (method and training seed: cells computed and imported, their summed wall time, the
    checkpoint paths, updates and distinct sha256 with their cell counts, flagged where they differ from the
    checkpoint now under ``cfg.checkpoints``)."""
    invocations = read_invocations(cfg.out)
    lines = [f"Invocations of the sweep into `{cfg.out}` (`sweep.json`, oldest first):", ""]
    lines += [_invocation_table(invocations) if invocations else "(none recorded)", ""]
    lines += [
        f"- Results: `{cfg.out}/<method>[-s<seed>]_obs<k>/N<n>.json` (Table I) and `{cfg.out}/scale/...` "
        "(scalability), one file per cell (metrics row + meta); a method behind a run-time filter, `METHOD:FILTER`, "
        "in `METHOD_FILTER[-s<seed>]_obs<k>/`.",
        f"- Evaluation seed {cfg.seed}; episode e at size N resets from `episode_seed({cfg.seed}, N, e)` "
        f"(`egcbf.evaluate.episodes`); {episodes_text(cfg)}; "
        f"episode length {cfg.max_steps or DEFAULT_MAX_STEPS} steps of "
        f"{1e3 * DEFAULT_DT:g} ms; l = {cfg.area:g} m; obstacle setting: "
        + (f"{cfg.obstacles} obstacles" if cfg.obstacles > 0 else "none")
        + f"; scalability: {scale_text(cfg)}.",
    ]
    filters = Counter(
        json.dumps({k: r["meta"][k] for k in ("filter", "filter_config")}, sort_keys=True)
        for r in records.values()
        if r["meta"].get("filter")
    )
    for text, count in sorted(filters.items()):
        d = json.loads(text)
        settings = ", ".join(f"{k} {v}" for k, v in d["filter_config"].items())
        lines.append(f"- Run-time filter `{d['filter']}` of {count} cell(s): {settings} (as the cells record it, "
                     "like `egcbf eval --filter` in run.json; `docs/safety_filters.md`).")  # fmt: skip
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
    codes = Counter(r["meta"].get("code") for r in records.values() if not _imported(r))
    if codes:
        parts = [f"{n} by `{c}`" for c, n in sorted((c, n) for c, n in codes.items() if c)]
        if codes.get(None):
            parts.append(f"{codes[None]} not recorded (computed before versions were recorded)")
        lines.append("- Code version of the computed cells (`egcbf.io.report.code_version`): " + "; ".join(parts) + ".")
    total = sum(float(i.get("wall_s") or 0.0) for i in invocations)
    status = [i.get("status", "finished") for i in invocations]
    killed = status.count("running") + status.count("interrupted")
    cut = (
        f", {killed} not recorded as finished (still running, or stopped: counted to their last finished cell)"
        if killed
        else ""
    )
    lines.append(
        f"- Sweep wall time: {_duration(total)} over {len(invocations)} recorded invocation(s){cut}; paused time, "
        "if any, is included."
    )
    computed = {c: r for c, r in records.items() if not _imported(r)}
    if computed:
        owners = cell_invocations(computed, invocations)
        cell_wall = sum(float(r["meta"].get("wall_s") or 0.0) for r in computed.values())
        ways = {c: _at_a_time(invocations[i]) for c, i in owners.items() if i is not None}
        parts = []
        for way in sorted(set(ways.values())):
            mine = [c for c, w in ways.items() if w == way]
            wall = sum(float(computed[c]["meta"].get("wall_s") or 0.0) for c in mine)
            workers = {int(invocations[owners[c]].get("workers") or 1) for c in mine}
            machine = (
                f": at least {_duration(wall / max(workers))} of the machine"
                if all(invocations[owners[c]].get("backend") != "ray" for c in mine)
                else ""
            )
            parts.append(f"{len(mine)} in recorded invocations, {way} ({_duration(wall)}{machine})")
        unowned = [c for c, i in owners.items() if i is None]
        if unowned:
            wall = sum(float(computed[c]["meta"].get("wall_s") or 0.0) for c in unowned)
            parts.append(
                f"{len(unowned)} in invocations not in `sweep.json` ({_duration(wall)}; cells at a time unknown)"
            )
        lines.append(
            f"- The {len(computed)} computed cells' own wall times sum to {_duration(cell_wall)}: "
            + "; ".join(parts)
            + "."
        )
    table, stale, missing = _runs_table(cfg, records)
    lines += ["", table]
    if stale:
        lines += [
            "",
            f"**{stale} cell(s) were computed with a checkpoint other than the one now in `{cfg.checkpoints}`** "
            "(marked above); `egcbf reproduce` without `--report-only` recomputes them.",
        ]
    if missing:
        lines += ["", f"No readable checkpoint under `{cfg.checkpoints}` for {', '.join(missing)}: their cells' "
                  "sha256 could not be compared with the current checkpoints."]  # fmt: skip
    imported = sorted({r["meta"]["imported_from"] for r in records.values() if _imported(r)})
    if imported:
        lines += ["", "Imported baseline cells (same `evaluate`, seeds and settings) come from:", ""]
        lines += [f"- `{d}`" for d in imported]
    return "\n".join(lines)
