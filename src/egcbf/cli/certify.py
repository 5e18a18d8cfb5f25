"""``egcbf certify``: is each shipped learned CBF a barrier? Sampled closed-loop checks with exact bounds, resumably
(:mod:`egcbf.certify`, docs/certificate.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .checks import prepare_out, require, usage_error
from .root import app

_DEFAULT_REPORT = Path("docs/certificate.md")
_DEFAULT_FIGURES = Path("docs/figures")


@app.command("certify")
def certify_cmd(
    seed: Annotated[int, typer.Option(help="evaluation seed of the rollouts")] = 0,
    window: Annotated[int, typer.Option(help="look-ahead W (steps) of the miss and conservativeness rates")] = 32,
    stride: Annotated[int, typer.Option(help="sample every k-th step of each agent")] = 4,
    only: Annotated[
        str | None, typer.Option(help="only the cells whose name contains this (--plan lists them)")
    ] = None,
    checkpoints: Annotated[Path, typer.Option(help="the shipped checkpoints' root")] = Path("checkpoints"),
    out: Annotated[Path, typer.Option(help="cells folder")] = Path("docs/results/certificate"),
    report: Annotated[
        Path, typer.Option(help="the report to write (the default, the committed one, only for the whole plan)")
    ] = _DEFAULT_REPORT,
    figures: Annotated[Path, typer.Option(help="folder of the report's figure")] = _DEFAULT_FIGURES,
    workers: Annotated[int, typer.Option(help="cells computed at a time (one process and one thread each)")] = 2,
    device: Annotated[str, typer.Option(help="cpu | cuda | cuda:K")] = "cpu",
    plan: Annotated[bool, typer.Option("--plan", help="list the cells and which are missing; run nothing")] = False,
    report_only: Annotated[bool, typer.Option("--report-only", help="only rewrite the report")] = False,
) -> None:
    """Record closed-loop rollouts of every shipped learned controller (alone and behind each run-time filter) and of
    the nominal controller, score every agent-state against the learned CBFs and the dcbf filter's hand-crafted
    barrier (containment, misses, the decrease condition, invariance, conservativeness, each with a 95 %
    Clopper-Pearson bound), and write docs/certificate.md. Resumable: rerun the same command."""
    from ..certify import CertifyConfig, pending, sweep, write_report
    from .checks import parse_device

    require(window >= 1 and stride >= 1 and workers >= 1, "--window, --stride and --workers must be >= 1")
    try:
        cfg = CertifyConfig(seed=seed, window=window, stride=stride, checkpoints=checkpoints, out=out,
                            workers=workers, device=str(parse_device(device)), only=only)  # fmt: skip
        require(cfg.cells(), f"--only {only!r} selects no cell; --plan lists them")
        todo = pending(cfg)
    except (ValueError, FileNotFoundError) as err:
        usage_error(str(err), err)
    default = CertifyConfig()
    narrowed = any(getattr(cfg, f) != getattr(default, f) for f in ("seed", "window", "stride", "out", "checkpoints",
                                                                     "only"))  # fmt: skip
    committed = report.resolve() == _DEFAULT_REPORT.resolve() or figures.resolve() == _DEFAULT_FIGURES.resolve()
    if not plan and narrowed and committed:
        usage_error(f"this selection is not the whole plan, and {_DEFAULT_REPORT} with its figure in "
                    f"{_DEFAULT_FIGURES} is the whole plan's report: pass --report PATH and --figures DIR for this "
                    "part's report, or drop the selecting flags")  # fmt: skip
    if plan:
        missing = {c for c, _, _ in todo}
        for c in cfg.cells():
            typer.echo(f"{'missing ' if c in missing else 'stored  '} {c.name}  ->  {c.filename}")
        typer.echo(f"{len(cfg.cells()) - len(todo)} of {len(cfg.cells())} cells stored")
        return
    prepare_out(report.parent, True, (), flag="--report", lock=False)
    prepare_out(figures, True, (), flag="--figures", lock=False)
    failures = {}
    if not report_only:
        try:
            failures = sweep(cfg, log=typer.echo)
        except (ValueError, RuntimeError) as err:
            usage_error(str(err), err)
    try:
        typer.echo(f"wrote {write_report(cfg, report, figures)}")
    except (ValueError, FileNotFoundError) as err:
        usage_error(str(err), err)
    if failures:
        typer.echo(f"Error: {len(failures)} cell(s) failed: {', '.join(c.name for c in failures)} (every other cell "
                   "was computed; rerun to retry them)", err=True)  # fmt: skip
        raise typer.Exit(1)
