"""What the report of ``egcbf reproduce`` says about one setting: the cells of a method over its training seeds, their
mean, range and 95 % interval, and the words for the sweep's settings.

A *setting* is ``(method, obstacles, N, scale)``: one cell per training seed of the method (one cell for a
hand-crafted controller). :func:`seed_rows` returns those cells with their training seed, :class:`Stat` a metric over
them: the mean over seeds, the min and max over seeds, and, where every cell kept its per-episode values, the 95 %
interval of the two-level bootstrap over training seeds and episodes (:func:`egcbf.evaluate.bootstrap.mean_ci`; over
episodes alone for one cell). Rates print with :func:`egcbf.io.report.pct` (never ``100.0`` for a rate below 1),
costs with :func:`egcbf.io.report.number` (a cost above 0 never prints as ``0.000``).
"""

from __future__ import annotations

import statistics
from functools import cached_property
from typing import NamedTuple

from ..evaluate.bootstrap import Interval, mean_ci
from ..io.report import pct
from .paper import LABELS
from .plan import Cell, SweepConfig

__all__ = [
    "SeedRow",
    "Stat",
    "episodes_text",
    "label",
    "partial",
    "scale_text",
    "seed_rows",
    "setting_text",
    "setting_value",
    "so_far",
    "stat",
]


class SeedRow(NamedTuple):
    """One cell of a setting: its training seed (``None`` for a hand-crafted controller), metrics row and meta."""

    train_seed: int | None
    row: dict
    meta: dict

    @property
    def imported(self) -> bool:
        """Whether the row was imported from an earlier ``egcbf eval`` output rather than computed by the sweep."""
        return bool(self.meta.get("imported_from"))


def seed_rows(
    records: dict[Cell, dict], method: str, obstacles: int, num_agents: int, scale: bool, steps: int | None = None
) -> list[SeedRow]:
    """The cells of ``method`` at one setting, one per training seed present, in training-seed order; each value is
    paired with its own training seed (a pending seed is absent, not shifted onto the next one). ``steps``: the
    scalability study's long horizon (``None``: the sweep's own episode length)."""
    want = (method, obstacles, num_agents, scale, steps)
    cells = sorted(
        (c for c in records if (c.method, c.obstacles, c.num_agents, c.scale, c.steps) == want),
        key=lambda c: -1 if c.train_seed is None else c.train_seed,
    )
    return [SeedRow(c.train_seed, records[c]["row"], records[c].get("meta", {})) for c in cells]


class Stat:
    """A metric over training seeds: ``mean``, ``lo`` and ``hi`` (min and max) of ``values``, ``n`` seeds,
    ``seeds``, the training seed of each value (``None`` where unknown), and ``runs``, each value's per-episode values
    (``None`` where a cell did not keep them), from which :attr:`interval` is drawn."""

    def __init__(
        self,
        values: list[float],
        seeds: list[int | None] | None = None,
        runs: list[list[float]] | None = None,
    ):
        if not values:
            raise ValueError("Stat needs at least one value")
        if seeds is not None and len(seeds) != len(values):
            raise ValueError(f"Stat got {len(values)} values but {len(seeds)} seeds")
        if runs is not None and len(runs) != len(values):
            raise ValueError(f"Stat got {len(values)} values but {len(runs)} runs of per-episode values")
        self.values = list(values)
        self.seeds = list(seeds) if seeds is not None else [None] * len(values)
        self.runs = None if runs is None else [list(r) for r in runs]
        self.n = len(values)
        self.mean = statistics.fmean(values)
        self.lo, self.hi = min(values), max(values)

    @cached_property
    def interval(self) -> Interval | None:
        """The 95 % two-level bootstrap interval over training seeds and episodes of the mean (10 000 resamples,
        seed 0: deterministic), or ``None`` without per-episode values."""
        return None if self.runs is None else mean_ci(self.runs)

    def text(self) -> str:
        """A rate in %: ``92.7 [91.0, 94.1]`` (the mean over seeds and its 95 % :attr:`interval`), or without
        per-episode values ``92.7`` (one seed) or ``92.7 (90.6-95.3)`` (mean, min-max over the seeds); each value
        formatted by :func:`egcbf.io.report.pct`."""
        iv = self.interval
        if iv is not None:
            return f"{pct(self.mean)} [{pct(iv.low)}, {pct(iv.high)}]"
        if self.n == 1:
            return pct(self.mean)
        return f"{pct(self.mean)} ({pct(self.lo)}-{pct(self.hi)})"


