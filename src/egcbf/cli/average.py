"""``egcbf average``: weight averaging of two checkpoints of one model (:mod:`egcbf.train.averaging`), how the shipped
EGCBF+ and GCBF+ policies are made from the fine-tuned ones and their starting points (checkpoints/README.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import require, usage_error
from .root import app


def average_cmd(
    a: Annotated[Path, typer.Option("--a", help="checkpoint A (or a run directory: its best/)")],
    b: Annotated[Path, typer.Option("--b", help="checkpoint B, the same model as A")],
    lam: Annotated[float, typer.Option(help="weight of A, in [0, 1]; B gets 1 - lam")],
    out: Annotated[Path, typer.Option(help="the checkpoint directory to write")],
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace OUT if it holds a checkpoint")] = False,
    allow_unrelated: Annotated[
        bool,
        typer.Option("--allow-unrelated", help="average two runs of no common training lineage (refused otherwise)"),
    ] = False,
) -> None:
    """Write OUT = lam x the weights of A + (1 - lam) x those of B (CBF, target CBF and policy), with A's config and
    both inputs recorded in OUT/state.json."""
    from ..train.averaging import average_checkpoints
    from ..train.checkpoint import CheckpointError

    require(0.0 <= lam <= 1.0, f"--lam must be in [0, 1], got {lam}")
    require(
        overwrite or not (out / "model.safetensors").exists(),
        f"--out {out} already holds a checkpoint; pass --overwrite to replace it",
    )
    try:
        path = average_checkpoints(a, b, lam, out, allow_unrelated=allow_unrelated)
    except (FileNotFoundError, CheckpointError) as err:
        usage_error(str(err), err)
    typer.echo(f"wrote {path} = {lam:g} x {a} + {1 - lam:g} x {b}")


app.command("average")(average_cmd)
