"""Running ``egcbf certify``'s cells resumably: each finished cell is written at once (atomically) to its file; a
rerun computes only the cells that are missing or whose key (settings, checkpoint SHA-256) changed; a cell that
raises is named at the end while the others go on; one sweep at a time holds the results folder
(:class:`egcbf.io.locks.DirLock`)."""

from __future__ import annotations

import json
import traceback
from collections.abc import Callable
from pathlib import Path

from ..io.atomic import write_json_atomic
from ..io.locks import DirLock
from ..train.checkpoint import sha256
from .plan import Cell, CellTask, CertifyConfig, run_cell, with_paths

__all__ = ["checkpoint_shas", "load_cells", "pending", "sweep"]


def _weights_sha(weights: Path, _seen: dict = {}) -> str:  # noqa: B006  (a per-process cache)
    stamp = (str(weights.resolve()), weights.stat().st_mtime_ns, weights.stat().st_size)
    if stamp not in _seen:
        _seen[stamp] = sha256(weights)
    return _seen[stamp]


def checkpoint_shas(cell: Cell, task: CellTask) -> dict[str, str]:
    """The SHA-256 of the weights of every checkpoint ``cell`` reads (its ``task.paths``)."""
    out = {}
    for name, path in task.paths.items():
        weights = Path(path) / "model.safetensors"
        if not weights.exists():
            raise FileNotFoundError(f"{cell.name}: no checkpoint at {path} (no model.safetensors)")
        out[name] = _weights_sha(weights)
    return out


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: unreadable cell file ({err}); delete it to recompute the cell") from None


def pending(cfg: CertifyConfig) -> list[tuple[Cell, CellTask, dict]]:
    """The cells of ``cfg`` whose stored file is missing or was made with another key: ``(cell, task, key)``."""
    out = []
    for cell in cfg.cells():
        task = with_paths(cell, cfg)
        key = cfg.key(cell, checkpoint_shas(cell, task))
        stored = _read(cfg.out / cell.filename)
        if stored is None or stored.get("key") != key:
            out.append((cell, task, key))
    return out


def load_cells(cfg: CertifyConfig, check: bool = True) -> list[tuple[Cell, dict]]:
    """The stored cells of ``cfg``'s plan, ``(cell, content)``; ``check``: refuse a cell whose key differs from
    the plan's (made with other settings or checkpoints: stale)."""
    out = []
    for cell in cfg.cells():
        stored = _read(cfg.out / cell.filename)
        if stored is None:
            continue
        if check:
            key = cfg.key(cell, checkpoint_shas(cell, with_paths(cell, cfg)))
            if stored.get("key") != key:
                raise ValueError(f"{cfg.out / cell.filename}: made with other settings or checkpoints than the plan's "
                                 "(stale); rerun egcbf certify to recompute it")  # fmt: skip
        out.append((cell, stored))
    return out


def _caught(task: CellTask):
    try:
        return task, run_cell(task), None
    except Exception:
        return task, None, traceback.format_exc()


def sweep(cfg: CertifyConfig, log: Callable[[str], None] = print) -> dict[Cell, str]:
    """Compute every pending cell of ``cfg`` on ``cfg.workers`` processes, writing each as it finishes; returns the
    failures ``{cell: traceback}`` (empty: all done)."""
    from ..reproduce.workers import run_processes

    failures: dict[Cell, str] = {}
    with DirLock(cfg.out, "egcbf certify"):
        todo = pending(cfg)
        log(f"{len(todo)} of {len(cfg.cells())} cells to compute")
        keys = {id(task): (cell, key) for cell, task, key in todo}
        tasks = [task for _, task, _ in todo]
        outcomes = run_processes(tasks, cfg.workers, _caught) if cfg.workers > 1 and len(tasks) > 1 else map(
            _caught, tasks)  # fmt: skip
        for k, (task, result, err) in enumerate(outcomes, 1):
            cell, key = keys[id(task)]
            if err is not None:
                failures[cell] = err
                log(f"[{k}/{len(tasks)}] {cell.name}: FAILED: {err.strip().splitlines()[-1]}")
                continue
            path = cfg.out / cell.filename
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, {"key": key, **result})
            log(f"[{k}/{len(tasks)}] {cell.name}: safe {100 * result['safe_rate']:.2f} % ({result['wall_s']:.0f} s)")
    return failures
