"""The reproduction's headline: one table that a README quotes (``<!-- reproduction-headline:begin/end -->``).

Rows: the learned policies alone, behind the recommended ``dcbf`` filter, and beside them the strongest
hand-crafted alternatives (the nominal controller behind the same filter, the decentralized and centralized
CBF-QPs, the nominal controller alone). Columns: safe and success rate at Table I's largest N and at the largest
fixed-density N of the scalability study, without obstacles, and there the success rate at the study's long horizon
(``long_steps``; ``-`` for a controller not run at it), each with its 95 % interval over training seeds and episodes
(:class:`~egcbf.reproduce.stats.Stat`). Every value is read from the cells; a missing one is ``pending``.
"""

from __future__ import annotations

from ..io.report import md_table
from ..robots.quadrotor.dynamics import DEFAULT_MAX_STEPS
from .paper import LABELS
from .plan import Cell, SweepConfig
from .stats import setting_text, setting_value

__all__ = ["HEADLINE_METHODS", "headline_markdown"]

#: the headline's rows, in order (those of the sweep's methods)
HEADLINE_METHODS = ("egcbf+", "gcbf+", "egcbf+:dcbf", "gcbf+:dcbf", "nominal:dcbf", "dcbf", "ccbf", "nominal")
_HAND_CRAFTED = ("nominal:dcbf", "dcbf", "ccbf", "nominal")


def headline_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """The headline table and one line saying what it is (module doc)."""
    settings = [(max(int(n) for n in cfg.num_agents), False)]
    if cfg.scale_sizes:
        settings.append((max(int(n) for n in cfg.scale_sizes), True))
    head = ["controller", "kind"] + [
        f"{what}, {setting_text(cfg, n, s)}" for n, s in settings for what in ("safe %", "success %")
    ]
    long_ = cfg.long_steps if cfg.long_cells() else None
    if long_ is not None:
        head.append(f"success %, {setting_text(cfg, settings[1][0], True)}, {long_} steps")
    rows = []
    for m in (m for m in HEADLINE_METHODS if m in cfg.methods):
        cells = [setting_value(cfg, records, m, n, s, k) for n, s in settings for k in ("safe_rate", "success_rate")]
        if long_ is not None:
            run = any(c.method == m for c in cfg.long_cells())
            cells.append(setting_value(cfg, records, m, settings[1][0], True, "success_rate", long_) if run else "-")
        kind = "hand-crafted" if m in _HAND_CRAFTED else "learned" if ":" not in m else "learned + hand-crafted filter"
        rows.append([LABELS[m], kind, *cells])
    scale = f"; N = {settings[1][0]}: {cfg.scale_agent_episodes} agent-episodes" if len(settings) > 1 else ""
    note = (
        f"No obstacles; l = {cfg.area:g} m at N = {settings[0][0]} ({cfg.episodes} episodes){scale}, the same "
        f"density; evaluation seed {cfg.seed}, {cfg.max_steps or DEFAULT_MAX_STEPS} steps"
        + (
            f" (the last column: {long_} steps, enough for the nominal controller alone to reach every goal)"
            if long_
            else ""
        )
        + ". `[low, high]`: 95 % "
        "interval, a two-level bootstrap over training seeds and episodes (episodes alone for one training seed and "
        "the hand-crafted controllers); `[1 of 3 seeds]`: the other training seeds are pending."
    )
    return md_table(head, rows) + "\n\n" + note
