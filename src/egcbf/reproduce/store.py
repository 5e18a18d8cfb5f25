"""What ``egcbf reproduce`` keeps on disk: checkpoints it evaluates, cell files, imported baselines, invocations.

A cell is written atomically to its file (:meth:`Cell.path`)::

    {"key":  what the result depends on (method, obstacles, num_agents, area, episodes, seed, max_steps,
              sha256 of the checkpoint's model.safetensors; behind a run-time filter also "filter" and
              "filter_config", as ``egcbf eval`` writes them in run.json): a cell file with the same key is never
              recomputed,
     "row":  the metrics row of docs/metrics.md (rates in [0, 1], cost in collision events per agent per episode,
              reward -sum_t ||u - u_nom||^2 in SI units, step_ms_median in ms per environment step),
     "meta": checkpoint path / step / training seed, wall time of the cell (s), device, machine, code version,
              "filter" and "filter_config" behind a run-time filter, and "imported_from" when the row was taken
              from an earlier ``egcbf eval`` output (docs/results/baselines)}

``OUT/sweep.json`` lists the sweep's invocations (command, code version, wall time, counts, status).
"""

from __future__ import annotations

import datetime
import json
import os
import shlex
import warnings
from dataclasses import dataclass
from pathlib import Path

from ..io.atomic import write_json_atomic
from ..robots import DEFAULT_ROBOT
from ..train.checkpoint import sha256
from .paper import BASELINES, LABELS, MARL, base_method
from .plan import Cell, SweepConfig, cell_key, filter_settings

__all__ = [
    "CheckpointInfo",
    "checkpoint_dir",
    "current_sha256",
    "describe_mismatch",
    "find_method_checkpoint",
    "import_baseline",
    "load_cells",
    "mismatched_cells",
    "pending_cells",
    "read_invocations",
    "unreadable_cells",
    "wanted_key",
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
        """``config.json``, ``model.safetensors`` and ``state.json`` as bytes (what a cell needs to load and check the
        weights, shipped to remote workers)."""
        names = ("config.json", "model.safetensors", "state.json", "marl.json")
        return {name: (self.path / name).read_bytes() for name in names if (self.path / name).exists()}


def checkpoint_dir(root: str | Path, method: str, train_seed: int = 0) -> Path:
    """Where the checkpoint of ``method`` trained with ``train_seed`` lives: ``ROOT/<method>`` for seed 0,
    ``ROOT/seeds/<method>-s<k>`` for seed ``k`` (checkpoints/README.md)."""
    return Path(root) / method if not train_seed else Path(root) / "seeds" / f"{method}-s{train_seed}"


def current_sha256(root: str | Path, method: str, train_seed: int | None) -> str | None:
    """The sha256 of the weights of ``method``'s checkpoint now under ``root`` for ``train_seed``
    (:func:`find_method_checkpoint`; a filtered method's: its base method's), or ``None``: a hand-crafted method
    (``train_seed`` None), or no readable checkpoint there (reports regenerate without the checkpoints). A stored
    cell whose sha256 differs from it was computed with other weights (stale)."""
    if train_seed is None:
        return None
    try:
        return find_method_checkpoint(root, base_method(method), train_seed).sha256
    except (FileNotFoundError, ValueError, OSError):
        return None


def find_method_checkpoint(root: str | Path, method: str, train_seed: int = 0) -> CheckpointInfo:
    """The checkpoint of ``method`` trained with ``train_seed`` under ``root`` (:func:`checkpoint_dir`, or its
    ``best`` subdirectory).

    Raises ``FileNotFoundError`` if there is none, :class:`~egcbf.train.checkpoint.CheckpointError` (a ``ValueError``
    naming the file) if its files are corrupted, truncated or of another method, and ``ValueError`` if its config
    was trained with another seed."""
    from ..train.checkpoint import check_identity, read_config, read_state, read_tensors

    base = checkpoint_dir(root, method, train_seed)
    if method in MARL:
        return _find_marl_checkpoint(base, method, train_seed)
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


def _find_marl_checkpoint(path: Path, method: str, train_seed: int) -> CheckpointInfo:
    """A MARL baseline's checkpoint (:mod:`egcbf.marl.checkpoint`: ``marl.json`` + ``model.safetensors``)."""
    from ..marl.checkpoint import WEIGHTS_FILE, is_marl_checkpoint, read_marl_config
    from ..train.checkpoint import read_tensors

    if not is_marl_checkpoint(path) or not (path / WEIGHTS_FILE).exists():
        raise FileNotFoundError(
            f"no checkpoint for {method} (training seed {train_seed}) in {path} (expected {path}/marl.json and "
            f"{path}/{WEIGHTS_FILE}): train one with `python -m egcbf.marl.ppo_lagrangian --seed {train_seed} --out "
            f"runs/{method}-s{train_seed}`, then copy it to {path}"
        )
    config, progress = read_marl_config(path)
    if config.algo != method:
        raise ValueError(f"{path}/marl.json is a {config.algo!r} checkpoint, expected {method!r}")
    if config.seed != train_seed:
        raise ValueError(f"{path}/marl.json was trained with seed {config.seed}, expected seed {train_seed}")
    read_tensors(path / WEIGHTS_FILE)
    return CheckpointInfo(method, path, sha256(path / WEIGHTS_FILE), progress.get("iteration"), config.seed)


# ---------------------------------------------------------------------------------------------------- cell files
def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, obj)


