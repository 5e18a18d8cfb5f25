"""Reproduce the paper's Table I and its scalability study: ``egcbf reproduce``.

    from egcbf.reproduce import SweepConfig, sweep, write_report
    cfg = SweepConfig(episodes=50, workers=2)
    records = sweep(cfg, command="egcbf reproduce")
    write_report(cfg, records, "docs/reproduction.md")

The sweep evaluates every method (GCBF, GCBF+, dCBF-QP, cCBF-QP, EGCBF, EGCBF+) at every swarm size ``N`` in an
arena ``[0, l]^3`` without obstacles, and the methods of ``obstacle_methods`` with ``obstacles`` sphere obstacles.
One *cell* is one ``(method, obstacles, N)``: it runs :func:`egcbf.evaluate.evaluate` for that single ``N`` (the
same function, seeds and batching as ``egcbf eval``, so a cell's metrics equal those of ``egcbf eval`` at that
``N``) and is written atomically to ``OUT/<method>_obs<k>/N<n>.json``::

    {"key":  what the result depends on (method, obstacles, num_agents, area, episodes, seed, max_steps,
              sha256 of the checkpoint's model.safetensors): a cell file with the same key is never recomputed,
     "row":  the metrics row of docs/metrics.md (rates in [0, 1], cost in collision events per agent per episode,
              reward -sum_t ||u - u_nom||^2 in SI units, step_ms_median in ms per environment step),
     "meta": checkpoint path / step / training seed, wall time of the cell (s), device, machine, and
              "imported_from" when the row was taken from an earlier ``egcbf eval`` output (docs/results/baselines)}

Learned methods load ``CHECKPOINTS/<method>/`` (``config.json`` + ``model.safetensors``, e.g. a run's ``best``
directory); the baselines come from :func:`egcbf.control.controllers.make_controller`. Cells run largest ``N``
first over ``workers`` processes with one torch thread each (``backend="process"``) or as Ray tasks
(``backend="ray"``, the optional ``ray`` extra, for a cluster: a task receives the checkpoint's bytes, not its path,
so the nodes need no shared file system). Either way, the same cell gives the same numbers.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime
import json
import multiprocessing
import os
import shlex
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from tqdm.auto import tqdm

from .atomic import write_json_atomic
from .ckpt_files import sha256
from .dynamics.quadrotor import DEFAULT_DT
from .report import machine_info

__all__ = [
    "BASELINES",
    "DEFAULT_SIZES",
    "LABELS",
    "LEARNED",
    "METHODS",
    "PAPER_TABLE_I",
    "Cell",
    "CellTask",
    "CheckpointInfo",
    "SweepConfig",
    "cell_key",
    "find_method_checkpoint",
    "import_baseline",
    "load_cells",
    "machine_info",
    "provenance_markdown",
    "require_ray",
    "run_cell",
    "scalability_figure",
    "sweep",
    "table_markdown",
    "validate",
    "write_report",
]

LEARNED = ("gcbf", "gcbf+", "egcbf", "egcbf+")
BASELINES = ("dcbf", "ccbf", "nominal")
# the paper's row order, then the nominal controller alone (not in the paper: what the learned residual starts from)
METHODS = ("gcbf", "gcbf+", "dcbf", "ccbf", "egcbf", "egcbf+", "nominal")
LABELS = {
    "nominal": "nominal (no CBF)",
    "gcbf": "GCBF",
    "gcbf+": "GCBF+",
    "dcbf": "dCBF-QP",
    "ccbf": "cCBF-QP",
    "egcbf": "EGCBF",
    "egcbf+": "EGCBF+",
}
DEFAULT_SIZES = (8, 16, 64, 128, 256, 512)
BACKENDS = ("process", "ray")

# The paper's Table I (l = 4): method -> N -> (safe %, reach %, success %, cost, cost min, cost max, reward);
# None where the paper prints '-' (its CBF-QPs stop at N = 16).
PaperRow = tuple[float, float, float, float, float, float, float]
PAPER_TABLE_I: dict[str, dict[int, PaperRow | None]] = {
    "nominal": {},
    "gcbf": {
        8: (100, 100, 100, 0, 0, 0, -315.1),
        16: (97.5, 100, 97.5, 0.33, 0, 2, -311.4),
        64: (87.7, 99.8, 87.5, 1.09, 0.31, 1.96, -315),
        128: (73.9, 99.1, 73.2, 2.47, 1.72, 4.12, -350.5),
        256: (52.1, 98.5, 51.1, 5.98, 4.66, 7.46, -409.3),
        512: (31.6, 96.8, 30, 11.07, 9.97, 13.4, -505.8),
    },
    "gcbf+": {
        8: (100, 100, 100, 0, 0, 0, -17.1),
        16: (100, 100, 100, 0, 0, 0, -17.5),
        64: (96.5, 100, 96.5, 0.23, 0, 1, -49.1),
        128: (93.6, 99.3, 92.9, 0.43, 0, 1.31, -104.2),
        256: (88.8, 98.7, 87.7, 0.72, 0.56, 0.92, -209.9),
        512: (77.8, 96.2, 74.5, 1.51, 1.2, 1.72, -484.2),
    },
    "dcbf": {
        8: (100, 100, 100, 0, 0, 0, -96.3),
        16: (100, 98.125, 98.13, 0, 0, 0, -182.8),
        64: None,
        128: None,
        256: None,
        512: None,
    },
    "ccbf": {
        8: (100, 100, 100, 0, 0, 0, -60.8),
        16: (100, 100, 100, 0, 0, 0, -120.5),
        64: None,
        128: None,
        256: None,
        512: None,
    },
    "egcbf": {
        8: (100, 91.2, 91.2, 0, 0, 0, -349.9),
        16: (100, 93.7, 93.7, 0, 0, 0, -338.5),
        64: (88.4, 94.2, 83.4, 1.256, 0.25, 2, -335.8),
        128: (74.1, 96.7, 71.7, 2.9, 2.04, 3.79, -358.1),
        256: (55.1, 97.5, 53.6, 5.42, 4.23, 7.36, -409.8),
        512: (33.1, 98.7, 31.7, 10.1, 7.03, 15.29, -487.3),
    },
    "egcbf+": {
        8: (100, 100, 100, 0, 0, 0, -9.3),
        16: (100, 100, 100, 0, 0, 0, -14.1),
        64: (98.8, 99.7, 98.5, 0.04, 0, 0.21, -34.7),
        128: (97.9, 99.5, 97, 0.12, 0, 0.23, -52.1),
        256: (94.2, 96.6, 91.1, 0.26, 0.06, 0.51, -97.8),
        512: (89.5, 92.1, 83.3, 0.51, 0.23, 0.73, -224.8),
    },
}


# ---------------------------------------------------------------------------------------------------- plan
class Cell(NamedTuple):
    """One evaluation of the sweep: ``method`` with ``obstacles`` obstacles at ``num_agents`` agents."""

    method: str
    obstacles: int
    num_agents: int

    def path(self, out: str | Path) -> Path:
        """Its result file ``OUT/<method>_obs<k>/N<n>.json``."""
        return Path(out) / f"{self.method}_obs{self.obstacles}" / f"N{self.num_agents}.json"


@dataclass(frozen=True)
class SweepConfig:
    """What to evaluate and how.

    ``methods`` run without obstacles; those of them also in ``obstacle_methods`` run again with ``obstacles``
    obstacles (``obstacles=0``: no obstacle setting). ``area`` is ``l`` (m), ``episodes`` per cell
    (``baseline_episodes``, if set, replaces it for the CBF-QP baselines, e.g. to reuse their 50-episode runs
    while the learned methods run fewer), ``seed`` the evaluation seed (episode ``e`` at size ``N`` resets from
    ``egcbf.evaluate.episode_seed(seed, N, e)``), ``max_steps`` the episode length (``None``: the environment's
    256 steps of 25 ms). ``checkpoints`` holds one
    checkpoint directory per learned method, ``out`` the cell files, ``baselines`` earlier ``egcbf eval`` outputs
    to import baseline cells from (``None``: never import). ``workers`` parallel cells, ``threads`` torch threads
    per cell, ``backend`` ``"process"`` or ``"ray"``.
    """

    methods: tuple[str, ...] = METHODS
    num_agents: tuple[int, ...] = DEFAULT_SIZES
    area: float = 4.0
    obstacles: int = 8
    obstacle_methods: tuple[str, ...] = (*LEARNED, "nominal")
    episodes: int = 50
    baseline_episodes: int | None = None
    seed: int = 0
    max_steps: int | None = None
    checkpoints: Path = Path("checkpoints")
    out: Path = Path("docs/results/reproduction")
    baselines: Path | None = Path("docs/results/baselines")
    device: str = "cpu"
    workers: int = 2
    threads: int = 1
    backend: str = "process"

    def __post_init__(self) -> None:
        for name in ("methods", "obstacle_methods"):
            bad = [m for m in getattr(self, name) if m not in METHODS]
            if bad:
                raise ValueError(f"unknown method(s) {bad} in {name}; choose from {list(METHODS)}")
        if not self.methods:
            raise ValueError("methods is empty")
        if not self.num_agents or any(int(n) < 1 for n in self.num_agents):
            raise ValueError(f"num_agents needs positive integers, got {self.num_agents}")
        if self.baseline_episodes is not None and int(self.baseline_episodes) < 1:
            raise ValueError(f"baseline_episodes must be >= 1 or None, got {self.baseline_episodes}")
        for name in ("episodes", "workers", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.obstacles < 0 or self.area <= 0:
            raise ValueError(f"need obstacles >= 0 and area > 0, got {self.obstacles}, {self.area}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")

    def cells(self) -> list[Cell]:
        """Every cell of the sweep: the no-obstacle setting, then the obstacle setting; methods in paper order."""
        settings = [(0, [m for m in METHODS if m in self.methods])]
        if self.obstacles > 0:
            settings.append((self.obstacles, [m for m in METHODS if m in self.methods and m in self.obstacle_methods]))
        return [Cell(m, k, int(n)) for k, ms in settings for m in ms for n in self.num_agents]

    def episodes_text(self) -> str:
        """``"50 episodes per cell"`` or ``"10 episodes per cell (CBF-QP baselines: 50)"``."""
        text = f"{self.episodes} episodes per cell"
        if self.baseline_episodes is not None and self.baseline_episodes != self.episodes:
            text += f" (CBF-QP baselines: {self.baseline_episodes})"
        return text

    def episodes_for(self, method: str) -> int:
        """Episodes per cell of ``method``: ``baseline_episodes`` for the CBF-QP baselines if set, else ``episodes``."""
        if method in BASELINES and self.baseline_episodes is not None:
            return int(self.baseline_episodes)
        return int(self.episodes)

    def learned_methods(self) -> list[str]:
        """The learned methods that appear in some cell."""
        return [m for m in LEARNED if m in {c.method for c in self.cells()}]


# ---------------------------------------------------------------------------------------------------- checkpoints
@dataclass(frozen=True)
class CheckpointInfo:
    """A learned method's checkpoint directory, the sha256 of its weights, its update and training seed."""

    method: str
    path: Path
    sha256: str
    step: int | None
    train_seed: int | None

    def files(self) -> dict[str, bytes]:
        """``config.json`` and ``model.safetensors`` as bytes (what a cell needs, shipped to remote workers)."""
        return {name: (self.path / name).read_bytes() for name in ("config.json", "model.safetensors")}


