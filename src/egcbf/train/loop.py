"""Training runs: the loop, logging, evaluation rollouts and resuming (the checkpoint files:
:mod:`egcbf.train.checkpoint`).

    from egcbf.algo.config import TrainConfig
    from egcbf.train.loop import train
    train(TrainConfig.preset("egcbf+", "cpu", steps=200), "runs/egcbf+")

Layout of a run directory ``OUT``::

    OUT/config.json                 the run's TrainConfig
    OUT/metrics.csv                 evaluation rollouts: step, wall_s, safe/reach/success rates, cost, reward
    OUT/scalars.csv                 every logged scalar, long format (step, wall_s, tag, value)
    OUT/tb/                         TensorBoard events (``tensorboard=True``: the optional ``tensorboard`` extra)
    OUT/checkpoints/step_000100/    a checkpoint (:mod:`egcbf.train.checkpoint`): config.json, model.safetensors,
                                    training_state.pt, buffers.safetensors (newest checkpoint only), state.json
    OUT/best/                       the policy with the best evaluation rollouts so far (highest success rate,
                                    ties to the higher safe rate, then to the later update): config.json,
                                    model.safetensors, state.json (step, wall time, its metrics row)

Model selection uses the evaluation rollouts of training (fixed episodes from ``seed + 1000``, not the evaluation
seed 0 of the reported results; ``egcbf eval --seed`` should stay away from training seed + 1000), so ``OUT/best``
is a validation choice: the learned policies can degrade late in
a run (docs/learning.md), and the best one seen is the one to ship.

A checkpoint directory alone is enough to evaluate (:func:`egcbf.train.checkpoint.load_controller`). Checkpoints and
``OUT/best`` are swapped into place whole (:mod:`egcbf.train.checkpoint`), so a kill at any moment leaves a complete
directory (the new one or the previous one). ``resume=True`` continues from the newest checkpoint that loads (losing
at most ``checkpoint_interval`` updates; a corrupted newer one is set aside as ``step_XXXXXX.corrupt`` and said so),
cuts the CSV logs back to its step by writing a copy and renaming it over the original (never rewriting a log in
place), and continues bit for bit on CPU: every random number comes from the seed, the update index or the saved
generator.
"""

from __future__ import annotations

import csv
import io
import os
import time
from pathlib import Path

import torch
from tqdm.auto import tqdm

from ..algo.config import TrainConfig
from ..algo.learner import GraphCBFLearner
from ..evaluate.episodes import episode_seed, run_episodes
from ..io.atomic import write_json_atomic, write_text_atomic, writing
from .checkpoint import (
    CheckpointError,
    best_metrics,
    list_checkpoints,
    load_learner,
    no_checkpoint,
    read_config,
    read_state,
    save_best,
    save_checkpoint,
    set_aside,
    warm_start,
)

__all__ = ["METRICS_FIELDS", "evaluate_policy", "require_tensorboard", "train"]

METRICS_FIELDS = (
    "step", "wall_s", "safe_rate", "reach_rate", "success_rate", "cost", "reward", "num_episodes", "cpu_s"
)  # fmt: skip
#: columns a log written before they existed leaves empty (``cpu_s``: process CPU time, added 2026-11)
_OPTIONAL_FIELDS = frozenset({"cpu_s"})


# ---------------------------------------------------------------------------------------------------- logging
def require_tensorboard():
    """torch's ``SummaryWriter``, or an ``ImportError`` saying how to install the optional ``tensorboard`` extra."""
    try:
        import tensorboard  # noqa: F401  (torch's wrapper imports it lazily; fail here, with the fix)
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise ImportError(
            "TensorBoard logging needs the tensorboard package, an optional extra: pip install -e '.[tensorboard]' "
            "(or pip install 'tensorboard>=2.14'); or train without --tensorboard"
        ) from None
    return SummaryWriter


#: what a failed append to a CSV log keeps (:func:`egcbf.io.atomic.writing`)
_ROWS_KEPT = "the rows logged before are intact (--resume drops a partial last row)"


class _Logger:
    """Scalars to ``scalars.csv`` (always) and, if ``tensorboard``, to TensorBoard events in ``OUT/tb``;
    evaluations to ``metrics.csv``."""

    def __init__(self, out: Path, start_step: int, tensorboard: bool = False):
        self.out = out
        self.tb = None
        if tensorboard:  # before any file is touched: a missing package fails cleanly
            writer = require_tensorboard()
        for name, header in (("scalars.csv", ("step", "wall_s", "tag", "value")), ("metrics.csv", METRICS_FIELDS)):
            _truncate_csv(out / name, header, start_step)
        if tensorboard:
            self.tb = writer(str(out / "tb"), purge_step=start_step + 1 if start_step else None)

    def scalars(self, step: int, wall_s: float, values: dict[str, float]) -> None:
        with writing(self.out / "scalars.csv", _ROWS_KEPT), open(self.out / "scalars.csv", "a", newline="") as f:
            w = csv.writer(f)
            for k, v in values.items():
                w.writerow((step, f"{wall_s:.3f}", k, repr(float(v))))
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(k, float(v), step)

    def metrics(self, row: dict) -> None:
        with writing(self.out / "metrics.csv", _ROWS_KEPT), open(self.out / "metrics.csv", "a", newline="") as f:
            csv.DictWriter(f, METRICS_FIELDS, extrasaction="ignore").writerow(row)
        if self.tb is not None:
            for k in METRICS_FIELDS[2:-1]:
                self.tb.add_scalar(f"eval/{k}", float(row[k]), int(row["step"]))

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def _complete_row(row: dict, keep_upto: int) -> bool:
    """A whole row (a kill in the middle of an append leaves a short last line) of a step ``<= keep_upto``."""
    if None in row or any(v is None or (v == "" and k not in _OPTIONAL_FIELDS) for k, v in row.items()):
        return False
    try:
        return int(row["step"]) <= keep_upto
    except (KeyError, ValueError):
        return False


