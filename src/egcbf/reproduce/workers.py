"""Evaluate one cell of ``egcbf reproduce``, and many at once on local processes or Ray.

One cell runs :func:`egcbf.evaluate.episodes.evaluate` for a single ``N`` (the same function, seeds and batching as
``egcbf eval``, so a cell's metrics equal those of ``egcbf eval`` at that ``N``; a ``METHOD:FILTER`` cell equals
``egcbf eval --checkpoint ... --filter FILTER``, or ``--controller nominal --filter FILTER``). A backend takes the
cells' tasks in order (largest ``N`` first) and yields ``(task, result, error)`` as each finishes:
``backend="process"`` over ``workers`` spawned processes with ``threads`` torch threads each, or Ray tasks
(``backend="ray"``, the optional ``ray`` extra, for a cluster: a task carries the checkpoint's bytes, not its path,
so the nodes need no shared file system). Either way, the same cell gives the same numbers. A cell that raises
yields its traceback text instead of stopping the others; closing the backend's iterator (an interruption) stops its
workers at once.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import signal
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import torch

from ..io.report import code_version, machine_info
from .plan import Cell

__all__ = ["CellTask", "Outcome", "execute", "require_ray", "run_cell", "run_processes"]


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
    checkpoint_dir: str | None = None  # instead of the bytes: a directory on this machine (the process backend)
    progress: bool = False
    code: str | None = None  # the code version the sweep started with (None: the worker's own)


def _evaluate_cell(task: CellTask) -> dict:
    from ..control.resolve import resolve
    from ..evaluate.episodes import evaluate
    from ..faults import parse_faults

    name = task.cell.method  # METHOD[:FILTER], a filter with `egcbf eval --filter KIND`'s defaults
    learned, env_overrides = None, None
    with tempfile.TemporaryDirectory(prefix="egcbf-ckpt-") as tmp:
        if task.checkpoint_files is not None or task.checkpoint_dir is not None:  # as `egcbf eval --checkpoint`
            path = task.checkpoint_dir or _write_checkpoint(tmp, task.checkpoint_files)
            built = resolve(name, path, device=task.device, dtype=torch.float32)
            learned, env_overrides = built.controller, built.env_overrides
        elif task.cell.filter != "none":  # `egcbf eval --controller nominal --filter KIND`
            learned = resolve(name).controller
    rows, _ = evaluate(
        (lambda cfg: learned) if learned is not None else (lambda cfg: resolve(task.cell.method).controller),
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
        faults=parse_faults(task.cell.faults),
    )
    return rows[0]


def _write_checkpoint(directory: str | Path, files: dict[str, bytes]) -> str:
    """Write a checkpoint's ``files`` (name -> bytes) into ``directory``; returns it."""
    for name, data in files.items():
        (Path(directory) / name).write_bytes(data)
    return str(directory)


def run_cell(task: CellTask) -> dict:
    """Evaluate one cell with ``task.threads`` torch threads: ``{"row": metrics row, "wall_s": s, "machine": ...,
    "code": version}`` (the machine names the GPU on a CUDA device)."""
    saved = torch.get_num_threads()
    torch.set_num_threads(task.threads)
    try:
        t0 = time.perf_counter()
        row = _evaluate_cell(task)
        wall = time.perf_counter() - t0
        machine = machine_info()
        if torch.device(task.device).type == "cuda":
            machine["gpu"] = torch.cuda.get_device_name(torch.device(task.device))
        return {"row": row, "wall_s": round(wall, 2), "machine": machine, "code": task.code or code_version()}
    finally:
        torch.set_num_threads(saved)


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


def _init_worker(threads: int, started=None) -> None:
    global _started
    _started = started
    torch.set_num_threads(threads)
    try:  # Linux: a worker dies with the sweep (even `kill -9` of the sweep) instead of finishing its cell alone
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


#: what a backend yields per cell: the task, then its result (``run_cell``'s dict) or ``None`` and the error text
Outcome = tuple[CellTask, dict | None, str | None]

#: in a worker process: the pool's shared flags, one per task, set when the worker starts that task
_started = None


def _run_cell_caught(task: CellTask) -> Outcome:
    try:
        return task, run_cell(task), None
    except Exception:  # reported by the sweep, which goes on with the other cells
        return task, None, traceback.format_exc()


def _run_flagged(fn: Callable[[CellTask], Outcome], index: int, task: CellTask) -> Outcome:
    _started[index] = 1  # the parent learns which cells were running if a worker dies
    return fn(task)


def _run_local(tasks: Sequence[CellTask]) -> Iterator[Outcome]:
    for task in tasks:
        yield _run_cell_caught(task)


_DIED = (
    "the worker process running this cell died ({}) while it ran alone: killed by a signal, or out of memory? "
    "The other cells went on in a new pool."
)


