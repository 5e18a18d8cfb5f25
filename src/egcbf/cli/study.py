"""``egcbf study``: the equivariance study (:mod:`egcbf.study`, docs/equivariance.md), resumably."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import require, warn_cells, warn_unreadable
from .root import app


def study_cmd(
    arms: Annotated[str, typer.Option(help="comma list of arms (default: all; `--plan` lists them)")] = "all",
    jobs: Annotated[int, typer.Option(help="training processes (and evaluation workers) at a time")] = 2,
    train: Annotated[bool, typer.Option("--train/--no-train", help="train the runs not trained yet")] = True,
    evaluate: Annotated[bool, typer.Option("--evaluate/--no-evaluate", help="evaluate the trained runs")] = True,
    report_only: Annotated[
        bool, typer.Option("--report-only", help="only rewrite the report from the results already there")
    ] = False,
    plan: Annotated[
        bool, typer.Option("--plan", help="print the arms, their runs and what is missing; run nothing")
    ] = False,
    report: Annotated[Path, typer.Option(help="the report to write")] = Path("docs/equivariance.md"),
    root: Annotated[Path, typer.Option(help="results folder (checkpoints, cells, rotated)")] = Path(
        "docs/results/equivariance"
    ),
    runs: Annotated[Path, typer.Option(help="training run directories (not committed)")] = Path("runs/equivariance"),
) -> None:
    """Train, evaluate and report the equivariance study (docs/equivariance.md): what SE(2)xR equivariance buys,
    claim by claim, with seeds and 95 % intervals. Everything resumes: rerun the same command."""
    from ..study import ARMS, arm, evaluate_arm, pending_cells, pending_runs, train_runs, write_report
    from ..study.report import default_quote_targets

    require(jobs >= 1, f"--jobs must be >= 1, got {jobs}")
    try:
        chosen = list(ARMS) if arms == "all" else [arm(a.strip()) for a in arms.split(",") if a.strip()]
    except ValueError as err:
        require(False, f"--arms: {err}")
    require(chosen, f"--arms {arms!r} names no arm; choose from {', '.join(a.name for a in ARMS)} (or all)")
    if plan:
        missing = set(pending_runs(chosen, root))
        cells = 0
        for a in chosen:
            runs_text = ", ".join(f"{r.name}{' (to train)' if r in missing else ''}" for r in a.all_runs())
            todo = pending_cells(a, root)
            cells += todo
            typer.echo(
                f"{a.name}: {a.claim}; preset {a.preset} {a.overrides or ''}, {a.minutes:g} min a run: {runs_text}"
                + (f"; {todo} cell(s) to evaluate" if todo else "")
            )
        hours = sum(a.minutes for a in chosen for r in a.all_runs() if r in missing) / 60 / jobs
        typer.echo(f"{len(missing)} run(s) to train: about {hours:.1f} h of wall time with --jobs {jobs}; "
                   f"{cells} cell(s) of trained runs to evaluate")  # fmt: skip
        return
    if not report_only:
        if train:
            train_runs(chosen, jobs=jobs, root=root, runs_dir=runs, log=typer.echo)
        if evaluate:
            for a in chosen:
                evaluate_arm(a, root, workers=jobs, log=typer.echo)
    if report_only:
        from ..study.results import stale_cells, unreadable_cells

        # the report reads every arm, whichever --arms chose
        warn_unreadable(unreadable_cells(ARMS, root), "egcbf study without --report-only")
        warn_cells(stale_cells(ARMS, root), f"cell(s) were computed with other weights than the checkpoints now "
                   f"under {root}", "left out of the report (pending)")  # fmt: skip
    path, verdicts = write_report(report, root, quote_in=default_quote_targets(report))
    for claim, v in verdicts.items():
        typer.echo(f"{claim}: {v}")
    typer.echo(f"wrote {path}")


app.command("study")(study_cmd)
