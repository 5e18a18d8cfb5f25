"""The body of ``egcbf eval`` (also run once per method by ``egcbf demo``): check every input, then evaluate,
writing each finished swarm size at once (atomically), and print the table."""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Annotated

import torch
import typer

from ..io.atomic import WriteError, write_json_atomic, writing
from ..io.report import machine_info, number, pct
from .checks import (
    check_env_flags,
    check_policy_memory,
    parse_device,
    parse_sizes,
    prepare_out,
    require,
    usage_error,
)
from .choices import (
    ROBOT_METAVAR,
    Controller,
    Dtype,
    SafetyFilter,
    SceneName,
    robot_choice,
)
from .root import _THREADS_HELP, _threads, _torch_threads, allocator_setting, app

__all__ = [
    "DTYPES",
    "EVAL_RESULTS",
    "build_controller",
    "format_table",
    "render_records",
    "run_eval",
    "say_run_checkpoint",
]

DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: the files an evaluation writes into --out (a new run refuses a folder holding any of them without --overwrite)
EVAL_RESULTS = ("metrics.json", "run.json", "*_N*.gif", "*_N*_topdown.png")
#: run.json fields that may differ between a run and its --resume (the rest must be equal)
_RESUME_FREE = ("command", "finished", "complete", "wall_s", "threads", "threads_reason", "allocator", "machine")


def format_table(rows: list[dict], title: str = "") -> str:
    """A fixed-width table of metric rows (rates in % and costs as :func:`egcbf.io.report.pct` and
    :func:`egcbf.io.report.number` print them)."""
    head = f"{'N':>5} {'Safe%':>7} {'Reach%':>7} {'Succ%':>7} {'Cost (min/max)':>20} {'Reward':>10} {'step ms':>8}"
    has_qp = any("qp_ms_median" in r for r in rows)
    if has_qp:
        head += f" {'QP ms':>7} {'slack':>6}"
    has_filter = any("filter_active" in r for r in rows)
    if has_filter:
        head += f" {'failed':>6} {'filtered%':>9}"
    lines = [title, head, "-" * len(head)] if title else [head, "-" * len(head)]
    for r in rows:
        cost = f"{number(r['cost'])} ({number(r['cost_min'], 2)}/{number(r['cost_max'], 2)})"
        line = (
            f"{r['num_agents']:>5} {pct(r['safe_rate']):>7} {pct(r['reach_rate']):>7} "
            f"{pct(r['success_rate']):>7} {cost:>20} {r['reward']:>10.2f} {r['step_ms_median']:>8.2f}"
        )
        if has_qp:
            line += f" {r.get('qp_ms_median', float('nan')):>7.2f} {r.get('qp_slack_steps', 0):>6}"
        if has_filter:  # agent-steps whose QP fell back to braking, and the share the filter changed
            line += f" {r.get('qp_failed', 0):>6} {pct(r.get('filter_active', 0.0)):>9}"
        lines.append(line)
    return "\n".join(lines)


def render_records(records: dict, out: Path, area: float, tag: str) -> list[Path]:
    """A GIF and a top-down PNG per recorded swarm size ``{N: EpisodeRecord}``; returns the paths written. A full disk
    or the file-size limit raises :class:`egcbf.io.atomic.WriteError` naming the image (no partial image is left)."""
    from ..viz.render import render_gif, render_topdown

    paths = []
    for n, rec in records.items():
        traj = torch.stack(rec.positions)
        coll = torch.stack(rec.collided)
        args = (traj, rec.goals, rec.centers, rec.radii, coll)
        for render, name in ((render_gif, f"{tag}_N{n}.gif"), (render_topdown, f"{tag}_N{n}_topdown.png")):
            final = out / name
            tmp = final.with_name(f".{final.stem}.partial{final.suffix}")  # a kill never leaves a half image
            try:
                with writing(final, f"the metrics of N = {n} are kept"):
                    render(tmp, *args, boxes=rec.boxes, area_size=area, title=f"{tag} N={n}")
                    os.replace(tmp, final)
            finally:
                tmp.unlink(missing_ok=True)
            paths.append(final)
    return paths


