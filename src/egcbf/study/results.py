"""Reading the equivariance study's results (:mod:`egcbf.study.plan`) and turning them into effects with confidence
intervals (:mod:`egcbf.evaluate.bootstrap`): the zero-shot cells of an arm, the rotated-world cells of a run, and the
validation curves of the training runs."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

from ..evaluate.bootstrap import Interval, difference_ci, mean_ci
from .plan import ROOT, Arm, RotatedCell, Run, rotated_cells

__all__ = [
    "arm_cells",
    "auc",
    "curve",
    "difference",
    "per_episode",
    "rotated_rows",
    "stale_cells",
    "unreadable_cells",
    "updates_to",
]


def _stored_cells(arm: Arm, root: str | Path) -> list[tuple]:
    """``[(cell, record, stale)]`` of the arm's stored zero-shot cells; ``stale``: computed with other weights than
    the checkpoint now under the arm's checkpoints (never where that checkpoint cannot be read)."""
    from ..reproduce import load_cells
    from ..reproduce.store import current_sha256
    from .driver import sweep_config

    cfg = sweep_config(arm, root)
    if not cfg.out.exists():
        return []
    now: dict[tuple[str, int], str | None] = {}
    out = []
    for c, rec in load_cells(cfg).items():
        run = (c.method, c.train_seed or 0)
        if run not in now:
            now[run] = current_sha256(cfg.checkpoints, *run)
        stored = rec["key"].get("checkpoint_sha256")
        out.append((c, rec, now[run] is not None and stored is not None and stored != now[run]))
    return out


def arm_cells(arm: Arm, root: str | Path = ROOT) -> dict[tuple[str, int, int, bool], dict]:
    """``{(algo, seed, N, scale): metrics row}`` of the arm's computed zero-shot cells (``scale``: a cell of the
    fixed-density study past N = 512); cells computed with other weights than the arm's checkpoints now hold are
    left out (:func:`stale_cells`)."""
    return {(c.method, c.train_seed or 0, c.num_agents, c.scale): rec["row"]
            for c, rec, stale in _stored_cells(arm, root) if not stale}  # fmt: skip


def _current_sha(run: Run, root: str | Path) -> str | None:
    from ..train.checkpoint import sha256

    try:
        return sha256(run.checkpoint_dir(root) / "model.safetensors")
    except OSError:
        return None


def stale_cells(arms: Sequence[Arm], root: str | Path = ROOT) -> list[Path]:
    """The arms' stored cells (zero-shot and rotated-world) computed with other weights than the checkpoint now
    under the root: the report leaves them out (pending), the study recomputes them, the command line names them."""
    from .driver import sweep_config

    out: list[Path] = []
    for arm in arms:
        if arm.evaluation != "rotated":
            out += [c.path(sweep_config(arm, root).out) for c, _, stale in _stored_cells(arm, root) if stale]
            continue
        for run in arm.all_runs():
            now = _current_sha(run, root)
            for cell, rec in _rotated_records(run, root).items():
                stored = rec["key"].get("checkpoint_sha256")
                if now is not None and stored not in (None, now):
                    out.append(cell.path(run, root))
    return sorted(out)


def per_episode(row: dict | None, key: str) -> list[float] | None:
    """The per-episode values of ``key`` in an evaluation row, or ``None`` (a row computed before they were kept)."""
    if row is None:
        return None
    values = (row.get("per_episode") or {}).get(key)
    return list(values) if values else None


def _runs(cells: dict, algo: str, seeds: Sequence[int], n: int, scale: bool, key: str) -> list[list[float]] | None:
    runs = [per_episode(cells.get((algo, s, n, scale)), key) for s in seeds]
    return None if any(r is None for r in runs) or not runs else runs


def difference(
    cells: dict, a: str, b: str, seeds_a: Sequence[int], seeds_b: Sequence[int], n: int, scale: bool = False,
    key: str = "safe_rate",
) -> Interval | None:  # fmt: skip
    """``mean(a) - mean(b)`` of ``key`` at ``n`` over the given training seeds, with its two-level bootstrap
    interval; ``None`` while a cell is missing."""
    ra, rb = _runs(cells, a, seeds_a, n, scale, key), _runs(cells, b, seeds_b, n, scale, key)
    return None if ra is None or rb is None else difference_ci(ra, rb)


