"""What ``egcbf reproduce`` evaluates: its cells, where their results live and what each result depends on."""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from ..control.names import path_name
from .paper import BASELINES, DEFAULT_SIZES, FILTERED, LEARNED, MARL, METHODS, SCALE_SIZES, base_method, method_filter

__all__ = ["BACKENDS", "Cell", "SweepConfig", "cell_key", "filter_settings"]

BACKENDS = ("process", "ray")


class Cell(NamedTuple):
    """One evaluation of the sweep: ``method`` with ``obstacles`` obstacles at ``num_agents`` agents.

    ``train_seed`` is the training seed of a learned method's checkpoint (``None`` for the hand-crafted
    controllers); a method behind a run-time filter (``egcbf+:dcbf``) uses its base method's checkpoint. ``area``
    is ``None`` for Table I's cells (the sweep's ``l``) and the side ``l`` of the arena for the cells of the
    scalability study past Table I (``N`` at the density of ``scale_reference`` agents). ``faults``: the
    :mod:`egcbf.faults` spec the cell runs under (``"none"``: the perfect world; ``egcbf robustness``). ``steps``:
    the episode length of a cell of the scalability study's second, longer horizon (``None``: the sweep's
    ``max_steps``)."""

    method: str
    obstacles: int
    num_agents: int
    train_seed: int | None = None
    area: float | None = None
    faults: str = "none"
    steps: int | None = None

    @property
    def run(self) -> str:
        """``egcbf+`` (training seed 0 or a baseline) or ``egcbf+-s2`` (training seed 2); ``egcbf+:dcbf-s2``
        behind a run-time filter."""
        return self.method if not self.train_seed else f"{self.method}-s{self.train_seed}"

    @property
    def base(self) -> str:
        """The method whose checkpoint (and training seeds) the cell uses: ``egcbf+`` for ``egcbf+:dcbf``."""
        return base_method(self.method)

    @property
    def filter(self) -> str:
        """The cell's run-time filter: ``"dcbf"`` for ``egcbf+:dcbf``, ``"none"`` for a method alone."""
        return method_filter(self.method)

    @property
    def scale(self) -> bool:
        """Whether the cell belongs to the scalability study (fixed density) rather than Table I."""
        return self.area is not None

    def path(self, out: str | Path) -> Path:
        """Its result file: ``OUT/<run>_obs<k>/N<n>.json``, or ``OUT/scale/<run>_obs<k>/N<n>.json`` (``METHOD:FILTER``
        written ``METHOD_FILTER``: ``OUT/egcbf+_dcbf-s2_obs0/N512.json``), ``OUT/scale-<steps>-steps/...`` at the long
        horizon; under faults ``OUT/faults/<spec>/...`` (the spec with every run of characters other than letters,
        digits, ``.`` and ``-`` written ``_``)."""
        base = Path(out)
        if self.scale:
            base = base / ("scale" if self.steps is None else f"scale-{self.steps}-steps")
        if self.faults != "none":
            base = Path(out) / "faults" / re.sub(r"[^A-Za-z0-9.-]+", "_", self.faults) / base.relative_to(out)
        return base / f"{path_name(self.run)}_obs{self.obstacles}" / f"N{self.num_agents}.json"


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_types(cfg: SweepConfig) -> None:
    """A :class:`TypeError` naming the field for a value of the wrong type: a float where an integer belongs (it would
    be truncated: a seed of 1.5 run as seed 1), a string where a sequence belongs (``methods="egcbf+"`` read as its
    characters), a bare number where a sequence belongs."""
    for name in ("seed", "obstacles", "episodes", "scale_reference", "scale_agent_episodes", "workers", "threads"):
        value = getattr(cfg, name)
        if not _is_int(value):
            raise TypeError(f"SweepConfig.{name} must be an integer, got {value!r}")
    for name in ("baseline_episodes", "max_steps"):
        value = getattr(cfg, name)
        if value is not None and not _is_int(value):
            raise TypeError(f"SweepConfig.{name} must be an integer or None, got {value!r}")
    if not isinstance(cfg.area, numbers.Real) or isinstance(cfg.area, bool) or not math.isfinite(cfg.area):
        raise TypeError(f"SweepConfig.area must be a finite number, got {cfg.area!r}")
    for name in ("methods", "obstacle_methods", "seed_methods", "scale_methods"):
        value = getattr(cfg, name)
        if isinstance(value, str) or not isinstance(value, (tuple, list)) or not all(isinstance(m, str) for m in value):
            raise TypeError(f"SweepConfig.{name} must be a tuple of method names (e.g. ('egcbf+',)), got {value!r}")
    for name in ("num_agents", "train_seeds", "scale_sizes"):
        value = getattr(cfg, name)
        if isinstance(value, str) or not isinstance(value, (tuple, list)) or not all(_is_int(v) for v in value):
            raise TypeError(f"SweepConfig.{name} must be a tuple of integers (e.g. (8, 16)), got {value!r}")