def find_method_checkpoint(root: str | Path, method: str) -> CheckpointInfo:
    """The checkpoint of ``method`` under ``root``: ``root/<method>`` itself, or its ``best`` subdirectory.

    Raises ``FileNotFoundError`` if there is none, :class:`~egcbf.ckpt_files.CheckpointError` (a ``ValueError``
    naming the file) if its files are corrupted, truncated or of another method."""
    from .ckpt_files import check_identity, read_config, read_state, read_tensors

    base = Path(root) / method
    path = next((d for d in (base, base / "best") if (d / "model.safetensors").exists()), None)
    if path is None or not (path / "config.json").exists():
        raise FileNotFoundError(
            f"no checkpoint for {method} in {base} (expected {base}/config.json and {base}/model.safetensors): "
            f"train one with `egcbf train --algo {method} --out runs/{method}`, then copy runs/{method}/best to {base}"
        )
    train_cfg = read_config(path)
    if train_cfg.algo != method:
        raise ValueError(f"{path}/config.json is a {train_cfg.algo!r} checkpoint, expected {method!r}")
    state = read_state(path)
    read_tensors(path / "model.safetensors")  # a truncated or corrupted file fails here, before any cell runs
    check_identity(path, train_cfg, state)
    step = state.get("step")
    return CheckpointInfo(method, path, sha256(path / "model.safetensors"), step, train_cfg.seed)


