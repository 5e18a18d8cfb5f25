"""``egcbf train``: learn a graph CBF and policy (one learner for the four methods)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .checks import (
    check_training_memory,
    parse_device,
    prepare_out,
    require,
    usage_error,
)
from .choices import (
    ROBOT_METAVAR,
    LearnedMethod,
    Preset,
    robot_choice,
)
from .root import app


@app.command()
def train(
    algo: Annotated[
        LearnedMethod | None, typer.Option(help="the learned method (default: egcbf+; not with --resume)")
    ] = None,
    out: Annotated[Path, typer.Option(help="run directory (config, logs, metrics.csv, checkpoints)")] = Path(
        "out/train"
    ),
    config: Annotated[
        Path | None, typer.Option(help="JSON file of TrainConfig fields overriding the preset (may set 'preset')")
    ] = None,
    preset: Annotated[
        Preset | None, typer.Option(help="the recipe the --config fields override (default: cpu)")
    ] = None,
    steps: Annotated[
        int | None, typer.Option(help="total number of updates (default: the config's; with --resume: extend to)")
    ] = None,
    device: Annotated[str | None, typer.Option(help="cpu | cuda (default: the config's)")] = None,
    seed: Annotated[int | None, typer.Option(help="seed (default: the config's)")] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="continue the run in OUT from its newest loadable checkpoint")
    ] = False,
    threads: Annotated[
        int | None, typer.Option(help="torch CPU threads (default: the preset's, 1 for the CPU presets)")
    ] = None,
    tensorboard: Annotated[
        bool,
        typer.Option(
            "--tensorboard/--no-tensorboard", help="also log to TensorBoard in OUT/tb (the `tensorboard` extra)"
        ),
    ] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    robot: Annotated[
        str | None,
        typer.Option(
            metavar=ROBOT_METAVAR,
            callback=robot_choice,
            help="the robot (default: quadrotor; the unicycle has the presets cpu and tiny)",
        ),
    ] = None,
    init_from: Annotated[
        Path | None,
        typer.Option(
            help="warm start: the networks' weights from this checkpoint (or run: its best/), fresh optimizers; "
            "the model config must match (fine-tuning)"
        ),
    ] = None,
) -> None:
    """Train GCBF, GCBF+, EGCBF or EGCBF+ (one learner; the group and the reference controller differ)."""
    from ..algo.config import PRESETS, TrainConfig
    from ..train.checkpoint import CheckpointError, checkpoint_step
    from ..train.loop import train as run_training

    algo = None if algo is None else algo.value
    preset = None if preset is None else preset.value
    require(steps is None or steps >= 1, f"--steps must be >= 1, got {steps}")
    require(threads is None or threads >= 1, f"--threads must be >= 1, got {threads}")
    if tensorboard:
        from ..train.loop import require_tensorboard

        try:
            require_tensorboard()
        except ImportError as err:
            usage_error(f"--tensorboard: {err}", err)
    if out.exists() and not out.is_dir():
        usage_error(f"--out {out} is a file, not a run directory; choose another --out")
    if resume:
        if algo is not None:
            usage_error("--algo cannot change a resumed run (its method is in OUT/config.json); drop --algo")
        if (config is not None or preset is not None or seed is not None or device is not None or robot is not None
                or init_from is not None):  # fmt: skip
            usage_error("--resume continues the saved config: only --steps, --threads and --tensorboard may change")
        current = checkpoint_step(out)
        if steps is not None and current is not None and steps < current:
            usage_error(f"--steps {steps} is below the run's current update {current}; pass --steps >= {current}")
        require(out.is_dir(), f"--resume --out {out}: no such run directory (no checkpoint to continue from)")
        prepare_out(out, False, (), run_dir_ok=True)  # locked: one process continues a run
        try:
            run_training(TrainConfig(), out, resume=True, steps=steps, progress=progress, tensorboard=tensorboard,
                         num_threads=threads)  # fmt: skip
        except (FileNotFoundError, CheckpointError) as err:
            usage_error(f"--resume --out {out}: {err}", err)
        return
    algo = algo or "egcbf+"
    fields = {}
    if config is not None:
        try:
            fields = json.loads(config.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            usage_error(f"--config {config}: {err}", err)
        require(isinstance(fields, dict), f"--config {config} must hold a JSON object of TrainConfig fields")
        file_algo = fields.pop("algo", algo)
        require(file_algo == algo, f"--config {config} says algo {file_algo!r} but --algo is {algo!r}")
        fields.pop("reference", None)
    name = preset or fields.pop("preset", "cpu")
    fields.pop("preset", None)
    file_robot = fields.pop("robot", None) or (fields.get("model") or {}).get("robot")
    require(
        robot is None or file_robot is None or file_robot == robot,
        f"--config {config} says robot {file_robot!r} but --robot is {robot!r}",
    )
    from ..robots import DEFAULT_ROBOT, ROBOTS

    robot = robot or file_robot or DEFAULT_ROBOT

    require(robot in ROBOTS, f"--robot must be one of {sorted(ROBOTS)}, got {robot!r}")
    require(name in PRESETS, f"--preset must be one of {PRESETS}, got {name!r}")
    if init_from is not None:
        fields["init_from"], fields["init_sha256"] = str(init_from), None
    for key, value in (("steps", steps), ("device", device), ("seed", seed), ("num_threads", threads)):
        if value is not None:
            fields[key] = value
    try:
        cfg = TrainConfig.preset(algo, name, robot=robot, **fields)
    except (TypeError, ValueError) as err:
        usage_error(f"{'--config ' + str(config) + ': ' if config is not None else ''}{err}", err)
    check_training_memory(cfg, parse_device(cfg.device))
    prepare_out(out, False, (), run_dir_ok=True)
    try:
        run_training(cfg, out, progress=progress, tensorboard=tensorboard)
    except FileExistsError as err:
        usage_error(f"--out {out}: {err}", err)
    except (FileNotFoundError, CheckpointError) as err:
        if cfg.init_from is None:
            raise
        usage_error(f"--init-from {cfg.init_from}: {err}", err)
