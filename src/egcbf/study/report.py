"""docs/equivariance.md: the equivariance study's tables, figures, effects with 95 % intervals and verdicts, written
from the result files under ``docs/results/equivariance`` (nothing is computed here).

Each claim's verdict is a rule on its effects (EGCBF(+) minus GCBF(+), :mod:`egcbf.evaluate.bootstrap` intervals):
``supported`` when every effect's interval lies above 0, ``not supported`` when none does (``the world-frame method
is better`` when one lies below 0 and none above), ``mixed`` otherwise, and ``pending`` while a cell it needs is not
computed. The sections between ``<!-- name:begin/end -->`` markers are regenerated; text around them is kept.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from ..evaluate.bootstrap import Interval, difference_ci, mean_ci
from ..io.atomic import write_text_atomic
from ..io.report import md_table, pct, quote_section, relative_link, replace_block
from ..reproduce.paper import LABELS
from .figures import curves_figure, rotated_figure, zero_shot_figure
from .plan import ARMS, ROOT, Arm, arm, rotated_cells
from .results import arm_cells, auc, curve, difference, method_mean, per_episode, rotated_rows, updates_to

__all__ = ["default_quote_targets", "verdict", "write_report"]

_SECTIONS = (
    ("status", "## What is computed"),
    ("generalization", "## Claim 1: zero-shot generalization to larger, denser swarms"),
    ("convergence", "## Claim 2: faster convergence and fewer samples"),
    ("rotated", "## Claim 3: transfer to transformed states (the rotated-world test)"),
    ("ablation", "## Our heads: do they close the gap?"),
)
_PAIRS = (("egcbf+", "gcbf+"), ("egcbf", "gcbf"))


def verdict(effects: list[Interval | None]) -> str:
    """The one-word verdict on a claim from its effects (module doc)."""
    if not effects or any(e is None for e in effects):
        return "pending"
    above = [e.low > 0 for e in effects]
    below = [e.high < 0 for e in effects]
    if all(above):
        return "supported"
    if not any(above):
        return "not supported (the world-frame method is better)" if any(below) else "not supported"
    return "mixed"


def _iv(e: Interval | None, scale: float = 100.0) -> str:
    return "pending" if e is None else e.text(scale)


def _mean(e: Interval | None) -> str:
    return "pending" if e is None else f"{pct(e.estimate)} [{pct(e.low)}, {pct(e.high)}]"


# ------------------------------------------------------------------------------------------------ the sections
def _status(root: Path) -> str:
    rows = []
    for a in ARMS:
        runs = a.all_runs()
        trained = [r for r in runs if (r.checkpoint_dir(root) / "model.safetensors").exists()]
        if a.evaluation == "rotated":
            done = sum(len(rotated_rows(r, root)) for r in trained)
            total = len(runs) * len(rotated_cells())
        else:
            from .driver import sweep_config

            done, total = len(arm_cells(a, root)), len(sweep_config(a, root).cells())
        rows.append([a.name, a.claim, f"`{a.preset}` {a.overrides or ''}", f"{a.minutes:g}",
                     f"{len(trained)} of {len(runs)}", _machines(trained, root), f"{done} of {total}"])  # fmt: skip
    head = ["arm", "tests", "recipe", "CPU minutes per run", "runs trained", "trained on", "cells evaluated"]
    return (
        md_table(head, rows)
        + "\n\nRuns: `egcbf study --arms ARM` (resumable; `--jobs K` runs at a time, one torch thread each). The budget"
        " is the training process's CPU time (`TrainConfig.max_cpu_minutes`), so that runs beside other jobs get "
        "the same compute; each checkpoint's `machine.json` names the machine, and its `metrics.csv` the updates "
        "reached (about 3 s an update on either machine for the paper regime). Evaluation seed 0, 20 episodes per"
        " N at l = 4, the scalability cells at the density of N = 512 with 10 240 agent-episodes each."
    )


def _machines(runs, root: Path) -> str:
    """The CPUs the runs were trained on (their checkpoints' ``machine.json``), e.g. ``"16-core Xeon (8)"``."""
    import json

    count: dict[str, int] = {}
    for r in runs:
        f = r.checkpoint_dir(root) / "machine.json"
        name = "?"
        if f.exists():
            m = json.loads(f.read_text())
            name = f"{m.get('cores', '?')}-core {str(m.get('cpu', '?')).split(' (')[0]}"
        count[name] = count.get(name, 0) + 1
    return ", ".join(f"{k} ({v})" for k, v in count.items()) or "-"


def _pair_effects(a: Arm, cells: dict, n: int, scale: bool) -> list[tuple[str, Interval | None]]:
    out = []
    for e, g in _PAIRS:
        if e in a.algos() and g in a.algos():
            name = f"{LABELS[e]} - {LABELS[g]}"
            if min(len(a.seeds(e)), len(a.seeds(g))) == 1:
                name += " (one training seed each: the interval covers episodes only)"
            out.append((name, difference(cells, e, g, a.seeds(e), a.seeds(g), n, scale)))
    return out


def _generalization(root: Path, figures: Path, report: Path) -> tuple[str, str, str]:
    arms = [arm("paper-cpu"), arm("paper-cpu-mlp")]
    cells = {a.name: arm_cells(a, root) for a in arms}
    lines, effects, evidence = [], [], []
    for a in arms:
        c = cells[a.name]
        head = [
            "method (seeds)",
            *[f"N = {n}" for n in a.table_sizes],
            *[f"N = {n} (fixed density)" for n in a.scale_sizes],
        ]
        rows = []
        for algo in a.algos():
            seeds = a.seeds(algo)
            vals = [_mean(method_mean(c, algo, seeds, n, False, "safe_rate")) for n in a.table_sizes]
            vals += [_mean(method_mean(c, algo, seeds, n, True, "safe_rate")) for n in a.scale_sizes]
            rows.append([f"{LABELS[algo]} ({len(seeds)})", *vals])
        lines += [f"**{a.name}** (safe %, 95 % interval over seeds and episodes):", "", md_table(head, rows), ""]
        points = [(512, False)] + [(n, True) for n in a.scale_sizes if n == 4096]
        for n, sc in points:
            for name, e in _pair_effects(a, c, n, sc):
                lines.append(f"- {a.name}, N = {n}: {name} = {_iv(e)} safe-rate points")
                if name.startswith("EGCBF+"):
                    effects.append(e)
                    evidence.append(f"{_iv(e)} ({a.name}, N = {n})")
        lines.append("")
    if any(cells.values()):
        png = zero_shot_figure(arms, cells, figures / "equivariance_zero_shot.png")
        lines += [f"![zero-shot safety against N]({relative_link(png, report)})", ""]
    v = verdict(effects)
    lines.append(f"**Verdict: {v}** (EGCBF+ minus GCBF+ at N = 512 under both heads, and at N = 4096).")
    return "\n".join(lines), v, "; ".join(evidence)


def _convergence(root: Path, figures: Path, report: Path) -> tuple[str, str, str]:
    arms = [arm("paper-cpu"), arm("paper-cpu-mlp"), arm("low-data")]
    curves = {a.name: [(r, c) for r in a.all_runs() if (c := curve(r, root)) is not None] for a in arms}
    lines, effects, evidence = [], [], []
    rows = []
    for a in arms[:2]:
        got = {(r.algo, r.seed): c for r, c in curves[a.name]}
        upto = min((c["step"][-1] for c in got.values()), default=None)
        for e, g in _PAIRS:
            se, sg = a.seeds(e), a.seeds(g)
            if not all((e, s) in got for s in se) or not all((g, s) in got for s in sg):
                rows.append([a.name, f"{LABELS[e]} - {LABELS[g]}", "pending", "pending", "pending"])
                if e == "egcbf+":
                    effects.append(None)
                continue
            ae = [[auc(got[(e, s)], "success_rate", upto)] for s in se]
            ag = [[auc(got[(g, s)], "success_rate", upto)] for s in sg]
            d = difference_ci(ae, ag)
            t90 = [updates_to(got[(x, s)], "success_rate", 0.9) for x, ss in ((e, se), (g, sg)) for s in ss]
            t90_text = ", ".join("never" if t is None else f"{t:g}" for t in t90)
            d_text = _iv(d) if min(len(se), len(sg)) > 1 else f"{100 * d.estimate:+.1f} (one seed each: no interval)"
            rows.append([a.name, f"{LABELS[e]} - {LABELS[g]}", f"{upto:g}", d_text, t90_text])
            if e == "egcbf+":
                effects.append(d)
                evidence.append(f"{_iv(d)} in mean validation success ({a.name})")
    lines += [
        md_table(
            [
                "arm",
                "effect",
                "updates compared",
                "mean validation success over them, points (95 %)",
                "first update at 90 % success (E seeds, then G seeds)",
            ],
            rows,
        ),
        "",
    ]
    low = arm("low-data")
    c = arm_cells(low, root)
    for name, e in _pair_effects(low, c, 512, False):
        lines.append(
            f"- low-data (a quarter of the rollouts per update), N = 512 zero-shot: {name} = {_iv(e)} safe points"
        )
        if name.startswith("EGCBF+"):
            effects.append(e)
            evidence.append(f"{_iv(e)} safe points at N = 512 (low-data)")
    if any(curves.values()):
        png = curves_figure({k: v for k, v in curves.items() if v}, figures / "equivariance_curves.png")
        lines += ["", f"![validation curves]({relative_link(png, report)})"]
    v = verdict(effects)
    lines += ["", f"**Verdict: {v}** (EGCBF+ minus GCBF+: validation success over training under both heads, and the "
              "low-data run's zero-shot safety at N = 512)."]  # fmt: skip
    return "\n".join(lines), v, "; ".join(evidence)


_ROTATED_METRICS = (("safe_rate", "Safe"), ("success_rate", "Success"))


def _rotated(root: Path, figures: Path, report: Path) -> tuple[str, str, str]:
    a = arm("crossing")
    head = ["run", "cell", "yaw 0", "yaw 90", "yaw 180", "uniform", "90 - 0 (points)", "180 - 0 (points)"]
    sizes = sorted({c.num_agents for c in rotated_cells()})
    got = {run: rotated_rows(run, root) for run in a.all_runs()}
    lines, panels = [], {}
    changes: dict[str, list[Interval | None]] = {}
    for metric, title in _ROTATED_METRICS:
        rows = []
        for run in a.all_runs():
            for n in sizes:
                at = {(c.scene, c.yaw): got[run].get(c) for c in rotated_cells() if c.num_agents == n}
                ests = {k: None if r is None else mean_ci([per_episode(r, metric)]) for k, r in at.items()}
                diffs = []
                for yaw in (90.0, 180.0):
                    r0, r1 = at.get(("crossing", 0.0)), at.get(("crossing", yaw))
                    d = None if r0 is None or r1 is None else difference_ci([per_episode(r1, metric)],
                                                                            [per_episode(r0, metric)])  # fmt: skip
                    diffs.append(d)
                    changes.setdefault(run.algo, []).append(d)
                cell = next(c for c in rotated_cells() if c.num_agents == n)
                rows.append([run.name, f"N = {n}, l = {cell.area:g}, {cell.obstacles} obst.",
                             *[_mean(ests.get(k)) for k in (("crossing", 0.0), ("crossing", 90.0),
                                                             ("crossing", 180.0), ("uniform", 0.0))],
                             *[_iv(d) for d in diffs]])  # fmt: skip
                pts = [(k[1], e.estimate, e.low, e.high) for k, e in ests.items()
                       if e is not None and k[0] == "crossing"]  # fmt: skip
                if pts:
                    panels.setdefault((metric, n), {})[run.name] = pts
        lines += [f"{title} % (95 % interval over episodes), trained on `crossing` scenes (every agent travels along "
                  "+x):", "", md_table(head, rows), ""]  # fmt: skip
    if panels:
        png = rotated_figure(panels, figures / "equivariance_rotated.png")
        lines += [f"![safety and success against rotation]({relative_link(png, report)})", ""]
    eq, wf = changes.get("egcbf+", []), changes.get("gcbf+", [])
    detail = ""
    if not eq or not wf or any(d is None for d in eq + wf):
        v = "pending"
    elif any(d.excludes_zero() for d in eq):
        v = "not constant for EGCBF+: a bug to find (equivariance makes it constant by construction)"
    elif any(d.high < 0 for d in wf):
        worst = min(wf, key=lambda d: d.estimate)
        lost = sum(d.high < 0 for d in wf)
        v = "supported"
        detail = (f"EGCBF+ is constant; GCBF+ loses up to {-100 * worst.estimate:.1f} points under rotation, beyond "
                  f"the interval in {lost} of its {len(wf)} rotated comparisons. ")  # fmt: skip
    else:
        v = "not supported (the world-frame method transfers as well)"
    lines.append(f"**Verdict: {v}** ({detail}EGCBF+ must be constant under rotation; GCBF+'s change is the effect; "
                 "safety and success).")  # fmt: skip
    return "\n".join(lines), v, detail.strip().rstrip(".")


def _ablation(root: Path) -> str:
    names = ("cpu-20", "no-closest", "mlp-cbf", "mlp-policy")
    rows, gaps = [], {}
    for name in names:
        a = arm(name)
        c = arm_cells(a, root)
        e = difference(c, "egcbf+", "gcbf+", (0,), (0,), 512)
        means = [_mean(method_mean(c, algo, (0,), 512, False, "safe_rate")) for algo in ("egcbf+", "gcbf+")]
        rows.append([name, a.claim, *means, _iv(e)])
        gaps[name] = e
    text = md_table(["arm", "what", "EGCBF+ safe % at N = 512", "GCBF+", "EGCBF+ - GCBF+ (points, 95 %)"], rows)
    text += "\n\nOne training seed per cell, so the intervals cover the episodes only, not the training seeds."
    return text + "\n\n" + _ablation_reading(gaps)


def _ablation_reading(gaps: dict[str, Interval | None]) -> str:
    """One line on the claim of docs/learning.md that our heads close the gap between the groups: switching a head
    off should then open a gap in EGCBF+'s favour (an interval above zero) where the full recipe has none."""
    if any(e is None for e in gaps.values()):
        return "**Reading: pending** (every arm's cell at N = 512 is needed)."
    base = gaps["cpu-20"]
    opened = [name for name, e in gaps.items() if name != "cpu-20" and e.low > 0 and not base.low > 0]
    closed = [name for name, e in gaps.items() if name != "cpu-20" and e.high < 0]
    if opened:
        what = f"supported for {', '.join(opened)}: switching it off opens a gap in EGCBF+'s favour"
    else:
        what = "not supported: no head, switched off, opens a gap in EGCBF+'s favour"
    if closed:
        what += f"; with {', '.join(closed)} switched off GCBF+ is ahead"
    return f"**Reading: {what}** (the full `cpu` recipe: {_iv(base)} points)."


def write_report(
    report: str | Path = "docs/equivariance.md", root: str | Path = ROOT, quote_in: Sequence[str | Path] = ()
) -> tuple[Path, dict]:
    """Write (or update) ``report`` and its figures (``<report dir>/figures/equivariance_*.png``); returns the path
    and the verdicts ``{claim: verdict}``. Each page of ``quote_in`` that holds an ``equivariance-verdicts`` block
    gets the verdicts and their effect sizes there (:func:`default_quote_targets`: the README and
    docs/reproduction.md)."""
    report, root = Path(report), Path(root)
    figures = report.parent / "figures"
    gen, v1, e1 = _generalization(root, figures, report)
    conv, v2, e2 = _convergence(root, figures, report)
    rot, v3, e3 = _rotated(root, figures, report)
    verdicts = {"generalization": v1, "convergence": v2, "transfer": v3}
    evidence = {"generalization": e1, "convergence": e2, "transfer": e3}
    bodies = {"status": _status(root), "generalization": gen, "convergence": conv, "rotated": rot,
              "ablation": _ablation(root)}  # fmt: skip
    text = report.read_text() if report.exists() else _TEMPLATE
    text = _SOURCE.sub(f"from the result files under `{root.as_posix().rstrip('/')}/`", text, count=1)
    for name, heading in _SECTIONS:
        text = replace_block(text, name, bodies[name], heading=heading)
    summary = "\n".join(f"- **{k}**: {v}" for k, v in verdicts.items())
    text = replace_block(text, "verdicts", summary, heading="## Verdicts")
    report.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(report, text)
    for target in quote_in:
        _quote(Path(target), report, verdicts, evidence)
    return report, verdicts


#: what each claim's verdict is about, for the quotes in other pages
_CLAIMS = {
    "generalization": "zero-shot generalization from 8 agents to larger, denser swarms (EGCBF+ minus GCBF+, safe %)",
    "convergence": "faster convergence and fewer samples (EGCBF+ minus GCBF+)",
    "transfer": "transfer to rotated states",
}


def default_quote_targets(report: Path) -> tuple[Path, ...]:
    """The pages that quote the verdicts of ``report`` (``docs/equivariance.md``): its sibling ``reproduction.md``
    and the README beside its folder, where they exist (a report written elsewhere quotes into nothing)."""
    return tuple(p for p in (report.parent / "reproduction.md", report.parent.parent / "README.md") if p.exists())


def _quote(target: Path, report: Path, verdicts: dict, evidence: dict) -> None:
    """Rewrite the ``equivariance-verdicts`` block of ``target`` (only where the page has the markers) with the
    verdicts and their effect sizes, so that no page paraphrases them by hand."""
    link = relative_link(report, target)
    items = [f"{_CLAIMS[k]}: **{v}**" + (f" ({evidence[k]})" if evidence[k] and v != "pending" else "")
             for k, v in verdicts.items()]  # fmt: skip
    body = (f"What equivariance buys, claim by claim ([{link}]({link}), generated by `egcbf study --report-only`; "
            "95 % intervals over training seeds and episodes): " + "; ".join(items) + ".")  # fmt: skip
    quote_section(target, "equivariance-verdicts", body)


#: the header's "from the result files under `ROOT/`", rewritten to the root the report was generated from
_SOURCE = re.compile(r"from the result files under `[^`]*`")

_TEMPLATE = """# What equivariance buys: the paper's three claims, tested

Generated by `egcbf study --report-only` from the result files under `docs/results/equivariance/`
(`egcbf.study`); the sections between the markers are regenerated, text around them is kept.

## Verdicts

<!-- verdicts:begin -->
<!-- verdicts:end -->
"""
