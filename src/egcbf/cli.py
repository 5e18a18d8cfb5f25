"""Command line: ``egcbf eval`` (evaluate a controller over swarm sizes), ``egcbf train`` (learn a graph CBF and
policy) and ``egcbf demo`` (the main job).

    egcbf eval --controller ccbf --num-agents 8,16,64 --area 4 --obstacles 0 --episodes 50 --seed 0 --out runs/ccbf
    egcbf train --algo egcbf+ --steps 300 --out runs/egcbf+          # CPU recipe; --preset paper --device cuda
    egcbf eval --checkpoint runs/egcbf+ --num-agents 8,16,64 --out runs/egcbf+/eval

Options with a fixed set of values take enums (:mod:`egcbf.cli_choices`): ``--help`` lists the values. A user
error (a bad flag value, an unusable file) ends a command with one ``Error: ...`` line naming the flag or file and
exit code 2 (:mod:`egcbf.cli_checks`); ``EGCBF_DEBUG=1`` shows the traceback instead. Every input is
checked before any work starts, and ``eval`` writes each swarm size's results as soon as it is finished.
"""

from __future__ import annotations

import json
import re
import shlex
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import torch
import typer
from typer.core import TyperGroup

from .allocator import keep_freed_memory
from .cli_checks import (
    _debug,
    check_env_flags,
    check_policy_memory,
    check_sweep_memory,
    check_training_memory,
    parse_device,
    parse_sizes,
    prepare_out,
    require,
    usage_error,
)
from .cli_choices import (
    Backend,
    Controller,
    DemoMethod,
    Dtype,
    LearnedMethod,
    Preset,
    RobotName,
    SafetyFilter,
    SceneName,
    choice_error,
)
from .cli_eval import EVAL_RESULTS, format_table, load_policy, run_eval, say_run_checkpoint
from .cli_study import study_cmd
from .threads import choose_threads

__all__ = ["app", "format_table", "main"]


class _OneLineErrors(TyperGroup):
    """The ``egcbf`` command group: a usage error that typer or click finds (a bad flag value, a value outside an
    option's choices, a missing argument, an unknown command or flag) ends the command with one ``Error:`` line
    naming the flag (exit code 2) instead of typer's boxed panel, whether it runs from :func:`main` or as ``app``
    (``typer.testing.CliRunner``); ``EGCBF_DEBUG=1`` re-raises."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except typer.Abort:
            typer.echo("Aborted!", err=True)
            sys.exit(1)
        except Exception as err:  # click's ClickException and UsageError (typer vendors click: duck-typed)
            if _debug() or not (hasattr(err, "format_message") and isinstance(getattr(err, "exit_code", None), int)):
                raise
            if type(err).__name__ == "NoArgsIsHelpError":
                err.show()
                sys.exit(0)
            typer.echo(f"Error: {_error_line(err)}", err=True)
            sys.exit(err.exit_code)
        sys.exit(code if isinstance(code, int) else 0)


def _error_line(err) -> str:
    """One line for a click usage error: the choices of an enum option spelled out (:func:`choice_error`), and a
    pointer to the command's ``--help``."""
    message = " ".join(err.format_message().split())
    param = getattr(err, "param", None)
    if param is not None and getattr(param, "opts", None):
        better = choice_error(param.opts[0], param.name or param.opts[0].lstrip("-"), message)
        message = better or message.replace("Value error, ", "")
    ctx = getattr(err, "ctx", None)
    return message + (f" (see `{ctx.command_path} --help`)" if ctx is not None else "")


app = typer.Typer(
    cls=_OneLineErrors,
    add_completion=False,
    no_args_is_help=True,
    help="Equivariant graph CBFs for quadrotor swarms. (EGCBF_DEBUG=1 shows the traceback of a usage error.)",
)


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"egcbf {__version__} (torch {torch.__version__})")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_print_version, is_eager=True, help="print the version and exit")
    ] = False,
) -> None:
    """Equivariant graph CBFs for quadrotor swarms. (EGCBF_DEBUG=1 shows the traceback of a usage error.)"""