def build_controller(name: str, checkpoint: Path | None, flag: str = "--checkpoint", **kwargs):
    """:func:`egcbf.control.resolve.resolve` of ``name`` (and ``checkpoint``), or a usage error naming ``flag``
    and saying why; which checkpoint of a run directory is used is said on stderr."""
    from ..control.resolve import ControllerError, resolve
    from ..train.checkpoint import CheckpointError

    try:
        built = resolve(name, checkpoint, **kwargs)
    except (FileNotFoundError, CheckpointError, ControllerError) as err:
        where = f"{flag} {checkpoint}" if checkpoint is not None else f"--controller {name}"
        usage_error(f"{where}: {err}", err)
    if checkpoint is not None:
        say_run_checkpoint(checkpoint, built.checkpoint, flag)
    return built


def say_run_checkpoint(given: Path, found: Path, flag: str) -> None:
    """On stderr, which checkpoint of the run directory ``given`` is used (nothing if ``given`` is one)."""
    if Path(found).resolve() != Path(given).resolve():
        why = "its best/ (selected on validation episodes)" if Path(found).name == "best" else "its newest checkpoint"
        typer.echo(f"{flag} {given}: a run directory; evaluating {why}, {found}", err=True)


def run_eval(
    controller: str | None,
    num_agents: str,
    area: float,
    obstacles: int,
    episodes: int,
    seed: int,
    out: Path,
    render: bool,
    max_steps: int | None,
    batch: int | None,
    device: str,
    dtype: str,
    progress: bool,
    checkpoint: Path | None,
    threads_reason: str,
    overwrite: bool = False,
    allocator: str = "default (the CLI's entry point did not run)",
    record: bool = False,
    robot: str | None = None,
    filter: str = "none",
    filter_alpha: float | None = None,
    filter_margin: float | None = None,
    scene: str = "uniform",
    scene_yaw: float = 0.0,
    max_travel: float | None = None,
    faults: str = "none",
    resume: bool = False,
    obstacle_sensing: str = "map",
    lidar_hits: str = "plane",
    record_to: Path | None = None,
    low_level: str = "attitude",
    record_cbf: bool = False,
    filter_qp_solver: str | None = None,
) -> dict:
    """The body of ``egcbf eval`` (and of each run of ``egcbf demo``), with torch's threads already set.

    Every input is checked first (flags, all swarm sizes, the checkpoint, ``out``); then each finished swarm size
    is written at once (``metrics.json`` with the rows so far, its renders, ``run.json``), atomically. Returns the
    first episode of each swarm size ``{N: EpisodeRecord}`` if ``render`` or ``record``, else ``{}``. ``robot``: the
    robot of a hand-crafted controller's swarm (a checkpoint's robot is its own; a different ``robot`` is an error).
    ``resume``: continue the interrupted run in ``out`` (same settings, checked against its ``run.json``): the swarm
    sizes it finished are kept, the others evaluated. ``record_to``: write the first episode of the first swarm size
    evaluated to this ``.mcap`` file (:class:`egcbf.ros.record.EpisodeRecorder`; needs the ``ros`` extra);
    ``record_cbf``: with it, the checkpoint's learned CBF value ``h`` too (one CBF forward per recorded step).
    ``filter_qp_solver``: the ``cbf`` and ``prior`` filters' QP solver (``FilterConfig.qp_solver``; ``None``: their
    default).
    ``low_level``: ``"attitude"`` (our attitude loop applies the controller's control) or ``"setpoint"`` (its
    acceleration command flown through the firmware-like setpoint tracker; :mod:`egcbf.evaluate.episodes`).
    """
    from ..control.controllers import CONTROLLERS
    from ..control.filters import FILTER_CLASSES, FILTERS, FilterConfig
    from ..control.names import join_method, split_method
    from ..control.resolve import POLICY
    from ..evaluate.episodes import LOW_LEVELS, evaluate, fault_support_error
    from ..robots import DEFAULT_ROBOT, ROBOTS

    require(dtype in DTYPES, f"--dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
    if record_to is not None:
        require(Path(record_to).suffix == ".mcap", f"--record writes an MCAP file: FILE must end with .mcap, got "
                f"{record_to}")  # fmt: skip
        from ..ros.messages import MissingExtraError, require_extra

        try:
            require_extra("--record")
        except MissingExtraError as err:
            usage_error(str(err), err)
    require(not record_cbf or record_to is not None, "--record-cbf adds the CBF's values to a recording: pass "
            "--record FILE.mcap too")  # fmt: skip
    require(not record_cbf or checkpoint is not None, "--record-cbf records a learned CBF's values: it needs a "
            "--checkpoint (the hand-crafted controllers have none)")  # fmt: skip
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    require(batch is None or batch >= 1, f"--batch must be >= 1 (episodes simulated together), got {batch}")
    require(filter in FILTERS, f"--filter must be one of {list(FILTERS)}, got {filter!r}")
    require(low_level in LOW_LEVELS, f"--low-level must be one of {list(LOW_LEVELS)}, got {low_level!r}")
    require(
        filter == "none" or checkpoint is not None or (controller == "nominal" and filter != "cbf"),
        f"--filter {filter} filters a learned policy's commands (its --checkpoint) or, as an ablation, the nominal "
        "controller's (--controller nominal; not with cbf, which reads a checkpoint's CBF)",
    )
    filter_config = None
    require(filter != "none" or (filter_alpha is None and filter_margin is None),
            "--filter-alpha and --filter-margin set a run-time filter's barrier: pass --filter KIND too")  # fmt: skip
    choices = () if filter == "none" else FILTER_CLASSES[filter].qp_solvers
    require(filter_qp_solver is None or filter_qp_solver in choices,
            f"--filter-qp-solver chooses a filter's QP solver: --filter {filter} offers "
            f"{list(choices) if choices else 'no choice'}, got {filter_qp_solver!r}")  # fmt: skip
    from ..robots.quadrotor.cbf_qp import LIDAR_HITS, OBSTACLE_SENSING

    require(obstacle_sensing in OBSTACLE_SENSING,
            f"--obstacle-sensing must be one of {list(OBSTACLE_SENSING)}, got {obstacle_sensing!r}")  # fmt: skip
    require(lidar_hits in LIDAR_HITS, f"--lidar-hits must be one of {list(LIDAR_HITS)}, got {lidar_hits!r}")
    require(lidar_hits == "plane" or obstacle_sensing == "lidar",
            f"--lidar-hits {lidar_hits} reads LiDAR hits: pass --obstacle-sensing lidar too")  # fmt: skip
    if filter != "none":
        try:
            filter_config = FilterConfig.for_kind(filter, filter_alpha, filter_margin, obstacle_sensing, lidar_hits,
                                                  filter_qp_solver)  # fmt: skip
        except ValueError as err:
            usage_error(str(err).replace("FilterConfig.alpha", "--filter-alpha").replace("FilterConfig.margin",
                        "--filter-margin").replace("FilterConfig.qp_solver", "--filter-qp-solver"), err)  # fmt: skip
    from ..faults import parse_faults

    try:
        fault_config = parse_faults(faults)
    except ValueError as err:
        usage_error(f"--faults: {err}", err)
    sizes = parse_sizes(num_agents)
    from ..faults import given_fields
    from ..faults.process import noncooperative_count

    noncoop_agents = {}
    for n in sizes if fault_config.noncoop > 0 else ():  # a fraction of non-cooperative agents, in agents
        try:
            noncoop_agents[n] = noncooperative_count(fault_config, n)
        except ValueError as err:
            usage_error(f"--faults {faults} at --num-agents {n}: {str(err).removeprefix('faults: ')}", err)
        if noncoop_agents[n] == 0:
            why = (f"noncoop={fault_config.noncoop:g} of {n} agents rounds to no non-cooperative agent (noncoop >= "
                   f"{0.5 / n:g} makes one)")  # fmt: skip
            require("noncoop" not in given_fields(faults), f"--faults {faults} at --num-agents {n}: {why}")
            typer.echo(f"--faults {faults}: at N = {n} {why}; that size runs without them", err=True)
    dev = parse_device(device)
    env_overrides = None
    if checkpoint is not None:  # a learned policy: everything it needs is in the checkpoint directory
        if controller is not None:
            usage_error("--controller and --checkpoint exclude each other (the checkpoint's policy is the controller)")
        built = build_controller(join_method(POLICY, filter), checkpoint, filter_config=filter_config, device=dev,
                                 dtype=DTYPES[dtype], with_cbf=record_cbf)  # fmt: skip
        require(
            robot in (None, built.robot),
            f"--robot {robot} but the checkpoint's policy drives a {built.robot}; drop --robot",
        )
        controller, robot, env_overrides = built.name, built.robot, built.env_overrides
    else:
        controller = controller or "nominal"
        require(controller in CONTROLLERS, f"--controller must be one of {sorted(CONTROLLERS)}, got {controller!r}")
    robot = robot or DEFAULT_ROBOT
    require(robot in ROBOTS, f"--robot must be one of {sorted(ROBOTS)}, got {robot!r}")
    robot_cls = ROBOTS[robot]
    from ..faults.process import for_robot

    try:  # the default field conditions mean something for every robot: what it cannot take is left out, and said
        fault_config, left_out = for_robot(fault_config, robot_cls(), given_fields(faults))
    except ValueError as err:
        usage_error(f"--faults {faults}: {str(err).removeprefix('faults: ')}", err)
    if left_out:
        typer.echo(
            f"--faults {faults} on the {robot}: left out " + "; ".join(f"{n} ({w})" for n, w in left_out.items()),
            err=True,
        )
    qp_options = {}
    base = split_method(controller)[0]
    if obstacle_sensing == "lidar":  # what reads the obstacle map must read the LiDAR instead
        require(robot_cls.lidar_obstacle_rows,
                f"--obstacle-sensing lidar: the {robot}'s controllers read the obstacle map")  # fmt: skip
        require(base != "ccbf", "--obstacle-sensing lidar: the centralized CBF-QP reads the obstacle map; use "
                "--controller dcbf (each agent's own LiDAR hits)")  # fmt: skip
        if base == "dcbf" and filter_config is None:
            qp_options.update(obstacle_sensing="lidar", lidar_hits=lidar_hits)
    require(filter_config is None or robot_cls.run_time_filters,
            f"--filter {filter}: the run-time filters are not written for the {robot}")  # fmt: skip
    if checkpoint is None:  # a hand-crafted controller, or the nominal command behind a filter
        built = build_controller(join_method(controller, filter), None, robot=robot, filter_config=filter_config,
                                 **qp_options)  # fmt: skip
        controller = built.name
    if fault_config.edge_faults:  # message and LiDAR faults: ask the controller which ones it perceives
        why = fault_support_error(built.controller, fault_config, name=controller)
        require(why is None, f"--faults {fault_config.spec()}: {why}")
    require(math.isfinite(scene_yaw), f"--scene-yaw must be a finite number of degrees, got {scene_yaw}")
    if scene != "uniform" or scene_yaw != 0:  # else the environment's defaults, as every earlier run recorded them
        env_overrides = {**(env_overrides or {}), "scene": scene, "scene_yaw": float(scene_yaw)}
    require(max_travel is None or (math.isfinite(max_travel) and max_travel > 0),
            f"--max-travel must be a number > 0 (m), got {max_travel}")  # fmt: skip
    require(max_travel is None or scene == "uniform", "--max-travel needs --scene uniform")
    if max_travel is not None:
        env_overrides = {**(env_overrides or {}), "max_travel": float(max_travel)}
    configs = check_env_flags(sizes, area, obstacles, max_steps, env_overrides, robot)
    setpoint_meta = _setpoint_meta(low_level, robot, built, fault_config, configs[0].dt)
    if checkpoint is not None and hasattr(built.train_config, "model"):  # a graph policy (not a MARL actor)
        check_policy_memory(configs, episodes, batch, built.train_config.model.hidden, dev)
    require(not (resume and overwrite), "--resume continues OUT's run and --overwrite would delete it: pass one")
    previous = _previous_run(out) if resume else None
    prepare_out(out, overwrite, () if resume else EVAL_RESULTS)
    t0 = time.time()
    meta = {
        "command": " ".join(["egcbf", *sys.argv[1:]]),
        "controller": controller,
        "robot": robot,
        "checkpoint": None if built.checkpoint is None else str(built.checkpoint),
        **({} if built.checkpoint is None else {"weights_sha256": built.weights_sha256}),
        "filter": filter,
        "filter_config": None if filter_config is None else filter_config.settings(),
        "num_agents": sizes,
        "finished": [],
        "complete": False,
        "area": area,
        "obstacles": obstacles,
        **({"scene": scene, "scene_yaw": float(scene_yaw)} if scene != "uniform" or scene_yaw != 0 else {}),
        **({"max_travel": float(max_travel)} if max_travel is not None else {}),
        **({"faults": fault_config.to_dict()} if not fault_config.is_null else {}),
        **({"faults_left_out": sorted(left_out)} if left_out else {}),
        **({"noncoop_agents": {str(n): k for n, k in noncoop_agents.items()}} if noncoop_agents else {}),
        **({"obstacle_sensing": obstacle_sensing, "lidar_hits": lidar_hits} if obstacle_sensing != "map" else {}),
        **setpoint_meta,
        "episodes": episodes,
        "seed": seed,
        "max_steps": max_steps,
        "batch": batch,
        "dtype": dtype,
        "device": str(dev),
        "wall_s": 0.0,
        "threads": torch.get_num_threads(),
        "threads_reason": threads_reason,
        "allocator": allocator,
        "machine": machine_info(),
    }
    done_rows: list[dict] = []
    if previous is not None:
        done_rows = _resumable(previous, meta, out)
        meta["finished"] = [r["num_agents"] for r in done_rows]
        sizes = [n for n in sizes if n not in meta["finished"]]
        typer.echo(f"resuming {out}: {len(done_rows)} swarm size(s) kept, {len(sizes)} to evaluate", err=True)
    write_json_atomic(out / "run.json", meta)
    written: list[Path] = []
    recorder = None
    if record_to is not None:
        from ..ros.record import EpisodeRecorder

        cbf = built.cbf if record_cbf else None
        recorder = EpisodeRecorder(record_to, cbf=cbf, metadata={"command": meta["command"], "controller": controller})
    recorded: dict = {}

    def save_size(rows: list[dict], episode) -> None:  # a later failure never loses a finished size
        rows = [*done_rows, *rows]
        write_json_atomic(out / "metrics.json", rows)
        if episode is not None:
            recorded[rows[-1]["num_agents"]] = episode
            if render:  # after metrics.json: an image that cannot be written is said, and the metrics stay
                try:
                    written.extend(render_records({rows[-1]["num_agents"]: episode}, out, area, controller))
                except WriteError as err:
                    typer.echo(f"Warning: {err}", err=True)
        meta.update(finished=[r["num_agents"] for r in rows], wall_s=round(time.time() - t0, 1))
        write_json_atomic(out / "run.json", meta)

    try:
        rows, _ = (
            ([], None)
            if not sizes
            else evaluate(
                (lambda cfg: built.controller)
                if checkpoint is not None or filter_config is not None
                else (lambda cfg: build_controller(controller, None, robot=robot, **qp_options).controller),
                sizes,
                area_size=area,
                num_obstacles=obstacles,
                episodes=episodes,
                seed=seed,
                batch=batch,
                max_steps=max_steps,
                device=dev,
                dtype=DTYPES[dtype],
                record=render or record,
                show_progress=progress,
                env_overrides=env_overrides,
                on_size=save_size,
                robot=robot,
                faults=fault_config,
                on_step=recorder,
                low_level=low_level,
            )
        )
        recording = None if recorder is None else recorder.close()
    except BaseException:
        if recorder is not None:
            recorder.abort()
        if previous is None and not meta["finished"]:  # nothing finished: a failed run leaves nothing behind
            (out / "run.json").unlink(missing_ok=True)
        raise
    rows = [*done_rows, *rows]
    meta.update(complete=True, wall_s=round(time.time() - t0, 1))
    write_json_atomic(out / "run.json", meta)
    title = f"{controller}: l={area:g}, {obstacles} obstacles, {episodes} episodes"
    if not fault_config.is_null:
        title += f", faults {fault_config.spec()}"
    typer.echo(format_table(rows, title=title))
    for p in written:
        typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out / 'metrics.json'}")
    if recording is not None:
        typer.echo(f"wrote {recording} (the first episode of N = {recorder.num_agents}: docs/ros.md)")
    elif record_to is not None:
        typer.echo(f"--record {record_to}: no swarm size was evaluated, nothing recorded", err=True)
    return recorded


