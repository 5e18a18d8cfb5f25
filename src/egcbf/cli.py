"""Command line: ``egcbf eval`` (evaluate a controller over swarm sizes), ``egcbf train`` (learn a graph CBF and
policy) and ``egcbf demo`` (the main job).

    egcbf eval --controller ccbf --num-agents 8,16,64 --area 4 --obstacles 0 --episodes 50 --seed 0 --out runs/ccbf
    egcbf train --algo egcbf+ --steps 300 --out runs/egcbf+          # CPU recipe; --preset paper --device cuda
    egcbf eval --checkpoint runs/egcbf+ --num-agents 8,16,64 --out runs/egcbf+/eval
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import torch
import typer

from .allocator import keep_freed_memory
from .report import machine_info
from .threads import choose_threads

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Equivariant graph CBFs for quadrotor swarms.")

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
#: the process's allocator setting (:mod:`egcbf.allocator`), set by :func:`main`; recorded in run.json
_ALLOCATOR = "default (the CLI's entry point did not run)"


def _parse_sizes(text: str) -> list[int]:
    try:
        sizes = [int(s) for s in text.replace(" ", "").split(",") if s]
    except ValueError:
        raise typer.BadParameter(f"--num-agents must be comma-separated integers, got {text!r}") from None
    if not sizes or any(n < 1 for n in sizes):
        raise typer.BadParameter(f"--num-agents needs positive integers, got {text!r}")
    return sizes


def _device(name: str) -> torch.device:
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("--device cuda was given but torch.cuda.is_available() is False")
    return dev


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
        raise typer.BadParameter(str(err)) from None


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


def format_table(rows: list[dict], title: str = "") -> str:
    """A fixed-width table of metric rows (rates in %)."""
    head = f"{'N':>5} {'Safe%':>7} {'Reach%':>7} {'Succ%':>7} {'Cost (min/max)':>20} {'Reward':>10} {'step ms':>8}"
    has_qp = any("qp_ms_median" in r for r in rows)
    if has_qp:
        head += f" {'QP ms':>7} {'slack':>6}"
    lines = [title, head, "-" * len(head)] if title else [head, "-" * len(head)]
    for r in rows:
        cost = f"{r['cost']:.3f} ({r['cost_min']:.2f}/{r['cost_max']:.2f})"
        line = (
            f"{r['num_agents']:>5} {100 * r['safe_rate']:>7.1f} {100 * r['reach_rate']:>7.1f} "
            f"{100 * r['success_rate']:>7.1f} {cost:>20} {r['reward']:>10.2f} {r['step_ms_median']:>8.2f}"
        )
        if has_qp:
            line += f" {r.get('qp_ms_median', float('nan')):>7.2f} {r.get('qp_slack_steps', 0):>6}"
        lines.append(line)
    return "\n".join(lines)


def _render(records: dict, out: Path, area: float, tag: str) -> list[Path]:
    from .render import render_gif, render_topdown

    paths = []
    for n, rec in records.items():
        traj = torch.stack(rec.positions)
        coll = torch.stack(rec.collided)
        args = (traj, rec.goals, rec.centers, rec.radii, coll)
        paths.append(render_gif(out / f"{tag}_N{n}.gif", *args, area_size=area, title=f"{tag} N={n}"))
        paths.append(render_topdown(out / f"{tag}_N{n}_topdown.png", *args, area_size=area, title=f"{tag} N={n}"))
    return paths


@app.command("eval")
def eval_cmd(
    controller: Annotated[str, typer.Option(help="nominal | ccbf | dcbf")] = "nominal",
    num_agents: Annotated[str, typer.Option("--num-agents", help="comma-separated swarm sizes")] = "8,16,64",
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="number of sphere obstacles")] = 0,
    episodes: Annotated[int, typer.Option(help="episodes per swarm size")] = 50,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    out: Annotated[Path, typer.Option(help="output directory (metrics.json, renders)")] = Path("out/eval"),
    render: Annotated[bool, typer.Option("--render/--no-render", help="write a GIF and a top-down PNG per N")] = False,
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    batch: Annotated[int | None, typer.Option(help="episodes simulated together (default: automatic)")] = None,
    device: Annotated[str, typer.Option(help="cpu | cuda")] = "cpu",
    dtype: Annotated[str, typer.Option(help="float32 | float64")] = "float32",
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    checkpoint: Annotated[
        Path | None,
        typer.Option(help="evaluate a trained policy: a checkpoint directory or a run directory (newest checkpoint)"),
    ] = None,
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
) -> None:
    """Evaluate a controller at several swarm sizes; print a table and write OUT/metrics.json."""
    n_threads, reason = _threads(threads)
    with _torch_threads(n_threads, reason):
        _eval(
            controller=controller,
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
            dtype=dtype,
            progress=progress,
            checkpoint=checkpoint,
            threads_reason=reason,
        )


def _eval(
    controller: str,
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
) -> None:
    """The body of ``egcbf eval`` (and of each run of ``egcbf demo``), with torch's threads already set."""
    from .control.controllers import CONTROLLERS, make_controller
    from .evaluate import evaluate

    env_overrides = None
    if checkpoint is not None:  # a learned policy: everything it needs is in the checkpoint directory
        from .train import find_checkpoint, load_controller

        try:
            ckpt = find_checkpoint(checkpoint)
        except FileNotFoundError as err:
            raise typer.BadParameter(str(err)) from None
        learned, train_cfg = load_controller(ckpt, device=_device(device), dtype=_DTYPES.get(dtype, torch.float32))
        controller = train_cfg.algo
        env_overrides = dict(train_cfg.env_overrides)  # the sensing the policy was trained with (radii, LiDAR)
    elif controller not in CONTROLLERS:
        raise typer.BadParameter(f"--controller must be one of {sorted(CONTROLLERS)}, got {controller!r}")
    if dtype not in _DTYPES:
        raise typer.BadParameter(f"--dtype must be one of {sorted(_DTYPES)}")
    if episodes < 1:
        raise typer.BadParameter("--episodes must be >= 1")
    sizes = _parse_sizes(num_agents)
    dev = _device(device)
    t0 = time.time()
    rows, records = evaluate(
        (lambda cfg: learned) if checkpoint is not None else (lambda cfg: make_controller(controller)),
        sizes,
        area_size=area,
        num_obstacles=obstacles,
        episodes=episodes,
        seed=seed,
        batch=batch,
        max_steps=max_steps,
        device=dev,
        dtype=_DTYPES[dtype],
        record=render,
        show_progress=progress,
        env_overrides=env_overrides,
    )
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    meta = {
        "command": " ".join(["egcbf", *sys.argv[1:]]),
        "controller": controller,
        "checkpoint": None if checkpoint is None else str(ckpt),
        "area": area,
        "obstacles": obstacles,
        "episodes": episodes,
        "seed": seed,
        "wall_s": round(time.time() - t0, 1),
        "threads": torch.get_num_threads(),
        "threads_reason": threads_reason,
        "allocator": _ALLOCATOR,
        "machine": machine_info(),
    }
    (out / "run.json").write_text(json.dumps(meta, indent=2) + "\n")
    typer.echo(format_table(rows, title=f"{controller}: l={area:g}, {obstacles} obstacles, {episodes} episodes"))
    if render:
        for p in _render(records, out, area, controller):
            typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out / 'metrics.json'}")