def run_processes(
    tasks: Sequence[CellTask], workers: int, fn: Callable[[CellTask], Outcome] = _run_cell_caught
) -> Iterator[Outcome]:
    """``fn`` over ``tasks`` on ``workers`` spawned processes, dispatched in order, yielded as they finish.

    A worker that dies (``kill -9``, the out-of-memory killer, a crash in native code) breaks its pool, which stops
    every cell in progress. The cells not yet started go on in a new pool; each cell that was running when it broke
    is run again alone first, so the cell that kills its worker is told apart from the ones that ran beside it:
    dying alone, it is yielded as failed with that error, and the sweep goes on. A pool that breaks before any of
    its lost cells started (a worker that cannot start) sends them all to be run alone, so every round resolves at
    least one cell and the iterator always ends."""
    ctx = multiprocessing.get_context("spawn")  # never fork a process whose torch thread pools are running
    threads = tasks[0].threads if tasks else 1
    waiting = list(range(len(tasks)))  # task indices never started, in dispatch order (largest N first)
    suspects: list[int] = []  # running when a pool broke: each is retried alone
    while waiting or suspects:
        alone = bool(suspects)
        batch = [suspects.pop(0)] if alone else waiting
        started = ctx.Array("b", len(tasks), lock=False)
        pool = ProcessPoolExecutor(
            1 if alone else min(workers, len(batch)),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(threads, started),
        )
        try:
            futures, done, broken = {}, set(), None
            try:
                for i in batch:
                    futures[pool.submit(_run_flagged, fn, i, tasks[i])] = i
            except BrokenProcessPool as err:  # a worker died while the cells were being handed out
                broken = err
            for future in as_completed(futures):
                i = futures[future]
                try:
                    outcome = future.result()
                except BrokenProcessPool as err:
                    broken = err
                    continue
                done.add(i)
                yield tasks[i], outcome[1], outcome[2]  # the caller's task object, not the worker's copy
            if not alone:
                waiting = []
            if broken is not None:
                lost = [i for i in batch if i not in done]
                if alone:
                    yield tasks[batch[0]], None, _DIED.format(broken)
                elif any(started[i] for i in lost):
                    suspects += [i for i in lost if started[i]]
                    waiting = [i for i in lost if not started[i]]
                else:  # it broke before any lost cell started (a worker's start-up, a task's unpickling)
                    suspects += lost
        finally:
            _stop(pool)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Shut ``pool`` down at once: cells in progress are dropped (an interruption), not awaited."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):  # no public terminate before 3.14
        if proc.is_alive():
            proc.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def _run_ray(tasks: Sequence[CellTask]) -> Iterator[Outcome]:
    ray = require_ray()
    if not ray.is_initialized():
        ray.init()  # RAY_ADDRESS selects a cluster; otherwise a local one
    remote = ray.remote(num_cpus=tasks[0].threads if tasks else 1)(_run_cell_caught)
    pending = {remote.remote(t): t for t in tasks}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                task = pending.pop(ref)
                try:
                    yield ray.get(ref)
                except Exception:  # the task itself died (worker lost, out of memory)
                    yield task, None, traceback.format_exc()
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def execute(tasks: Sequence[CellTask], backend: str, workers: int) -> Iterator[Outcome]:
    """Run ``tasks`` on ``backend`` (``"process"``: ``workers`` processes, in this process if one suffices;
    ``"ray"``); yields an :data:`Outcome` per task as it finishes."""
    if backend == "ray":
        return _run_ray(tasks)
    if workers <= 1 or len(tasks) <= 1:
        return _run_local(tasks)
    return _run_on_disk(tasks, min(workers, len(tasks)))


def _run_on_disk(tasks: Sequence[CellTask], workers: int) -> Iterator[Outcome]:
    """:func:`run_processes` with each checkpoint written once to a temporary directory that the tasks name, so
    a task crosses the process boundary in a few kilobytes, not the checkpoint's bytes (a task larger than a pipe's
    buffer can hang a broken pool's shutdown on Python < 3.11.5, CPython gh-94777)."""
    with tempfile.TemporaryDirectory(prefix="egcbf-sweep-") as root:
        dirs: dict[tuple, str] = {}
        local = []
        for task in tasks:
            if task.checkpoint_files is None:
                local.append(task)
                continue
            key = tuple(sorted(task.checkpoint_files.items()))  # equal contents: one directory
            if key not in dirs:
                directory = Path(root) / str(len(dirs))
                directory.mkdir()
                dirs[key] = _write_checkpoint(directory, task.checkpoint_files)
            local.append(dataclasses.replace(task, checkpoint_files=None, checkpoint_dir=dirs[key]))
        originals = {id(t): task for t, task in zip(local, tasks)}  # run_processes yields the objects it got
        for task, res, err in run_processes(local, workers):
            yield originals[id(task)], res, err
