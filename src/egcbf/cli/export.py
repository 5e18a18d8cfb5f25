"""``egcbf export``: one agent's learned controller as a self-contained TorchScript or ONNX file
(:mod:`egcbf.export`, docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import require, usage_error
from .choices import ExportFormat
from .root import app


def export_cmd(
    checkpoint: Annotated[Path, typer.Option(help="checkpoint directory (or a run directory: its best/)")],
    fmt: Annotated[ExportFormat, typer.Option("--format", help="file format")],
    out: Annotated[Path, typer.Option(help="the file to write (and OUT.json, its input/output layout)")],
    max_neighbours: Annotated[int, typer.Option(help="neighbour rows of the fixed-shape input")] = 64,
    max_hits: Annotated[
        int | None, typer.Option(help="LiDAR hit rows (default: the checkpoint's lidar_max_hits)")
    ] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace OUT if it exists")] = False,
) -> None:
    """Write one agent's controller (policy, group actions, nominal controller, attitude loop) with fixed-shape,
    masked inputs to OUT; the file is checked against PyTorch before it is kept. ONNX runs under onnxruntime alone."""
    from ..checkpoint import CheckpointError
    from ..deploy import AgentController
    from ..export import export_controller

    require(max_neighbours >= 1, f"--max-neighbours must be >= 1 (a controller that reads no neighbour would not "
            f"avoid them), got {max_neighbours}")  # fmt: skip
    require(max_hits is None or max_hits >= 0, f"--max-hits must be >= 0, got {max_hits}")
    require(not out.is_dir(), f"--out {out} is a directory; name the file to write")
    require(overwrite or not out.exists(), f"--out {out} exists; pass --overwrite to replace it")
    try:
        ctrl = AgentController.from_checkpoint(checkpoint, max_neighbours=max_neighbours, max_hits=max_hits)
    except (FileNotFoundError, CheckpointError, ValueError) as err:
        usage_error(f"--checkpoint {checkpoint}: {err}", err)
    if fmt.value == "onnx":
        try:
            import onnx  # noqa: F401
            import onnxruntime  # noqa: F401
        except ImportError as err:
            usage_error("--format onnx needs the onnx and onnxruntime packages: pip install -e '.[export]'", err)
    path = export_controller(ctrl, fmt.value, out, checkpoint)
    m = ctrl.module
    typer.echo(f"wrote {path} ({fmt.value}; {m.max_neighbours} neighbour rows, {m.max_hits} hit rows) and "
               f"{path.name}.json (its layout)")  # fmt: skip


app.command("export")(export_cmd)
