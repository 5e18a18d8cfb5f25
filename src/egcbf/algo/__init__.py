"""Learning graph CBFs and policies: one learner for GCBF, GCBF+, EGCBF and EGCBF+.

``labels`` (finite-horizon safe/unsafe labels), ``buffer`` (trajectory and unsafe-graph buffers), ``qp`` (the
learned-CBF QP target), ``loss`` (the paper's loss), ``learner`` (the update), ``actions`` (normalized controls).
"""

from .actions import control_bounds, control_scale, normalize, policy_control, unnormalize
from .buffer import Samples, TrajectoryBuffer, UnsafeBuffer
from .labels import finite_horizon_labels
from .learner import GraphCBFLearner, LearnedController, rollout_seed
from .loss import cbf_loss
from .qp import CBFQPResult, cbf_jacobian, cbf_lie_derivatives, solve_cbf_qp

__all__ = [
    "CBFQPResult",
    "GraphCBFLearner",
    "LearnedController",
    "Samples",
    "TrajectoryBuffer",
    "UnsafeBuffer",
    "cbf_jacobian",
    "cbf_lie_derivatives",
    "cbf_loss",
    "control_bounds",
    "control_scale",
    "finite_horizon_labels",
    "normalize",
    "policy_control",
    "rollout_seed",
    "solve_cbf_qp",
    "unnormalize",
]