def _demo_source(name: str, checkpoints: Path) -> Path | None:
    """The checkpoint directory of a learned method (``checkpoints/<name>``), or ``None`` for a hand-crafted
    controller name; a clear error naming the path and the training command if a learned method has none."""
    from .config import METHODS
    from .control.controllers import CONTROLLERS

    if name in CONTROLLERS:
        return None
    if name not in METHODS:
        raise typer.BadParameter(
            f"unknown method {name!r}: a learned method {sorted(METHODS)} or a controller {sorted(CONTROLLERS)}"
        )
    from .train import find_checkpoint

    path = checkpoints / name
    try:
        return find_checkpoint(path)
    except FileNotFoundError:
        raise typer.BadParameter(
            f"no {name} checkpoint at {path} (config.json + model.safetensors). Train one with\n"
            f"  egcbf train --algo {name} --steps 200 --threads 1 --out runs/{name}\n"
            f"and pass --checkpoints with a directory holding {name}/ (e.g. a copy of runs/{name}/best)."
        ) from None


@app.command()
def demo(
    checkpoints: Annotated[
        Path, typer.Option(help="directory holding one checkpoint directory per learned method (egcbf+/, gcbf+/, ...)")
    ] = Path("checkpoints"),
    method: Annotated[
        str, typer.Option(help="a learned method (gcbf, gcbf+, egcbf, egcbf+) or a controller (nominal, ccbf, dcbf)")
    ] = "egcbf+",
    baseline: Annotated[
        str | None,
        typer.Option(help="compared on the same seeds; 'none' to skip (default: gcbf+ for a learned --method)"),
    ] = None,
    num_agents: Annotated[int, typer.Option("--num-agents")] = 64,
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="number of sphere obstacles")] = 8,
    episodes: Annotated[int, typer.Option()] = 4,
    seed: Annotated[int, typer.Option()] = 0,
    out: Annotated[Path, typer.Option(help="output directory")] = Path("out/demo"),
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    device: Annotated[str, typer.Option()] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP.replace("run.json", "demo.json"))] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """The main job: the learned EGCBF+ policy and GCBF+ on the same episodes (64 agents, l = 4, 8 obstacles by
    default): both metrics tables, a one-line comparison, OUT/<method>/metrics.json, a GIF and a top-down PNG of
    the first EGCBF+ episode, and OUT/demo.json. ``--method ccbf`` runs the hand-crafted centralized CBF-QP."""
    t0 = time.time()
    if baseline is None:
        baseline = "none" if _demo_source(method, checkpoints) is None else "gcbf+"
    names = [method] + ([] if baseline.lower() in ("none", "") or baseline == method else [baseline])
    sources = {name: _demo_source(name, checkpoints) for name in names}  # fail before any work
    n_threads, reason = _threads(threads)
    with _torch_threads(n_threads, reason):
        rows = {}
        for name, ckpt in sources.items():
            _eval(
                controller=name if ckpt is None else "nominal",
                num_agents=str(num_agents),
                area=area,
                obstacles=obstacles,
                episodes=episodes,
                seed=seed,
                out=out / name,
                render=name == method,
                max_steps=max_steps,
                batch=None,
                device=device,
                dtype="float32",
                progress=progress,
                checkpoint=ckpt,
                threads_reason=reason,
            )
            rows[name] = json.loads((out / name / "metrics.json").read_text())[0]
        if len(rows) == 2:
            (a, ra), (b, rb) = rows.items()
            parts = ", ".join(
                f"{k} {100 * ra[f'{k}_rate']:.1f}% vs {100 * rb[f'{k}_rate']:.1f}%"
                for k in ("safe", "reach", "success")
            )
            typer.echo(f"{a} vs {b} on the same {episodes} episodes (N={num_agents}, l={area:g}, seed {seed}): {parts}")
        summary = {
            "command": " ".join(["egcbf", *sys.argv[1:]]),
            "method": method,
            "baseline": None if len(rows) == 1 else names[1],
            "checkpoints": {k: None if v is None else str(v) for k, v in sources.items()},
            "num_agents": num_agents,
            "area": area,
            "obstacles": obstacles,
            "episodes": episodes,
            "seed": seed,
            "max_steps": max_steps,
            "metrics": rows,
            "wall_s": round(time.time() - t0, 1),
            "threads": torch.get_num_threads(),
            "threads_reason": reason,
            "allocator": _ALLOCATOR,
            "machine": machine_info(),
        }
        out.mkdir(parents=True, exist_ok=True)
        (out / "demo.json").write_text(json.dumps(summary, indent=2) + "\n")
        typer.echo(f"wrote {out / 'demo.json'}")


