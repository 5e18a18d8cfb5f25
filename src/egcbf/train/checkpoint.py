"""Checkpoints on disk: writing, finding, checking and loading the directories of trained learners.

A checkpoint directory (``OUT/checkpoints/step_XXXXXX`` of a run, ``OUT/best``, or a shipped ``checkpoints/<algo>``)
holds::

    config.json             the run's TrainConfig
    model.safetensors       the weights: cbf.*, policy.*, cbf_target.* (safetensors: no pickle)
    state.json              step, wall time and what the weights are (below); OUT/best adds its metrics row
    training_state.pt       optimizer states and RNG state (run checkpoints only; loaded with weights_only=True)
    buffers.safetensors     replay buffers (the newest run checkpoint only, with save_buffers)

``config.json`` and ``model.safetensors`` are enough to evaluate (:func:`load_controller`, :func:`load_network`);
:func:`load_learner` restores everything training needs to continue.

Every checkpoint records what it is, ``format_version`` (:data:`FORMAT_VERSION`), ``algo``, ``group`` and
``interface``, twice: in the header of its ``model.safetensors`` (:func:`save_weights`, :func:`weights_identity`),
which travels with the weights and which editing the JSON files does not change, and in ``state.json`` beside
``weights_sha256`` (the hash of the weights file). :func:`check_identity` compares both with the directory's
``config.json`` on load, so that one method's weights (or another run's) are never loaded or reported under
another's name. Weights written before format 2 carry no header identity: their ``state.json`` must then exist
(format 1: with all three keys and the hash; unversioned: checked on ``algo`` only). A missing, corrupted, truncated
or mismatched file raises :class:`CheckpointError` (a ``ValueError``) naming the file instead of a raw parser error.

Directories are written into ``NAME.tmp`` and swapped into place (:mod:`egcbf.io.atomic`), so a kill at any moment
leaves a complete directory (the new one or the previous one); every reader recovers a swap killed half-way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform
import re
import shutil
import struct
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from ..io.atomic import WriteError, recover_dir, replace_dir, writing

if TYPE_CHECKING:
    from ..algo.config import TrainConfig
    from ..algo.learner import GraphCBFLearner, LearnedController
    from ..nn import CBFNet, PolicyNet

__all__ = [
    "CHECKPOINTS_DIR",
    "FORMAT_VERSION",
    "CheckpointContents",
    "CheckpointError",
    "best_metrics",
    "build_network",
    "check_identity",
    "check_sizes",
    "checkpoint_step",
    "find_checkpoint",
    "identity",
    "list_checkpoints",
    "load_controller",
    "load_learner",
    "load_network",
    "no_checkpoint",
    "read_checkpoint",
    "read_config",
    "read_state",
    "read_tensors",
    "read_training_state",
    "save_best",
    "save_checkpoint",
    "save_weights",
    "set_aside",
    "sha256",
    "weights_identity",
    "write_checkpoint_dir",
]

#: Version of the checkpoint layout written by this code (``state.json["format_version"]``). 2: ``model.safetensors``
#: carries the identity in its own header (:func:`weights_identity`).
FORMAT_VERSION = 2
#: What a checkpoint's weights are: the keys of :func:`identity` compared on load.
IDENTITY_KEYS = ("algo", "group", "interface", "robot")
#: The keys every format-1+ checkpoint records (``robot`` came later: compared where recorded)
_REQUIRED_KEYS = ("algo", "group", "interface")
#: The subdirectory of a run directory holding its ``step_XXXXXX`` checkpoints.
CHECKPOINTS_DIR = "checkpoints"
_STEP_DIR = re.compile(r"step_(\d+)")


class CheckpointError(ValueError):
    """A checkpoint file that is missing, corrupted, truncated or does not match its config."""


# ---------------------------------------------------------------------------------------------------- reading files
def identity(config: TrainConfig) -> dict:
    """What a checkpoint of ``config`` (a :class:`~egcbf.algo.config.TrainConfig`) is, as stored in ``state.json``."""
    return {
        "format_version": FORMAT_VERSION,
        "algo": config.algo,
        "group": config.group,
        "interface": config.model.interface,
        "robot": config.robot,
    }


def weights_identity(path: Path) -> dict:
    """The identity stored in the header of a ``model.safetensors`` (format 2: ``format_version``, ``algo``,
    ``group``, ``interface``, and in weights written since it was added ``robot``, as strings); ``{}`` for weights
    written before format 2."""
    try:
        with safe_open(str(path), "pt") as f:
            meta = f.metadata() or {}
    except Exception as err:  # safetensors raises its own SafetensorError (and OSError) on bad files
        raise CheckpointError(f"{path} is corrupted or truncated ({type(err).__name__}: {err})") from None
    return {k: meta[k] for k in ("format_version", *IDENTITY_KEYS) if k in meta}


def save_weights(tensors: dict[str, torch.Tensor], path: Path, config: TrainConfig) -> None:
    """Write ``tensors`` to the safetensors file ``path`` with the identity of ``config`` in its header, so that what
    the weights are travels with them (relabelling ``config.json`` and ``state.json`` is caught on load)."""
    meta = {k: str(v) for k, v in identity(config).items()}
    save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(path), metadata=meta)


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_config(ckpt: Path) -> TrainConfig:
    """The :class:`~egcbf.algo.config.TrainConfig` of ``ckpt/config.json``."""
    from ..algo.config import TrainConfig

    path = Path(ckpt) / "config.json"
    try:
        return TrainConfig.from_json(path)
    except FileNotFoundError:
        raise CheckpointError(f"{path} is missing (a checkpoint holds config.json and model.safetensors)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CheckpointError(f"{path} is corrupted or truncated (not JSON: {err})") from None
    except (TypeError, ValueError, KeyError) as err:
        raise CheckpointError(f"{path} is not a valid training config: {err}") from None


def read_state(ckpt: Path) -> dict:
    """``ckpt/state.json`` as a dict (``{}`` if the file is absent)."""
    path = Path(ckpt) / "state.json"
    if not path.exists():
        return {}
    try:
        state = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise CheckpointError(f"{path} is corrupted or truncated (not JSON: {err})") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path} is not a JSON object")
    return state


def read_tensors(path: Path) -> dict[str, torch.Tensor]:
    """A safetensors file, or :class:`CheckpointError` naming it if it is missing, truncated or corrupted."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path} is missing")
    try:
        return load_file(str(path))
    except Exception as err:  # safetensors raises its own SafetensorError (and OSError) on bad files
        raise CheckpointError(f"{path} is corrupted or truncated ({type(err).__name__}: {err})") from None


