"""Training runs: the loop, logging, evaluation rollouts, checkpoints and resuming.

    from egcbf.config import TrainConfig
    from egcbf.train import train
    train(TrainConfig.preset("egcbf+", "cpu", steps=200), "runs/egcbf+")

Layout of a run directory ``OUT``::

    OUT/config.json                 the run's TrainConfig
    OUT/metrics.csv                 evaluation rollouts: step, wall_s, safe/reach/success rates, cost, reward
    OUT/scalars.csv                 every logged scalar, long format (step, wall_s, tag, value)
    OUT/tb/                         TensorBoard events (``tensorboard=True``: the optional ``tensorboard`` extra)
    OUT/checkpoints/step_000100/    config.json, model.safetensors (cbf., policy., cbf_target. weights),
                                    training_state.pt (optimizer states and RNG state; loads with weights_only),
                                    buffers.safetensors (replay buffers; newest checkpoint only),
                                    state.json (step, wall time, versions)
    OUT/best/                       the policy with the best evaluation rollouts so far (highest success rate,
                                    ties to the higher safe rate, then to the later update): config.json,
                                    model.safetensors, state.json (step, wall time, its metrics row)

Model selection uses the evaluation rollouts of training (fixed episodes from ``seed + 1000``, never the seeds of
:func:`egcbf.evaluate.evaluate`), so ``OUT/best`` is a validation choice: the learned policies can degrade late in
a run (docs/learning.md), and the best one seen is the one to ship.

A checkpoint directory alone is enough to evaluate (:func:`load_controller`). Checkpoints and ``OUT/best`` are
written to a temporary directory and swapped into place (:mod:`egcbf.atomic`), so a kill at any moment leaves a
complete directory (the new one or the previous one); ``state.json`` records what the weights are (method, group,
interface, format version: :mod:`egcbf.ckpt_files`), checked on load. ``resume=True`` continues from the newest
checkpoint that loads (losing at most ``checkpoint_interval`` updates; a corrupted newer one is set aside as
``step_XXXXXX.corrupt`` and said so), cuts the CSV logs back to its step by writing a copy and renaming it over the
original (never rewriting a log in place), and continues bit for bit on CPU: every random number comes from the
seed, the update index or the saved generator.
"""

from __future__ import annotations

import csv
import io
import json
import os
import platform
import re
import shutil
import sys
import time
import warnings
from pathlib import Path

import torch
from safetensors.torch import save_file
from tqdm.auto import tqdm

from .algo.learner import GraphCBFLearner, LearnedController
from .atomic import recover_dir, replace_dir, write_json_atomic, write_text_atomic
from .ckpt_files import (
    CheckpointError,
    check_identity,
    identity,
    read_config,
    read_state,
    read_tensors,
    read_training_state,
    sha256,
)
from .config import TrainConfig
from .evaluate import episode_seed, run_episodes
from .nn import CBFNet, PolicyNet

__all__ = [
    "METRICS_FIELDS",
    "CheckpointError",
    "evaluate_policy",
    "find_checkpoint",
    "load_controller",
    "load_learner",
    "load_network",
    "require_tensorboard",
    "save_best",
    "save_checkpoint",
    "train",
]

METRICS_FIELDS = ("step", "wall_s", "safe_rate", "reach_rate", "success_rate", "cost", "reward", "num_episodes")
_CKPT = "checkpoints"
_STEP_DIR = re.compile(r"step_(\d+)")


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
        with open(self.out / "scalars.csv", "a", newline="") as f:
            w = csv.writer(f)
            for k, v in values.items():
                w.writerow((step, f"{wall_s:.3f}", k, repr(float(v))))
        if self.tb is not None:
            for k, v in values.items():
                self.tb.add_scalar(k, float(v), step)

    def metrics(self, row: dict) -> None:
        with open(self.out / "metrics.csv", "a", newline="") as f:
            csv.DictWriter(f, METRICS_FIELDS, extrasaction="ignore").writerow(row)
        if self.tb is not None:
            for k in METRICS_FIELDS[2:]:
                self.tb.add_scalar(f"eval/{k}", float(row[k]), int(row["step"]))

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def _complete_row(row: dict, keep_upto: int) -> bool:
    """A whole row (a kill in the middle of an append leaves a short last line) of a step ``<= keep_upto``."""
    if None in row or any(v is None or v == "" for v in row.values()):
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
def evaluate_policy(learner: GraphCBFLearner, config: TrainConfig) -> dict:
    """Evaluation rollouts of the current policy on fixed episodes (the same at every call): the metrics row of
    :mod:`egcbf.metrics` (rates in ``[0, 1]``)."""
    env_cfg = config.eval_env_config()
    seeds = [episode_seed(config.seed + 1_000, env_cfg.num_agents, e) for e in range(config.eval_episodes)]
    stats, _, _ = run_episodes(learner.controller(), env_cfg, seeds, device=learner.device, dtype=learner.dtype)
    return stats.result()


