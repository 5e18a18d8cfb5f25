"""The committed cells of ``egcbf robustness`` as the report reads them, and how it writes their numbers: rates in
percent, a paired change with its 95 % interval, a before-and-after table row."""

from __future__ import annotations

from collections import Counter

from ..evaluate.bootstrap import Interval, mean_ci
from ..reproduce.paper import BASELINES, base_method
from ..reproduce.plan import Cell
from ..reproduce.provenance import machine_text
from ..reproduce.store import current_sha256, made_with, read_json
from .plan import RobustnessConfig, axis

__all__ = [
    "before_after",
    "computed_where",
    "episodes",
    "load_cells",
    "load_records",
    "paired_change",
    "pct",
    "rate_band",
    "stale_records",
    "stored_cell",
]


def _cell(method: str, spec: str, n: int, obstacles: int) -> Cell:
    return Cell(method, obstacles, n, None if base_method(method) in BASELINES else 0, None, spec)


def stale_records(cfg: RobustnessConfig, records: dict) -> dict[tuple[str, str, int, int], str]:
    """The keys of ``records`` (:func:`load_records`) whose cell was computed with another checkpoint than the one
    now under ``cfg.checkpoints``: ``{key: stored sha256}`` (none where the current checkpoint cannot be read)."""
    methods = {base_method(m) for m in cfg.controllers} - set(BASELINES)
    shas = {m: current_sha256(cfg.checkpoints, m, 0) for m in methods}  # the shipped checkpoints: training seed 0
    out = {}
    for key, rec in records.items():
        now = shas.get(base_method(key[0]))
        stored = rec["key"].get("checkpoint_sha256")
        if now is not None and stored is not None and stored != now:
            out[key] = stored
    return out


def load_records(cfg: RobustnessConfig) -> dict[tuple[str, str, int, int], dict]:
    """``{(method, axis-level spec, N, obstacles): record}`` of every computed cell, the whole stored record (``row``
    and ``meta``); the level spec as the axis names it, a controller that does not read messages looked up under
    the level's state-level spec (so one stored cell can stand under several keys). Only cells made with ``cfg``'s
    settings count (episodes, seed, area, episode length, results version: :func:`egcbf.reproduce.store.made_with`);
    the others show as pending. Cells of another checkpoint than the current one are kept here; the report leaves
    them out as stale (:func:`stale_records`)."""
    out = {}
    for a in (axis(n) for n in cfg.axes):
        for spec in a.specs():
            for m in cfg.controllers:
                run = cfg.cell_spec(m, spec)
                if run is None:
                    continue
                sweep = cfg.sweep(run, (m,))
                for n in cfg.num_agents:
                    for k in (0, cfg.obstacles):
                        cell = _cell(m, run, n, k)
                        rec = read_json(cell.path(cfg.out))
                        if made_with(rec, sweep, cell):
                            out[(m, spec, n, k)] = rec
    return out


def unreadable_files(cfg: RobustnessConfig) -> list:
    """The cell files of every sweep of ``cfg`` that exist but cannot be read (:func:`egcbf.reproduce.store.
    unreadable_cells`; each once, sorted): the report shows them as pending, the command line names them."""
    from ..reproduce.store import unreadable_cells

    return sorted({p for _, _, sw in cfg.sweeps() for p in unreadable_cells(sw)})


def load_cells(cfg: RobustnessConfig) -> dict[tuple[str, str, int, int], dict]:
    """``{(method, axis-level spec, N, obstacles): row}`` of every computed cell (:func:`load_records`' rows)."""
    return {key: rec["row"] for key, rec in load_records(cfg).items()}


def stored_cell(cfg: RobustnessConfig, key: tuple[str, str, int, int]) -> tuple[str, str, int, int]:
    """The stored cell behind a :func:`load_records` key ``(method, axis-level spec, N, obstacles)``: the spec
    replaced by the one the method runs (:meth:`RobustnessConfig.cell_spec`), so keys sharing a file compare equal."""
    m, spec, n, k = key
    return m, cfg.cell_spec(m, spec), n, k


def computed_where(cfg: RobustnessConfig, records: dict[tuple[str, str, int, int], dict]) -> list[tuple[str, int]]:
    """``[(where, cells)]``, most cells first: the stored cells of ``records`` (:func:`load_records`) counted once
    each by the machine, torch build and device their meta records (cells of equal settings from different
    machines agree in distribution, not necessarily bit for bit, where the torch build or CPU differs)."""
    stored = {stored_cell(cfg, key): rec for key, rec in records.items()}
    where = Counter()
    for rec in stored.values():
        meta = rec.get("meta", {})
        machine = meta.get("machine") or {}
        device = meta.get("device") or "cpu"
        where[f"{machine_text(machine)}, torch {machine.get('torch', 'not recorded')}, device {device}"] += 1
    return sorted(where.items(), key=lambda p: (-p[1], p[0]))


def episodes(row: dict, key: str) -> list[float]:
    return list(row.get("per_episode", {}).get(key, [])) or [row[key]]


def rate_band(row: dict, key: str) -> tuple[float, float]:
    """The 95 % band over episodes of the rate ``key`` of one cell (``(rate, rate)`` with fewer than two
    episodes): the figures' bands and the report's borderline marks use this one interval."""
    values = episodes(row, key)
    if len(values) < 2:
        return row[key], row[key]
    ci = mean_ci([values], resamples=2000)
    return ci.low, ci.high


def pct(row: dict | None, key: str) -> str:
    return "-" if row is None else f"{100 * row[key]:.2f}"


def code_list(names) -> str:
    """The names as a comma list of inline code (`` `a`, `b` ``), in their order."""
    return ", ".join(f"`{name}`" for name in names)


def paired_interval(before: dict, after: dict, key: str = "safe_rate") -> Interval | None:
    """``after - before`` of the rate ``key`` with its paired 95 % interval (the same scenes, episode by episode;
    the rows' ``per_episode`` values in episode order); ``None`` without two paired episodes."""
    a, b = episodes(after, key), episodes(before, key)
    if len(a) != len(b) or len(a) < 2:
        return None
    return mean_ci([[x - y for x, y in zip(a, b)]], resamples=2000)


def paired_change(clean: dict, faulty: dict) -> str:
    """Safe-rate change (points) with its paired 95 % interval (the same scenes, episode by episode)."""
    interval = paired_interval(clean, faulty)
    if interval is None:
        return f"{100 * (faulty['safe_rate'] - clean['safe_rate']):+.2f}"
    return interval.text(100, 2)


def before_after(before: dict | None, after: dict | None) -> str:
    """The table cells ``safe before | safe after | change [95 % CI] | success before | success after``."""
    change = "-" if before is None or after is None else paired_change(before, after)
    return (f"{pct(before, 'safe_rate')} | {pct(after, 'safe_rate')} | {change} | {pct(before, 'success_rate')} | "
            f"{pct(after, 'success_rate')}")  # fmt: skip
