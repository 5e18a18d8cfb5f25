"""``egcbf export``: one agent's learned controller as a self-contained TorchScript or ONNX file
(:mod:`egcbf.deploy.export`, docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import check_output_file, require, usage_error
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
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace OUT and OUT.json if they exist")] = False,
) -> None:
    """Write one agent's controller (policy, group actions, nominal controller, attitude loop) with fixed-shape,
    masked inputs to OUT; the file is checked against PyTorch before it is kept. ONNX runs under onnxruntime alone."""
    from ..deploy.agent import AgentController
    from ..deploy.export import export_controller
    from ..train.checkpoint import CheckpointError

    require(max_neighbours >= 1, f"--max-neighbours must be >= 1 (a controller that reads no neighbour would not "
            f"avoid them), got {max_neighbours}")  # fmt: skip
    require(max_hits is None or max_hits >= 0, f"--max-hits must be >= 0, got {max_hits}")
    check_output_file(out, overwrite, companions=(".json",))
    try:
        ctrl = AgentController.from_checkpoint(checkpoint, max_neighbours=max_neighbours, max_hits=max_hits)
    except (FileNotFoundError, CheckpointError, ValueError) as err:
        usage_error(f"--checkpoint {checkpoint}: {err}", err)
    except MemoryError as err:
        usage_error(f"--checkpoint {checkpoint}: loading it ran out of memory; free memory or raise the limit "
                    "(ulimit -v, the cgroup's)", err)  # fmt: skip
    if fmt.value == "onnx":
        try:
            import onnx  # noqa: F401
            import onnxruntime  # noqa: F401
        except ImportError as err:
            usage_error("--format onnx needs the onnx and onnxruntime packages: pip install -e '.[export]'", err)
    try:
        path = export_controller(ctrl, fmt.value, out, checkpoint)
    except MemoryError as err:
        usage_error(f"--format {fmt.value}: exporting ran out of memory ({type(err).__name__}); free memory or raise "
                    "the limit (ulimit -v, the cgroup's), or export with fewer --max-neighbours / --max-hits; "
                    f"nothing was written to {out}", err)  # fmt: skip
    except RuntimeError as err:
        if "alloc" not in str(err).lower():
            raise
        first = str(err).splitlines()[0][:200]
        usage_error(f"--format {fmt.value}: exporting ran out of memory ({first}); free memory or raise the limit "
                    f"(ulimit -v, the cgroup's); nothing was written to {out}", err)  # fmt: skip
    m = ctrl.module
    typer.echo(f"wrote {path} ({fmt.value}; {m.max_neighbours} neighbour rows, {m.max_hits} hit rows) and "
               f"{path.name}.json (its layout)")  # fmt: skip


app.command("export")(export_cmd)