def _truncate_csv(path: Path, header: tuple[str, ...], keep_upto: int) -> None:
    """Create ``path`` with ``header``, or keep only its complete rows with ``step <= keep_upto`` (resume).

    The new content is written to a temporary file and renamed over ``path``: a kill leaves the old log or the new
    one, never an erased history."""
    rows = []
    if path.exists() and keep_upto > 0:
        with open(path, newline="") as f:
            rows = [r for r in csv.DictReader(f) if _complete_row(r, keep_upto)]
    buf = io.StringIO()
    w = csv.DictWriter(buf, header, extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(path, buf.getvalue())


# ---------------------------------------------------------------------------------------------------- evaluation
def _selection_key(row: dict) -> tuple[float, float] | None:
    """Model selection (``OUT/best``): the higher success rate, ties to the higher safe rate (then the later
    update); ``None`` for a row that cannot be read."""
    try:
        return (float(row["success_rate"]), float(row["safe_rate"]))
    except (KeyError, TypeError, ValueError):
        return None


def evaluate_policy(learner: GraphCBFLearner, config: TrainConfig) -> dict:
    """Evaluation rollouts of the current policy on fixed episodes (the same at every call): the metrics row of
    :mod:`egcbf.evaluate.metrics` (rates in ``[0, 1]``)."""
    env_cfg = config.eval_env_config()
    seeds = [episode_seed(config.seed + 1_000, env_cfg.num_agents, e) for e in range(config.eval_episodes)]
    stats, _, _ = run_episodes(learner.controller(), env_cfg, seeds, device=learner.device, dtype=learner.dtype)
    return stats.result()


# ---------------------------------------------------------------------------------------------------- loop
def _resume(
    out: Path, steps: int | None, log, num_threads: int | None = None
) -> tuple[GraphCBFLearner, TrainConfig, Path, tuple]:
    """The learner of the newest checkpoint of ``out`` that loads; newer ones that do not are renamed
    ``*.corrupt`` (kept for inspection, out of the way of new checkpoints) and said so on ``log``."""
    found = list_checkpoints(out)
    if not found:
        raise no_checkpoint(out)
    errors = []
    for ckpt in reversed(found):
        try:
            config = read_config(ckpt)
            if steps is not None:
                if steps < int(read_state(ckpt).get("step", 0)):
                    raise ValueError(
                        f"steps={steps} is below the update count {read_state(ckpt)['step']} of {ckpt}; "
                        "pass a larger --steps (the total number of updates)"
                    )
                config = config.replace(steps=steps)
            if num_threads is not None:
                config = config.replace(num_threads=num_threads)
            saved = _setup_torch(config)
            try:
                learner = load_learner(ckpt, config=config)
            except BaseException:
                _restore_torch(saved)
                raise
        except CheckpointError as err:
            errors.append(str(err))
            log(f"checkpoint {ckpt} cannot be loaded ({err}); trying the previous one")
            continue
        for bad in found[found.index(ckpt) + 1 :]:
            aside = set_aside(bad)
            log(f"set aside {bad} as {aside.name}; resuming from {ckpt}")
        return learner, config, ckpt, saved
    raise CheckpointError(f"no checkpoint of {out} can be loaded: " + "; ".join(errors))


def _setup_torch(config: TrainConfig) -> tuple:
    """Apply the config's threads and determinism; returns what to restore afterwards."""
    saved = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(),
             torch.is_deterministic_algorithms_warn_only_enabled())  # fmt: skip
    if config.num_threads > 0:
        torch.set_num_threads(config.num_threads)
    if config.deterministic:
        if config.device.startswith("cuda"):
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
    return saved


def _restore_torch(saved: tuple) -> None:
    torch.set_num_threads(saved[0])
    torch.use_deterministic_algorithms(saved[1], warn_only=saved[2])


