"""``egcbf reproduce``: the paper's Table I and the scalability study, resumably (:mod:`egcbf.reproduce`)."""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path
from typing import Annotated

import typer

from .checks import (
    check_env_flags,
    check_sweep_memory,
    parse_device,
    parse_sizes,
    prepare_out,
    usage_error,
    warn_unreadable,
)
from .choices import (
    Backend,
)
from .root import app


def _parse_methods(text: str, option: str) -> tuple[str, ...]:
    from ..reproduce import METHODS

    names = tuple(s for s in text.replace(" ", "").split(",") if s)
    bad = [m for m in names if m not in METHODS]
    if bad:
        usage_error(
            f"{option}: unknown method(s) {bad}; choose from {', '.join(METHODS)} (METHOD:FILTER: a method behind a "
            "run-time filter)"
        )
    return names


#: the reproduction's default methods (``egcbf.reproduce.METHODS``; tests/egcbf/test_reproduce.py checks they agree)
_REPRO_METHODS = (
    "gcbf,gcbf+,dcbf,ccbf,egcbf,egcbf+,nominal,egcbf+:dcbf,gcbf+:dcbf,egcbf+:cbf,egcbf+:prior,nominal:dcbf,ippo-lag"
)
_REPRO_OBSTACLE_METHODS = (
    "gcbf,gcbf+,egcbf,egcbf+,nominal,egcbf+:dcbf,gcbf+:dcbf,egcbf+:cbf,egcbf+:prior,nominal:dcbf,ippo-lag"
)
_LONG_METHODS = "gcbf+,egcbf+,dcbf,ccbf,nominal,egcbf+:dcbf,gcbf+:dcbf,nominal:dcbf"


def _parse_steps(text: str) -> int | None:
    """``--long-steps``: a positive episode length, or ``none``."""
    if text.strip().lower() in ("", "none"):
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"--long-steps must be a number of steps or 'none', got {text!r}") from None


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
    long_steps: Annotated[
        str,
        typer.Option(
            "--long-steps",
            help="the scalability study's second horizon: LONG-METHODS at the SCALE-SIZES again with episodes of "
            "this many steps ('none': skip)",
        ),
    ] = "384",
    long_methods: Annotated[
        str, typer.Option("--long-methods", help="methods of the long horizon (comma list, among --scale-methods)")
    ] = _LONG_METHODS,
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
    from ..control.names import split_method
    from ..reproduce import (
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
    from ..reproduce.paper import MARL
    from ..reproduce.store import pending_cells
    from ..train.checkpoint import read_config

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
            long_steps=_parse_steps(long_steps),
            long_methods=_parse_methods(long_methods, "--long-methods"),
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
        "--long-methods": (long_methods, _LONG_METHODS, "long_methods"),
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
                if cfg.long_cells():
                    check_env_flags([n], cfg.scale_area(n), 0, cfg.long_steps)
            ckpts = validate(cfg)
            learned = [
                (c.num_agents, cfg.area_for(c), cfg.episodes_for(c))
                for c in pending_cells(cfg, ckpts)
                if c.train_seed is not None
            ]
            graph = [ck for ck in ckpts.values() if ck.method not in MARL]  # a MARL actor needs no graph memory
            hidden = max((read_config(ck.path).model.hidden for ck in graph), default=64)
            comm = check_env_flags([8], area, 0, None)[0].comm_radius
            check_sweep_memory(learned, cfg.workers, hidden, comm, parse_device(device))
    except (ValueError, FileNotFoundError, ImportError) as err:
        usage_error(str(err), err)
    if not report_only:
        prepare_out(out, True, ())  # writable (finished cells in it are reused; other settings are refused)
    prepare_out(report.parent, True, (), flag="--report", lock=False)
    if report_only:
        records = load_cells(cfg)
        warn_unreadable(unreadable_cells(cfg), "the sweep")
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
    "scale_methods", "scale_agent_episodes", "long_steps", "long_methods", "max_steps", "episodes", "obstacles",
    "workers", "area",
)  # fmt: skip


def _sweep_flags(message: str) -> str:
    """``message`` with SweepConfig's field names written as the flags that set them."""
    fields = "|".join(_SWEEP_FIELDS)
    return re.sub(rf"(?<![-\w])({fields})\b", lambda m: "--" + m.group(1).replace("_", "-"), message)