@app.command()
def train(
    algo: Annotated[str, typer.Option(help="gcbf | gcbf+ | egcbf | egcbf+")] = "egcbf+",
    out: Annotated[Path, typer.Option(help="run directory (config, logs, metrics.csv, checkpoints)")] = Path(
        "runs/train"
    ),
    config: Annotated[
        Path | None, typer.Option(help="JSON file of TrainConfig fields overriding the preset (may set 'preset')")
    ] = None,
    preset: Annotated[str | None, typer.Option(help="cpu (default) | paper | tiny")] = None,
    steps: Annotated[int | None, typer.Option(help="number of updates (default: the config's)")] = None,
    device: Annotated[str | None, typer.Option(help="cpu | cuda (default: the config's)")] = None,
    seed: Annotated[int | None, typer.Option(help="seed (default: the config's)")] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="continue the run in OUT from its newest checkpoint")
    ] = False,
    threads: Annotated[int | None, typer.Option(help="torch CPU threads (default: torch's)")] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """Train GCBF, GCBF+, EGCBF or EGCBF+ (one learner; the group and the reference controller differ)."""
    from .config import METHODS, PRESETS, TrainConfig
    from .train import train as run_training

    if algo not in METHODS:
        raise typer.BadParameter(f"--algo must be one of {sorted(METHODS)}, got {algo!r}")
    if resume:
        if config is not None or preset is not None or seed is not None or device is not None:
            raise typer.BadParameter("--resume continues the saved config: only --steps and --threads may change")
        if threads is not None:
            torch.set_num_threads(threads)
        try:
            run_training(TrainConfig(), out, resume=True, steps=steps, progress=progress)
        except FileNotFoundError as err:
            raise typer.BadParameter(str(err)) from None
        return
    fields = {}
    if config is not None:
        try:
            fields = json.loads(config.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise typer.BadParameter(f"--config {config}: {err}") from None
        file_algo = fields.pop("algo", algo)
        if file_algo != algo:
            raise typer.BadParameter(f"--config says algo {file_algo!r} but --algo is {algo!r}")
        fields.pop("reference", None)
    name = preset or fields.pop("preset", "cpu")
    fields.pop("preset", None)
    if name not in PRESETS:
        raise typer.BadParameter(f"--preset must be one of {PRESETS}, got {name!r}")
    for key, value in (("steps", steps), ("device", device), ("seed", seed), ("num_threads", threads)):
        if value is not None:
            fields[key] = value
    try:
        cfg = TrainConfig.preset(algo, name, **fields)
    except (TypeError, ValueError) as err:
        raise typer.BadParameter(str(err)) from None
    _device(cfg.device)
    try:
        run_training(cfg, out, progress=progress)
    except FileExistsError as err:
        raise typer.BadParameter(str(err)) from None


def _parse_methods(text: str, option: str) -> tuple[str, ...]:
    from .reproduce import METHODS

    names = tuple(s for s in text.replace(" ", "").split(",") if s)
    bad = [m for m in names if m not in METHODS]
    if bad:
        raise typer.BadParameter(f"{option}: unknown method(s) {bad}; choose from {', '.join(METHODS)}")
    return names


@app.command()
def reproduce(
    methods: Annotated[str, typer.Option(help="comma list of gcbf,gcbf+,dcbf,ccbf,egcbf,egcbf+,nominal")] = (
        "gcbf,gcbf+,dcbf,ccbf,egcbf,egcbf+,nominal"
    ),
    num_agents: Annotated[str, typer.Option("--num-agents", help="comma-separated swarm sizes")] = (
        "8,16,64,128,256,512"
    ),
    area: Annotated[float, typer.Option(help="side l of the arena [0, l]^3 (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="obstacles of the obstacle setting (0: none)")] = 8,
    obstacle_methods: Annotated[
        str, typer.Option("--obstacle-methods", help="methods also run with obstacles (comma list)")
    ] = "gcbf,gcbf+,egcbf,egcbf+,nominal",
    episodes: Annotated[int, typer.Option(help="episodes per cell (method, obstacles, N)")] = 50,
    baseline_episodes: Annotated[
        int | None, typer.Option(help="episodes per cell of the CBF-QP baselines (default: --episodes)")
    ] = None,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's 256 steps)")] = None,
    checkpoints: Annotated[
        Path, typer.Option(help="one checkpoint directory per learned method: CHECKPOINTS/<method>/")
    ] = Path("checkpoints"),
    out: Annotated[Path, typer.Option(help="results directory (one JSON file per cell)")] = Path(
        "docs/results/reproduction"
    ),
    report: Annotated[Path, typer.Option(help="markdown report (figures go to its directory's figures/)")] = Path(
        "docs/reproduction.md"
    ),
    baselines: Annotated[
        Path | None, typer.Option(help="earlier `egcbf eval` outputs to import baseline cells from")
    ] = Path("docs/results/baselines"),
    workers: Annotated[int, typer.Option(help="cells evaluated in parallel (one torch thread each)")] = 2,
    backend: Annotated[str, typer.Option(help="process | ray (optional extra, for several machines)")] = "process",
    device: Annotated[str, typer.Option(help="cpu | cuda")] = "cpu",
    report_only: Annotated[
        bool, typer.Option("--report-only", help="regenerate the report from the existing cells")
    ] = False,
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """Reproduce the paper's Table I and scalability study: evaluate every method at every N (without obstacles,
    and OBSTACLE-METHODS with OBSTACLES obstacles), resumably (finished cells are kept), and write REPORT."""
    from .reproduce import SweepConfig, load_cells, sweep, validate, write_report

    try:
        cfg = SweepConfig(
            methods=_parse_methods(methods, "--methods"),
            num_agents=tuple(_parse_sizes(num_agents)),
            area=area,
            obstacles=obstacles,
            obstacle_methods=_parse_methods(obstacle_methods, "--obstacle-methods"),
            episodes=episodes,
            baseline_episodes=baseline_episodes,
            seed=seed,
            max_steps=max_steps,
            checkpoints=checkpoints,
            out=out,
            baselines=baselines,
            device=device,
            workers=workers,
            backend=backend,
        )
        if not report_only:
            validate(cfg)
    except (ValueError, FileNotFoundError, ImportError) as err:
        raise typer.BadParameter(str(err)) from None
    if report_only:
        records = load_cells(cfg)
    else:
        records = sweep(cfg, command=" ".join(["egcbf", *sys.argv[1:]]), progress=progress, log=typer.echo)
    path = write_report(cfg, records, report)
    typer.echo(f"{len(records)} of {len(cfg.cells())} cells; wrote {path}")


def main() -> None:  # pragma: no cover
    global _ALLOCATOR
    _ALLOCATOR = keep_freed_memory()[1]
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