def method_mean(cells: dict, algo: str, seeds: Sequence[int], n: int, scale: bool, key: str) -> Interval | None:
    """The method's mean of ``key`` at ``n`` over its seeds, with its interval; ``None`` while a cell is missing."""
    runs = _runs(cells, algo, seeds, n, scale, key)
    return None if runs is None else mean_ci(runs)


# ------------------------------------------------------------------------------------------------------ rotated
def rotated_rows(run: Run, root: str | Path = ROOT) -> dict[RotatedCell, dict]:
    """``{cell: metrics row}`` of the run's computed rotated-world cells made with the weights its checkpoint now
    holds (:func:`stale_cells`)."""
    now = _current_sha(run, root)
    return {cell: rec["row"] for cell, rec in _rotated_records(run, root).items()
            if now is None or rec["key"].get("checkpoint_sha256") in (None, now)}  # fmt: skip


def _rotated_records(run: Run, root: str | Path) -> dict[RotatedCell, dict]:
    """The run's readable rotated-world cell records (``key`` and ``row``)."""
    from ..reproduce.store import read_json

    out = {}
    for cell in rotated_cells():
        rec = read_json(cell.path(run, root))
        if isinstance(rec, dict) and "row" in rec and isinstance(rec.get("key"), dict):
            out[cell] = rec
    return out


def unreadable_cells(arms: Sequence[Arm], root: str | Path = ROOT) -> list[Path]:
    """The arms' cell files (zero-shot and rotated-world) that exist but cannot be read (truncated or corrupted):
    the report shows them as pending, the study recomputes them, the command line names them."""
    from ..reproduce.store import read_json
    from ..reproduce.store import unreadable_cells as unreadable_sweep_cells
    from .driver import sweep_config

    bad: set[Path] = set()
    for arm in arms:
        cfg = sweep_config(arm, root)
        if cfg.out.exists():
            bad.update(unreadable_sweep_cells(cfg))
        for run in arm.all_runs():
            for cell in rotated_cells():
                path = cell.path(run, root)
                if not path.exists():
                    continue
                rec = read_json(path)
                if not (isinstance(rec, dict) and "row" in rec):
                    bad.add(path)
    return sorted(bad)


# ------------------------------------------------------------------------------------------------------- curves
def curve(run: Run, root: str | Path = ROOT) -> dict[str, list[float]] | None:
    """The run's validation curve (``metrics.csv``: ``step``, ``wall_s``, rates) with ``agent_steps`` (simulated
    agent-steps of training rollouts up to each update), or ``None`` if it is not trained yet."""
    d = run.checkpoint_dir(root)
    if not (d / "metrics.csv").exists():
        return None
    cfg = json.loads((d / "config.json").read_text())
    per_update = int(cfg["rollout_envs"]) * int(cfg["rollout_steps"]) * int(cfg["num_agents"])
    with open(d / "metrics.csv", newline="") as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["step"]))
    out = {k: [float(r[k]) for r in rows] for k in ("step", "wall_s", "safe_rate", "reach_rate", "success_rate")}
    out["agent_steps"] = [s * per_update for s in out["step"]]
    return out


def auc(c: dict[str, list[float]], key: str, upto: float) -> float:
    """The mean of ``key`` over updates ``0 ... upto`` (trapezoids between validations; the area under the curve
    divided by ``upto``): one number for how early and how well a run learned."""
    steps, vals = c["step"], c[key]
    area, last_s, last_v = 0.0, steps[0], vals[0]
    for s, v in zip(steps[1:], vals[1:]):
        if s > upto:
            v = last_v + (v - last_v) * (upto - last_s) / (s - last_s)
            area += 0.5 * (last_v + v) * (upto - last_s)
            return area / upto
        area += 0.5 * (last_v + v) * (s - last_s)
        last_s, last_v = s, v
    return area / upto if upto <= last_s else (area + last_v * (upto - last_s)) / upto


def updates_to(c: dict[str, list[float]], key: str, level: float) -> float | None:
    """The first validated update at which ``key`` reached ``level``, or ``None``."""
    return next((s for s, v in zip(c["step"], c[key]) if v >= level), None)