#: the process's allocator setting (:mod:`egcbf.allocator`), set by :func:`main`; recorded in run.json
_ALLOCATOR = "default (the CLI's entry point did not run)"


_THREADS_HELP = (
    "torch CPU threads (default: automatic: OMP_NUM_THREADS if set, else the CPUs available minus the busy ones "
    "(sampled over 0.2 s), at least 1, so that another busy process does not oversubscribe the cores); "
    "printed on stderr and recorded in run.json"
)


def _threads(requested: int | None) -> tuple[int, str]:
    """``(threads, reason)`` from :func:`egcbf.threads.choose_threads`; a bad ``--threads`` is a usage error."""
    try:
        return choose_threads(requested)
    except ValueError as err:
        usage_error(str(err), err)


@contextmanager
def _torch_threads(threads: int, reason: str) -> Iterator[None]:
    """Run the body with ``threads`` torch threads, said on stderr; the previous count is restored afterwards."""
    typer.echo(f"threads: {threads} ({reason})", err=True)
    saved = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


@app.command("eval")
def eval_cmd(
    controller: Annotated[
        Controller | None, typer.Option(help="a hand-crafted controller (default: nominal); not with --checkpoint")
    ] = None,
    num_agents: Annotated[str, typer.Option("--num-agents", help="comma-separated swarm sizes")] = "8,16,64",
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="number of sphere obstacles")] = 0,
    episodes: Annotated[int, typer.Option(help="episodes per swarm size")] = 50,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    out: Annotated[Path, typer.Option(help="output directory (metrics.json, renders)")] = Path("out/eval"),
    render: Annotated[bool, typer.Option("--render/--no-render", help="write a GIF and a top-down PNG per N")] = False,
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    batch: Annotated[int | None, typer.Option(help="episodes simulated together (default: automatic)")] = None,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    dtype: Annotated[Dtype, typer.Option(help="floating-point type of the simulation and the policy")] = Dtype.float32,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    checkpoint: Annotated[
        Path | None,
        typer.Option(
            help="evaluate a trained policy: a checkpoint directory or a run directory (its best/, else its newest)"
        ),
    ] = None,
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="replace the results already in OUT (default: refuse to mix runs)")
    ] = False,
    robot: Annotated[
        RobotName | None,
        typer.Option(help="the robot of a --controller's swarm (default: quadrotor); a --checkpoint's is its own"),
    ] = None,
    filter: Annotated[
        SafetyFilter,
        typer.Option(
            help="run-time safety filter of the --checkpoint's commands (docs/safety_filters.md): none (the policy "
            "alone), dcbf (hand-crafted pairwise barriers: the recommended one), cbf (the learned per-edge "
            "barriers), prior (the untrained barrier); with --controller nominal, the nominal command's (dcbf, prior)"
        ),
    ] = SafetyFilter.none,
    filter_alpha: Annotated[
        float | None,
        typer.Option(help="class-K gain: alpha (1/s) of cbf and prior (default 1); gamma of dcbf's barrier (50)"),
    ] = None,
    filter_margin: Annotated[
        float | None,
        typer.Option(help="clearance (m): the barrier offset of cbf and prior (default 0); dcbf's margin (0.02)"),
    ] = None,
    scene: Annotated[
        SceneName,
        typer.Option(
            help="where starts and goals are drawn: uniform (the arena; the paper's) or crossing (starts in x < l/2, "
            "goals in x > l/2); never taken from the checkpoint"
        ),
    ] = SceneName.uniform,
    scene_yaw: Annotated[
        float,
        typer.Option(help="rotate every sampled scene by this many degrees about the arena's vertical centre axis"),
    ] = 0.0,
) -> None:
    """Evaluate a controller at several swarm sizes; print a table and write OUT/metrics.json (after each size)."""
    n_threads, reason = _threads(threads)
    with _torch_threads(n_threads, reason):
        run_eval(
            controller=None if controller is None else controller.value,
            num_agents=num_agents,
            area=area,
            obstacles=obstacles,
            episodes=episodes,
            seed=seed,
            out=out,
            render=render,
            max_steps=max_steps,
            batch=batch,
            device=device,
            dtype=dtype.value,
            progress=progress,
            checkpoint=checkpoint,
            threads_reason=reason,
            overwrite=overwrite,
            allocator=_ALLOCATOR,
            robot=None if robot is None else robot.value,
            filter=filter.value,
            filter_alpha=filter_alpha,
            filter_margin=filter_margin,
            scene=scene.value,
            scene_yaw=scene_yaw,
        )


