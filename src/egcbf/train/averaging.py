"""Weight averaging of two checkpoints of one model: ``lam`` of A plus ``1 - lam`` of B, every network (CBF, target
CBF, policy) averaged tensor by tensor.

This is how the shipped EGCBF+ and GCBF+ policies are made (checkpoints/README.md): A is the policy fine-tuned with
the per-edge QP target, B the policy it started from (trained with the paper's QP target). Averaging a fine-tuned
model with its start is weight-space ensembling (WiSE-FT, Wortsman et al. 2022); here it keeps most of the
fine-tuning's safety and most of the starting policy's speed in large swarms (docs/learning.md, "The fine-tuned
policy is slower at scale").

    egcbf average --a checkpoints/fine-tuned/egcbf+ --b checkpoints/paper-target/egcbf+ --lam 0.3 \\
        --out checkpoints/egcbf+

The written checkpoint has A's ``config.json`` (so its ``init_from`` still names where the fine-tuning started) and
records in ``state.json["weight_average"]`` both inputs, the SHA-256 of their weights and ``lam``, so it can be
rebuilt: the same tensors exactly (the file's SHA-256 may differ, as safetensors orders the header's metadata
freely).
"""

from __future__ import annotations

from pathlib import Path

import torch

from .checkpoint import (
    CheckpointError,
    check_identity,
    check_sizes,
    find_checkpoint,
    read_config,
    read_tensors,
    sha256,
    write_checkpoint_dir,
)

__all__ = ["average_checkpoints", "average_weights", "related"]


def average_weights(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], lam: float) -> dict[str, torch.Tensor]:
    """``lam * a + (1 - lam) * b`` for every tensor (same names, shapes and floating dtypes; else ``ValueError``),
    in each tensor's own dtype."""
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lam must be in [0, 1], got {lam}")
    if a.keys() != b.keys():
        diff = sorted(set(a) ^ set(b))
        raise ValueError(f"the two sets of weights have different tensors: {diff[:5]}")
    out = {}
    for name, ta in a.items():
        tb = b[name]
        if ta.shape != tb.shape or ta.dtype != tb.dtype or not ta.is_floating_point():
            raise ValueError(f"{name}: cannot average {ta.dtype}{tuple(ta.shape)} with {tb.dtype}{tuple(tb.shape)}")
        out[name] = lam * ta + (1.0 - lam) * tb
    return out


def related(ca: Path, cfg_a, cb: Path, cfg_b) -> bool:
    """Whether checkpoints ``ca`` and ``cb`` (configs ``cfg_a``, ``cfg_b``) share a training lineage, as their
    configs record it (``init_sha256``: the weights a run was warm-started from): one was fine-tuned from the other,
    or both from the same weights. Averaging is meant for such pairs (module doc); two independent runs sit in
    different basins, and their average is neither."""
    sha_a, sha_b = sha256(ca / "model.safetensors"), sha256(cb / "model.safetensors")
    start_a, start_b = cfg_a.init_sha256, cfg_b.init_sha256
    return start_a == sha_b or start_b == sha_a or (start_a is not None and start_a == start_b)


def average_checkpoints(
    a: str | Path, b: str | Path, lam: float, out: str | Path, allow_unrelated: bool = False
) -> Path:
    """Write the checkpoint directory ``out`` (``config.json``, ``model.safetensors``, ``state.json``, atomically)
    holding ``lam`` x the weights of checkpoint ``a`` + ``(1 - lam)`` x those of ``b``. ``a`` and ``b`` are checkpoint
    or run directories (a run's ``best/``) of the same method, group, interface and network shapes, and of one
    training lineage (:func:`related`; ``allow_unrelated`` lifts that); anything else raises
    :class:`~egcbf.train.checkpoint.CheckpointError` before anything is written, as does an ``out`` that exists but is
    not a checkpoint directory, or that is or holds one of the inputs. Returns ``out``."""
    from ..algo.learner import GraphCBFLearner

    if not 0.0 <= lam <= 1.0:
        raise CheckpointError(f"lam must be in [0, 1], got {lam}")
    ca, cb = find_checkpoint(a, prefer_best=True), find_checkpoint(b, prefer_best=True)
    cfg_a, cfg_b = read_config(ca), read_config(cb)
    check_identity(ca, cfg_a)
    check_identity(cb, cfg_b)
    if (cfg_a.algo, cfg_a.group, cfg_a.model) != (cfg_b.algo, cfg_b.group, cfg_b.model):
        raise CheckpointError(f"{ca} and {cb} are not the same model ({cfg_a.algo}/{cfg_a.group} and "
                              f"{cfg_b.algo}/{cfg_b.group}, or different network settings)")  # fmt: skip
    if not allow_unrelated and not related(ca, cfg_a, cb, cfg_b):
        raise CheckpointError(
            f"{ca} and {cb} are not one training lineage (neither was fine-tuned from the other, nor both from the "
            "same weights: their configs' init_sha256); averaging two independent runs gives neither policy "
            "(pass --allow-unrelated to average them anyway)"
        )
    wa = read_tensors(ca / "model.safetensors")
    check_sizes(ca, cfg_a, wa)
    try:
        mixed = average_weights(wa, read_tensors(cb / "model.safetensors"), lam)
    except ValueError as err:
        raise CheckpointError(f"{ca} and {cb}: {err}") from None
    out = Path(out)
    target = out.resolve()
    for src in (ca, cb):  # never replace an input, nor a directory holding one
        if src.resolve() == target or src.resolve().is_relative_to(target):
            raise CheckpointError(f"{out} is (or holds) one of the checkpoints being averaged: {src}")
    if out.exists() and not (out.is_dir() and (out / "model.safetensors").exists()):
        raise CheckpointError(f"{out} exists and is not a checkpoint directory: refusing to replace it")
    learner = GraphCBFLearner(cfg_a)
    learner.load_weights(mixed)
    source = {"a": str(ca), "a_sha256": sha256(ca / "model.safetensors"), "lam": lam}
    source |= {"b": str(cb), "b_sha256": sha256(cb / "model.safetensors")}
    state = {"step": 0, "wall_s": 0.0, "algo": cfg_a.algo, "weight_average": source, "metrics": None}
    return write_checkpoint_dir(learner, out, state)