def _positive_ints(name: str, values) -> None:
    if any(int(v) < 1 for v in values):
        raise ValueError(f"{name} needs positive integers, got {tuple(values)}")


@dataclass(frozen=True)
class SweepConfig:
    """What to evaluate and how.

    **Table I.** ``methods`` run at every ``num_agents`` in ``[0, area]^3`` without obstacles; those also in
    ``obstacle_methods`` run again with ``obstacles`` obstacles (``obstacles=0``: no obstacle setting).
    ``episodes`` per cell (``baseline_episodes``, if set, replaces it for the hand-crafted controllers, e.g. to
    reuse their 50-episode runs while the learned methods run fewer).

    **Training seeds.** The learned methods of ``seed_methods`` run once per seed of ``train_seeds`` (the
    checkpoint ``CHECKPOINTS/<method>`` for seed 0, ``CHECKPOINTS/seeds/<method>-s<k>`` for seed ``k``); the other
    learned methods run their seed-0 checkpoint.

    **Run-time filters** (``FILTERED``, ``METHOD:FILTER``): a learned method behind a filter runs the checkpoints
    and training seeds of its base method (``egcbf+:dcbf`` those of ``egcbf+``), ``nominal:dcbf`` none; the filter
    has ``egcbf eval --filter``'s default settings (:func:`filter_settings`), recorded in the cell's key and meta.

    **Scalability past Table I.** The methods of ``scale_methods`` (among ``methods``) also run without obstacles
    at every ``scale_sizes`` N, in the arena of side ``l_N = area (N / scale_reference)^(1/3)`` (the density of
    ``scale_reference`` agents at ``l = area``), for ``ceil(scale_agent_episodes / N)`` episodes (as many
    agent-episodes as ``scale_agent_episodes``: 50 episodes at N = 512 are 25 600). Those also in ``long_methods``
    run these cells again with episodes of ``long_steps`` steps (``None``: no second horizon), long enough for the
    nominal controller alone to reach every goal at these N (``docs/results/horizon/``), where the default 256 steps
    cap the success rate.

    **Faults.** ``faults`` (an :mod:`egcbf.faults` spec, stored canonical: ``FaultConfig.spec()``): every cell runs
    under them (``egcbf robustness`` makes one sweep per fault level); ``"none"``: the perfect world.

    ``seed`` is the evaluation seed (episode ``e`` at size ``N`` resets from
    ``egcbf.evaluate.episodes.episode_seed(seed, N, e)``), ``max_steps`` the episode length (``None``: the environment's
    256 steps of 25 ms). ``checkpoints`` holds the learned methods' checkpoints, ``out`` the cell files, ``baselines``
    earlier ``egcbf eval`` outputs to import baseline cells from (``None``: never import). ``workers`` parallel cells,
    ``threads`` torch threads per cell, ``backend`` ``"process"`` or ``"ray"``."""

    methods: tuple[str, ...] = METHODS
    num_agents: tuple[int, ...] = DEFAULT_SIZES
    area: float = 4.0
    obstacles: int = 8
    obstacle_methods: tuple[str, ...] = (*LEARNED, "nominal", *FILTERED, *MARL)
    episodes: int = 50
    baseline_episodes: int | None = None
    train_seeds: tuple[int, ...] = (0, 1, 2)
    seed_methods: tuple[str, ...] = ("gcbf+", "egcbf+")
    scale_sizes: tuple[int, ...] = SCALE_SIZES
    scale_methods: tuple[str, ...] = METHODS
    scale_reference: int = 512
    scale_agent_episodes: int = 25_600
    long_steps: int | None = 384
    long_methods: tuple[str, ...] = (
        "gcbf+",
        "egcbf+",
        "dcbf",
        "ccbf",
        "nominal",
        "egcbf+:dcbf",
        "gcbf+:dcbf",
        "nominal:dcbf",
    )
    seed: int = 0
    max_steps: int | None = None
    checkpoints: Path = Path("checkpoints")
    out: Path = Path("out/reproduction/cells")
    baselines: Path | None = Path("docs/results/baselines")
    device: str = "cpu"
    workers: int = 2
    threads: int = 1
    backend: str = "process"
    faults: str = "none"

    def __post_init__(self) -> None:
        _check_types(self)
        from ..faults import parse_faults

        if not isinstance(self.faults, str):
            raise TypeError(f"SweepConfig.faults must be a fault spec string, got {self.faults!r}")
        object.__setattr__(self, "faults", parse_faults(self.faults).spec())  # canonical: one spelling, one cell
        for name in ("methods", "obstacle_methods", "scale_methods", "long_methods"):
            bad = [m for m in getattr(self, name) if m not in METHODS]
            if bad:
                raise ValueError(f"unknown method(s) {bad} in {name}; choose from {list(METHODS)}")
        bad = [m for m in self.seed_methods if m not in LEARNED]
        if bad:
            raise ValueError(f"seed_methods must be among the learned {list(LEARNED)}, got {bad}")
        if not self.methods:
            raise ValueError("methods is empty")
        if not self.num_agents:
            raise ValueError("num_agents is empty")
        _positive_ints("num_agents", self.num_agents)
        _positive_ints("scale_sizes", self.scale_sizes)
        if not self.train_seeds or any(int(s) < 0 for s in self.train_seeds):
            raise ValueError(f"train_seeds needs one or more seeds >= 0, got {self.train_seeds}")
        if len(set(self.train_seeds)) != len(self.train_seeds):
            raise ValueError(f"train_seeds has repeats: {self.train_seeds}")
        if self.baseline_episodes is not None and int(self.baseline_episodes) < 1:
            raise ValueError(f"baseline_episodes must be >= 1 or None, got {self.baseline_episodes}")
        for name in ("episodes", "workers", "threads", "scale_reference", "scale_agent_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.obstacles < 0:
            raise ValueError(f"obstacles must be >= 0, got {self.obstacles}")
        if self.area <= 0:
            raise ValueError(f"area must be > 0, got {self.area}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.long_steps is not None and self.long_steps < 1:
            raise ValueError(f"long_steps must be >= 1 or None, got {self.long_steps}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")

    # ------------------------------------------------------------------------------------------------ cells
    def seeds_for(self, method: str) -> tuple[int | None, ...]:
        """The training seeds evaluated for ``method``: ``(None,)`` for a hand-crafted controller (also behind a
        filter); a filtered learned method's are its base method's."""
        base = base_method(method)
        if base in BASELINES:
            return (None,)
        return tuple(int(s) for s in self.train_seeds) if base in self.seed_methods else (0,)

    def scale_area(self, num_agents: int) -> float:
        """``l`` of the scalability cell at ``num_agents``: the density of ``scale_reference`` agents at ``area``
        (rounded to 0.1 mm so that the value, and the cell's key, is the same on every machine)."""
        return round(self.area * (num_agents / self.scale_reference) ** (1.0 / 3.0), 4)

    def table_cells(self) -> list[Cell]:
        """Table I's cells: the no-obstacle setting, then the obstacle setting; methods in paper order."""
        settings = [(0, [m for m in METHODS if m in self.methods])]
        if self.obstacles > 0:
            settings.append((self.obstacles, [m for m in METHODS if m in self.methods and m in self.obstacle_methods]))
        return [
            Cell(m, k, int(n), s, None, self.faults)
            for k, ms in settings
            for m in ms
            for s in self.seeds_for(m)
            for n in self.num_agents
        ]

    def scale_cells(self) -> list[Cell]:
        """The scalability study's cells (no obstacles, fixed density)."""
        ms = [m for m in METHODS if m in self.methods and m in self.scale_methods]
        return [
            Cell(m, 0, int(n), s, self.scale_area(int(n)), self.faults)
            for m in ms
            for s in self.seeds_for(m)
            for n in self.scale_sizes
        ]

    def long_cells(self) -> list[Cell]:
        """The scalability study's cells at the long horizon (``long_steps``; none if it is ``None``)."""
        if self.long_steps is None:
            return []
        steps = int(self.long_steps)
        return [c._replace(steps=steps) for c in self.scale_cells() if c.method in self.long_methods]

    def cells(self) -> list[Cell]:
        """Every cell of the sweep: Table I's, then the scalability study's, then its long-horizon cells."""
        return self.table_cells() + self.scale_cells() + self.long_cells()

    def checkpoint_runs(self) -> list[tuple[str, int]]:
        """``(method, training seed)`` of every learned checkpoint some cell needs (a filtered method's is its base
        method's)."""
        return list(dict.fromkeys((c.base, c.train_seed) for c in self.cells() if c.train_seed is not None))

    # ------------------------------------------------------------------------------------------------ episodes
    def episodes_for(self, cell: Cell) -> int:
        """Episodes of ``cell``: ``ceil(scale_agent_episodes / N)`` in the scalability study; in Table I
        ``baseline_episodes`` for the hand-crafted controllers if set (not behind a filter: the filtered cells are
        never imported), else ``episodes``."""
        if cell.scale:
            return math.ceil(self.scale_agent_episodes / cell.num_agents)
        if cell.method in BASELINES and self.baseline_episodes is not None:
            return int(self.baseline_episodes)
        return int(self.episodes)

    def steps_for(self, cell: Cell) -> int | None:
        """The episode length of ``cell``: its own ``steps`` at the long horizon, else ``max_steps`` (``None``: the
        environment's 256 steps)."""
        return cell.steps if cell.steps is not None else self.max_steps

    def area_for(self, cell: Cell) -> float:
        """The side ``l`` of ``cell``'s arena."""
        return float(self.area if cell.area is None else cell.area)


def filter_settings(method: str) -> dict | None:
    """The run-time filter of ``method`` as ``egcbf eval`` records it in run.json: ``{"filter": kind,
    "filter_config": settings}`` with ``egcbf eval --filter KIND``'s defaults (``FilterConfig.for_kind``); ``None``
    for a method without a filter."""
    kind = method_filter(method)
    if kind == "none":
        return None
    from ..control.filters import FilterConfig

    return {"filter": kind, "filter_config": FilterConfig.for_kind(kind).settings()}


#: The version of what the simulation computes: bump it by hand in the commit that changes a cell's results (the
#: dynamics, a controller, a fault model, the metrics), so that stored cells made before it are not reused.
#: ``tests/egcbf/test_results_version.py`` pins tiny evaluations of every controller under every fault family and
#: fails until the pinned values are regenerated, which is the moment to bump this. Version 1 (every cell stored
#: before versions were keyed) adds no field to the key.
RESULTS_VERSION = 1


def cell_key(cfg: SweepConfig, cell: Cell, checkpoint_sha256: str | None) -> dict:
    """What a cell's result depends on; a stored cell with an equal key is reused. A filtered method's key also
    holds its filter and the filter's settings (:func:`filter_settings`); the keys of the other cells are those of
    the sweep before the filtered methods (so their stored cells are still found); from :data:`RESULTS_VERSION` 2
    on, the version."""
    key = {
        "method": cell.method,
        "obstacles": cell.obstacles,
        "num_agents": cell.num_agents,
        "area": cfg.area_for(cell),
        "episodes": cfg.episodes_for(cell),
        "seed": int(cfg.seed),
        "max_steps": cfg.steps_for(cell),
        "checkpoint_sha256": checkpoint_sha256,
    }
    if cell.faults != "none":  # the keys of the perfect world's cells are those of the sweep before faults existed
        key["faults"] = cell.faults
    if RESULTS_VERSION != 1:
        key["results_version"] = RESULTS_VERSION
    return key | (filter_settings(cell.method) or {})