def _demo_source(name: str, checkpoints: Path) -> Path | None:
    """The checkpoint directory of a learned method (``checkpoints/<name>``), or ``None`` for a hand-crafted
    controller name; a clear error naming the path and the training command if a learned method has none."""
    from .config import LEARNED_METHODS
    from .control.controllers import CONTROLLERS
    from .filter_names import FILTERS, split_method

    if name in CONTROLLERS:
        return None
    try:
        method = split_method(name)[0]
    except ValueError:
        method = None
    if method not in LEARNED_METHODS:
        usage_error(
            f"unknown method {name!r}: a learned method {sorted(LEARNED_METHODS)}, "
            f"one behind a run-time filter as METHOD:FILTER with FILTER in {list(FILTERS[1:])} (e.g. egcbf+:dcbf), "
            f"or a controller {sorted(CONTROLLERS)}"
        )
    name = method
    from .checkpoint import find_checkpoint

    path = checkpoints / name
    try:
        found = find_checkpoint(path, prefer_best=True)
    except FileNotFoundError as err:
        usage_error(
            f"--checkpoints: no {name} checkpoint at {path} (config.json + model.safetensors); train one with "
            f"`egcbf train --algo {name} --out runs/{name}` and pass --checkpoints with a folder holding {name}/",
            err,
        )
    say_run_checkpoint(path, found, "--checkpoints")
    return found


#: what a learned --method is compared with by default ("{method}": the method itself behind a run-time filter)
_DEMO_COMPARE = ("{method}:dcbf", "gcbf+", "nominal", "dcbf")