# ---------------------------------------------------------------------------------------------------- one cell
@dataclass(frozen=True)
class CellTask:
    """Everything a worker needs to evaluate one cell (picklable; a learned method carries its checkpoint files)."""

    cell: Cell
    area: float
    episodes: int
    seed: int
    max_steps: int | None
    device: str
    threads: int = 1
    checkpoint_files: dict[str, bytes] | None = None
    progress: bool = False


def _evaluate_cell(task: CellTask) -> dict:
    from .control.controllers import make_controller
    from .evaluate import evaluate

    learned, env_overrides = None, None
    with tempfile.TemporaryDirectory(prefix="egcbf-ckpt-") as tmp:
        if task.checkpoint_files is not None:  # the same loading as `egcbf eval --checkpoint`
            from .train import load_controller

            for name, data in task.checkpoint_files.items():
                (Path(tmp) / name).write_bytes(data)
            learned, train_cfg = load_controller(tmp, device=task.device, dtype=torch.float32)
            env_overrides = dict(train_cfg.env_overrides)
    rows, _ = evaluate(
        (lambda cfg: learned) if learned is not None else (lambda cfg: make_controller(task.cell.method)),
        [task.cell.num_agents],
        area_size=task.area,
        num_obstacles=task.cell.obstacles,
        episodes=task.episodes,
        seed=task.seed,
        max_steps=task.max_steps,
        device=task.device,
        dtype=torch.float32,
        show_progress=task.progress,
        env_overrides=env_overrides,
    )
    return rows[0]


