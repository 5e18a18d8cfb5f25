"""Is a learned CBF a barrier? ``egcbf certify``: sampled closed-loop checks with exact binomial bounds.

    from egcbf.certify import CertifyConfig, sweep, write_report
    cfg = CertifyConfig()            # every shipped learned CBF, the dcbf filter's barrier as the reference
    sweep(cfg)                       # resumable: computes the missing cells into cfg.out
    write_report(cfg, "docs/certificate.md")

One job per module:

* :mod:`~egcbf.certify.barriers`: the barriers scored (a checkpoint's learned CBF, the dcbf filter's hand-crafted
  braking-distance barrier), each with its class-K function;
* :mod:`~egcbf.certify.rollout`: closed-loop rollouts recording every agent's barrier values, collisions and filter
  QP status;
* :mod:`~egcbf.certify.rates`: the counts (containment, misses, false-safe, the decrease condition, invariance,
  conservativeness), pooling and Clopper-Pearson bounds;
* :mod:`~egcbf.certify.plan`: the cells (controller x setting x barriers) and running one;
* :mod:`~egcbf.certify.runner`: the resumable sweep and the stored cells;
* :mod:`~egcbf.certify.report`: docs/certificate.md and its figure.
"""

from .barriers import BrakingBarrier, LearnedBarrier
from .plan import CONTROLLERS, Cell, CertifyConfig, Learned, run_cell
from .rates import RATES, clopper_pearson, count_rates, pool_counts, rate
from .report import VALID_BOUND, verdict, write_report
from .rollout import Trajectory, roll_out
from .runner import load_cells, pending, sweep

__all__ = [
    "CONTROLLERS",
    "RATES",
    "VALID_BOUND",
    "BrakingBarrier",
    "Cell",
    "CertifyConfig",
    "Learned",
    "LearnedBarrier",
    "Trajectory",
    "clopper_pearson",
    "count_rates",
    "load_cells",
    "pending",
    "pool_counts",
    "rate",
    "roll_out",
    "run_cell",
    "sweep",
    "verdict",
    "write_report",
]