def stat(rows: list[SeedRow], metric: str) -> Stat | None:
    """``metric`` over ``rows`` (with their training seeds); ``None`` if there are no rows or one of them lacks
    ``metric`` (a column an older cell does not have)."""
    if not rows or any(metric not in r.row for r in rows):
        return None
    episodes = [r.row.get("per_episode", {}).get(metric) for r in rows]
    runs = None if any(not e for e in episodes) else episodes
    return Stat([float(r.row[metric]) for r in rows], [r.train_seed for r in rows], runs)


def setting_value(
    cfg: SweepConfig,
    records: dict[Cell, dict],
    method: str,
    num_agents: int,
    scale: bool,
    metric: str,
    steps: int | None = None,
) -> str:
    """``metric`` of ``method`` at one setting without obstacles (``steps``: the long horizon, :func:`seed_rows`) as
    :meth:`Stat.text`, ending in :func:`partial`'s note while some training seeds are pending; ``"pending"`` without
    any cell."""
    rows = seed_rows(records, method, 0, num_agents, scale, steps)
    st = stat(rows, metric)
    return "pending" if st is None else st.text() + partial(len(rows), len(cfg.seeds_for(method)))


# ---------------------------------------------------------------------------------------------------- words
def label(cfg: SweepConfig, method: str, done: int | None = None) -> str:
    """The method's row label: ``EGCBF+ (3 seeds)``, or ``EGCBF+ (2 of 3 seeds)`` when only ``done`` of its
    training seeds are in the row (``done=None`` or ``0``: the row's seeds are not counted, e.g. a pending row)."""
    planned = len(cfg.seeds_for(method))
    if planned < 2:
        return LABELS[method]
    if done and done < planned:
        return f"{LABELS[method]} ({done} of {planned} seeds)"
    return f"{LABELS[method]} ({planned} seeds)"


def partial(done: int, planned: int) -> str:
    """`` [1 of 3 seeds]`` after a value made of only some of a method's training seeds, else ``""``."""
    return f" [{done} of {planned} seeds]" if 0 < done < planned else ""


def so_far(st: Stat, cfg: SweepConfig, method: str, *more: tuple[Stat, str]) -> str:
    """`` (1 of 3 seeds of EGCBF+ so far)`` while some of ``method``'s training seeds are pending, else ``""``; with
    ``more`` (stat, method) pairs, one note for all of them (`` (1 of 3 seeds of EGCBF+, 1 of 3 of GCBF+ so far)``)."""
    parts = []
    for s, m in ((st, method), *more):
        planned = len(cfg.seeds_for(m))
        if s.n < planned:
            parts.append(f"{s.n} of {planned} {'seeds of ' if not parts else 'of '}{LABELS[m]}")
    return f" ({', '.join(parts)} so far)" if parts else ""


def setting_text(cfg: SweepConfig, num_agents: int, scale: bool) -> str:
    """``N = 512`` (Table I) or ``N = 4096 (l = 8 m)`` (the scalability study)."""
    return f"N = {num_agents}" + (f" (l = {cfg.scale_area(num_agents):g} m)" if scale else "")


def episodes_text(cfg: SweepConfig) -> str:
    """Table I's episodes: ``"50 episodes per cell"`` or ``"10 episodes per cell (CBF-QPs and the nominal
    controller: 50)"`` (``baseline_episodes`` applies to every hand-crafted controller, the nominal one too)."""
    text = f"{cfg.episodes} episodes per cell"
    if cfg.baseline_episodes is not None and cfg.baseline_episodes != cfg.episodes:
        text += f" (CBF-QPs and the nominal controller: {cfg.baseline_episodes})"
    return text


def scale_text(cfg: SweepConfig) -> str:
    """How the scalability cells are set up, in words; ``"not run (no scale sizes)"`` without any."""
    episodes = {c.num_agents: cfg.episodes_for(c) for c in cfg.scale_cells()}
    if not episodes:
        return "not run (no scale sizes or no scale method)"
    sizes = ", ".join(f"N = {n}: l = {cfg.scale_area(n):g} m, {e} episodes" for n, e in sorted(episodes.items()))
    return (
        f"the density of N = {cfg.scale_reference} at l = {cfg.area:g} m "
        f"({cfg.scale_reference / cfg.area**3:g} agents per m^3), at least {cfg.scale_agent_episodes} "
        f"agent-episodes per cell ({sizes})"
    )
