"""``egcbf robustness``: every controller under every fault axis (:mod:`egcbf.faults`), five levels each, as
``egcbf reproduce`` sweeps; docs/robustness.md from the committed cells.

:mod:`~egcbf.robustness.plan` (axes, levels, controllers, one sweep per level), :mod:`~egcbf.robustness.report`
(the report, from :mod:`~egcbf.robustness.cells`, :mod:`~egcbf.robustness.fixes`, :mod:`~egcbf.robustness.advice`
and :mod:`~egcbf.robustness.figures`).
"""

from .cells import load_cells
from .plan import AXES, Axis, RobustnessConfig, axis, reads_sensing, state_level
from .report import write_report

__all__ = ["AXES", "Axis", "RobustnessConfig", "axis", "load_cells", "reads_sensing", "state_level", "write_report"]