def run_cell(task: CellTask) -> dict:
    """Evaluate one cell with ``task.threads`` torch threads: ``{"row": metrics row, "wall_s": s, "machine": ...}``."""
    saved = torch.get_num_threads()
    torch.set_num_threads(task.threads)
    try:
        t0 = time.perf_counter()
        row = _evaluate_cell(task)
        wall = time.perf_counter() - t0
        return {"row": row, "wall_s": round(wall, 2), "machine": machine_info()}
    finally:
        torch.set_num_threads(saved)


# ---------------------------------------------------------------------------------------------------- cell files
def cell_key(cfg: SweepConfig, cell: Cell, checkpoint: CheckpointInfo | None) -> dict:
    """What a cell's result depends on; a stored cell with an equal key is reused."""
    return {
        "method": cell.method,
        "obstacles": cell.obstacles,
        "num_agents": cell.num_agents,
        "area": float(cfg.area),
        "episodes": cfg.episodes_for(cell.method),
        "seed": int(cfg.seed),
        "max_steps": cfg.max_steps,
        "checkpoint_sha256": None if checkpoint is None else checkpoint.sha256,
    }


def _write_json_atomic(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, obj)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _record(cfg: SweepConfig, cell: Cell, key: dict, ckpt: CheckpointInfo | None, row: dict, **meta) -> dict:
    base = {
        "method": cell.method,
        "label": LABELS[cell.method],
        "num_agents": cell.num_agents,
        "obstacles": cell.obstacles,
        "area": float(cfg.area),
        "episodes": cfg.episodes_for(cell.method),
        "seed": cfg.seed,
        "max_steps": cfg.max_steps,
        "checkpoint": None if ckpt is None else str(ckpt.path),
        "checkpoint_step": None if ckpt is None else ckpt.step,
        "train_seed": None if ckpt is None else ckpt.train_seed,
        "device": cfg.device,
        "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    base.update(meta)
    return {"key": key, "row": row, "meta": base}


_NOT_IMPORTABLE = ("--max-steps", "--batch", "--dtype", "--checkpoint")


def import_baseline(baselines: str | Path, cell: Cell, key: dict) -> tuple[dict, dict] | None:
    """``(row, meta)`` of ``cell`` from an ``egcbf eval`` output ``BASELINES/<method>[_obs<k>]`` made with the same
    episodes, seed, area, obstacles and default episode length, batching, dtype and device; else ``None``."""
    if cell.method not in BASELINES or key["max_steps"] is not None:
        return None
    d = Path(baselines) / (cell.method if cell.obstacles == 0 else f"{cell.method}_obs{cell.obstacles}")
    rows, run = _read_json(d / "metrics.json"), _read_json(d / "run.json")
    if not isinstance(rows, list) or not isinstance(run, dict):
        return None
    args = shlex.split(run.get("command", ""))
    same = (
        run.get("controller") == cell.method
        and run.get("checkpoint") is None
        and run.get("episodes") == key["episodes"]
        and run.get("seed") == key["seed"]
        and run.get("obstacles") == cell.obstacles
        and float(run.get("area", -1)) == key["area"]
        and not any(a.split("=")[0] in _NOT_IMPORTABLE for a in args)
        and ("--device" not in args or args[args.index("--device") + 1 :][:1] == ["cpu"])
    )
    row = next((r for r in rows if r.get("num_agents") == cell.num_agents), None) if same else None
    if row is None:
        return None
    meta = {"imported_from": str(d), "command": run.get("command"), "wall_s": None, "machine": run.get("machine")}
    return row, meta


# ---------------------------------------------------------------------------------------------------- backends
def require_ray():
    """The ``ray`` module, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ImportError(
            "--backend ray needs Ray, an optional extra: pip install -e '.[ray]' (or pip install 'ray>=2.9')"
        ) from None
    return ray


def _init_worker(threads: int) -> None:
    torch.set_num_threads(threads)


def _run_local(tasks: Sequence[CellTask]) -> Iterator[tuple[CellTask, dict]]:
    for task in tasks:
        yield task, run_cell(task)


def _run_processes(tasks: Sequence[CellTask], workers: int) -> Iterator[tuple[CellTask, dict]]:
    ctx = multiprocessing.get_context("spawn")  # never fork a process whose torch thread pools are running
    ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(1,))
    try:
        futures = {ex.submit(run_cell, t): t for t in tasks}  # submitted in order: largest N starts first
        for fut in cf.as_completed(futures):
            yield futures[fut], fut.result()
    finally:
        ex.shutdown(wait=True, cancel_futures=True)


def _run_ray(tasks: Sequence[CellTask]) -> Iterator[tuple[CellTask, dict]]:
    ray = require_ray()
    if not ray.is_initialized():
        ray.init()  # RAY_ADDRESS selects a cluster; otherwise a local one
    remote = ray.remote(num_cpus=tasks[0].threads if tasks else 1)(run_cell)
    pending = {remote.remote(t): t for t in tasks}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            yield pending.pop(ref), ray.get(ref)


def _execute(tasks: Sequence[CellTask], backend: str, workers: int) -> Iterator[tuple[CellTask, dict]]:
    if backend == "ray":
        return _run_ray(tasks)
    if workers <= 1 or len(tasks) <= 1:
        return _run_local(tasks)
    return _run_processes(tasks, min(workers, len(tasks)))


# ---------------------------------------------------------------------------------------------------- the sweep
def _schedule(cells: Sequence[Cell]) -> list[Cell]:
    """Largest ``N`` first (the longest cells start first, so the workers finish together)."""
    order = {m: i for i, m in enumerate(("ccbf", "dcbf", *LEARNED, "nominal"))}
    return sorted(cells, key=lambda c: (-c.num_agents, -c.obstacles, order[c.method]))


def _checkpoints(cfg: SweepConfig) -> dict[str, CheckpointInfo]:
    return {m: find_method_checkpoint(cfg.checkpoints, m) for m in cfg.learned_methods()}


def validate(cfg: SweepConfig) -> dict[str, CheckpointInfo]:
    """Fail early (FileNotFoundError, ValueError, ImportError) on missing checkpoints or a missing backend; returns
    the checkpoints of the learned methods of the sweep."""
    if cfg.backend == "ray":
        require_ray()
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {cfg.device!r} was given but torch.cuda.is_available() is False")
    return _checkpoints(cfg)


def _log_cell(log: Callable[[str], None], rec: dict) -> None:
    r, m = rec["row"], rec["meta"]
    how = f"imported from {m['imported_from']}" if m.get("imported_from") else f"{m['wall_s']:.1f} s"
    log(
        f"{m['label']:8s} obstacles {m['obstacles']:2d}  N {m['num_agents']:4d}: safe {100 * r['safe_rate']:5.1f}%  "
        f"reach {100 * r['reach_rate']:5.1f}%  success {100 * r['success_rate']:5.1f}%  ({how})"
    )


def _append_invocation(out: Path, entry: dict) -> None:
    log = _read_json(out / "sweep.json")
    log = log if isinstance(log, list) else []
    log.append(entry)
    _write_json_atomic(out / "sweep.json", log)


def sweep(
    cfg: SweepConfig,
    *,
    command: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict[Cell, dict]:
    """Run every cell of ``cfg`` that has no up-to-date result in ``cfg.out`` (module doc); returns every cell's
    record ``{"key", "row", "meta"}``. Appends this invocation (command, wall time, counts) to ``OUT/sweep.json``."""
    log = log or tqdm.write
    t0 = time.perf_counter()
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    ckpts = validate(cfg)
    records, todo, counts = {}, [], {"reused": 0, "imported": 0, "computed": 0}
    for cell in cfg.cells():
        key = cell_key(cfg, cell, ckpts.get(cell.method))
        old = _read_json(cell.path(cfg.out))
        if isinstance(old, dict) and old.get("key") == key:
            records[cell], counts["reused"] = old, counts["reused"] + 1
            continue
        found = None if cfg.baselines is None else import_baseline(cfg.baselines, cell, key)
        if found is not None:
            rec = _record(cfg, cell, key, None, found[0], **found[1])
            _write_json_atomic(cell.path(cfg.out), rec)
            records[cell], counts["imported"] = rec, counts["imported"] + 1
            continue
        todo.append(cell)
    local = cfg.backend == "process" and (cfg.workers <= 1 or len(todo) <= 1)
    tasks = [
        CellTask(
            cell=c,
            area=float(cfg.area),
            episodes=cfg.episodes_for(c.method),
            seed=cfg.seed,
            max_steps=cfg.max_steps,
            device=cfg.device,
            threads=cfg.threads,
            checkpoint_files=ckpts[c.method].files() if c.method in ckpts else None,
            progress=progress and local,
        )
        for c in _schedule(todo)
    ]
    bar = tqdm(total=len(tasks), desc="reproduce", unit="cell", disable=not progress)
    try:
        for task, res in _execute(tasks, cfg.backend, cfg.workers):
            cell = task.cell
            ckpt = ckpts.get(cell.method)
            rec = _record(
                cfg, cell, cell_key(cfg, cell, ckpt), ckpt, res["row"], wall_s=res["wall_s"], machine=res["machine"]
            )
            _write_json_atomic(cell.path(cfg.out), rec)
            records[cell], counts["computed"] = rec, counts["computed"] + 1
            bar.update(1)
            _log_cell(log, rec)
    finally:
        bar.close()
        entry = {
            "command": command,
            "started": started,
            "wall_s": round(time.perf_counter() - t0, 1),
            "backend": cfg.backend,
            "workers": cfg.workers,
            "threads_per_cell": cfg.threads,
            **counts,
            "machine": machine_info(),
        }
        _append_invocation(Path(cfg.out), entry)
    return {c: records[c] for c in cfg.cells() if c in records}


def load_cells(cfg: SweepConfig) -> dict[Cell, dict]:
    """The stored records of ``cfg``'s cells made with its episodes, seed, area and episode length (any checkpoint:
    for regenerating the report without the checkpoints)."""
    out = {}
    for cell in cfg.cells():
        rec = _read_json(cell.path(cfg.out))
        if not isinstance(rec, dict) or "key" not in rec:
            continue
        want = cell_key(cfg, cell, None)
        if all(rec["key"].get(k) == v for k, v in want.items() if k != "checkpoint_sha256"):
            out[cell] = rec
    return out


# ---------------------------------------------------------------------------------------------------- report
def _fmt_ours(row: dict | None) -> list[str]:
    if row is None:
        return ["pending"] + [""] * 5
    return [
        f"{100 * row['safe_rate']:.1f}",
        f"{100 * row['reach_rate']:.1f}",
        f"{100 * row['success_rate']:.1f}",
        f"{row['cost']:.3f} ({row['cost_min']:.2f}/{row['cost_max']:.2f})",
        f"{row['reward']:.4g}",
        f"{row['step_ms_median']:.2f}",
    ]


def _fmt_paper(p: PaperRow | None) -> list[str]:
    if p is None:
        return ["-"] * 5
    safe, reach, succ, cost, lo, hi, rew = p
    return [f"{safe:g}", f"{reach:g}", f"{succ:g}", f"{cost:g} ({lo:g}/{hi:g})", f"{rew:g}"]


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def table_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """Our metrics beside the paper's Table I per swarm size (no obstacles), then the obstacle setting."""
    ours = ["Safe %", "Reach %", "Succ %", "Cost (min/max)", "Rew", "step ms"]
    paper = ["paper Safe", "paper Reach", "paper Succ", "paper Cost (min/max)", "paper Rew"]
    parts = [
        f"l = {cfg.area:g} m, {cfg.episodes_text()}, evaluation seed {cfg.seed}. Rates in %, Cost = "
        "collision events per agent per episode (mean over episodes, min/max over episodes). Our Rew is "
        "-sum_t ||u - u_nom||^2 in SI units (N m and N; `docs/metrics.md`), so its scale differs from "
        "the paper's; compare it between methods, not with the paper. The paper's dCBF/cCBF columns stop at "
        "N = 16 (its QPs did not scale); ours run to the largest N. `step ms`: median wall time of one environment "
        "step (controller + simulation, batched steps divided by their number of environments). `pending`: the "
        "cell has not been computed yet.\n",
        "### Without obstacles, beside the paper's Table I\n",
    ]
    for n in cfg.num_agents:
        rows = []
        for m in (m for m in METHODS if m in cfg.methods):
            rec = records.get(Cell(m, 0, int(n)))
            rows.append([LABELS[m], *_fmt_ours(rec and rec["row"]), *_fmt_paper(PAPER_TABLE_I[m].get(int(n)))])
        parts.append(f"**N = {n}**\n\n" + _md_table(["method", *ours, *paper], rows) + "\n")
    obstacle_cells = [c for c in cfg.cells() if c.obstacles > 0]
    if obstacle_cells:
        parts.append(f"### With {cfg.obstacles} obstacles (not in Table I)\n")
        rows = []
        for c in obstacle_cells:
            rec = records.get(c)
            rows.append([str(c.num_agents), LABELS[c.method], *_fmt_ours(rec and rec["row"])])
        rows.sort(key=lambda r: int(r[0]))
        parts.append(_md_table(["N", "method", *ours], rows) + "\n")
    return "\n".join(parts)