@app.command()
def demo(
    checkpoints: Annotated[
        Path, typer.Option(help="directory holding one checkpoint directory per learned method (egcbf+/, gcbf+/, ...)")
    ] = Path("checkpoints"),
    method: Annotated[
        DemoMethod, typer.Option(help="a learned method (its checkpoint in CHECKPOINTS) or a hand-crafted controller")
    ] = DemoMethod.egcbf_plus,
    compare: Annotated[
        str | None,
        typer.Option(
            "--compare",
            "--baseline",
            help="controllers run on the same episodes, comma list; METHOD:FILTER is a learned method behind a "
            "run-time filter (--filter of eval); 'none' to skip (default: METHOD:dcbf,gcbf+,nominal,dcbf; nominal "
            "for a hand-crafted --method)",
        ),
    ] = None,
    num_agents: Annotated[int, typer.Option("--num-agents")] = 128,
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="number of sphere obstacles")] = 8,
    episodes: Annotated[int, typer.Option()] = 4,
    seed: Annotated[int, typer.Option()] = 0,
    out: Annotated[Path, typer.Option(help="output directory")] = Path("out/demo"),
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP.replace("run.json", "demo.json"))] = None,
    render: Annotated[bool, typer.Option("--render/--no-render", help="the comparison GIF and a still")] = True,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="replace the results already in OUT (default: refuse to mix runs)")
    ] = False,
) -> None:
    """The main job: the learned EGCBF+ policy, alone and behind the dCBF run-time filter, beside GCBF+, the nominal
    controller and the hand-crafted dCBF-QP on the same episodes (128 agents, l = 4, 8 obstacles by default): one
    table, OUT/summary.md, a GIF of the first episode of every controller side by side (OUT/compare_N<n>.gif),
    OUT/<controller>/metrics.json and OUT/demo.json."""
    from .cli_demo import out_dir, run_demo
    from .filter_names import split_method

    method = method.value
    if compare is None:  # a hand-crafted --method alone is compared with the nominal controller only
        learned = _demo_source(method, checkpoints) is not None
        default = [c.format(method=method) for c in _DEMO_COMPARE] if learned else ["nominal"]
        names = [method, *(c for c in default if c != method)]
    else:
        extra = [c for c in compare.replace(" ", "").split(",") if c and c.lower() != "none"]
        names = list(dict.fromkeys([method, *extra]))
    sources = {name: _demo_source(name, checkpoints) for name in names}  # fail before any work
    n_threads, reason = _threads(threads)
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    require(num_agents >= 1, f"--num-agents must be >= 1, got {num_agents}")
    dev = parse_device(device)
    check_env_flags([num_agents], area, obstacles, max_steps)
    for name, ckpt in sources.items():  # every checkpoint loads and fits in memory, before the first method runs
        if ckpt is not None:
            _, _, train_cfg = load_policy(ckpt, dev, torch.float32, "--checkpoints")
            base = split_method(name)[0]
            require(  # the label comes from what the weights are, not from the folder's name
                train_cfg.algo == base,
                f"--checkpoints: {ckpt} holds {train_cfg.algo} weights (its model.safetensors says so), not {base}; "
                f"the folders of --checkpoints are named after their method (put {base}'s checkpoint there)",
            )
            require(
                train_cfg.robot == "quadrotor",
                f"--checkpoints: {ckpt} drives a {train_cfg.robot}; the demo compares quadrotor controllers (for "
                f"another robot: `egcbf eval --checkpoint {ckpt}`, or docs/gen_planar.py --gif for the unicycle)",
            )
            configs = check_env_flags([num_agents], area, obstacles, max_steps, train_cfg.env_overrides)
            check_policy_memory(configs, episodes, None, train_cfg.model.hidden, dev)
    prepare_out(out, overwrite, ("demo.json", "summary.md", f"compare_N{num_agents}.gif"))
    for name in names:
        prepare_out(out_dir(out, name), overwrite, EVAL_RESULTS)
    with _torch_threads(n_threads, reason):
        run_demo(
            sources,
            num_agents=num_agents,
            area=area,
            obstacles=obstacles,
            episodes=episodes,
            seed=seed,
            out=out,
            max_steps=max_steps,
            device=device,
            progress=progress,
            threads_reason=reason,
            allocator=_ALLOCATOR,
            render=render,
        )


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
    threads: Annotated[int | None, typer.Option(help="torch CPU threads (default: torch's)")] = None,
    tensorboard: Annotated[
        bool,
        typer.Option(
            "--tensorboard/--no-tensorboard", help="also log to TensorBoard in OUT/tb (the `tensorboard` extra)"
        ),
    ] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    robot: Annotated[
        RobotName | None, typer.Option(help="the robot (default: quadrotor; the unicycle has the presets cpu and tiny)")
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
    from .checkpoint import CheckpointError, checkpoint_step
    from .config import PRESETS, TrainConfig
    from .train import train as run_training

    algo = None if algo is None else algo.value
    preset = None if preset is None else preset.value
    robot = None if robot is None else robot.value
    require(steps is None or steps >= 1, f"--steps must be >= 1, got {steps}")
    require(threads is None or threads >= 1, f"--threads must be >= 1, got {threads}")
    if tensorboard:
        from .train import require_tensorboard

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
        if threads is not None:
            torch.set_num_threads(threads)
        require(out.is_dir(), f"--resume --out {out}: no such run directory (no checkpoint to continue from)")
        prepare_out(out, False, (), run_dir_ok=True)  # locked: one process continues a run
        try:
            run_training(TrainConfig(), out, resume=True, steps=steps, progress=progress, tensorboard=tensorboard)
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
    robot = robot or file_robot or "quadrotor"
    from .robots import ROBOTS

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


def _parse_methods(text: str, option: str) -> tuple[str, ...]:
    from .reproduce import METHODS

    names = tuple(s for s in text.replace(" ", "").split(",") if s)
    bad = [m for m in names if m not in METHODS]
    if bad:
        usage_error(
            f"{option}: unknown method(s) {bad}; choose from {', '.join(METHODS)} (METHOD:FILTER: a method behind a "
            "run-time filter)"
        )
    return names


#: the reproduction's default methods (``egcbf.reproduce.METHODS``; tests/egcbf/test_reproduce.py checks they agree)
_REPRO_METHODS = "gcbf,gcbf+,dcbf,ccbf,egcbf,egcbf+,nominal,egcbf+:dcbf,gcbf+:dcbf,egcbf+:cbf,egcbf+:prior,nominal:dcbf"
_REPRO_OBSTACLE_METHODS = "gcbf,gcbf+,egcbf,egcbf+,nominal,egcbf+:dcbf,gcbf+:dcbf,egcbf+:cbf,egcbf+:prior,nominal:dcbf"


def _parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.replace(" ", "").split(",") if s]
    except ValueError:
        usage_error(f"--train-seeds must be comma-separated integers >= 0, got {text!r} (e.g. --train-seeds 0,1,2)")
    if not seeds or any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        usage_error(f"--train-seeds needs distinct integers >= 0, got {text!r}")
    return seeds


