"""``docs/certificate.md``: the certificate's rates for every barrier, from the stored cells, with exact bounds.

Sections: the definitions and choices; every barrier pooled over its cells (its verdict); every barrier per
controller; the acceptance setting of the learned filter (EGCBF+ behind its own CBF at N = 512); every cell; the
figure (``h`` against the time to collision); where and when the cells were computed.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path

from ..io.atomic import write_text_atomic
from ..io.report import md_table, quote_section, relative_link
from ..robots import DEFAULT_ROBOT
from .plan import REFERENCE, Cell, CertifyConfig
from .rates import RATES, bin_centers, pool_counts, rate
from .runner import load_cells

__all__ = ["VALID_BOUND", "certificate_figure", "headline", "verdict", "write_report"]

_PENDING = "pending: the learned filter's own cells are not computed yet."
#: the largest 95 % upper bound of the miss and condition-violation rates for which a barrier is called valid
VALID_BOUND = 0.01

_CONTROLLER_WORDS = {
    "policy": "its policy alone",
    "policy:cbf": "its policy behind its learned-CBF filter",
    "policy:prior": "its policy behind the prior-CBF filter",
    "policy:dcbf": "its policy behind the dcbf filter",
    "nominal": "the nominal controller",
    "nominal:dcbf": "the nominal controller behind the dcbf filter",
}


def _pct(x: float) -> str:
    if math.isnan(x):
        return "n/a"
    p = 100 * x
    return f"{p:.2g}" if 0 < p < 0.1 else f"{p:.1f}" if p >= 10 else f"{p:.2f}"


def _cell_text(r: dict, bound: str = "upper") -> str:
    """``k / n: rate (<= upper)`` (two-sided: ``[lower, upper]``), rates in %."""
    if not r["n"]:
        return "n/a (0 states)"
    if bound == "two":
        return f"{r['k']} / {r['n']}: {_pct(r['rate'])} [{_pct(r['lower'])}, {_pct(r['upper'])}]"
    return f"{r['k']} / {r['n']}: {_pct(r['rate'])} (≤ {_pct(r['upper'])})"


def verdict(counts: dict) -> str:
    """``valid`` where the miss rate's and the condition-violation rate's (filter QPs included) 95 % upper bounds are
    both <= :data:`VALID_BOUND`, else which of them exceeds it."""
    miss, viol = rate(counts, "miss"), rate(counts, "violation_or_bad")
    bad = [w for w, r in (("miss", miss), ("condition", viol)) if r["upper"] > VALID_BOUND]
    return "valid" if not bad else "not valid (" + ", ".join(bad) + f" bound > {_pct(VALID_BOUND)} %)"


_HEAD = ["states", "containment: unsafe with h ≥ 0", "miss: collides within W, h ≥ 0", "false-safe among h ≥ 0",
         "condition fails among h ≥ 0", "filter QP slack / braked", "condition or QP fails", "left {h ≥ 0} (of starts)",
         "of those collided", "conservative: h < 0 yet safe for W"]  # fmt: skip


def _row(counts: dict) -> list[str]:
    cols = [f"{counts.get('states', 0):,}"]
    for name in ("containment", "miss", "false_safe", "violation", "filter_bad", "violation_or_bad", "breach",
                 "breach_collided", "cautious"):  # fmt: skip
        r = rate(counts, name)
        if name == "filter_bad" and not r["n"]:
            cols.append("no filter")
            continue
        cols.append(_cell_text(r, "two" if RATES[name][3] else "upper"))
    return cols


def _pooled(cells: Iterable[tuple[Cell, dict]], name: str, keep=lambda c: True) -> dict:
    return pool_counts(stored["barriers"][name] for c, stored in cells if keep(c) and name in stored["barriers"])


def _short(counts: dict, name: str) -> str:
    r = rate(counts, name)
    return f"{_pct(r['rate'])} % (≤ {_pct(r['upper'])} %, {r['k']} of {r['n']})" if r["n"] else "n/a"


def headline(cells: list[tuple[Cell, dict]], learned: list[str]) -> str | None:
    """One paragraph of the findings, from the cells (``None`` before the learned filter's own cells exist):
    EGCBF+'s CBF behind its own filter at N = 512 (each obstacle setting), how many learned CBFs are valid, and the
    hand-crafted barrier behind its filter."""

    def own(k: int) -> dict:
        return _pooled(cells, "egcbf+-s0", lambda c: c.run == "egcbf+-s0" and c.controller == "policy:cbf"
                       and c.num_agents == 512 and c.robot == DEFAULT_ROBOT and c.obstacles == k)  # fmt: skip

    settings = [(k, own(k)) for k in sorted({c.obstacles for c, _ in cells})]
    settings = [(k, c) for k, c in settings if c]
    if not settings:
        return None

    def each(name: str) -> str:
        return " / ".join(_short(c, name) for _, c in settings)

    scored = [n for n in learned if any(n in s["barriers"] for _, s in cells)]
    valid = [n for n in scored if verdict(_pooled(cells, n)) == "valid"]
    ref = _pooled(cells, REFERENCE, lambda c: c.controller.endswith(":dcbf"))
    window = cells[0][1]["key"]["window"]
    text = (
        "EGCBF+'s learned CBF (training seed 0) behind its own filter (`--filter cbf`), N = 512, l = 4, "
        + " / ".join(f"{k} obstacles" for k, _ in settings)
        + f": unsafe states with h ≥ 0 {each('containment')}; it misses {each('miss')} of the states that precede a "
        f"collision within {window} steps; its decrease condition fails in {each('violation')} of the states it "
        f"calls safe; the filter's QP needs slack or brakes in {each('filter_bad')} of the agent-steps: "
        + " / ".join(f"**{verdict(c)}**" for _, c in settings)
        + f". Of the {len(scored)} shipped learned CBFs scored, {len(valid)} "
        + ("is" if len(valid) == 1 else "are")
        + " valid on their own rollouts"
        + (f" ({', '.join(f'`{n}`' for n in valid)})" if valid else "")
        + "."
    )
    if ref:
        text += (" The dcbf filter's hand-crafted barrier behind that filter (policy or nominal controller, pooled): "
                 f"misses {_short(ref, 'miss')}, condition fails in {_short(ref, 'violation')}: "
                 f"**{verdict(ref)}**.")  # fmt: skip
    return text


def _barrier_words(name: str) -> str:
    if name == REFERENCE:
        return "hand-crafted: the dcbf filter's braking-distance barrier"
    return f"learned: the CBF of `{name}`"


def certificate_figure(cells: list[tuple[Cell, dict]], names: list[str], window: int, out_png: Path) -> Path | None:
    """For each barrier of ``names`` (pooled over its cells): the share of states with ``h >= 0`` against the time to
    collision, and the median ``h`` with its 10-90 % band; ``None`` if nothing is drawable."""
    from matplotlib.figure import Figure

    centers = bin_centers()
    fig = Figure(figsize=(9.0, 3.8))
    ax_share, ax_h = fig.subplots(1, 2)
    drawn = False
    for name in names:
        hist = _pooled(cells, name).get("histogram", {})
        by_ttc: dict[int, dict[int, int]] = defaultdict(dict)
        for key, n in hist.items():
            t, b = (int(v) for v in key.split(":"))
            by_ttc[t][b] = n
        xs, share, med, lo, hi = [], [], [], [], []
        for t in range(window + 2):
            bins = by_ttc.get(t)
            if not bins:
                continue
            total = sum(bins.values())
            pos = sum(n for b, n in bins.items() if centers[b] >= 0)
            acc, q = 0, {}
            for b in sorted(bins):
                acc += bins[b]
                for p in (0.1, 0.5, 0.9):
                    if p not in q and acc >= p * total:
                        q[p] = centers[b]
            xs.append(t)
            share.append(100 * pos / total)
            med.append(q[0.5])
            lo.append(q[0.1])
            hi.append(q[0.9])
        if not xs:
            continue
        drawn = True
        (line,) = ax_share.plot(xs, share, marker=".", label=name)
        ax_h.plot(xs, med, color=line.get_color(), label=name)
        ax_h.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.15)
    if not drawn:
        return None
    for ax in (ax_share, ax_h):
        ax.set_xlabel(f"steps to the next collision ({window + 1}: none in {window})")
        ax.axvline(0.5, color="0.7", lw=0.8)
        ax.grid(alpha=0.3)
    ax_share.set_ylabel("states with h ≥ 0 (%)")
    ax_h.set_ylabel("h: median and 10-90 %")
    ax_h.axhline(0, color="k", lw=0.8)
    ax_h.set_ylim(-0.6, 1.2)
    ax_share.legend(fontsize=7)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    return out_png


def write_report(cfg: CertifyConfig, path: str | Path = "docs/certificate.md",
                 figures: str | Path = "docs/figures") -> Path:  # fmt: skip
    """Write the report from the stored cells of ``cfg`` (module doc); returns its path."""
    path, figures = Path(path), Path(figures)
    cells = load_cells(cfg)
    planned = cfg.cells()
    learned = [c.barrier for c in cfg.learned()]
    names = [n for n in (*learned, REFERENCE) if any(n in s["barriers"] for _, s in cells)]
    lines = [
        "# Is the learned CBF a barrier? The certificate, measured",
        "",
        f"Generated by `egcbf certify --report-only` from the cells in `{cfg.out}` ({len(cells)} of {len(planned)} "
        f"cells computed{'' if len(cells) == len(planned) else '; rerun `egcbf certify` to compute the rest'}). "
        "Every cell records the closed-loop rollouts of one controller on one setting (evaluation seed "
        f"{cfg.seed}, never a training or validation seed) and scores every agent-state against the barriers it "
        "names: the learned CBF of the checkpoint whose policy runs, or, for the nominal controller, every learned "
        "CBF of the robot, and on the quadrotor the dcbf filter's hand-crafted barrier as the reference row.",
        "",
        "## What is measured",
        "",
        f"`h_i` is the barrier of agent `i`; `h ≥ 0` claims it is safe. Sampled states: every {cfg.stride}th step "
        f"of every agent (`t < T`); W = {cfg.window} steps (0.8 s at the quadrotor's 25 ms).",
        "",
        "- **containment**: among sampled states in collision (with an agent or an obstacle), the share with h ≥ 0;",
        f"- **miss**: among states not in collision from which the agent collides within 1 to {cfg.window} steps "
        "under the controller it runs, the share with h ≥ 0 (the barrier did not warn); **false-safe**: among "
        "states with h ≥ 0 whose next W steps are known, the share in collision or preceding one;",
        "- **condition**: among states with h ≥ 0, the share where `h(x_{t+1}) - h(x_t) ≥ -dt κ(h(x_t))` fails under "
        "the commands every agent applied (the joint step, no assumption about the neighbours), and, behind a "
        "run-time filter, the share of agent-steps whose filter QP needed slack or braked, and the union of the two;",
        "- **invariance**: agent-episodes that start in {h ≥ 0} and leave it later, and how many of those collide "
        "at or after leaving;",
        "- **conservativeness**: among states with h < 0, the share from which the agent stays collision-free "
        "for W steps (high: the barrier marks safe space unsafe, which stalls a filter).",
        "",
        "Bounds are exact binomial (Clopper-Pearson) at 95 %: one-sided upper bounds `(≤ u)`, two-sided for "
        "conservativeness `[l, u]`. States of one trajectory are correlated; the bounds treat the thinned states "
        "as independent draws, so read them with the number of distinct agent-episodes behind each failure count "
        f"(the per-cell table). A barrier is called **valid on this distribution** only where the miss rate's and "
        f"the condition rate's (QP failures included) upper bounds are both ≤ {_pct(VALID_BOUND)} %.",
        "",
        "Choices (where the paper is loose): the learned `h` is the network's output (`CBFNet`, the `tanh` of the "
        "soft-min head, the quantity training constrains) and `κ(h) = α h` with the checkpoint's training α; the "
        "hand-crafted `h` is, per agent, the minimum over its neighbours within the communication radius and its "
        "obstacles within range of the dcbf filter's braking-distance barrier `sqrt(2 A (d - D)) + d'` (its margin, "
        "deceleration and γ; `d - D` inside the safety distance, where that barrier is undefined) read at the "
        "current state, with its own `κ(h) = γ h³`; an agent with nothing in range has `h = +∞` (always claims "
        "safety, never violates). Implementation: `egcbf.certify` (rates: `egcbf.certify.rates`).",
        "",
    ]
    summary = headline(cells, learned)
    if summary is not None:
        lines[2:2] = ["## In short", "", summary, ""]
    lines += ["## Every barrier, pooled over its cells", ""]
    pooled = {n: _pooled(cells, n) for n in names}
    lines.append(md_table(["barrier", "verdict", *_HEAD], [[f"`{n}`", verdict(pooled[n]), *_row(pooled[n])]
                                                          for n in names]))  # fmt: skip
    lines += ["", "Rows: " + "; ".join(f"`{n}`: {_barrier_words(n)}" for n in names[-1:]) + "; the others: the "
              "learned CBF of the named shipped checkpoint (`<robot>/` for the GCBF+ suite's robots).", ""]  # fmt: skip
    lines += ["## Every barrier per controller", "",
              "Pooled over N and obstacles; the controller is the one that ran (a checkpoint's policy, or the "
              "nominal controller), the barrier the one scored.", ""]  # fmt: skip
    rows = []
    for n in names:
        for ctrl in dict.fromkeys(c.controller for c, s in cells if n in s["barriers"]):
            counts = _pooled(cells, n, lambda c, ctrl=ctrl: c.controller == ctrl)
            rows.append([f"`{n}`", _CONTROLLER_WORDS[ctrl], verdict(counts), *_row(counts)])
    lines += [md_table(["barrier", "controller", "verdict", *_HEAD], rows), ""]
    lines += ["## The learned filter's own setting", "",
              "EGCBF+ (training seed 0) behind its own learned-CBF filter (`--filter cbf`), N = 512, l = 4: the "
              "setting in which the learned CBF should be a certificate (no unsafe state with h ≥ 0, miss and "
              f"condition bounds ≤ {_pct(VALID_BOUND)} %).", ""]  # fmt: skip
    rows = []
    for c, s in cells:
        if c.run == "egcbf+-s0" and c.controller == "policy:cbf" and c.num_agents == 512 and c.robot == DEFAULT_ROBOT:
            counts = s["barriers"]["egcbf+-s0"]
            rows.append([str(c.obstacles), f"{100 * s['safe_rate']:.2f}", verdict(counts), *_row(counts)])
    lines += [md_table(["obstacles", "safe %", "verdict", *_HEAD], rows) if rows else "(not computed yet)", ""]
    figure = certificate_figure(cells, [n for n in ("egcbf+-s0", "gcbf+-s0", REFERENCE) if n in names],
                                cfg.window, figures / "certificate_h_vs_ttc.png")  # fmt: skip
    if figure is not None:
        lines += ["## h against the time to collision", "",
                  f"![h against time to collision]({relative_link(figure, path)})", "",
                  "Pooled over every cell each barrier was scored in. Left: the share of states with h ≥ 0 by how "
                  "many steps away the agent's next collision is (0: in collision now; a certificate would be 0 % "
                  "from 0 to W and high at the right); right: the median h with its 10-90 % band.", ""]  # fmt: skip
    lines += ["## Every cell", ""]
    rows = []
    for c, s in cells:
        for n in c.barriers:
            counts = s["barriers"][n]
            miss, viol = rate(counts, "miss"), rate(counts, "violation")
            rows.append([c.robot, c.run, c.controller, str(c.num_agents), f"{c.area:g}", str(c.obstacles),
                         str(c.episodes), f"{100 * s['safe_rate']:.2f}", f"`{n}`", verdict(counts),
                         *_row(counts), f"{miss['agents']} / {viol['agents']}"])  # fmt: skip
    lines += [md_table(["robot", "run", "controller", "N", "l", "obstacles", "episodes", "safe %", "barrier",
                        "verdict", *_HEAD, "agent-episodes with a miss / a violation"], rows), ""]  # fmt: skip
    machines = sorted({f"{s['machine'].get('cpu', '?')} ({s['machine'].get('cores', '?')} cores)" for _, s in cells})
    codes = sorted({s.get("code", "?") for _, s in cells})
    wall = sum(s["wall_s"] for _, s in cells)
    lines += ["## Provenance", "",
              f"Computed on {', '.join(machines) or 'n/a'}; code {', '.join(codes) or 'n/a'}; {wall / 3600:.2f} "
              "CPU-hours of cells (one torch thread each). Each cell file records its key (the settings and the "
              "SHA-256 of every checkpoint it read): a changed checkpoint makes its cells stale, and this report "
              "refuses them. Regenerate:", "",
              "    egcbf certify                 # compute the missing cells (resumable), then write this page",
              "    egcbf certify --report-only   # this page from the committed cells", ""]  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, "\n".join(lines))
    readme = path.parent.parent / "README.md"  # the README beside the report's folder quotes the short version
    link = relative_link(path, readme)
    quote_section(readme, "certificate-headline", f"The learned barrier as a certificate ([{link}]({link}), generated "
                  f"by `egcbf certify --report-only`; 95 % Clopper-Pearson upper bounds): "
                  f"{summary or _PENDING}")  # fmt: skip
    return path
