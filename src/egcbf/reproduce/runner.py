"""The sweep of ``egcbf reproduce``: which cells to run, in which order, and keeping every finished one.

Cells run largest ``N`` first (:mod:`~egcbf.reproduce.workers`); each is written as soon as it finishes
(:mod:`~egcbf.reproduce.store`). Nothing finished is lost: a cell that raises is reported and the others go on
(the sweep raises :class:`CellsFailed` at the end); stopping a sweep (Ctrl-C, ``kill``) stops its workers at once
and loses only the cells in progress; the same command resumes it. A stored cell made with other settings
(episodes, seed, area, episode length) is never overwritten unless asked (``recompute=True``); a cell whose
checkpoint changed is recomputed. One sweep at a time may write into a results directory
(:class:`egcbf.io.locks.DirLock`).
"""

from __future__ import annotations

import dataclasses
import datetime
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..io.locks import DirLock
from ..io.report import code_version, machine_info
from .paper import LEARNED, METHODS, base_method, method_filter
from .plan import Cell, SweepConfig
from .store import (
    CheckpointInfo,
    describe_mismatch,
    find_method_checkpoint,
    import_baseline,
    make_record,
    mismatched_cells,
    read_json,
    record_invocation,
    wanted_key,
    write_json,
)
from .workers import CellTask, execute, require_ray

__all__ = ["CellsFailed", "sweep", "sweep_many", "validate"]


# ---------------------------------------------------------------------------------------------------- the sweep
def _schedule(cells: Sequence[Cell]) -> list[Cell]:
    """The rows every table needs first: Table I's cells of training seed 0 and the hand-crafted controllers, then
    its further seeds, then the scalability study (seed 0, then further seeds); within each group largest ``N``
    first (the longest cells start first, so the workers finish together)."""
    order = {m: i for i, m in enumerate(dict.fromkeys(("ccbf", "dcbf", *LEARNED, "nominal", *METHODS)))}
    return sorted(
        cells, key=lambda c: (c.scale, bool(c.train_seed), -c.num_agents, -c.obstacles, order[c.method], c.run)
    )


def _checkpoints(cfg: SweepConfig) -> dict[tuple[str, int], CheckpointInfo]:
    return {(m, s): find_method_checkpoint(cfg.checkpoints, m, s) for m, s in cfg.checkpoint_runs()}


def _check_filters(cfg: SweepConfig, ckpts: dict[tuple[str, int], CheckpointInfo]) -> None:
    """Refuse, before any cell runs, a checkpoint that a filtered method cannot put behind its filter (what
    ``egcbf eval --filter`` would refuse): the filters act on the ``accel`` interface's command, and the ``cbf``
    filter reads the soft-min CBF head's per-edge barriers."""
    from ..train.checkpoint import read_config

    for m, s in dict.fromkeys((c.method, c.train_seed) for c in cfg.cells() if c.train_seed is not None):
        kind = method_filter(m)
        if kind == "none":
            continue
        info = ckpts[base_method(m), s]
        model = read_config(info.path).model
        if model.interface != "accel":
            why = f"the run-time filters act on the acceleration command, but its interface is {model.interface!r}"
        elif kind == "cbf" and (model.cbf_head != "edge_min" or model.cbf_z_symmetric):
            why = (
                f"the learned-CBF filter needs the soft-min CBF head (cbf_head = 'edge_min', cbf_z_symmetric = False), "
                f"but it has cbf_head = {model.cbf_head!r}, cbf_z_symmetric = {model.cbf_z_symmetric}"
            )
        else:
            continue
        raise ValueError(f"{m} cannot use the checkpoint {info.path}: {why}; leave {m} out of --methods")


def validate(cfg: SweepConfig) -> dict[tuple[str, int], CheckpointInfo]:
    """Fail early (FileNotFoundError, ValueError, ImportError) on missing checkpoints, a checkpoint a filtered
    method cannot filter, or a missing backend; returns the checkpoints ``{(method, training seed): info}`` of the
    learned methods of the sweep (a filtered method uses its base method's)."""
    if cfg.backend == "ray":
        require_ray()
    if cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {cfg.device!r} was given but torch.cuda.is_available() is False")
    ckpts = _checkpoints(cfg)
    _check_filters(cfg, ckpts)
    return ckpts


def _cell_name(cell: Cell) -> str:
    """How errors name a cell: its run, obstacles, N and faults (when any)."""
    faults = "" if cell.faults == "none" else f" faults {cell.faults}"
    return f"{cell.run} obstacles {cell.obstacles} N {cell.num_agents}{faults}"


