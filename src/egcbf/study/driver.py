"""Running the equivariance study (:mod:`egcbf.study.plan`): training its runs, keeping their checkpoints, and
evaluating them, resumably.

* **Training.** Each run is ``egcbf train --algo A --config <arm config> --seed K --threads 1`` in its own process
  (``RUNS/<arm>/<algo>-s<k>``), ``jobs`` at a time; a run directory that holds checkpoints but no ``study_done.json``
  (a run that was stopped) resumes with ``--resume`` (its wall time continues, so the budget still holds). When a run
  ends, its ``best/`` and ``metrics.csv`` are copied to :meth:`Run.checkpoint_dir` (in the repository) and
  ``study_done.json`` is written.
* **Evaluation.** A ``table`` arm is an ``egcbf reproduce`` sweep over its checkpoints (``cells/<arm>``, Table I's
  sizes at ``l = 4`` without obstacles, the arm's scale sizes, evaluation seed :data:`EVAL_SEED`); a ``rotated`` arm's
  runs are evaluated on :func:`rotated_cells` (``rotated/<run>/``). A cell already computed with the same checkpoint
  and settings is never recomputed.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ..io.atomic import write_json_atomic
from .plan import EVAL_SEED, ROOT, Arm, RotatedCell, Run, rotated_cells

__all__ = [
    "evaluate_arm",
    "evaluate_rotated",
    "evaluate_rotated_many",
    "pending_cells",
    "pending_runs",
    "train_command",
    "train_runs",
]

RUNS = Path("runs/equivariance")
DONE = "study_done.json"


def _config_fields(run: Run, arm: Arm) -> dict:
    """The ``--config`` JSON of a run: its arm's preset and overrides, the wall-time budget and the seed."""
    fields = {"preset": arm.preset, "max_wall_minutes": None, "max_cpu_minutes": float(arm.minutes), "seed": run.seed,
              **arm.overrides}  # fmt: skip
    arm.config(run.algo, run.seed)  # a clear error now for a recipe that does not build
    return fields


def train_command(run: Run, arm: Arm, runs_dir: str | Path = RUNS) -> list[str]:
    """The ``egcbf train`` command of ``run`` (writing its config file beside the run directory)."""
    out = Path(runs_dir) / run.arm / run.name
    cfg_file = Path(runs_dir) / run.arm / f"{run.name}.config.json"
    cfg_file.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(cfg_file, _config_fields(run, arm))
    cmd = [sys.executable, "-m", "egcbf", "train", "--out", str(out), "--threads", "1", "--no-progress"]
    if any(out.glob("checkpoints/*")):
        return [*cmd, "--resume"]
    return [*cmd, "--algo", run.algo, "--config", str(cfg_file), "--seed", str(run.seed)]


def pending_runs(arms: Sequence[Arm], root: str | Path = ROOT) -> list[Run]:
    """The runs of ``arms`` whose checkpoint is not in ``root`` yet."""
    return [r for a in arms for r in a.all_runs() if not (r.checkpoint_dir(root) / "model.safetensors").exists()]


def pending_cells(arm: Arm, root: str | Path = ROOT) -> int:
    """How many evaluation cells of ``arm``'s trained runs have no up-to-date stored result in ``root`` (missing, or
    made with other settings or weights): what ``egcbf study`` would evaluate. Runs not trained yet count none
    (:func:`pending_runs` names them)."""
    from ..train.checkpoint import sha256

    missing = set(pending_runs([arm], root))
    if arm.evaluation == "rotated":
        cells = rotated_cells()
        return sum(
            not _rotated_stored(run, c, root, sha256(run.checkpoint_dir(root) / "model.safetensors"))
            for run in arm.all_runs() if run not in missing for c in cells
        )  # fmt: skip
    if missing:
        return 0
    from ..reproduce import validate
    from ..reproduce.store import pending_cells as sweep_pending

    cfg = sweep_config(arm, root)
    return len(sweep_pending(cfg, validate(cfg)))