def scalability_figure(cfg: SweepConfig, records: dict[Cell, dict], out_png: str | Path) -> Path:
    """Safe and success rates (%) against N (log2 axis): solid with obstacles, dashed without; one colour per
    method. Returns ``out_png``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2, sharey=True)
    settings = [(cfg.obstacles, "-o", 1.0)] if cfg.obstacles > 0 else []
    settings.append((0, "--s" if settings else "-o", 0.6 if settings else 1.0))
    for i, method in enumerate(METHODS):
        for k, style, alpha in settings:
            pts = sorted(
                (c.num_agents, r["row"]) for c, r in records.items() if c.method == method and c.obstacles == k
            )
            if not pts:
                continue
            label = LABELS[method] + ("" if k or len(settings) == 1 else " (no obstacles)")
            for ax, metric in zip(axes, ("safe_rate", "success_rate")):
                y = [100 * row[metric] for _, row in pts]
                color = "k" if method == "nominal" else f"C{i}"
                ax.plot([n for n, _ in pts], y, style, color=color, label=label, ms=4, lw=1.5, alpha=alpha)
    for ax, title in zip(axes, ("safety rate", "success rate")):
        ax.set_xscale("log", base=2)
        ax.set_xticks(list(cfg.num_agents), [str(n) for n in cfg.num_agents])
        ax.set_xlabel("number of agents N")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("%")
    setting = f", solid: {cfg.obstacles} obstacles, dashed: no obstacles" if cfg.obstacles else ", no obstacles"
    fig.suptitle(f"l = {cfg.area:g} m, {cfg.episodes_text().replace('cell', 'point')}{setting}", fontsize=10)
    axes[0].set_ylim(-3, 103)
    axes[1].legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    return out


def _rel(path: Path, report: Path) -> str:
    return Path(os.path.relpath(path, report.parent)).as_posix()


def _scalability_section(cfg: SweepConfig, records: dict[Cell, dict], report: Path, figures: Path) -> str:
    if not records:
        return "No cells computed yet."
    png = scalability_figure(cfg, records, figures / "reproduction_scalability.png")
    return (
        f"![safety and success rate against N]({_rel(png, report)})\n\nSafety rate (left) and success rate "
        f"(right) against the number of agents, l = {cfg.area:g}, {cfg.episodes_text().replace('cell', 'point')}: "
        "solid lines "
        f"with {cfg.obstacles} obstacles, dashed lines without obstacles."
    )


def _convergence_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    from .curves import training_curves

    runs = {LABELS[m]: cfg.checkpoints / m for m in LEARNED if (cfg.checkpoints / m / "metrics.csv").exists()}
    if not runs:
        return f"Training curves: no `{cfg.checkpoints}/<method>/metrics.csv` (copy each run's metrics.csv there)."
    try:
        png = training_curves(runs, figures / "reproduction_convergence.png")
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"Training curves failed: `{type(err).__name__}: {err}`."
    return (
        f"![training curves]({_rel(png, report)})\n\nSafe, reach and success rates of the evaluation rollouts "
        "during training, against update (top) and wall time (bottom); circles mark the shipped checkpoints."
    )


def _contour_section(cfg: SweepConfig, report: Path, figures: Path) -> str:
    from .contour import cbf_contour_figure

    ckpts = {}
    for m in ("egcbf+", "gcbf+"):
        try:
            ckpts[LABELS[m]] = find_method_checkpoint(cfg.checkpoints, m).path
        except (FileNotFoundError, ValueError):
            continue
    if not ckpts:
        return f"CBF contour figure: no EGCBF+ or GCBF+ checkpoint under `{cfg.checkpoints}`."
    png = figures / "reproduction_contour.png"
    try:
        diffs = cbf_contour_figure(ckpts, png)
    except Exception as err:  # a figure must not lose a finished sweep's report
        return f"CBF contour figure failed: `{type(err).__name__}: {err}`."
    gaps = ", ".join(f"{k}: {v:.2e}" for k, v in (diffs or {}).items())
    return (
        f"![CBF contour]({_rel(png, report)})\n\nThe learned CBF of one agent over the horizontal plane in a scene "
        f"G and in its transformed copy phi_g(G) (`egcbf.contour`); max |h(g . G) - h(G)|: {gaps}."
    )


def _duration(seconds: float) -> str:
    """``3.25 h``, ``12.5 min`` or ``40 s``."""
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _wall_by_method(records: dict[Cell, dict]) -> dict[str, tuple[float, int, int]]:
    """method -> (sum of computed cells' wall time in s, computed cells, imported cells)."""
    acc: dict[str, list] = {}
    for c, rec in records.items():
        a = acc.setdefault(c.method, [0.0, 0, 0])
        if rec["meta"].get("imported_from"):
            a[2] += 1
        else:
            a[0], a[1] = a[0] + float(rec["meta"].get("wall_s") or 0.0), a[1] + 1
    return {m: tuple(acc[m]) for m in METHODS if m in acc}


def provenance_markdown(cfg: SweepConfig, records: dict[Cell, dict]) -> str:
    """Commands, seeds, machine, wall times and checkpoints behind the report."""
    invocations = _read_json(Path(cfg.out) / "sweep.json") or []
    commands = list(dict.fromkeys(i.get("command") for i in invocations if i.get("command")))
    lines = ["Commands (every invocation of the sweep into the same results directory):", ""]
    lines += [f"    {c}" for c in commands] or ["    (none recorded)"]
    lines += [
        "",
        f"- Results: `{cfg.out}/<method>_obs<k>/N<n>.json`, one file per cell (metrics row + meta).",
        f"- Evaluation seed {cfg.seed}; episode e at size N resets from `episode_seed({cfg.seed}, N, e)` "
        f"(`egcbf.evaluate`); {cfg.episodes_text()}; episode length "
        f"{cfg.max_steps or 256} steps of {1e3 * DEFAULT_DT:g} ms; l = {cfg.area:g} m; obstacle setting: "
        f"{cfg.obstacles} obstacles.",
    ]
    machines = {
        json.dumps(r["meta"].get("machine"), sort_keys=True) for r in records.values() if r["meta"].get("machine")
    }
    for m in sorted(machines):
        d = json.loads(m)
        lines.append(
            f"- Machine: {d.get('cpu')}, {d.get('cores', '?')} cores, torch {d.get('torch')}, python "
            f"{d.get('python')}, {d.get('threads')} torch thread(s) per cell."
        )
    total = sum(float(i.get("wall_s") or 0.0) for i in invocations)
    last = invocations[-1] if invocations else {}
    lines.append(
        f"- Sweep wall time: {_duration(total)} over {len(invocations)} invocation(s) (last: {last.get('workers')} "
        f"worker(s), backend {last.get('backend')})."
    )
    lines += ["", "| method | cells computed | cells imported | sum of cell wall times | checkpoint | step | "
              "train seed |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for m, (wall, computed, imported) in _wall_by_method(records).items():
        meta = next(r["meta"] for c, r in records.items() if c.method == m)
        sha = next((r["key"].get("checkpoint_sha256") for c, r in records.items() if c.method == m), None)
        ck = f"`{meta.get('checkpoint')}` (sha256 {sha[:12]})" if sha else "-"
        step, seed = meta.get("checkpoint_step"), meta.get("train_seed")
        cells = [LABELS[m], str(computed), str(imported), _duration(wall), ck]
        cells += ["-" if step is None else str(step), "-" if seed is None else str(seed)]
        lines.append("| " + " | ".join(cells) + " |")
    imported = sorted({r["meta"]["imported_from"] for r in records.values() if r["meta"].get("imported_from")})
    if imported:
        lines += ["", "Imported baseline cells (same `evaluate`, seeds and settings) come from:", ""]
        lines += [f"- `{d}`" for d in imported]
    return "\n".join(lines)


_INTRO = """# Reproducing Table I and the scalability study

Generated by `egcbf reproduce` (`src/egcbf/reproduce.py`) from the cell results in `{out}`; the sections between
the `<!-- name:begin/end -->` markers are regenerated, text around them is kept. Regenerate the report alone with
`egcbf reproduce --report-only`.
"""

_SECTIONS = (
    ("table", "## Table I: ours beside the paper's"),
    ("scalability", "## Scalability with obstacles"),
    ("convergence", "## Convergence of training"),
    ("contour", "## CBF contour"),
    ("provenance", "## Provenance"),
)


def write_report(
    cfg: SweepConfig, records: dict[Cell, dict], report: str | Path, figures: str | Path | None = None
) -> Path:
    """Write (or update) the markdown ``report`` and its figures (default: ``<report dir>/figures``)."""
    from .report import replace_section

    report = Path(report)
    figures = Path(figures) if figures is not None else report.parent / "figures"
    if not report.exists():
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(_INTRO.format(out=cfg.out))
    bodies = {
        "table": table_markdown(cfg, records),
        "scalability": _scalability_section(cfg, records, report, figures),
        "convergence": _convergence_section(cfg, report, figures),
        "contour": _contour_section(cfg, report, figures),
        "provenance": provenance_markdown(cfg, records),
    }
    for name, heading in _SECTIONS:
        replace_section(report, name, bodies[name], heading=heading)
    return report
