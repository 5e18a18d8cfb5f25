"""Run the cells of ``egcbf reproduce``: find checkpoints, evaluate cells on processes or Ray, keep finished ones.

One cell runs :func:`egcbf.evaluate.evaluate` for a single ``N`` (the same function, seeds and batching as
``egcbf eval``, so a cell's metrics equal those of ``egcbf eval`` at that ``N``) and is written atomically to its
file (:meth:`Cell.path`)::

    {"key":  what the result depends on (method, obstacles, num_agents, area, episodes, seed, max_steps,
              sha256 of the checkpoint's model.safetensors): a cell file with the same key is never recomputed,
     "row":  the metrics row of docs/metrics.md (rates in [0, 1], cost in collision events per agent per episode,
              reward -sum_t ||u - u_nom||^2 in SI units, step_ms_median in ms per environment step),
     "meta": checkpoint path / step / training seed, wall time of the cell (s), device, machine, and
              "imported_from" when the row was taken from an earlier ``egcbf eval`` output (docs/results/baselines)}

Cells run largest ``N`` first over ``workers`` processes with one torch thread each (``backend="process"``) or as
Ray tasks (``backend="ray"``, the optional ``ray`` extra, for a cluster: a task receives the checkpoint's bytes, not
its path, so the nodes need no shared file system). Either way, the same cell gives the same numbers. Stopping a
sweep (Ctrl-C, kill) loses only the cells in progress; the same command resumes it.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime
import json
import multiprocessing
import shlex
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..atomic import write_json_atomic
from ..checkpoint import sha256
from ..report import machine_info
from .paper import BASELINES, LABELS, LEARNED
from .plan import Cell, SweepConfig, cell_key

__all__ = [
    "CellTask",
    "CheckpointInfo",
    "checkpoint_dir",
    "find_method_checkpoint",
    "import_baseline",
    "load_cells",
    "read_invocations",
    "require_ray",
    "run_cell",
    "sweep",
    "validate",
]


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


def checkpoint_dir(root: str | Path, method: str, train_seed: int = 0) -> Path:
    """Where the checkpoint of ``method`` trained with ``train_seed`` lives: ``ROOT/<method>`` for seed 0,
    ``ROOT/seeds/<method>-s<k>`` for seed ``k`` (checkpoints/README.md)."""
    return Path(root) / method if not train_seed else Path(root) / "seeds" / f"{method}-s{train_seed}"


def find_method_checkpoint(root: str | Path, method: str, train_seed: int = 0) -> CheckpointInfo:
    """The checkpoint of ``method`` trained with ``train_seed`` under ``root`` (:func:`checkpoint_dir`, or its
    ``best`` subdirectory).

    Raises ``FileNotFoundError`` if there is none, :class:`~egcbf.checkpoint.CheckpointError` (a ``ValueError``
    naming the file) if its files are corrupted, truncated or of another method, and ``ValueError`` if its config
    was trained with another seed."""
    from ..checkpoint import check_identity, read_config, read_state, read_tensors

    base = checkpoint_dir(root, method, train_seed)
    path = next((d for d in (base, base / "best") if (d / "model.safetensors").exists()), None)
    if path is None or not (path / "config.json").exists():
        raise FileNotFoundError(
            f"no checkpoint for {method} (training seed {train_seed}) in {base} (expected {base}/config.json and "
            f"{base}/model.safetensors): train one with `egcbf train --algo {method} --seed {train_seed} --out "
            f"runs/{method}-s{train_seed}`, then copy its best/ directory to {base}"
        )
    train_cfg = read_config(path)
    if train_cfg.algo != method:
        raise ValueError(f"{path}/config.json is a {train_cfg.algo!r} checkpoint, expected {method!r}")
    if train_cfg.seed != train_seed:
        raise ValueError(f"{path}/config.json was trained with seed {train_cfg.seed}, expected seed {train_seed}")
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
    from ..control.controllers import make_controller
    from ..evaluate import evaluate

    learned, env_overrides = None, None
    with tempfile.TemporaryDirectory(prefix="egcbf-ckpt-") as tmp:
        if task.checkpoint_files is not None:  # the same loading as `egcbf eval --checkpoint`
            from ..checkpoint import load_controller

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
        "area": cfg.area_for(cell),
        "episodes": cfg.episodes_for(cell),
        "seed": cfg.seed,
        "max_steps": cfg.max_steps,
        "checkpoint": None if ckpt is None else str(ckpt.path),
        "checkpoint_step": None if ckpt is None else ckpt.step,
        "train_seed": cell.train_seed,
        "device": cfg.device,
        "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    base.update(meta)
    return {"key": key, "row": row, "meta": base}


_NOT_IMPORTABLE = ("--max-steps", "--batch", "--dtype", "--checkpoint")


def import_baseline(baselines: str | Path, cell: Cell, key: dict) -> tuple[dict, dict] | None:
    """``(row, meta)`` of ``cell`` from an ``egcbf eval`` output ``BASELINES/<method>[_obs<k>]`` made with the same
    episodes, seed, area, obstacles and default episode length, batching, dtype and device; else ``None``."""
    if cell.method not in BASELINES or cell.scale or key["max_steps"] is not None:
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
    """The rows every table needs first: Table I's cells of training seed 0 and the hand-crafted controllers, then
    its further seeds, then the scalability study (seed 0, then further seeds); within each group largest ``N``
    first (the longest cells start first, so the workers finish together)."""
    order = {m: i for i, m in enumerate(("ccbf", "dcbf", *LEARNED, "nominal"))}
    return sorted(
        cells, key=lambda c: (c.scale, bool(c.train_seed), -c.num_agents, -c.obstacles, order[c.method], c.run)
    )


def _checkpoints(cfg: SweepConfig) -> dict[tuple[str, int], CheckpointInfo]:
    return {(m, s): find_method_checkpoint(cfg.checkpoints, m, s) for m, s in cfg.checkpoint_runs()}


def validate(cfg: SweepConfig) -> dict[tuple[str, int], CheckpointInfo]:
    """Fail early (FileNotFoundError, ValueError, ImportError) on missing checkpoints or a missing backend; returns
    the checkpoints ``{(method, training seed): info}`` of the learned methods of the sweep."""
    if cfg.backend == "ray":
        require_ray()
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {cfg.device!r} was given but torch.cuda.is_available() is False")
    return _checkpoints(cfg)


def _log_cell(log: Callable[[str], None], rec: dict) -> None:
    r, m = rec["row"], rec["meta"]
    how = f"imported from {m['imported_from']}" if m.get("imported_from") else f"{m['wall_s']:.1f} s"
    log(
        f"{m['label']:8s} seed {'-' if m.get('train_seed') is None else m['train_seed']}  obstacles "
        f"{m['obstacles']:2d}  N {m['num_agents']:4d}  l {m['area']:g}: safe {100 * r['safe_rate']:5.1f}%  "
        f"reach {100 * r['reach_rate']:5.1f}%  success {100 * r['success_rate']:5.1f}%  ({how})"
    )


def read_invocations(out: str | Path) -> list[dict]:
    """Every recorded invocation of the sweep into ``out`` (``OUT/sweep.json``), oldest first."""
    log = _read_json(Path(out) / "sweep.json")
    return log if isinstance(log, list) else []


def _record_invocation(out: Path, entry: dict, index: int | None = None) -> int:
    """Append ``entry`` to ``OUT/sweep.json`` (``index=None``) or overwrite the entry at ``index``; returns its
    index. The sweep rewrites its entry after every cell, so a killed invocation still counts up to its last
    finished cell."""
    log = read_invocations(out)
    if index is None or index >= len(log):
        log.append(entry)
        index = len(log) - 1
    else:
        log[index] = entry
    _write_json_atomic(out / "sweep.json", log)
    return index


def sweep(
    cfg: SweepConfig,
    *,
    command: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> dict[Cell, dict]:
    """Run every cell of ``cfg`` that has no up-to-date result in ``cfg.out`` (module doc); returns every cell's
    record ``{"key", "row", "meta"}``. Records this invocation (command, wall time, counts, ``status``) in
    ``OUT/sweep.json``: ``"running"`` and updated after every cell, then ``"finished"`` or ``"interrupted"``
    (an exception or Ctrl-C; a killed process stays ``"running"`` with the wall time of its last cell)."""
    log = log or tqdm.write
    t0 = time.perf_counter()
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    ckpts = validate(cfg)
    records, todo, counts = {}, [], {"reused": 0, "imported": 0, "computed": 0}
    for cell in cfg.cells():
        ckpt = ckpts.get((cell.method, cell.train_seed))
        key = cell_key(cfg, cell, None if ckpt is None else ckpt.sha256)
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
            area=cfg.area_for(c),
            episodes=cfg.episodes_for(c),
            seed=cfg.seed,
            max_steps=cfg.max_steps,
            device=cfg.device,
            threads=cfg.threads,
            checkpoint_files=ckpts[c.method, c.train_seed].files() if (c.method, c.train_seed) in ckpts else None,
            progress=progress and local,
        )
        for c in _schedule(todo)
    ]

    def entry(status: str) -> dict:
        return {
            "command": command,
            "started": started,
            "wall_s": round(time.perf_counter() - t0, 1),
            "status": status,
            "backend": cfg.backend,
            "workers": cfg.workers,
            "threads_per_cell": cfg.threads,
            **counts,
            "machine": machine_info(),
        }

    index = _record_invocation(Path(cfg.out), entry("running"))
    bar = tqdm(total=len(tasks), desc="reproduce", unit="cell", disable=not progress)
    finished = False
    try:
        for task, res in _execute(tasks, cfg.backend, cfg.workers):
            cell = task.cell
            ckpt = ckpts.get((cell.method, cell.train_seed))
            key = cell_key(cfg, cell, None if ckpt is None else ckpt.sha256)
            rec = _record(cfg, cell, key, ckpt, res["row"], wall_s=res["wall_s"], machine=res["machine"])
            _write_json_atomic(cell.path(cfg.out), rec)
            records[cell], counts["computed"] = rec, counts["computed"] + 1
            bar.update(1)
            _log_cell(log, rec)
            _record_invocation(Path(cfg.out), entry("running"), index)
        finished = True
    finally:
        bar.close()
        _record_invocation(Path(cfg.out), entry("finished" if finished else "interrupted"), index)
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