def read_training_state(path: Path) -> dict:
    """The optimizer and RNG state of ``training_state.pt`` (``weights_only`` load)."""
    try:
        return torch.load(path, weights_only=True, map_location="cpu")
    except Exception as err:  # zip / pickle errors of a truncated file
        raise CheckpointError(f"{path} is corrupted or truncated ({type(err).__name__}: {err})") from None


def check_identity(
    ckpt: Path,
    config: TrainConfig,
    state: dict | None = None,
    *,
    stored: dict | None = None,
    weights_sha256: str | None = None,
) -> None:
    """Raise :class:`CheckpointError` unless the weights of ``ckpt`` are what ``config`` (its ``config.json``) says.

    What the weights are is read from the header of ``model.safetensors`` (format 2, :func:`weights_identity`), which
    editing ``config.json`` or ``state.json`` does not change; for weights without it (format 0-1) from
    ``state.json``, which must then exist. ``state.json``, when present, must agree too, and its ``weights_sha256``
    must be the hash of the weights file. ``stored`` and ``weights_sha256``: the header identity and the hash of the
    weights when the caller has read the file already (:func:`read_checkpoint`), else read here."""
    ckpt = Path(ckpt)
    weights = ckpt / "model.safetensors"
    state_path = ckpt / "state.json"
    if state is None:
        state = read_state(ckpt) if state_path.exists() else None
    if stored is None:
        stored = weights_identity(weights) if weights.exists() else {}
    if not stored and state is None:
        raise CheckpointError(
            f"{state_path} is missing, and {weights} does not record what it is (written before format 2): the "
            "method, group and interface of the weights cannot be checked; copy the whole checkpoint directory"
        )
    want = identity(config)
    for key in IDENTITY_KEYS if stored else ():
        if key not in stored and key not in _REQUIRED_KEYS:  # older format-2 weights: state.json's then
            continue
        if stored.get(key) != str(want[key]):
            raise CheckpointError(
                f"{weights} holds weights of {key} {stored.get(key)!r} but {ckpt / 'config.json'} says "
                f"{want[key]!r}: the config was edited or comes from another run (copy the whole checkpoint directory)"
            )
    if state is None:
        return
    version = state.get("format_version", 0)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise CheckpointError(
            f"{state_path} has checkpoint format {version!r}; this egcbf reads up to {FORMAT_VERSION} (upgrade egcbf)"
        )
    keys = IDENTITY_KEYS if version >= 1 else ("algo",)
    if version >= 1 and not stored and not all(k in state for k in _REQUIRED_KEYS):
        raise CheckpointError(f"{state_path} does not say what the weights are (missing {keys}); it was edited")
    for key in keys:
        if key in state and state[key] != want[key]:
            raise CheckpointError(
                f"{ckpt}: state.json says the weights are {key} {state[key]!r} but config.json says "
                f"{want[key]!r}; the files come from different runs (copy the whole checkpoint directory)"
            )
    if version >= 1 and "weights_sha256" not in state:
        raise CheckpointError(f"{state_path} has no weights_sha256 (format {version} writes one); it was edited")
    if weights_sha256 is None and "weights_sha256" in state and weights.exists():
        weights_sha256 = sha256(weights)
    if "weights_sha256" in state and weights_sha256 is not None and weights_sha256 != state["weights_sha256"]:
        raise CheckpointError(
            f"{weights} is not the file its state.json was written with (SHA-256 differs): replaced by another "
            "run's weights, or corrupted; copy the whole checkpoint directory"
        )


