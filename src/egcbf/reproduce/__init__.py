"""Reproduce the paper's Table I and a scalability study past it: ``egcbf reproduce``.

    from egcbf.reproduce import SweepConfig, sweep, write_report
    cfg = SweepConfig(episodes=50, workers=2)
    records = sweep(cfg, command="egcbf reproduce")
    write_report(cfg, records, "docs/reproduction.md")

The sweep evaluates every method (GCBF, GCBF+, dCBF-QP, cCBF-QP, EGCBF, EGCBF+, the nominal controller alone, and
past the paper the run-time safety-filtered controllers ``METHOD:FILTER``: EGCBF+ and GCBF+ behind the dCBF filter,
EGCBF+ behind its learned CBF and behind the untrained prior, the nominal controller behind the dCBF filter) at
every swarm size of Table I in an arena ``[0, l]^3`` without obstacles and (the methods of ``obstacle_methods``) with
sphere obstacles; EGCBF+ and GCBF+ (alone and filtered) once per training seed; and, past the paper, at
N = 1024 ... 4096 at the density of N = 512. One job per module:

* :mod:`~egcbf.reproduce.paper`: the paper's Table I and the method names;
* :mod:`~egcbf.reproduce.plan`: :class:`SweepConfig`, its cells and what a cell's result depends on;
* :mod:`~egcbf.reproduce.store`: what is kept on disk: checkpoints, cell files, imported baselines, invocations;
* :mod:`~egcbf.reproduce.workers`: evaluating one cell, and many on local processes or Ray;
* :mod:`~egcbf.reproduce.runner`: the sweep: order, resuming, failures, interruptions, the lock;
* :mod:`~egcbf.reproduce.stats`: a setting's cells over training seeds, their mean and range, the words for the
  settings;
* :mod:`~egcbf.reproduce.tables`, :mod:`~egcbf.reproduce.summary`, :mod:`~egcbf.reproduce.figures`,
  :mod:`~egcbf.reproduce.provenance`: the report's tables, summary sentences, figures, and provenance (with the
  command that regenerates the report);
* :mod:`~egcbf.reproduce.report`: :func:`write_report`, the markdown file assembled from those sections.
"""

from .figures import scalability_figure
from .paper import BASELINES, DEFAULT_SIZES, FILTERED, LABELS, LEARNED, MARL, METHODS, PAPER_TABLE_I, SCALE_SIZES
from .plan import Cell, SweepConfig, cell_key
from .provenance import provenance_markdown, regenerate_command
from .report import write_report
from .runner import CellsFailed, sweep, sweep_many, validate
from .store import (
    CheckpointInfo,
    checkpoint_dir,
    describe_mismatch,
    find_method_checkpoint,
    import_baseline,
    load_cells,
    mismatched_cells,
    read_invocations,
    unreadable_cells,
)
from .summary import summary_markdown
from .tables import table_markdown
from .workers import CellTask, require_ray, run_cell

__all__ = [
    "BASELINES",
    "DEFAULT_SIZES",
    "FILTERED",
    "LABELS",
    "LEARNED",
    "MARL",
    "METHODS",
    "PAPER_TABLE_I",
    "SCALE_SIZES",
    "Cell",
    "CellTask",
    "CellsFailed",
    "CheckpointInfo",
    "SweepConfig",
    "cell_key",
    "checkpoint_dir",
    "describe_mismatch",
    "find_method_checkpoint",
    "import_baseline",
    "load_cells",
    "mismatched_cells",
    "provenance_markdown",
    "read_invocations",
    "regenerate_command",
    "require_ray",
    "run_cell",
    "scalability_figure",
    "summary_markdown",
    "sweep",
    "sweep_many",
    "table_markdown",
    "unreadable_cells",
    "validate",
    "write_report",
]
