"""``egcbf export``: one agent's learned controller as a self-contained TorchScript or ONNX file
(:mod:`egcbf.deploy.export`), or with ``--controller METHOD:dcbf`` the policy behind the ``dcbf`` filter as a
directory that numpy and onnxruntime run alone (:mod:`egcbf.deploy.controller_export`); docs/deploy.md."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import check_output_file, require, usage_error
from .choices import ExportFormat
from .root import app


def export_cmd(
    checkpoint: Annotated[Path, typer.Option(help="checkpoint directory (or a run directory: its best/)")],
    out: Annotated[
        Path,
        typer.Option(
            help="the file to write (and OUT.json, its input/output layout); with --controller, the directory"
        ),
    ],
    fmt: Annotated[ExportFormat | None, typer.Option("--format", help="file format of the policy alone")] = None,
    controller: Annotated[
        str | None,
        typer.Option(
            help="METHOD:dcbf (METHOD: the checkpoint's, or 'policy'): the policy behind the dcbf filter, as a "
            "directory (policy.onnx, controller.json, egcbf_runtime.py); not with --format"
        ),
    ] = None,
    max_neighbours: Annotated[int, typer.Option(help="neighbour rows of the fixed-shape input")] = 64,
    max_hits: Annotated[
        int | None, typer.Option(help="LiDAR hit rows (default: the checkpoint's lidar_max_hits)")
    ] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace OUT and OUT.json if they exist")] = False,
) -> None:
    """Write one agent's controller (policy, group actions, nominal controller, attitude loop) with fixed-shape,
    masked inputs to OUT; the file is checked against PyTorch before it is kept. ONNX runs under onnxruntime alone.
    With --controller METHOD:dcbf, OUT is a directory holding the policy behind the dcbf filter (numpy runtime)."""
    from ..deploy.agent import AgentController
    from ..deploy.export import export_controller
    from ..train.checkpoint import CheckpointError

    require(max_neighbours >= 1, f"--max-neighbours must be >= 1 (a controller that reads no neighbour would not "
            f"avoid them), got {max_neighbours}")  # fmt: skip
    require(max_hits is None or max_hits >= 0, f"--max-hits must be >= 0, got {max_hits}")
    require((fmt is None) != (controller is None), "pass one of --format (the policy alone, one file) and "
            "--controller METHOD:dcbf (the filtered controller, a directory)")  # fmt: skip
    if controller is not None:
        return _export_filtered(controller, checkpoint, out, max_neighbours, max_hits, overwrite)
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


def _export_filtered(name: str, checkpoint: Path, out: Path, max_neighbours: int, max_hits: int | None,
                     overwrite: bool) -> None:  # fmt: skip
    """``--controller METHOD:dcbf``: the directory of
    :func:`egcbf.deploy.controller_export.export_filtered_controller`."""
    from ..control.names import split_method
    from ..control.resolve import POLICY
    from ..deploy.agent import AgentFilteredController
    from ..deploy.controller_export import CONTROLLER_FILES, export_filtered_controller
    from ..train.checkpoint import CheckpointError, read_checkpoint
    from .checks import holding_checkpoint

    try:
        method, kind = split_method(name)
    except ValueError as err:
        usage_error(f"--controller {name}: {err}", err)
    require(kind == "dcbf", f"--controller {name}: the exported controller is a policy behind the dcbf filter "
            f"(METHOD:dcbf), not {kind!r}")  # fmt: skip
    require(not out.is_file(), f"--out {out} is a file; with --controller, name the directory to write")
    home = holding_checkpoint(out)
    require(home is None, f"--out {out} is inside the checkpoint or training run {home}; write it elsewhere")
    existing = [f for f in CONTROLLER_FILES if (out / f).exists()]
    require(overwrite or not existing, f"--out {out}: {', '.join(existing)} exist(s); pass --overwrite to replace")
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError as err:
        usage_error("--controller needs the onnx and onnxruntime packages: pip install -e '.[export]'", err)
    try:
        algo = read_checkpoint(checkpoint).config.algo
    except (FileNotFoundError, CheckpointError, ValueError) as err:
        usage_error(f"--checkpoint {checkpoint}: {err}", err)
    require(method in (POLICY, algo), f"--controller {name}: {checkpoint} holds a {algo} policy, not {method}")
    try:
        ctrl = AgentFilteredController.from_checkpoint(checkpoint, max_neighbours=max_neighbours, max_hits=max_hits)
        path = export_filtered_controller(ctrl, out, checkpoint, f"{algo}:{kind}")
    except (FileNotFoundError, CheckpointError, ValueError) as err:
        usage_error(f"--checkpoint {checkpoint}: {err}", err)
    except MemoryError as err:
        usage_error(f"--controller {name}: exporting ran out of memory; free memory or raise the limit (ulimit -v, "
                    f"the cgroup's); nothing was written to {out}", err)  # fmt: skip
    m = ctrl.controller.module
    typer.echo(f"wrote {path}/ ({', '.join(CONTROLLER_FILES)}; {m.max_neighbours} neighbour rows, {m.max_hits} hit "
               "rows): run it with egcbf_runtime.Controller.load (numpy and onnxruntime)")  # fmt: skip


app.command("export")(export_cmd)