def _collect(run: Run, runs_dir: Path, root: Path) -> None:
    out = runs_dir / run.arm / run.name
    best = out / "best"
    if not (best / "model.safetensors").exists():
        raise RuntimeError(f"{out} finished without a best/ checkpoint")
    dest = run.checkpoint_dir(root)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in ("config.json", "model.safetensors", "state.json"):
        shutil.copy2(best / name, tmp / name)
    shutil.copy2(out / "metrics.csv", tmp / "metrics.csv")
    from ..io.report import machine_info

    write_json_atomic(tmp / "machine.json", machine_info())  # where the CPU-minute budget was spent
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    write_json_atomic(out / DONE, {"checkpoint": str(dest), "finished": time.strftime("%Y-%m-%dT%H:%M:%S")})


def train_runs(
    arms: Sequence[Arm],
    *,
    jobs: int = 2,
    root: str | Path = ROOT,
    runs_dir: str | Path = RUNS,
    log: Callable[[str], None] = print,
    poll_s: float = 5.0,
) -> list[Run]:
    """Train every pending run of ``arms``, ``jobs`` processes at a time; returns the runs trained. A run whose
    process fails stops the study with a ``RuntimeError`` naming its log (the others finish first)."""
    root, runs_dir = Path(root), Path(runs_dir)
    by_name = {a.name: a for a in arms}
    todo, running, done, failed = pending_runs(arms, root), [], [], []
    while todo or running:
        while todo and len(running) < jobs:
            run = todo.pop(0)
            out = runs_dir / run.arm / run.name
            if (out / DONE).exists():  # trained, but its checkpoint was not kept (deleted since): keep it again
                _collect(run, runs_dir, root)
                done.append(run)
                continue
            cmd = train_command(run, by_name[run.arm], runs_dir)
            logf = (runs_dir / run.arm / f"{run.name}.log").open("a")
            log(f"train {run.arm}/{run.name}: {' '.join(cmd[2:])}")
            running.append((run, subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT), logf))
        time.sleep(poll_s if running else 0)
        for item in list(running):
            run, proc, logf = item
            if proc.poll() is None:
                continue
            running.remove(item)
            logf.close()
            if proc.returncode != 0:
                failed.append(run)
                log(f"FAILED {run.arm}/{run.name} (exit {proc.returncode}): see {runs_dir / run.arm / run.name}.log")
                continue
            _collect(run, runs_dir, root)
            done.append(run)
            log(f"done {run.arm}/{run.name} -> {run.checkpoint_dir(root)}")
    if failed:
        raise RuntimeError(f"{len(failed)} training run(s) failed: {[f'{r.arm}/{r.name}' for r in failed]}")
    return done


# ---------------------------------------------------------------------------------------------------- evaluation
def sweep_config(arm: Arm, root: str | Path = ROOT, workers: int = 2):
    """The ``egcbf reproduce`` sweep of a ``table`` arm (its checkpoints, its cells folder)."""
    from ..reproduce import SweepConfig

    seeded = tuple(a for a in arm.algos() if arm.seeds(a) != (0,))
    seeds = tuple(sorted({s for a in seeded for s in arm.seeds(a)})) or (0,)
    return SweepConfig(
        methods=arm.algos(),
        num_agents=arm.table_sizes,
        obstacles=0,
        obstacle_methods=(),
        episodes=arm.episodes,
        train_seeds=seeds,
        seed_methods=seeded,
        scale_sizes=arm.scale_sizes,
        scale_methods=arm.algos() if arm.scale_sizes else (),
        scale_agent_episodes=arm.scale_agent_episodes,
        long_steps=None,
        seed=EVAL_SEED,
        checkpoints=Path(root) / "checkpoints" / arm.name,
        out=Path(root) / "cells" / arm.name,
        baselines=None,
        workers=workers,
    )


def _rotated_key(run: Run, cell: RotatedCell, sha: str) -> dict:
    return {"run": f"{run.arm}/{run.name}", "checkpoint_sha256": sha, "seed": EVAL_SEED, **cell.__dict__}


def _rotated_stored(run: Run, cell: RotatedCell, root: str | Path, sha: str) -> bool:
    from ..reproduce.store import read_json

    rec = read_json(cell.path(run, root))  # None for a missing or unreadable file: (re)computed
    return isinstance(rec, dict) and rec.get("key") == _rotated_key(run, cell, sha)