class CellsFailed(RuntimeError):
    """Some cells raised; every other cell finished and was written. ``failures``: ``{cell: traceback text}``."""

    def __init__(self, failures: dict[Cell, str]):
        self.failures = failures
        names = ", ".join(_cell_name(c) for c in failures)
        last = next(reversed(failures.values())).strip().splitlines()[-1]
        super().__init__(f"{len(failures)} cell(s) failed ({names}); the last error: {last}")


def _log_cell(log: Callable[[str], None], rec: dict) -> None:
    r, m = rec["row"], rec["meta"]
    how = f"imported from {m['imported_from']}" if m.get("imported_from") else f"{m['wall_s']:.1f} s"
    log(
        f"{m['label']:8s} seed {'-' if m.get('train_seed') is None else m['train_seed']}  obstacles "
        f"{m['obstacles']:2d}  N {m['num_agents']:4d}  l {m['area']:g}: safe {100 * r['safe_rate']:5.1f}%  "
        f"reach {100 * r['reach_rate']:5.1f}%  success {100 * r['success_rate']:5.1f}%  ({how})"
        + (f"  faults {rec['key']['faults']}" if rec.get("key", {}).get("faults") else "")
    )


class _TermAsInterrupt:
    """Within the block, SIGTERM (``kill``) raises KeyboardInterrupt like Ctrl-C, so the sweep stops its workers
    and records itself as interrupted (main thread only; elsewhere a no-op)."""

    def __enter__(self):
        self.old = None
        try:
            self.old = signal.signal(signal.SIGTERM, self._raise)
        except ValueError:  # not the main thread
            pass
        return self

    @staticmethod
    def _raise(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    def __exit__(self, *exc):
        if self.old is not None:
            signal.signal(signal.SIGTERM, self.old)


def sweep(
    cfg: SweepConfig,
    *,
    command: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    recompute: bool = False,
) -> dict[Cell, dict]:
    """Run every cell of ``cfg`` that has no up-to-date result in ``cfg.out`` (module doc); returns every cell's
    record ``{"key", "row", "meta"}``.

    Raises ``ValueError`` before computing anything if stored cells were made with other settings
    (:func:`mismatched_cells`) unless ``recompute`` (then they are recomputed and replaced), ``RuntimeError`` if
    another sweep holds ``OUT``'s lock, and :class:`CellsFailed` after the other cells if some cells raised.

    Records this invocation (command, code version, wall time, counts, ``status``) in ``OUT/sweep.json``:
    ``"running"`` and updated after every cell, then ``"finished"``, ``"failed"`` (some cells raised) or
    ``"interrupted"`` (Ctrl-C, SIGTERM, an error); a process killed with SIGKILL stays ``"running"`` with the wall
    time of its last cell."""
    return sweep_many([cfg], commands=[command], progress=progress, log=log, recompute=recompute)[0]


def _stored(cfg: SweepConfig, ckpts: dict, counts: dict) -> tuple[dict[Cell, dict], list[Cell]]:
    """The records of ``cfg``'s cells already up to date in ``cfg.out`` (or imported from its baselines), and the
    cells still to compute; ``counts`` gets the reused and imported ones."""
    records, todo = {}, []
    for cell in cfg.cells():
        key = wanted_key(cfg, cell, ckpts)
        old = read_json(cell.path(cfg.out))
        if isinstance(old, dict) and old.get("key") == key:
            records[cell], counts["reused"] = old, counts["reused"] + 1
            continue
        found = None if cfg.baselines is None or cell.faults != "none" else import_baseline(cfg.baselines, cell, key)
        if found is not None:
            rec = make_record(cfg, cell, key, None, found[0], **found[1])
            write_json(cell.path(cfg.out), rec)
            records[cell], counts["imported"] = rec, counts["imported"] + 1
            continue
        todo.append(cell)
    return records, todo


def sweep_many(
    cfgs: Sequence[SweepConfig],
    *,
    commands: Sequence[str | None] | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    recompute: bool = False,
) -> list[dict[Cell, dict]]:
    """:func:`sweep` for several sweeps into one results directory, run as one queue of cells: the workers go on
    to the next sweep's cells instead of waiting for the slowest cell of the one before. Every sweep is checked
    before any cell runs and recorded in ``OUT/sweep.json`` as its own invocation (``commands[i]``); a cell that
    several sweeps share is computed once. Returns each sweep's records, in order; raises :class:`CellsFailed` for
    every failed cell of every sweep at the end.

    Raises ``ValueError`` if the sweeps differ in results directory, backend, workers, threads or device, or want
    one cell with different settings."""
    cfgs = list(cfgs)
    commands = [None] * len(cfgs) if commands is None else list(commands)
    if len(commands) != len(cfgs):
        raise ValueError(f"sweep_many: {len(cfgs)} sweeps but {len(commands)} commands")
    if not cfgs:
        return []
    shared = ("out", "backend", "workers", "threads", "device")
    odd = [f for f in shared if len({str(getattr(c, f)) for c in cfgs}) > 1]
    if odd:
        raise ValueError(f"sweep_many: the sweeps must share {', '.join(shared)}; they differ in {', '.join(odd)}")
    with DirLock(Path(cfgs[0].out), "egcbf reproduce"):  # before planning: another sweep may be writing there
        return _run_sweeps(cfgs, commands, progress, log or tqdm.write, recompute)


def _run_sweeps(
    cfgs: list[SweepConfig],
    commands: list[str | None],
    progress: bool,
    log: Callable[[str], None],
    recompute: bool,
) -> list[dict[Cell, dict]]:
    """:func:`sweep_many`'s work, with ``OUT``'s lock held."""
    first = cfgs[0]
    t0 = time.perf_counter()
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    plans = []  # per sweep: checkpoints, records, counts
    owners: dict[Path, list[int]] = {}  # a cell's file -> the sweeps that compute it
    wanted: dict[Path, dict] = {}
    tasks: list[CellTask] = []
    for j, cfg in enumerate(cfgs):
        ckpts = validate(cfg)
        mismatched = mismatched_cells(cfg, ckpts)
        if mismatched and not recompute:
            raise ValueError(
                describe_mismatch(cfg, mismatched) + ". Use another --out, or pass --recompute to replace them."
            )
        counts = {"reused": 0, "imported": 0, "computed": 0, "failed": 0}
        records, todo = _stored(cfg, ckpts, counts)
        plans.append((ckpts, records, counts))
        for c in _schedule(todo):
            path, key = c.path(cfg.out), wanted_key(cfg, c, ckpts)
            if path in owners:
                if wanted[path] != key:
                    raise ValueError(f"sweep_many: two sweeps want {path} with different settings")
                owners[path].append(j)
                continue
            owners[path], wanted[path] = [j], key
            tasks.append(
                CellTask(
                    cell=c,
                    area=cfg.area_for(c),
                    episodes=cfg.episodes_for(c),
                    seed=cfg.seed,
                    max_steps=cfg.steps_for(c),
                    device=cfg.device,
                    threads=cfg.threads,
                    checkpoint_files=ckpts[c.base, c.train_seed].files() if (c.base, c.train_seed) in ckpts else None,
                    progress=False,
                )
            )
    code, machine = code_version(), machine_info()
    tasks = [dataclasses.replace(t, code=code) for t in tasks]  # the code the sweep loaded, not HEAD at a cell's end
    if first.backend == "process" and (first.workers <= 1 or len(tasks) <= 1):  # one cell at a time, here
        tasks = [dataclasses.replace(t, progress=progress) for t in tasks]

    def entry(j: int, status: str) -> dict:
        cfg = cfgs[j]
        return {
            "command": commands[j],
            "started": started,
            "wall_s": round(time.perf_counter() - t0, 1),
            "status": status,
            "code": code,
            "backend": cfg.backend,
            "workers": cfg.workers,
            "threads_per_cell": cfg.threads,
            **plans[j][2],
            "machine": machine,
        }

    failures: dict[Cell, str] = {}
    out = Path(first.out)
    with _TermAsInterrupt():
        index = [record_invocation(out, entry(j, "running")) for j in range(len(cfgs))]
        bar = tqdm(total=len(tasks), desc="reproduce", unit="cell", disable=not progress)
        status, outcomes = "interrupted", execute(tasks, first.backend, first.workers)
        try:
            for task, res, error in outcomes:
                cell = task.cell
                bar.update(1)
                js = owners[cell.path(first.out)]
                if error is not None:
                    failures[cell] = error
                    for j in js:
                        plans[j][2]["failed"] += 1
                    log(f"FAILED {_cell_name(cell)}:\n{error.rstrip()}")
                else:
                    meta = {k: res[k] for k in ("wall_s", "machine", "code") if k in res}
                    for j in js:
                        ckpts, records, counts = plans[j]
                        rec = make_record(cfgs[j], cell, wanted_key(cfgs[j], cell, ckpts),
                                          ckpts.get((cell.base, cell.train_seed)), res["row"], **meta)  # fmt: skip
                        records[cell], counts["computed"] = rec, counts["computed"] + 1
                    write_json(cell.path(first.out), rec)
                    _log_cell(log, rec)
                for j in js:
                    record_invocation(out, entry(j, "running"), index[j])
            status = "done"
        finally:
            outcomes.close()  # stops the workers now if the loop was left early
            bar.close()
            for j in range(len(cfgs)):
                final = status if status == "interrupted" else "failed" if plans[j][2]["failed"] else "finished"
                record_invocation(out, entry(j, final), index[j])
    if failures:
        raise CellsFailed(failures)
    return [{c: plans[j][1][c] for c in cfg.cells() if c in plans[j][1]} for j, cfg in enumerate(cfgs)]