@app.command()
def reproduce(
    methods: Annotated[
        str,
        typer.Option(
            help="comma list of gcbf,gcbf+,dcbf,ccbf,egcbf,egcbf+,nominal and the run-time filtered controllers "
            "METHOD:FILTER egcbf+:dcbf,gcbf+:dcbf,egcbf+:cbf,egcbf+:prior,nominal:dcbf (default: all)"
        ),
    ] = _REPRO_METHODS,
    num_agents: Annotated[str, typer.Option("--num-agents", help="comma-separated swarm sizes")] = (
        "8,16,64,128,256,512"
    ),
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="obstacles of the obstacle setting (0: none)")] = 8,
    obstacle_methods: Annotated[
        str, typer.Option("--obstacle-methods", help="methods also run with obstacles (comma list)")
    ] = _REPRO_OBSTACLE_METHODS,
    episodes: Annotated[int, typer.Option(help="episodes per cell (method, obstacles, N)")] = 50,
    baseline_episodes: Annotated[
        int | None,
        typer.Option(help="episodes per cell of the hand-crafted controllers (CBF-QPs, nominal; default: --episodes)"),
    ] = None,
    train_seeds: Annotated[
        str, typer.Option("--train-seeds", help="training seeds of the SEED-METHODS (comma list)")
    ] = "0,1,2",
    seed_methods: Annotated[
        str, typer.Option("--seed-methods", help="learned methods evaluated once per training seed")
    ] = "gcbf+,egcbf+",
    scale_sizes: Annotated[
        str,
        typer.Option("--scale-sizes", help="swarm sizes past Table I at the density of N=512, l scaled ('none': skip)"),
    ] = "1024,2048,4096",
    scale_methods: Annotated[
        str, typer.Option("--scale-methods", help="methods of the scalability study (comma list)")
    ] = _REPRO_METHODS,
    scale_agent_episodes: Annotated[
        int, typer.Option("--scale-agent-episodes", help="agent-episodes per scalability cell (episodes = this / N)")
    ] = 25_600,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's 256 steps)")] = None,
    checkpoints: Annotated[
        Path,
        typer.Option(
            help="learned checkpoints: CHECKPOINTS/<method>/ (training seed 0), CHECKPOINTS/seeds/<method>-s<k>/"
        ),
    ] = Path("checkpoints"),
    out: Annotated[Path, typer.Option(help="results directory (one JSON file per cell)")] = Path(
        "out/reproduction/cells"
    ),
    report: Annotated[Path, typer.Option(help="markdown report (figures go to its directory's figures/)")] = Path(
        "out/reproduction/reproduction.md"
    ),
    baselines: Annotated[
        Path | None, typer.Option(help="earlier `egcbf eval` outputs to import baseline cells from")
    ] = Path("docs/results/baselines"),
    workers: Annotated[int, typer.Option(help="cells evaluated in parallel (one torch thread each)")] = 2,
    backend: Annotated[
        Backend, typer.Option(help="local processes, or Ray (the optional `ray` extra, for several machines)")
    ] = Backend.process,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    report_only: Annotated[
        bool, typer.Option("--report-only", help="regenerate the report from the existing cells")
    ] = False,
    recompute: Annotated[
        bool, typer.Option("--recompute", help="replace stored cells made with other settings (else refused)")
    ] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """Reproduce the paper's Table I and a scalability study past it: evaluate every method at every N (without
    obstacles, and OBSTACLE-METHODS with OBSTACLES obstacles; SEED-METHODS once per training seed) and at the
    SCALE-SIZES at fixed density, resumably (finished cells are kept; stop and rerun the same command), and write
    REPORT."""
    from .checkpoint import read_config
    from .filter_names import split_method
    from .reproduce import (
        CellsFailed,
        SweepConfig,
        describe_mismatch,
        load_cells,
        mismatched_cells,
        sweep,
        unreadable_cells,
        validate,
        write_report,
    )
    from .reproduce.store import pending_cells

    try:
        sweep_cfg = dict(
            methods=_parse_methods(methods, "--methods"),
            num_agents=tuple(parse_sizes(num_agents)),
            area=area,
            obstacles=obstacles,
            obstacle_methods=_parse_methods(obstacle_methods, "--obstacle-methods"),
            episodes=episodes,
            baseline_episodes=baseline_episodes,
            train_seeds=tuple(_parse_seeds(train_seeds)),
            seed_methods=_parse_methods(seed_methods, "--seed-methods"),
            scale_sizes=()
            if scale_sizes.strip().lower() in ("", "none")
            else tuple(parse_sizes(scale_sizes, "--scale-sizes")),
            scale_methods=_parse_methods(scale_methods, "--scale-methods"),
            scale_agent_episodes=scale_agent_episodes,
            seed=seed,
            max_steps=max_steps,
            checkpoints=checkpoints,
            out=out,
            baselines=baselines,
            device=device,
            workers=workers,
            backend=backend.value,
        )
    except ValueError as err:
        usage_error(str(err), err)
    try:
        cfg = SweepConfig(**sweep_cfg)
    except ValueError as err:
        usage_error(_sweep_flags(str(err)), err)
    given = {  # method lists the user gave (not the defaults): every entry must be one --methods runs
        "--obstacle-methods": (obstacle_methods, _REPRO_OBSTACLE_METHODS, "obstacle_methods"),
        "--seed-methods": (seed_methods, "gcbf+,egcbf+", "seed_methods"),
        "--scale-methods": (scale_methods, _REPRO_METHODS, "scale_methods"),
    }
    run_bases = {split_method(m)[0] for m in sweep_cfg["methods"]}  # a filtered method runs its base's seeds
    for flag, (text, default, field) in given.items():
        runs_it = run_bases if field == "seed_methods" else set(sweep_cfg["methods"])
        extra = [m for m in sweep_cfg[field] if m not in runs_it]
        if text != default and extra:
            runs = ",".join(sweep_cfg["methods"])
            usage_error(f"{flag} names {', '.join(extra)}, which --methods does not run (--methods {runs}); add "
                        f"them to --methods or drop them from {flag}")  # fmt: skip
    try:
        if not report_only:
            parse_device(device)
            check_env_flags(cfg.num_agents, area, obstacles, max_steps)
            for n in cfg.scale_sizes:
                check_env_flags([n], cfg.scale_area(n), 0, max_steps)
            ckpts = validate(cfg)
            learned = [
                (c.num_agents, cfg.area_for(c), cfg.episodes_for(c))
                for c in pending_cells(cfg, ckpts)
                if c.train_seed is not None
            ]
            hidden = max((read_config(ck.path).model.hidden for ck in ckpts.values()), default=64)
            comm = check_env_flags([8], area, 0, None)[0].comm_radius
            check_sweep_memory(learned, cfg.workers, hidden, comm, parse_device(device))
    except (ValueError, FileNotFoundError, ImportError) as err:
        usage_error(str(err), err)
    if not report_only:
        prepare_out(out, True, ())  # writable (finished cells in it are reused; other settings are refused)
    prepare_out(report.parent, True, (), flag="--report", lock=False)
    if report_only:
        records = load_cells(cfg)
        unreadable = unreadable_cells(cfg)
        if unreadable:
            names = ", ".join(str(p) for p in unreadable[:5]) + (" ..." if len(unreadable) > 5 else "")
            typer.echo(f"Warning: {len(unreadable)} cell file(s) cannot be read (truncated or corrupted): {names}; "
                       "they show as pending (run the sweep to recompute them)", err=True)  # fmt: skip
        stale = mismatched_cells(cfg)
        if stale and not records:
            usage_error(describe_mismatch(cfg, stale) + "; pass the flags of the sweep that made them")
        if stale:
            typer.echo(f"Warning: {describe_mismatch(cfg, stale)}; they show as pending", err=True)
    else:
        try:
            records = sweep(
                cfg, command=shlex.join(["egcbf", *sys.argv[1:]]), progress=progress, log=typer.echo,
                recompute=recompute,
            )  # fmt: skip
        except CellsFailed as err:
            typer.echo(f"Error: {err}; the finished cells are kept, rerun the command to retry", err=True)
            write_report(cfg, load_cells(cfg), report)
            raise typer.Exit(1) from None
        except (ValueError, RuntimeError) as err:  # stored cells of other settings; another sweep holds the lock
            usage_error(str(err), err)
    path = write_report(cfg, records, report)
    typer.echo(f"{len(records)} of {len(cfg.cells())} cells; wrote {path}")