def _setpoint_meta(low_level: str, robot: str, built, fault_config, dt: float) -> dict:
    """What run.json records of ``--low-level`` (nothing for ``attitude``, as every earlier run), after a usage error
    for a robot, controller or faults the setpoint tracker cannot fly; ``dt``: the control period (s)."""
    if low_level == "attitude":
        return {}
    from ..robots import ROBOTS

    require(ROBOTS[robot].flies_setpoints, f"--low-level {low_level} flies the acceleration command through a "
            f"firmware-like setpoint tracker (the quadrotor's: the Crazyflie's Mellinger controller); the {robot} "
            "has none")  # fmt: skip
    model = getattr(built.train_config, "model", None)
    interface = getattr(model, "interface", "accel") if built.checkpoint is not None else None
    require(interface in (None, "accel") or built.filter != "none",
            f"--low-level {low_level} flies an acceleration command; {built.name}'s interface is {interface!r} "
            "(no acceleration command): evaluate it with --low-level attitude")  # fmt: skip
    require(built.checkpoint is not None or built.filter != "none",
            f"--low-level {low_level} flies an acceleration command; the hand-crafted {built.name} returns body "
            "controls only: evaluate a --checkpoint's policy (alone or behind --filter) or --controller nominal "
            "--filter dcbf")  # fmt: skip
    require(fault_config.is_null, f"--low-level {low_level} with --faults: the faults corrupt the body control, "
            "which the setpoint tracker does not apply; evaluate without --faults")  # fmt: skip
    from ..robots.quadrotor.setpoint import DEFAULT_INNER_RATE, DEFAULT_MELLINGER_GAINS, inner_steps

    n = inner_steps(dt, DEFAULT_INNER_RATE)
    tracker = {"controller": "mellinger", "inner_rate_hz": DEFAULT_INNER_RATE, "inner_steps": n,
               "inner_dt_s": dt / n, "gains": DEFAULT_MELLINGER_GAINS.to_dict()}  # fmt: skip
    return {"low_level": low_level, "setpoint_tracker": tracker}