# ---------------------------------------------------------------------------------------------------- writing
def _ckpt_dir(out: Path, step: int) -> Path:
    return out / CHECKPOINTS_DIR / f"step_{step:06d}"


def _to_cpu(obj):
    if isinstance(obj, torch.Tensor):
        return obj.cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def write_checkpoint_dir(learner: GraphCBFLearner, final: Path, state: dict, extra=None) -> Path:
    """Write ``config.json``, ``model.safetensors``, ``state.json`` (and whatever ``extra(tmp_dir, at)`` adds, each
    file passed through ``at``, :func:`egcbf.io.atomic.writing`) into ``final.tmp``, then swap it into place
    (:func:`egcbf.io.atomic.replace_dir`): a kill at any moment leaves a complete ``final`` (new or previous) or a
    previous one that :func:`egcbf.io.atomic.recover_dir` restores. A full disk or the file-size limit raises
    :class:`egcbf.io.atomic.WriteError` naming the file, with ``final.tmp`` removed and ``final`` unchanged."""
    tmp = final.with_name(final.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with writing(tmp, f"{final} was not saved; the checkpoints already saved are unchanged") as at:
            tmp.mkdir(parents=True)
            learner.config.to_json(at(tmp / "config.json"))
            save_weights(learner.weights(), at(tmp / "model.safetensors"), learner.config)
            if extra is not None:
                extra(tmp, at)
            state = {**state, **identity(learner.config), "weights_sha256": sha256(tmp / "model.safetensors")}
            at(tmp / "state.json").write_text(json.dumps(state, indent=2) + "\n")
    except WriteError:
        shutil.rmtree(tmp, ignore_errors=True)  # the partial copy: give its space back
        raise
    return replace_dir(tmp, final)


def save_checkpoint(
    learner: GraphCBFLearner, out: Path, wall_s: float, keep: int = 0, buffers: bool = True, cpu_s: float = 0.0
) -> Path:
    """Write the learner's checkpoint ``OUT/checkpoints/step_XXXXXX`` atomically (``wall_s`` and ``cpu_s``: the
    run's training wall and process CPU time so far, for a resumed run's budgets); keep the newest ``keep`` (0: all)."""

    def training_files(tmp: Path, at) -> None:
        with open(at(tmp / "training_state.pt"), "wb") as f:  # a file object: a failed write's OSError is kept
            torch.save(_to_cpu(learner.training_state()), f)
        if buffers:
            save_file({k: v.cpu() for k, v in learner.buffers().items()}, str(at(tmp / "buffers.safetensors")))

    state = {
        "step": learner.step,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "algo": learner.config.algo,
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
    }
    out = Path(out)
    final = write_checkpoint_dir(learner, _ckpt_dir(out, learner.step), state, training_files)
    older = list_checkpoints(out)[:-1]
    for old in older:  # resuming needs the buffers of the newest checkpoint only (they can be large)
        (old / "buffers.safetensors").unlink(missing_ok=True)
    if keep > 0:
        for old in older[: max(0, len(older) + 1 - keep)]:
            shutil.rmtree(old, ignore_errors=True)
    return final


def save_best(learner: GraphCBFLearner, out: Path, wall_s: float, row: dict) -> Path:
    """Write ``OUT/best`` (weights, config, and the evaluation ``row`` that selected it) atomically."""
    state = {"step": learner.step, "wall_s": wall_s, "algo": learner.config.algo, "metrics": row}
    return write_checkpoint_dir(learner, Path(out) / "best", state)


def best_metrics(out: str | Path) -> dict | None:
    """The evaluation row that selected ``OUT/best`` (:func:`save_best`); ``None`` if there is none or it cannot be
    read (an unreadable ``best/`` is replaced by the next one saved)."""
    f = recover_dir(Path(out) / "best") / "state.json"
    try:
        row = json.loads(f.read_text())["metrics"] if f.exists() else None
    except (ValueError, KeyError, TypeError):
        return None
    return row if isinstance(row, dict) else None


def set_aside(ckpt: Path) -> Path:
    """Rename the checkpoint ``ckpt`` (one that does not load) to ``step_XXXXXX.corrupt`` (``.corrupt1``, ... if
    taken), out of the way of new checkpoints and kept for inspection; returns the new path."""
    aside = ckpt.with_name(ckpt.name + ".corrupt")
    k = 1
    while aside.exists():  # an earlier fallback set aside the same step
        aside, k = ckpt.with_name(f"{ckpt.name}.corrupt{k}"), k + 1
    os.replace(ckpt, aside)
    return aside


# ---------------------------------------------------------------------------------------------------- finding
def list_checkpoints(out: str | Path) -> list[Path]:
    """Complete checkpoints of the run ``out``, oldest first (``step_XXXXXX`` directories with a ``state.json``; a
    checkpoint swap killed between its renames is recovered first)."""
    root = Path(out) / CHECKPOINTS_DIR
    if not root.is_dir():
        return []
    for old in root.glob("step_*.old"):
        recover_dir(old.with_name(old.name[: -len(".old")]))
    done = [
        p for p in root.glob("step_*") if _STEP_DIR.fullmatch(p.name) and p.is_dir() and (p / "state.json").exists()
    ]
    return sorted(done, key=lambda p: int(p.name.split("_")[1]))


def no_checkpoint(out: str | Path) -> FileNotFoundError:
    """The error for a run directory ``out`` without a checkpoint."""
    return FileNotFoundError(f"no checkpoint in {out} (expected {out}/{CHECKPOINTS_DIR}/step_*/model.safetensors)")


def _check_path(path, func: str) -> None:
    """A :class:`TypeError` naming ``func``'s argument ``path`` unless it is a ``str`` or ``os.PathLike``."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(
            f"{func}() argument path must be a checkpoint or run directory (str or pathlib.Path), got "
            f"{type(path).__name__}"
        )


def find_checkpoint(path: str | Path, prefer_best: bool = False) -> Path:
    """A checkpoint directory: ``path`` itself if it holds one, else, of the run ``path``, its ``best/`` (the
    checkpoint selected on validation episodes) if ``prefer_best`` and it exists, else its newest checkpoint
    (what resuming needs)."""
    _check_path(path, "find_checkpoint")
    p = recover_dir(Path(path))
    if (p / "model.safetensors").exists() and (p / "config.json").exists():
        return p
    if p.exists() and not p.is_dir():
        raise FileNotFoundError(f"{p} is a file; pass a checkpoint directory (config.json + model.safetensors)")
    if (p / "model.safetensors").exists():  # a checkpoint directory missing its config: not a run directory
        raise CheckpointError(
            f"{p / 'config.json'} is missing: {p} holds weights but not the config they were trained with (a "
            "checkpoint holds config.json and model.safetensors; copy the whole directory)"
        )
    best = recover_dir(p / "best")
    if prefer_best and (best / "model.safetensors").exists() and (best / "config.json").exists():
        return best
    found = list_checkpoints(p)
    if not found:
        raise no_checkpoint(p)
    return found[-1]


def checkpoint_step(out: str | Path) -> int | None:
    """The update count of the newest checkpoint of run ``out`` (``None`` without a readable one)."""
    found = list_checkpoints(out)
    if not found:
        return None
    try:
        return int(read_state(found[-1])["step"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return None


# ---------------------------------------------------------------------------------------------------- loading
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


#: the fields of ``ModelConfig`` that size the networks' tensors (each appears as a dimension of some weight)
_SIZE_FIELDS = ("hidden", "head_hidden", "heads")


def check_sizes(ckpt: Path, cfg: TrainConfig, weights: dict[str, torch.Tensor]) -> None:
    """Raise :class:`CheckpointError` if a size field of ``cfg.model`` (``hidden``, ...) exceeds every dimension of
    every tensor in ``weights``: such a config cannot describe these weights, and building its networks first
    could try to allocate far more memory than the machine has (an edited ``config.json``)."""
    largest = max((max(t.shape, default=1) for t in weights.values()), default=0)
    for name in _SIZE_FIELDS:
        value = getattr(cfg.model, name)
        if value > largest:
            raise CheckpointError(
                f"{ckpt / 'config.json'} says model.{name} = {value!r}, but no tensor of {ckpt / 'model.safetensors'} "
                f"has a dimension above {largest}: the config does not describe these weights (edited, or from "
                "another run; copy the whole checkpoint directory)"
            )


def _optim_to(learner: GraphCBFLearner, device) -> None:
    for opt in (learner.opt_cbf, learner.opt_policy):
        for st in opt.state.values():
            for k, v in st.items():
                if isinstance(v, torch.Tensor) and k != "step":
                    st[k] = v.to(device)


def load_learner(path: str | Path, device=None, dtype=None, config: TrainConfig | None = None) -> GraphCBFLearner:
    """The learner of checkpoint ``path`` (a checkpoint or run directory): weights, optimizers, RNG, buffers."""
    from ..algo.learner import GraphCBFLearner

    _check_path(path, "load_learner")
    ckpt = find_checkpoint(path)
    cfg = config or read_config(ckpt)
    weights = read_tensors(ckpt / "model.safetensors")
    check_identity(ckpt, cfg)
    check_sizes(ckpt, cfg, weights)
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


def warm_start(learner: GraphCBFLearner, path: str | Path, sha: str | None = None) -> tuple[Path, str]:
    """Load the network weights of checkpoint ``path`` (a checkpoint or run directory; a run's ``best/``) into
    ``learner`` (CBF, target CBF, policy; optimizers, buffers and update count stay fresh). Returns the checkpoint
    directory and the SHA-256 of its weights.

    Raises :class:`CheckpointError` if the checkpoint is another method, group or interface, if its networks'
    configuration (``model``) differs from ``learner.config.model`` (naming the fields), or if ``sha`` is given and
    is not the hash of its weights."""
    ckpt = find_checkpoint(path, prefer_best=True)
    cfg = read_config(ckpt)
    weights_path = ckpt / "model.safetensors"
    weights = read_tensors(weights_path)
    check_identity(ckpt, cfg)
    want = learner.config
    if identity(cfg) != identity(want):
        raise CheckpointError(
            f"{ckpt} holds {cfg.algo} weights ({cfg.group}, {cfg.model.interface} interface); this run trains "
            f"{want.algo} ({want.group}, {want.model.interface} interface): warm-start from a checkpoint of the same "
            "method"
        )
    ours, theirs = dataclasses.asdict(want.model), dataclasses.asdict(cfg.model)
    differ = sorted(k for k in ours if ours[k] != theirs.get(k))
    if differ:
        pairs = ", ".join(f"{k}: {theirs.get(k)!r} there, {ours[k]!r} here" for k in differ)
        raise CheckpointError(f"{ckpt}: the networks differ from this run's model config ({pairs})")
    digest = sha256(weights_path)
    if sha is not None and sha != digest:
        raise CheckpointError(
            f"{weights_path} has SHA-256 {digest}, but the config's init_sha256 is {sha}: the weights changed since "
            "the run was configured"
        )
    _load_state_dict(
        ckpt, lambda: learner.load_weights({k: v.to(learner.device, learner.dtype) for k, v in weights.items()})
    )
    return ckpt, digest


@dataclasses.dataclass(frozen=True)
class CheckpointContents:
    """What an evaluation needs of a checkpoint directory, each file read once and checked (:func:`read_checkpoint`).

    ``directory``: the checkpoint directory (of a run: the one :func:`find_checkpoint` picked); ``config``: its
    ``config.json``; ``weights``: every tensor of its ``model.safetensors`` on the CPU; ``weights_sha256``: the hex
    SHA-256 of that file's bytes."""

    directory: Path
    config: TrainConfig
    weights: dict[str, torch.Tensor]
    weights_sha256: str


def _read_file(path: Path) -> bytes:
    """The bytes of a checkpoint file (every read of :func:`read_checkpoint` goes through here)."""
    if not path.exists():
        raise CheckpointError(f"{path} is missing")
    return path.read_bytes()


def _parse_weights(path: Path, data: bytes) -> tuple[dict[str, torch.Tensor], dict]:
    """``(tensors, header identity)`` of the bytes ``data`` of the safetensors file ``path`` (the identity as
    :func:`weights_identity` reads it)."""
    from safetensors.torch import load as load_bytes

    try:
        tensors = load_bytes(data)
        (length,) = struct.unpack("<Q", data[:8])
        meta = json.loads(data[8 : 8 + length]).get("__metadata__") or {}
    except Exception as err:  # safetensors raises its own SafetensorError on bad files
        raise CheckpointError(f"{path} is corrupted or truncated ({type(err).__name__}: {err})") from None
    return tensors, {k: meta[k] for k in ("format_version", *IDENTITY_KEYS) if k in meta}


def read_checkpoint(path: str | Path) -> CheckpointContents:
    """A checkpoint (or run) directory's ``config.json`` and ``model.safetensors``, each read once, checked
    (:func:`check_identity`, :func:`check_sizes`). Of a run directory: its ``best/`` (selected on validation
    episodes) if it has one, else its newest checkpoint. Raises :class:`CheckpointError` or ``FileNotFoundError``
    naming the file."""
    _check_path(path, "read_checkpoint")
    ckpt = find_checkpoint(path, prefer_best=True)
    cfg = read_config(ckpt)
    data = _read_file(ckpt / "model.safetensors")
    weights, stored = _parse_weights(ckpt / "model.safetensors", data)
    sha = hashlib.sha256(data).hexdigest()
    check_identity(ckpt, cfg, stored=stored, weights_sha256=sha)
    check_sizes(ckpt, cfg, weights)
    return CheckpointContents(ckpt, cfg, weights, sha)


def build_network(
    contents: CheckpointContents, part: str, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> CBFNet | PolicyNet:
    """The trained network ``part = "policy"`` or ``"cbf"`` of a checkpoint read by :func:`read_checkpoint` (its
    ``<part>.*`` weights), on ``device`` in ``dtype``, in eval mode."""
    from ..nn import CBFNet, PolicyNet

    nets = {"policy": PolicyNet, "cbf": CBFNet}
    if part not in nets:
        raise ValueError(f"part must be one of {sorted(nets)}, got {part!r}")
    net = nets[part](contents.config.model)
    prefix = part + "."
    weights = {k[len(prefix) :]: v for k, v in contents.weights.items() if k.startswith(prefix)}
    _load_state_dict(contents.directory, lambda: net.load_state_dict(weights))
    return net.to(device=device, dtype=dtype).eval()


def load_network(
    path: str | Path, part: str, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[CBFNet | PolicyNet, TrainConfig]:
    """One trained network, ``part = "policy"`` or ``"cbf"``, of a checkpoint (or run) directory, in eval mode, and
    the training config; needs only ``config.json`` and ``model.safetensors`` (:func:`read_checkpoint`,
    :func:`build_network`)."""
    _check_path(path, "load_network")
    if part not in ("policy", "cbf"):
        raise ValueError(f"part must be one of ['cbf', 'policy'], got {part!r}")
    contents = read_checkpoint(path)
    return build_network(contents, part, device, dtype), contents.config


def load_controller(
    path: str | Path, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[LearnedController, TrainConfig]:
    """An evaluation controller ``(state, env_config) -> (u, info)`` from a checkpoint (or run) directory; needs only
    its ``config.json`` and ``model.safetensors``. Returns the controller and the training config."""
    from ..algo.learner import LearnedController

    _check_path(path, "load_controller")
    policy, cfg = load_network(path, "policy", device, dtype)
    return LearnedController(policy, cfg.model), cfg