#: SweepConfig's fields set by the reproduce command's flags of the same name (``--num-agents`` for ``num_agents``)
_SWEEP_FIELDS = (
    "methods", "num_agents", "obstacle_methods", "baseline_episodes", "train_seeds", "seed_methods", "scale_sizes",
    "scale_methods", "scale_agent_episodes", "max_steps", "episodes", "obstacles", "workers", "area",
)  # fmt: skip


def _sweep_flags(message: str) -> str:
    """``message`` with SweepConfig's field names written as the flags that set them."""
    fields = "|".join(_SWEEP_FIELDS)
    return re.sub(rf"(?<![-\w])({fields})\b", lambda m: "--" + m.group(1).replace("_", "-"), message)


app.command("study")(study_cmd)


def main(argv: list[str] | None = None) -> None:
    """The ``egcbf`` command: keeps freed memory for reuse (:mod:`egcbf.allocator`) and runs :data:`app`, which
    prints a bad flag value or a missing argument as one ``Error:`` line naming the flag (exit code 2) instead of
    typer's boxed panel; ``EGCBF_DEBUG=1`` re-raises. ``argv``: the arguments (default: ``sys.argv[1:]``)."""
    global _ALLOCATOR
    _ALLOCATOR = keep_freed_memory()[1]
    app(args=argv, prog_name="egcbf")


if __name__ == "__main__":  # pragma: no cover
    main()
