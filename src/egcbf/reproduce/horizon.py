"""The report's section on the scalability study's second, longer horizon.

At the scalability study's N the default 256-step episode caps the success rate: an agent far from its goal cannot
reach it in time, whatever the controller. The sweep therefore runs the study's cells again with ``long_steps``
steps (:class:`~egcbf.reproduce.plan.SweepConfig`), for the controllers of ``long_methods``; this section sets the two
horizons side by side, one row per (N, method): safety, reach and success at each, as the mean over training seeds
with its 95 % interval (:class:`~egcbf.reproduce.stats.Stat`), ``pending`` where a cell is not computed yet.
"""

from __future__ import annotations

from ..io.report import md_table
from ..robots.quadrotor.dynamics import DEFAULT_MAX_STEPS
from .paper import METHODS
from .plan import Cell, SweepConfig
from .stats import label, scale_text, setting_value

__all__ = ["horizon_markdown"]

_METRICS = (("safe_rate", "Safe %"), ("reach_rate", "Reach %"), ("success_rate", "Succ %"))


def horizon_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """The section (module doc); a sentence saying it is not run where the sweep has no long-horizon cell."""
    cells = cfg.long_cells()
    if not cells:
        return "Not run: the sweep has no second horizon (`--long-steps none`, or no scale size or long method).\n"
    short, long_ = cfg.max_steps or DEFAULT_MAX_STEPS, int(cfg.long_steps)
    methods = [m for m in METHODS if any(c.method == m for c in cells)]
    head = ["N", "method"] + [f"{name} ({t} steps)" for _, name in _METRICS for t in (short, long_)]
    rows = []
    for n in cfg.scale_sizes:
        for m in methods:
            values = [
                setting_value(cfg, records, m, int(n), True, metric, steps)
                for metric, _ in _METRICS
                for steps in (None, long_)
            ]
            rows.append([f"{n} (l = {cfg.scale_area(int(n)):g} m)", label(cfg, m), *values])
    done = sum(c in records for c in cells)
    return (
        f"The scalability study's cells ({scale_text(cfg)}) again with episodes of {long_} steps instead of {short} "
        f"({done} of {len(cells)} cells computed). At these N the {short}-step episode ends before every agent can "
        f"reach its goal; {long_} steps are enough for the nominal controller alone to reach every goal at "
        "N = 1024, 2048 and 4096 (`docs/results/horizon/`, whose README has the command), so the long horizon's "
        "reach and success measure the controllers rather than the clock. Values: the mean over training seeds "
        "with its 95 % interval (two-level bootstrap over seeds and episodes, as in the tables above); "
        "`[k of 3 seeds]` where only some are computed.\n\n" + md_table(head, rows) + "\n"
    )
