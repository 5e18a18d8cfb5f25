"""Learning graph CBFs and policies: one learner for GCBF, GCBF+, EGCBF and EGCBF+.

``labels`` (finite-horizon safe/unsafe labels), ``buffer`` (trajectory and unsafe-graph buffers), ``qp`` (the
learned-CBF QP target), ``loss`` (the paper's loss), ``learner`` (the update), ``actions`` (normalized controls),
``interface`` (what the policy, the QP and the loss act on: accelerations or torques), ``edge_qp`` (per-agent QPs
with one row per learned edge barrier: the per-edge target and the run-time filters), ``filtered`` (run-time
safety filters).
"""

from .actions import control_bounds, control_scale, normalize, unnormalize
from .buffer import Samples, TrajectoryBuffer, UnsafeBuffer
from .interface import (
    INTERFACES,
    AccelInterface,
    CommandInterface,
    TorqueInterface,
    make_interface,
    solve_command_qp,
)
from .labels import finite_horizon_labels
from .learner import GraphCBFLearner, LearnedController, policy_command, rollout_seed
from .loss import cbf_loss
from .qp import CBFQPResult, cbf_jacobian, solve_cbf_qp

__all__ = [
    "INTERFACES",
    "AccelInterface",
    "CBFQPResult",
    "CommandInterface",
    "GraphCBFLearner",
    "LearnedController",
    "Samples",
    "TorqueInterface",
    "TrajectoryBuffer",
    "UnsafeBuffer",
    "cbf_jacobian",
    "cbf_loss",
    "control_bounds",
    "control_scale",
    "finite_horizon_labels",
    "make_interface",
    "normalize",
    "policy_command",
    "rollout_seed",
    "solve_cbf_qp",
    "solve_command_qp",
    "unnormalize",
]