# ---------------------------------------------------------------------------------------------------- checkpoints
def _ckpt_dir(out: Path, step: int) -> Path:
    return out / _CKPT / f"step_{step:06d}"


def _write_dir_atomically(learner: GraphCBFLearner, final: Path, state: dict, extra=None) -> Path:
    """Write ``config.json``, ``model.safetensors``, ``state.json`` (and whatever ``extra(tmp_dir)`` adds) into
    ``final.tmp``, then swap it into place (:func:`egcbf.atomic.replace_dir`): a kill at any moment leaves a
    complete ``final`` (new or previous) or a previous one that :func:`egcbf.atomic.recover_dir` restores."""
    tmp = final.with_name(final.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    learner.config.to_json(tmp / "config.json")
    save_file({k: v.cpu() for k, v in learner.weights().items()}, str(tmp / "model.safetensors"))
    if extra is not None:
        extra(tmp)
    state = {**state, **identity(learner.config), "weights_sha256": sha256(tmp / "model.safetensors")}
    (tmp / "state.json").write_text(json.dumps(state, indent=2) + "\n")
    return replace_dir(tmp, final)


def save_checkpoint(learner: GraphCBFLearner, out: Path, wall_s: float, keep: int = 0, buffers: bool = True) -> Path:
    """Write the learner's checkpoint ``OUT/checkpoints/step_XXXXXX`` atomically; keep the newest ``keep`` (0: all)."""

    def training_files(tmp: Path) -> None:
        torch.save(_to_cpu(learner.training_state()), tmp / "training_state.pt")
        if buffers:
            save_file({k: v.cpu() for k, v in learner.buffers().items()}, str(tmp / "buffers.safetensors"))

    state = {
        "step": learner.step,
        "wall_s": wall_s,
        "algo": learner.config.algo,
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
    }
    final = _write_dir_atomically(learner, _ckpt_dir(out, learner.step), state, training_files)
    older = _checkpoints(out)[:-1]
    for old in older:  # resuming needs the buffers of the newest checkpoint only (they can be large)
        (old / "buffers.safetensors").unlink(missing_ok=True)
    if keep > 0:
        for old in older[: max(0, len(older) + 1 - keep)]:
            shutil.rmtree(old, ignore_errors=True)
    return final


def _selection_key(row: dict) -> tuple[float, float]:
    return (float(row["success_rate"]), float(row["safe_rate"]))


def save_best(learner: GraphCBFLearner, out: Path, wall_s: float, row: dict) -> Path:
    """Write ``OUT/best`` (weights, config, and the evaluation ``row`` that selected it) atomically."""
    state = {"step": learner.step, "wall_s": wall_s, "algo": learner.config.algo, "metrics": row}
    return _write_dir_atomically(learner, out / "best", state)


def _best_key(out: Path) -> tuple[float, float] | None:
    f = recover_dir(out / "best") / "state.json"
    try:
        return _selection_key(json.loads(f.read_text())["metrics"]) if f.exists() else None
    except (ValueError, KeyError, TypeError):  # an unreadable best/ is replaced by the next evaluation
        return None


def _to_cpu(obj):
    if isinstance(obj, torch.Tensor):
        return obj.cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def _checkpoints(out: Path) -> list[Path]:
    """Complete checkpoints of a run, oldest first (``step_XXXXXX`` directories with a ``state.json``; a
    checkpoint swap killed between its renames is recovered first)."""
    root = out / _CKPT
    if not root.is_dir():
        return []
    for old in root.glob("step_*.old"):
        recover_dir(old.with_name(old.name[: -len(".old")]))
    done = [
        p for p in root.glob("step_*") if _STEP_DIR.fullmatch(p.name) and p.is_dir() and (p / "state.json").exists()
    ]
    return sorted(done, key=lambda p: int(p.name.split("_")[1]))


def find_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory: ``path`` itself if it holds one, else the newest checkpoint of the run ``path``."""
    p = recover_dir(Path(path))
    if (p / "model.safetensors").exists() and (p / "config.json").exists():
        return p
    if p.exists() and not p.is_dir():
        raise FileNotFoundError(f"{p} is a file; pass a checkpoint directory (config.json + model.safetensors)")
    found = _checkpoints(p)
    if not found:
        raise FileNotFoundError(f"no checkpoint in {p} (expected {p}/{_CKPT}/step_*/model.safetensors)")
    return found[-1]


def load_learner(path: str | Path, device=None, dtype=None, config: TrainConfig | None = None) -> GraphCBFLearner:
    """The learner of checkpoint ``path`` (a checkpoint or run directory): weights, optimizers, RNG, buffers."""
    ckpt = find_checkpoint(path)
    cfg = config or read_config(ckpt)
    weights = read_tensors(ckpt / "model.safetensors")
    check_identity(ckpt, cfg)
    learner = GraphCBFLearner(cfg, device=device, dtype=dtype)
    _load_state_dict(
        ckpt, lambda: learner.load_weights({k: v.to(learner.device, learner.dtype) for k, v in weights.items()})
    )
    if (ckpt / "training_state.pt").exists():
        state = read_training_state(ckpt / "training_state.pt")
        _load_state_dict(ckpt, lambda: learner.load_training_state(state), "training_state.pt")
        _optim_to(learner, learner.device)
    if (ckpt / "buffers.safetensors").exists():
        buffers = read_tensors(ckpt / "buffers.safetensors")
        _load_state_dict(ckpt, lambda: learner.load_buffers(buffers), "buffers.safetensors")
    elif learner.step > 0:
        warnings.warn(
            f"{ckpt} holds no replay buffers (only the newest checkpoint of a run keeps them, and only with "
            "save_buffers): continuing with empty buffers, not bit for bit",
            stacklevel=2,
        )
    return learner


def _load_state_dict(ckpt: Path, load, name: str = "model.safetensors") -> None:
    """Run ``load()`` (a ``load_state_dict``); a key or shape mismatch becomes a :class:`CheckpointError`."""
    try:
        load()
    except (RuntimeError, KeyError, ValueError, TypeError) as err:
        first = str(err).strip().splitlines()[0][:300]
        raise CheckpointError(
            f"{ckpt / name} does not match {ckpt / 'config.json'} ({first}); were the files written by another "
            "method or config?"
        ) from None


def _optim_to(learner: GraphCBFLearner, device) -> None:
    for opt in (learner.opt_cbf, learner.opt_policy):
        for st in opt.state.values():
            for k, v in st.items():
                if isinstance(v, torch.Tensor) and k != "step":
                    st[k] = v.to(device)


def load_network(
    path: str | Path, part: str, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[CBFNet | PolicyNet, TrainConfig]:
    """One trained network, ``part = "policy"`` or ``"cbf"``, of a checkpoint (or run) directory, in eval mode, and
    the training config; needs only ``config.json`` and ``model.safetensors`` (the ``<part>.*`` weights)."""
    nets = {"policy": PolicyNet, "cbf": CBFNet}
    if part not in nets:
        raise ValueError(f"part must be one of {sorted(nets)}, got {part!r}")
    ckpt = find_checkpoint(path)
    cfg = read_config(ckpt)
    weights = read_tensors(ckpt / "model.safetensors")
    check_identity(ckpt, cfg)
    net = nets[part](cfg.model)
    prefix = part + "."
    _load_state_dict(
        ckpt, lambda: net.load_state_dict({k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)})
    )
    return net.to(device=device, dtype=dtype).eval(), cfg


def load_controller(
    path: str | Path, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[LearnedController, TrainConfig]:
    """An evaluation controller ``(state, env_config) -> (u, info)`` from a checkpoint (or run) directory; needs only
    its ``config.json`` and ``model.safetensors``. Returns the controller and the training config."""
    policy, cfg = load_network(path, "policy", device, dtype)
    return LearnedController(policy, cfg.model), cfg


# ---------------------------------------------------------------------------------------------------- loop
def checkpoint_step(out: str | Path) -> int | None:
    """The update count of the newest checkpoint of run ``out`` (``None`` without a readable one)."""
    found = _checkpoints(Path(out))
    if not found:
        return None
    try:
        return int(read_state(found[-1])["step"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return None


def _resume(out: Path, steps: int | None, log) -> tuple[GraphCBFLearner, TrainConfig, Path, tuple]:
    """The learner of the newest checkpoint of ``out`` that loads; newer ones that do not are renamed
    ``*.corrupt`` (kept for inspection, out of the way of new checkpoints) and said so on ``log``."""
    found = _checkpoints(out)
    if not found:
        raise FileNotFoundError(f"no checkpoint in {out} (expected {out}/{_CKPT}/step_*/model.safetensors)")
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
            aside = bad.with_name(bad.name + ".corrupt")
            k = 1
            while aside.exists():  # an earlier fallback set aside the same step
                aside, k = bad.with_name(f"{bad.name}.corrupt{k}"), k + 1
            os.replace(bad, aside)
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
) -> GraphCBFLearner:
    """Train ``config`` into the run directory ``out`` (module doc); returns the learner.

    Args:
        config: the run's configuration (with ``resume``, the checkpoint's config is used instead).
        out: the run directory; a fresh run refuses a directory that already holds checkpoints.
        resume: continue from the newest checkpoint in ``out``.
        steps: train up to this many updates (default ``config.steps``; with ``resume`` it may extend the run).
        progress: show a tqdm bar.
        log: a callable receiving one line per evaluation (default: ``tqdm.write``).
        tensorboard: also log to TensorBoard (``OUT/tb``); needs the ``tensorboard`` extra
            (:func:`require_tensorboard` raises an ``ImportError`` saying how to install it).
    """
    if tensorboard:
        require_tensorboard()  # before any work
    out = Path(out)
    log = log or tqdm.write
    if resume:
        learner, config, ckpt, saved = _resume(out, steps, log)
        wall0 = float(read_state(ckpt).get("wall_s", 0.0))
        log(f"resumed {config.algo} from {ckpt} at update {learner.step}")
    else:
        if _checkpoints(out):
            raise FileExistsError(f"{out} already holds a run; pass resume=True (--resume) or another directory")
        if steps is not None:
            config = config.replace(steps=steps)
        saved = _setup_torch(config)
        out.mkdir(parents=True, exist_ok=True)
        learner = GraphCBFLearner(config)
        wall0 = 0.0
    write_json_atomic(out / "config.json", config.to_dict())  # a kill never leaves a half-written config
    logger = _Logger(out, learner.step, tensorboard)
    best = [_best_key(out) if resume else None]
    t_start = time.perf_counter()

    def wall() -> float:
        return wall0 + time.perf_counter() - t_start

    def evaluate_now() -> None:
        row = evaluate_policy(learner, config)
        row.update(step=learner.step, wall_s=round(wall(), 3))
        logger.metrics(row)
        key = _selection_key(row)
        if best[0] is None or key >= best[0]:
            best[0] = key
            save_best(learner, out, row["wall_s"], row)
        log(
            f"[{config.algo}] update {learner.step:5d}  {row['wall_s']:8.1f}s  safe {100 * row['safe_rate']:5.1f}%  "
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
            out_of_time = config.max_wall_minutes is not None and wall() >= 60.0 * config.max_wall_minutes
            last = learner.step == config.steps or out_of_time
            if learner.step % config.eval_interval == 0 or last:
                evaluate_now()
            if learner.step % config.checkpoint_interval == 0 or last:
                save_checkpoint(learner, out, wall(), keep=config.keep_checkpoints, buffers=config.save_buffers)
            if out_of_time and learner.step < config.steps:
                log(f"[{config.algo}] stopped at update {learner.step}: max_wall_minutes={config.max_wall_minutes:g}")
                break
    finally:
        bar.close()
        logger.close()
        _restore_torch(saved)
    return learner