def train(
    config: TrainConfig,
    out: str | Path,
    *,
    resume: bool = False,
    steps: int | None = None,
    progress: bool = True,
    log=None,
    tensorboard: bool = False,
    num_threads: int | None = None,
) -> GraphCBFLearner:
    """Train ``config`` into the run directory ``out`` (module doc); returns the learner.

    Args:
        config: the run's configuration (with ``resume``, the checkpoint's config is used instead; may be None).
        out: the run directory; a fresh run refuses a directory that already holds checkpoints.
        resume: continue from the newest checkpoint in ``out``.
        steps: train up to this many updates (default ``config.steps``; with ``resume`` it may extend the run).
        progress: show a tqdm bar.
        log: a callable receiving one line per evaluation (default: ``tqdm.write``).
        tensorboard: also log to TensorBoard (``OUT/tb``); needs the ``tensorboard`` extra
            (:func:`require_tensorboard` raises an ``ImportError`` saying how to install it).
        num_threads: with ``resume``, torch CPU threads instead of the saved config's (``None``: the saved ones).
    """
    if not isinstance(config, TrainConfig) and not (resume and config is None):  # resume reads the run's config
        raise TypeError(f"train() argument config must be a TrainConfig, got {type(config).__name__}")
    if not isinstance(out, (str, os.PathLike)) or str(out) == "":
        raise TypeError(f"train() argument out must be a run directory (str or pathlib.Path), got {out!r}")
    if tensorboard:
        require_tensorboard()  # before any work
    out = Path(out)
    log = log or tqdm.write
    if resume:
        learner, config, ckpt, saved = _resume(out, steps, log, num_threads)
        state = read_state(ckpt)
        wall0, cpu0 = float(state.get("wall_s", 0.0)), float(state.get("cpu_s", 0.0))
        log(f"resumed {config.algo} from {ckpt} at update {learner.step}")
    else:
        if list_checkpoints(out):
            raise FileExistsError(f"{out} already holds a run; pass resume=True (--resume) or another directory")
        if steps is not None:
            config = config.replace(steps=steps)
        saved = _setup_torch(config)
        try:
            learner = GraphCBFLearner(config)
            if config.init_from is not None:
                ckpt, digest = warm_start(learner, config.init_from, config.init_sha256)
                config = learner.config = config.replace(init_sha256=digest)
                log(f"[{config.algo}] warm start from {ckpt} (weights {digest[:12]})")
        except BaseException:
            _restore_torch(saved)
            raise
        out.mkdir(parents=True, exist_ok=True)
        wall0 = cpu0 = 0.0
    write_json_atomic(out / "config.json", config.to_dict())  # a kill never leaves a half-written config
    logger = _Logger(out, learner.step, tensorboard)
    best_row = best_metrics(out) if resume else None
    best = [_selection_key(best_row) if best_row is not None else None]
    t_start, c_start = time.perf_counter(), time.process_time()

    def wall() -> float:
        return wall0 + time.perf_counter() - t_start

    def cpu() -> float:
        return cpu0 + time.process_time() - c_start

    def budget_spent() -> str | None:
        """Which time budget is spent (``"max_wall_minutes=30"``), or ``None``."""
        for name, used in (("max_wall_minutes", wall), ("max_cpu_minutes", cpu)):
            limit = getattr(config, name)
            if limit is not None and used() >= 60.0 * limit:
                return f"{name}={limit:g}"
        return None

    def evaluate_now() -> None:
        row = evaluate_policy(learner, config)
        row.update(step=learner.step, wall_s=round(wall(), 3), cpu_s=round(cpu(), 3))
        logger.metrics(row)
        key = _selection_key(row)
        if best[0] is None or key >= best[0]:
            best[0] = key
            save_best(learner, out, row["wall_s"], row)
        log(
            f"[{config.algo}] update {learner.step:5d}  {row['wall_s']:8.1f}s wall {row['cpu_s']:8.1f}s cpu  "
            f"safe {100 * row['safe_rate']:5.1f}%  "
            f"reach {100 * row['reach_rate']:5.1f}%  success {100 * row['success_rate']:5.1f}%  "
            f"reward {row['reward']:9.2f}"
        )

    bar = tqdm(total=config.steps, initial=learner.step, desc=config.algo, unit="upd", disable=not progress)
    try:
        if learner.step == 0:
            evaluate_now()
        while learner.step < config.steps:
            info = learner.update()
            logger.scalars(learner.step, wall(), info)
            bar.update(1)
            bar.set_postfix(loss=f"{info['loss/total']:.4f}", unsafe=int(info["data/unsafe"]), refresh=False)
            out_of_time = budget_spent()
            last = learner.step == config.steps or out_of_time is not None
            if learner.step % config.eval_interval == 0 or last:
                evaluate_now()
            if learner.step % config.checkpoint_interval == 0 or last:
                save_checkpoint(learner, out, wall(), keep=config.keep_checkpoints, buffers=config.save_buffers,
                                cpu_s=cpu())  # fmt: skip
            if out_of_time is not None and learner.step < config.steps:
                log(f"[{config.algo}] stopped at update {learner.step}: {out_of_time}")
                break
    finally:
        bar.close()
        logger.close()
        _restore_torch(saved)
    return learner
