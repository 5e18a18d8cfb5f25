"""``egcbf robustness``: every controller under every fault axis, resumably (:mod:`egcbf.robustness`,
docs/robustness.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import check_env_flags, parse_device, parse_sizes, prepare_out, require, usage_error, warn_unreadable
from .choices import Backend
from .root import app

_DEFAULT_REPORT = Path("docs/robustness.md")
_DEFAULT_FIGURES = Path("docs/figures")


def _narrowed(cfg) -> bool:
    """Whether ``cfg`` selects other cells than the default plan (the committed report's)."""
    from ..robustness import RobustnessConfig

    fields = ("controllers", "axes", "num_agents", "area", "obstacles", "episodes", "seed", "max_steps", "out",
              "checkpoints")  # fmt: skip
    default = RobustnessConfig()
    return any(getattr(cfg, f) != getattr(default, f) for f in fields)


@app.command("robustness")
def robustness_cmd(
    axes: Annotated[str, typer.Option(help="comma list of fault axes (default: all; --plan lists them)")] = "all",
    controllers: Annotated[
        str, typer.Option("--controllers", "--methods", help="comma list of egcbf reproduce methods")
    ] = "nominal,ccbf,dcbf,gcbf+,egcbf+,egcbf+:dcbf",
    num_agents: Annotated[str, typer.Option("--num-agents", help="comma-separated swarm sizes")] = "128,512",
    area: Annotated[float, typer.Option(help="side l of the arena (m)")] = 4.0,
    obstacles: Annotated[int, typer.Option(help="obstacles of the obstacle setting (both settings run)")] = 8,
    episodes: Annotated[int, typer.Option(help="episodes per cell")] = 20,
    seed: Annotated[int, typer.Option(help="evaluation seed")] = 0,
    max_steps: Annotated[int | None, typer.Option(help="episode length (default: the env's)")] = None,
    checkpoints: Annotated[Path, typer.Option(help="learned checkpoints (training seed 0)")] = Path("checkpoints"),
    out: Annotated[Path, typer.Option(help="cells folder")] = Path("docs/results/robustness"),
    report: Annotated[
        Path, typer.Option(help="the report to write (the default, the committed one, only for the whole plan)")
    ] = _DEFAULT_REPORT,
    figures: Annotated[Path, typer.Option(help="folder of the report's figures")] = _DEFAULT_FIGURES,
    workers: Annotated[int, typer.Option(help="cells evaluated at a time")] = 2,
    backend: Annotated[Backend, typer.Option(help="process or ray (as egcbf reproduce)")] = Backend.process,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    plan: Annotated[bool, typer.Option("--plan", help="print the axes, levels and sweeps; run nothing")] = False,
    report_only: Annotated[bool, typer.Option("--report-only", help="only rewrite the report")] = False,
    recompute: Annotated[
        bool, typer.Option("--recompute", help="replace stored cells made with other settings (else refused)")
    ] = False,
) -> None:
    """Evaluate every controller under every fault axis (five levels each, and the default field conditions), as
    egcbf reproduce sweeps (resumable: rerun the same command), and write docs/robustness.md."""
    from ..reproduce import METHODS, sweep_many
    from ..reproduce.runner import CellsFailed, validate
    from ..robustness import AXES, RobustnessConfig, write_report

    names = [a.name for a in AXES] if axes == "all" else [a.strip() for a in axes.split(",") if a.strip()]
    bad = [a for a in names if a not in {x.name for x in AXES}]
    require(not bad, f"--axes: unknown {bad}; choose from {[a.name for a in AXES]}")
    methods = tuple(m.strip() for m in controllers.split(",") if m.strip())
    bad = [m for m in methods if m not in METHODS]
    require(methods and not bad, f"--controllers: unknown {bad}; choose from {list(METHODS)}")
    require(episodes >= 1 and workers >= 1 and obstacles >= 0, "--episodes and --workers must be >= 1, "
            "--obstacles >= 0")  # fmt: skip
    sizes = tuple(parse_sizes(num_agents))
    try:  # every input checked before anything runs or is written: one "Error:" line, exit 2
        check_env_flags(sizes, area, obstacles, max_steps)
        cfg = RobustnessConfig(
            controllers=methods, axes=tuple(names), num_agents=sizes, area=area, obstacles=obstacles,
            episodes=episodes, seed=seed, max_steps=max_steps, checkpoints=checkpoints, out=out, workers=workers,
            backend=backend.value, device=str(parse_device(device)),
        )  # fmt: skip
        sweeps = cfg.sweeps()
        if not (plan or report_only):
            validate(sweeps[0][2])  # the perfect world runs every controller: checkpoints, filters, backend
    except (ValueError, FileNotFoundError, ImportError) as err:
        usage_error(str(err), err)
    committed = report.resolve() == _DEFAULT_REPORT.resolve() or figures.resolve() == _DEFAULT_FIGURES.resolve()
    if not plan and _narrowed(cfg) and committed:
        usage_error(f"this selection is not the whole plan, and {_DEFAULT_REPORT} with its figures in "
                    f"{_DEFAULT_FIGURES} is the whole plan's report: pass --report PATH and --figures DIR for this "
                    "part's report, or drop the selecting flags")  # fmt: skip
    if not plan:
        prepare_out(report.parent, True, (), flag="--report", lock=False)
        prepare_out(figures, True, (), flag="--figures", lock=False)
    if plan:
        for a in (x for x in AXES if x.name in names):
            typer.echo(f"{a.name}: {a.title} ({a.unit}): levels {', '.join(f'{v:g}' for v in a.levels)}")
        for _, spec, sw in sweeps:
            typer.echo(f"  sweep {spec}: {', '.join(sw.methods)} ({len(sw.cells())} cells)")
        typer.echo(f"{sum(len(s.cells()) for _, _, s in sweeps)} cells in {len(sweeps)} sweeps")
        return
    failed = None
    if not report_only:
        for k, (_, spec, sw) in enumerate(sweeps, 1):
            typer.echo(f"[{k}/{len(sweeps)}] faults {spec}: {', '.join(sw.methods)}")
        commands = [f"egcbf robustness --axes {name}" for name, _, _ in sweeps]
        try:  # every level's cells in one queue: no level waits for the slowest cell of the one before
            sweep_many([sw for _, _, sw in sweeps], commands=commands, progress=progress, log=typer.echo,
                       recompute=recompute)  # fmt: skip
        except CellsFailed as err:  # every other cell was computed; the failures are named at the end
            failed = err
        except (ValueError, RuntimeError) as err:  # stored cells of other settings; another sweep holds the lock
            usage_error(str(err), err)
    if report_only:
        from ..robustness.cells import unreadable_files

        warn_unreadable(unreadable_files(cfg), "egcbf robustness without --report-only")
    typer.echo(f"wrote {write_report(cfg, report, figures)}")
    if failed is not None:
        typer.echo(f"Error: {failed} (every other cell was computed)", err=True)
        raise typer.Exit(1)
