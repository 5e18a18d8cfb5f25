"""The equivariance study (docs/equivariance.md): the paper's three claims about what SE(2)xR
equivariance buys, tested with training seeds and confidence intervals.

* :mod:`~egcbf.study.plan`: the arms (training recipes), their runs and their evaluation cells;
* :mod:`~egcbf.study.driver`: training the runs (``egcbf train`` processes, resumable) and evaluating them
  (``egcbf reproduce`` sweeps and the rotated-world cells);
* :mod:`~egcbf.study.results`: reading the results back, effects with two-level bootstrap intervals;
* :mod:`~egcbf.study.report` and :mod:`~egcbf.study.figures`: docs/equivariance.md and its figures.

    egcbf study --arms paper-cpu --jobs 2      # train what is missing, evaluate, write docs/equivariance.md
    egcbf study --report-only                  # only rewrite the report from the committed results
"""

from .driver import evaluate_arm, pending_cells, pending_runs, train_command, train_runs
from .plan import ARMS, ROOT, Arm, RotatedCell, Run, arm, rotated_cells
from .report import verdict, write_report

__all__ = [
    "ARMS",
    "ROOT",
    "Arm",
    "RotatedCell",
    "Run",
    "arm",
    "evaluate_arm",
    "pending_cells",
    "pending_runs",
    "rotated_cells",
    "train_command",
    "train_runs",
    "verdict",
    "write_report",
]