def read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None


def make_record(cfg: SweepConfig, cell: Cell, key: dict, ckpt: CheckpointInfo | None, row: dict, **meta) -> dict:
    base = {
        "method": cell.method,
        "label": LABELS[cell.method],
        "num_agents": cell.num_agents,
        "obstacles": cell.obstacles,
        "area": cfg.area_for(cell),
        "episodes": cfg.episodes_for(cell),
        "seed": cfg.seed,
        "max_steps": cfg.steps_for(cell),
        "checkpoint": None if ckpt is None else str(ckpt.path),
        "checkpoint_step": None if ckpt is None else ckpt.step,
        "train_seed": cell.train_seed,
        **(filter_settings(cell.method) or {}),
        **({"faults": cell.faults} if cell.faults != "none" else {}),
        "device": cfg.device,
        "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    base.update(meta)
    return {"key": key, "row": row, "meta": base}


#: ``egcbf eval`` flags that leave a hand-crafted controller's metrics unchanged: with any value, as switches, and
#: with one value only
_FREE_VALUE_FLAGS = frozenset(
    ("--controller", "--num-agents", "--area", "--obstacles", "--episodes", "--seed", "--out", "--threads")
)
_SWITCHES = frozenset(("--render", "--no-render", "--progress", "--no-progress", "--overwrite"))
_REQUIRED_VALUES = {"--device": "cpu", "--dtype": "float32", "--robot": DEFAULT_ROBOT}


def _importable_command(command: str) -> bool:
    """Whether ``command`` is an ``egcbf eval`` that used only flags of the allow-list above (an unknown flag, or
    ``--device cuda``, ``--max-steps``, ``--batch``..., makes its output not importable)."""
    try:
        args = shlex.split(command)
    except ValueError:
        return False
    if args[:2] != ["egcbf", "eval"]:
        return False
    rest = iter(args[2:])
    for arg in rest:
        flag, eq, value = arg.partition("=")
        if flag in _SWITCHES and not eq:
            continue
        if flag not in _FREE_VALUE_FLAGS and flag not in _REQUIRED_VALUES:
            return False
        if not eq:
            value = next(rest, None)
        if value is None or (flag in _REQUIRED_VALUES and value != _REQUIRED_VALUES[flag]):
            return False
    return True


def import_baseline(baselines: str | Path, cell: Cell, key: dict) -> tuple[dict, dict] | None:
    """``(row, meta)`` of ``cell`` from an ``egcbf eval`` output ``BASELINES/<method>[_obs<k>]`` made with the same
    episodes, seed, area, obstacles and default episode length, batching, dtype and device; else ``None``."""
    if cell.method not in BASELINES or cell.scale or key["max_steps"] is not None:
        return None
    d = Path(baselines) / (cell.method if cell.obstacles == 0 else f"{cell.method}_obs{cell.obstacles}")
    rows, run = read_json(d / "metrics.json"), read_json(d / "run.json")
    if not isinstance(rows, list) or not isinstance(run, dict):
        return None
    area = run.get("area")
    same = (
        run.get("controller") == cell.method
        and run.get("checkpoint") is None
        and run.get("episodes") == key["episodes"]
        and run.get("seed") == key["seed"]
        and run.get("obstacles") == cell.obstacles
        and isinstance(area, (int, float))
        and float(area) == key["area"]
        and _importable_command(str(run.get("command", "")))
    )
    row = next((r for r in rows if r.get("num_agents") == cell.num_agents), None) if same else None
    if row is None:
        return None
    meta = {
        "imported_from": str(d),
        "command": run.get("command"),
        "wall_s": None,
        "machine": run.get("machine"),
        "device": "cpu",
    }
    return row, meta


def read_invocations(out: str | Path) -> list[dict]:
    """Every recorded invocation of the sweep into ``out`` (``OUT/sweep.json``), oldest first."""
    log = read_json(Path(out) / "sweep.json")
    return log if isinstance(log, list) else []


def record_invocation(out: Path, entry: dict, index: int | None = None) -> int:
    """Append ``entry`` to ``OUT/sweep.json`` (``index=None``) or overwrite the entry at ``index``; returns its
    index. The sweep rewrites its entry after every cell, so a killed invocation still counts up to its last
    finished cell. A ``sweep.json`` that cannot be read is moved aside (``sweep.json.unreadable-<time>``) with a
    warning, never overwritten."""
    path = Path(out) / "sweep.json"
    log = read_json(path)
    if not isinstance(log, list):
        if path.exists():
            aside = path.with_name(f"sweep.json.unreadable-{datetime.datetime.now():%Y%m%dT%H%M%S}")
            os.replace(path, aside)
            warnings.warn(f"{path} could not be read as a list of invocations: moved aside to {aside.name}, a new "
                          "history starts", stacklevel=2)  # fmt: skip
            index = None
        log = []
    if index is None or index >= len(log):
        log.append(entry)
        index = len(log) - 1
    else:
        log[index] = entry
    write_json(out / "sweep.json", log)
    return index


def _settings_diff(stored: dict, wanted: dict) -> dict[str, tuple]:
    """``{field: (stored, wanted)}`` of the key fields that differ, other than the checkpoint's sha256."""
    return {k: (stored.get(k), v) for k, v in wanted.items() if k != "checkpoint_sha256" and stored.get(k) != v}


def wanted_key(cfg: SweepConfig, cell: Cell, ckpts: dict | None) -> dict:
    """:func:`cell_key` of ``cell`` with the sha256 of its checkpoint among ``ckpts`` (``None`` if it has none; a
    filtered method's checkpoint is its base method's)."""
    ckpt = (ckpts or {}).get((cell.base, cell.train_seed))
    return cell_key(cfg, cell, None if ckpt is None else ckpt.sha256)


def mismatched_cells(cfg: SweepConfig, ckpts: dict | None = None) -> dict[Cell, dict[str, tuple]]:
    """The cells of ``cfg`` whose stored file was made with other settings (episodes, seed, area, episode length):
    ``{cell: {field: (stored, wanted)}}``. A cell whose checkpoint alone changed is not a mismatch (the sweep
    recomputes it)."""
    out = {}
    for cell in cfg.cells():
        rec = read_json(cell.path(cfg.out))
        if not isinstance(rec, dict) or not isinstance(rec.get("key"), dict):
            continue
        diff = _settings_diff(rec["key"], wanted_key(cfg, cell, ckpts))
        if diff:
            out[cell] = diff
    return out


def pending_cells(cfg: SweepConfig, ckpts: dict) -> list[Cell]:
    """The cells of ``cfg`` without an up-to-date stored result (what a sweep would import or compute);
    ``ckpts``: :func:`egcbf.reproduce.validate`'s checkpoints."""
    pending = []
    for cell in cfg.cells():
        rec = read_json(cell.path(cfg.out))
        if not isinstance(rec, dict) or rec.get("key") != wanted_key(cfg, cell, ckpts):
            pending.append(cell)
    return pending


def describe_mismatch(cfg: SweepConfig, mismatched: dict[Cell, dict[str, tuple]]) -> str:
    """One sentence on the stored cells made with other settings, with an example."""
    cell, diff = next(iter(mismatched.items()))
    what = ", ".join(f"{k} {a} (stored) vs {b} (asked)" for k, (a, b) in diff.items())
    return (
        f"{len(mismatched)} stored cell(s) in {cfg.out} were made with other settings, e.g. "
        f"{cell.path(cfg.out)}: {what}"
    )


def unreadable_cells(cfg: SweepConfig) -> list[Path]:
    """The cell files of ``cfg`` that exist but cannot be read (truncated or corrupted JSON, or no ``key``): the
    report shows them as pending and the sweep recomputes them; the command line names them."""
    bad = []
    for cell in cfg.cells():
        path = cell.path(cfg.out)
        if path.exists():
            rec = read_json(path)
            if not isinstance(rec, dict) or "key" not in rec:
                bad.append(path)
    return bad


def made_with(rec, cfg: SweepConfig, cell: Cell) -> bool:
    """Whether the stored record ``rec`` of ``cell`` was made with ``cfg``'s settings (episodes, seed, area, episode
    length, faults, filter, results version; any checkpoint)."""
    return (
        isinstance(rec, dict)
        and "key" in rec
        and "row" in rec
        and not _settings_diff(rec["key"], cell_key(cfg, cell, None))
    )


def load_cells(cfg: SweepConfig) -> dict[Cell, dict]:
    """The stored records of ``cfg``'s cells made with its settings (:func:`made_with`; any checkpoint: for
    regenerating the report without the checkpoints)."""
    out = {}
    for cell in cfg.cells():
        rec = read_json(cell.path(cfg.out))
        if made_with(rec, cfg, cell):
            out[cell] = rec
    return out