def _previous_run(out: Path) -> dict:
    """``out``'s ``run.json`` (for ``--resume``), or a usage error saying why there is nothing to resume."""
    path = out / "run.json"
    require(path.is_file(), f"--resume: {path} does not exist (nothing to continue); run without --resume")
    try:
        previous = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        usage_error(f"--resume: {path} cannot be read ({err}); rerun with --overwrite", err)
    require(isinstance(previous, dict) and "finished" in previous, f"--resume: {path} is not an eval run's record")
    return previous


def _resumable(previous: dict, meta: dict, out: Path) -> list[dict]:
    """The finished rows of ``out``'s run if it was made with ``meta``'s settings, or a usage error naming the
    settings that differ."""
    now = json.loads(json.dumps(meta))  # tuples as lists, as run.json stores them
    was, is_now = previous.get("weights_sha256"), now.get("weights_sha256")
    require(was == is_now, f"--resume: {out} was made from other weights than {now.get('checkpoint')}'s now "
            f"(model.safetensors sha256 {str(was)[:12]} then, {str(is_now)[:12]} now); its sizes would mix two "
            "policies: rerun with --overwrite")  # fmt: skip
    differ = sorted(k for k in set(now) | set(previous) if k not in _RESUME_FREE and now.get(k) != previous.get(k))
    require(not differ, f"--resume: {out} was made with other settings ({', '.join(differ)}); pass the same flags, "
            "or --overwrite to start again")  # fmt: skip
    rows = []
    if (out / "metrics.json").exists():
        try:
            rows = json.loads((out / "metrics.json").read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            usage_error(f"--resume: {out / 'metrics.json'} cannot be read ({err}); rerun with --overwrite", err)
    finished = previous["finished"]
    require([r.get("num_agents") for r in rows] == finished,
            f"--resume: {out / 'metrics.json'} does not hold the finished sizes {finished} of run.json; rerun with "
            "--overwrite")  # fmt: skip
    return rows


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
    resume: Annotated[
        bool,
        typer.Option("--resume", help="continue OUT's interrupted run (same flags): its finished swarm sizes are kept"),
    ] = False,
    robot: Annotated[
        str | None,
        typer.Option(
            metavar=ROBOT_METAVAR,
            callback=robot_choice,
            help="the robot of a --controller's swarm (default: quadrotor); a --checkpoint's is its own",
        ),
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
    obstacle_sensing: Annotated[
        str,
        typer.Option(
            help="map | lidar: where the dcbf QP and the dcbf filter read obstacles (lidar: each agent's own "
            "hits, as the learned policies and the cbf / prior filters do)"
        ),
    ] = "map",
    lidar_hits: Annotated[
        str,
        typer.Option(
            help="plane | point: with --obstacle-sensing lidar, what one hit stands for in the dcbf rows (plane: the "
            "plane through the hit normal to the ray; point: a point obstacle, optimistic beside large obstacles)"
        ),
    ] = "plane",
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
    max_travel: Annotated[
        float | None,
        typer.Option(help="each goal within this distance (m) of its agent's start (GCBF+'s --max-travel)"),
    ] = None,
    faults: Annotated[
        str,
        typer.Option(
            help="real-world faults (docs/robustness.md): 'none', 'default' (the default field conditions), key=value "
            "pairs such as 'pos=0.01,vel=0.02,loss=0.1,delay=1,thrust_gain=0.1,noncoop=0.05' (after 'default' they "
            "override it), or a JSON file of egcbf.faults.FaultConfig fields"
        ),
    ] = "none",
    low_level: Annotated[
        str,
        typer.Option(
            "--low-level",
            help="attitude | setpoint: what flies the controller's acceleration command: our attitude loop (default) "
            "or the Crazyflie firmware's Mellinger controller tracking it as a full-state setpoint at 500 Hz "
            "(docs/deploy.md)",
        ),
    ] = "attitude",
    record: Annotated[
        Path | None,
        typer.Option(
            "--record",
            metavar="FILE.mcap",
            help="write the first episode of the first swarm size as an MCAP file of ROS 2 messages (Foxglove, "
            "ros2 bag; docs/ros.md); needs the ros extra",
        ),
    ] = None,
    record_cbf: Annotated[
        bool,
        typer.Option(
            "--record-cbf",
            help="with --record and a --checkpoint: also record the checkpoint's learned CBF value h of every agent "
            "at every step (/egcbf/cbf; one more network evaluation per step, the larger part of such a recording's "
            "cost: docs/ros.md)",
        ),
    ] = False,
    filter_qp_solver: Annotated[
        str | None,
        typer.Option(
            help="active_set | ipm: how the cbf and prior filters solve their per-agent QPs: the exact batched "
            "active-set method (their default) or the interior-point method (docs/safety_filters.md)"
        ),
    ] = None,
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
            allocator=allocator_setting(),
            robot=robot,
            filter=filter.value,
            filter_alpha=filter_alpha,
            filter_margin=filter_margin,
            scene=scene.value,
            scene_yaw=scene_yaw,
            max_travel=max_travel,
            faults=faults,
            resume=resume,
            obstacle_sensing=obstacle_sensing,
            lidar_hits=lidar_hits,
            record_to=record,
            low_level=low_level,
            record_cbf=record_cbf,
            filter_qp_solver=filter_qp_solver,
        )
