"""Reading a checkpoint directory's files with errors that name the file: a corrupted, truncated or mismatched
file raises :class:`CheckpointError` (a ``ValueError``) instead of a raw parser error.

Every checkpoint (and ``OUT/best``) records what it is in ``state.json``: ``format_version``
(:data:`FORMAT_VERSION`), ``algo``, ``group``, ``interface`` and ``weights_sha256`` (the hash of its
``model.safetensors``). :func:`check_identity` compares them with the directory's ``config.json`` and weights file
on load, so that one method's weights (or another run's) are never loaded under another's config. Checkpoints
written before the format was versioned (no ``format_version``) are checked on ``algo`` only.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from safetensors.torch import load_file

__all__ = [
    "FORMAT_VERSION",
    "CheckpointError",
    "check_identity",
    "identity",
    "read_config",
    "read_state",
    "read_tensors",
    "read_training_state",
    "sha256",
]

#: Version of the checkpoint layout written by this code (``state.json["format_version"]``).
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint file that is missing, corrupted, truncated or does not match its config."""


def identity(config) -> dict:
    """What a checkpoint of ``config`` (a :class:`~egcbf.config.TrainConfig`) is, as stored in ``state.json``."""
    return {
        "format_version": FORMAT_VERSION,
        "algo": config.algo,
        "group": config.group,
        "interface": config.model.interface,
    }


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_config(ckpt: Path):
    """The :class:`~egcbf.config.TrainConfig` of ``ckpt/config.json``."""
    from .config import TrainConfig

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


def check_identity(ckpt: Path, config, state: dict | None = None) -> None:
    """Raise :class:`CheckpointError` if ``ckpt/state.json`` says the weights are of another method, group,
    interface or a newer format than ``config`` (the directory's ``config.json``)."""
    state = read_state(ckpt) if state is None else state
    version = state.get("format_version", 0)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise CheckpointError(
            f"{Path(ckpt) / 'state.json'} has checkpoint format {version!r}; this egcbf reads up to "
            f"{FORMAT_VERSION} (upgrade egcbf)"
        )
    want = identity(config)
    keys = ("algo", "group", "interface") if version >= 1 else ("algo",)
    for key in keys:
        if key in state and state[key] != want[key]:
            raise CheckpointError(
                f"{ckpt}: state.json says the weights are {key} {state[key]!r} but config.json says "
                f"{want[key]!r}; the files come from different runs (copy the whole checkpoint directory)"
            )
    weights = Path(ckpt) / "model.safetensors"
    if "weights_sha256" in state and weights.exists() and sha256(weights) != state["weights_sha256"]:
        raise CheckpointError(
            f"{weights} is not the file its state.json was written with (SHA-256 differs): replaced by another "
            "run's weights, or corrupted; copy the whole checkpoint directory"
        )