def evaluate_rotated(
    run: Run,
    root: str | Path = ROOT,
    log: Callable[[str], None] = print,
    cells: Sequence[RotatedCell] | None = None,
) -> int:
    """Evaluate ``run`` on every cell of ``cells`` (default :func:`rotated_cells`) not yet stored with its
    checkpoint; returns how many were computed."""
    import torch

    from ..control.resolve import POLICY, resolve
    from ..evaluate.episodes import evaluate
    from ..io.report import machine_info
    from ..train.checkpoint import sha256

    ckpt = run.checkpoint_dir(root)
    sha = sha256(ckpt / "model.safetensors")
    computed = 0
    controller = train_cfg = None
    for cell in rotated_cells() if cells is None else cells:
        path = cell.path(run, root)
        key = _rotated_key(run, cell, sha)
        if _rotated_stored(run, cell, root, sha):
            continue
        if controller is None:
            built = resolve(POLICY, ckpt, device="cpu", dtype=torch.float32)
            controller, train_cfg = built.controller, built.train_config
        t0 = time.perf_counter()
        rows, _ = evaluate(
            lambda cfg, ctrl=controller: ctrl,
            [cell.num_agents],
            area_size=cell.area,
            num_obstacles=cell.obstacles,
            episodes=cell.episodes,
            seed=EVAL_SEED,
            show_progress=False,
            env_overrides={**train_cfg.env_overrides, "scene": cell.scene, "scene_yaw": cell.yaw},
            robot=train_cfg.robot,
        )
        meta = {"checkpoint": str(ckpt), "wall_s": round(time.perf_counter() - t0, 2), "machine": machine_info()}
        path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(path, {"key": key, "row": rows[0], "meta": meta})
        computed += 1
        row = rows[0]
        log(f"rotated {run.arm}/{run.name} {cell.scene} yaw {cell.yaw:g} N {cell.num_agents}: safe "
            f"{100 * row['safe_rate']:.1f} % success {100 * row['success_rate']:.1f} %")  # fmt: skip
    return computed


def _rotated_task(task: tuple[Run, RotatedCell, str]) -> list[str]:
    """One rotated cell in a worker process (one torch thread); returns its log lines."""
    import torch

    torch.set_num_threads(1)
    run, cell, root = task
    lines: list[str] = []
    evaluate_rotated(run, root, lines.append, [cell])
    return lines


def evaluate_rotated_many(
    runs: Sequence[Run],
    root: str | Path = ROOT,
    workers: int = 1,
    log: Callable[[str], None] = print,
    cells: Sequence[RotatedCell] | None = None,
) -> int:
    """:func:`evaluate_rotated` for every run of ``runs``, the cells not stored yet spread over ``workers``
    processes (one cell each, largest swarms first); returns how many cells were computed."""
    from ..train.checkpoint import sha256

    cells = rotated_cells() if cells is None else list(cells)
    todo = []
    for run in runs:
        sha = sha256(run.checkpoint_dir(root) / "model.safetensors")
        todo += [(run, c, str(root)) for c in cells if not _rotated_stored(run, c, root, sha)]
    todo.sort(key=lambda t: -t[1].num_agents)
    if workers <= 1 or len(todo) <= 1:
        return sum(evaluate_rotated(run, root, log, [cell]) for run, cell, _ in todo)
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(min(workers, len(todo))) as pool:
        for lines in pool.imap_unordered(_rotated_task, todo):
            for line in lines:
                log(line)
    return len(todo)


def evaluate_arm(arm: Arm, root: str | Path = ROOT, workers: int = 2, log: Callable[[str], None] = print) -> None:
    """Evaluate every trained run of ``arm`` (runs not trained yet are skipped and named)."""
    missing = pending_runs([arm], root)
    if missing:
        log(f"{arm.name}: not trained yet, not evaluated: {[r.name for r in missing]}")
    if arm.evaluation == "rotated":
        evaluate_rotated_many([r for r in arm.all_runs() if r not in missing], root, workers, log)
        return
    if missing:  # the sweep needs every checkpoint of the arm
        return
    from ..reproduce import sweep

    sweep(sweep_config(arm, root, workers), progress=False, log=log, command=f"egcbf study --arms {arm.name}")
