"""Per-edge CBF-QPs: every agent's QP over its own acceleration, one row per barrier of an edge it senses.

The soft-min CBF head (:class:`egcbf.nn.edge_min.EdgeMinHead`) computes ``h_i`` as a smooth minimum of per-edge
barriers ``b_ij`` (m). Enforcing the CBF condition on every edge's barrier, instead of on their smooth minimum,
is the standard treatment of a barrier that is a minimum of several (the condition on each piece implies it on
the minimum), and it gives each agent one row per threat instead of one row for the worst of them. Each agent
``i`` solves::

    min  1/2 ||a_i - a_ref,i||^2 + 1/2 w2 s_i^2 + w1 s_i
    s.t. n_k . a_i + s_i >= r_k      (one row per agent neighbour and LiDAR hit: :func:`edge_rows`)
         the command box of the interface, in the agent's yaw frame;  s_i >= 0

Pair rows are split in halves (the ``dCBF-QP``'s convention), so no agent needs another's command. All ``B N`` QPs
are one batch of the dense interior-point solver (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`, the learner's
target) or of the exact batched dual active-set method
(:func:`egcbf.qp.dense_active_set.solve_dense_batch_active_set`, the filters' default: ``solver`` of
:func:`edge_qp_commands`); an agent whose QP fails or whose solution fails the check brakes. Used by the run-time
filters (:mod:`egcbf.control.filters`, ``cbf`` and ``prior``) and by the learner's per-edge QP target
(``TrainConfig.qp_constraints = "edges"``).

Robots driven through their raw control (:class:`~egcbf.algo.interface.ControlInterface`: GCBF+'s double
integrator and linear drone, the cars) get the same rows through their control-affine acceleration
``a_i = A_i + B_i u_i`` (:func:`edge_qp_controls`), each agent's QP over its own normalized control in the box that
acts at its state. With frame-averaged networks (the point masses' quarter turns) each edge's barrier is averaged
over the receiver's frames (:func:`edge_barriers`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from groupcanon.groups import Trivial

from ..env.graph import KIND_AGENT, KIND_GOAL, SwarmGraph
from ..nn.edge_min import EdgeMinHead, closest_approach
from ..nn.models import CBFNet, frames_for
from ..qp.dense_active_set import solve_dense_batch_active_set
from ..qp.dense_qp import assemble_decentralized, solve_dense_batch_ipm, verified
from ..qp.sparse_qp import SlackPenalty
from ..robots.point_mass_qp import acceleration_affine, solve_own_qps
from ..robots.quadrotor.barriers import AccelBounds, bound_rows
from ..robots.quadrotor.cbf_qp import brake_acceleration
from .interface import AccelInterface, ControlInterface

__all__ = ["BRAKE_GAIN", "SLACK_TOL", "EdgeBarriers", "EdgeRows", "edge_barriers", "edge_qp_commands",
           "edge_qp_controls", "edge_rows"]  # fmt: skip

#: an agent whose QP fails gets ``a = -BRAKE_GAIN v`` (1/s), within the box's inscribed ball
BRAKE_GAIN = 4.0
#: a solution "needs slack" above this (m/s^2); also the tolerance of the solution check
SLACK_TOL = 1e-4
#: the batched solvers of the per-agent QPs (:func:`edge_qp_commands`' ``solver``)
SOLVERS = {"ipm": solve_dense_batch_ipm, "active_set": solve_dense_batch_active_set}


@dataclass
class EdgeRows:
    """Per-agent rows ``normal[r] . a_{owner[r]} >= rhs[r]`` (world frame, m/s^2) and their barrier values."""

    owner: Tensor  # (R,) receiver row in the graph
    normal: Tensor  # (R, 3)
    rhs: Tensor  # (R,)
    value: Tensor  # (R,) b (m)
    gain: Tensor  # (R,) |g_v| (s): the row is the edge's condition divided by it (and halved for agent edges)
    edge: Tensor  # (R,) the row's edge, an index into the graph's edges of kind other than goal
    dropped: int  # edges whose row was dropped (|g_v| too small to act on)


@dataclass
class EdgeBarriers:
    """The per-edge barriers of a graph's agent and LiDAR-hit edges (its edges of kind other than goal, in order),
    float64: ``value`` ``b`` (m), its gradients ``grad_p = db/d dp`` and ``grad_v = db/d dv`` ``(E', d)`` (``dp``,
    ``dv`` sender minus receiver, world frame), ``dv`` itself, each edge's ``receiver`` and ``kind`` ``(E',)``."""

    receiver: Tensor
    kind: Tensor
    value: Tensor
    grad_p: Tensor
    grad_v: Tensor
    dv: Tensor


def edge_barriers(
    graph: SwarmGraph, cbf: CBFNet | None = None, distance: float = 0.25, horizon: float = 1.0
) -> EdgeBarriers:
    """The ``cbf``'s per-edge barriers (``cbf`` given) or the prior's ``b = d_min - distance`` (``cbf = None``) of
    every agent and LiDAR-hit edge of ``graph``, with their gradients (:class:`EdgeBarriers`).

    Agents that carry frame sets (the point masses' quarter turns, :meth:`SwarmGraph.expand_frames`) get each
    edge's barrier averaged over their frames, as the CBF averages its value: invariant under the finite group."""
    sel = graph.edge_kind != KIND_GOAL
    ei = graph.edge_index[:, sel]
    kind = graph.edge_kind[sel]
    dp = graph.edge_attr[sel].detach().to(torch.float64).requires_grad_(True)
    dv = graph.relative_velocity(ei).detach().to(torch.float64).requires_grad_(True)
    with torch.enable_grad():
        if cbf is None:
            b = closest_approach(dp, dv, horizon)[:, 0] - distance
        else:
            head = cbf.head
            if not isinstance(head, EdgeMinHead) or cbf.config.cbf_z_symmetric:
                raise ValueError(
                    "the 'cbf' filter needs the soft-min CBF head (cbf_head = 'edge_min', cbf_z_symmetric = False): "
                    "it reads the head's per-edge barriers; use --filter prior or dcbf for this checkpoint"
                )
            f = 1 if isinstance(cbf.encoder.group, Trivial) else graph.frames_per_agent
            g = graph.expand_frames() if f > 1 else graph  # each edge copied f times in a row, one per frame
            with torch.no_grad():  # z_i: the receiver's neighbourhood summary, held fixed over the step
                z = cbf.encoder(g)
            frames = frames_for(cbf.encoder.group, g)
            dp_f, dv_f = (t.repeat_interleave(f, 0).to(z.dtype) for t in (dp, dv))
            b, _ = head.edge_values(g, z, frames, dp_f, dv_f)
            b = b.to(torch.float64).view(-1, f).mean(1)
        gp, gv = torch.autograd.grad(b.sum(), (dp, dv))
    return EdgeBarriers(ei[1], kind, b.detach(), gp, gv, dv.detach())


def own_share(e: EdgeBarriers, alpha: float, margin: float) -> Tensor:
    """``(E',)``: what the receiver's own acceleration term ``-gv . a_i`` must reach so that
    ``db/dt + alpha (b - margin) >= 0`` with ``db/dt = gp . dv + gv . (a_j - a_i)``: half of it on agent edges (the
    neighbour keeps the other half), all of it on LiDAR hits (static)."""
    rhs = -alpha * (e.value - margin) - (e.grad_p * e.dv).sum(-1)
    return torch.where(e.kind == KIND_AGENT, 0.5 * rhs, rhs)


def edge_rows(
    graph: SwarmGraph, alpha: float, margin: float, cbf: CBFNet | None = None, distance: float = 0.25,
    horizon: float = 1.0,
) -> EdgeRows:  # fmt: skip
    """The ``cbf`` (``cbf`` given) or ``prior`` (``cbf = None``: ``b = d_min - distance``) rows of every agent
    (module doc), from the agent and LiDAR-hit edges of ``graph``. float64 inside (the rows' gradients)."""
    e = edge_barriers(graph, cbf, distance, horizon)
    b, gv = e.value, e.grad_v
    rhs = own_share(e, alpha, margin)
    norm = gv.norm(dim=-1)
    keep = norm > 1e-6
    normal = -gv[keep] / norm[keep, None]
    edge = keep.nonzero()[:, 0]
    return EdgeRows(e.receiver[keep], normal, rhs[keep] / norm[keep], b[keep], norm[keep], edge, int((~keep).sum()))


def edge_qp_controls(
    graph: SwarmGraph, x: Tensor, itf: ControlInterface, c_ref: Tensor, *, alpha: float, margin: float,
    cbf: CBFNet | None, distance: float, horizon: float, penalty: SlackPenalty | None = None,
    slack_tol: float = SLACK_TOL, min_authority: float = 1e-9,
) -> tuple[Tensor, dict]:  # fmt: skip
    """The per-edge QPs of a robot driven through its raw control (:class:`ControlInterface`; the point masses of
    relative degree 2 and the cars): every agent's QP over its own normalized control ``c`` around ``c_ref``
    ``(B, N, k)``, in the box that acts at its state (:meth:`ControlInterface.state_bounds`), one row
    ``db_ij/dt + alpha (b_ij - margin) >= 0`` per agent neighbour (halved) and LiDAR hit, with the world
    acceleration ``a_i = A_i + B_i s c_i`` of the robot's control-affine model
    (:func:`egcbf.robots.point_mass_qp.acceleration_affine`) and each neighbour's acceleration left to its own half.
    Solved by :func:`egcbf.robots.point_mass_qp.solve_own_qps`; an agent whose QP fails keeps ``c_ref`` projected
    into its box (counted). Returns the commands ``(B, N, k)`` float64 and the counts of :func:`edge_qp_commands`.

    ``min_authority``: a row is dropped (counted in ``rows_dropped``) when a unit of normalized control changes its
    ``db/dt`` by no more than this (m/s per unit): a barrier the agent barely moves (a separating pair, whose
    closest approach is now) would otherwise demand a huge push, and the agent's one slack would then relax all its
    rows. The Dubins car's runs use ``0.1`` (``TrainConfig.qp_edge_min_authority``; why: docs/robots.md)."""
    robot = itf.robot
    if robot.kinematic:
        raise ValueError(f"the per-edge QPs need a robot whose velocity is part of its state, not the {robot.name} "
                         "(its control is its velocity)")  # fmt: skip
    penalty = penalty or SlackPenalty()
    b, n = x.shape[:2]
    m = b * n
    xf = x.reshape(m, -1).detach().to(torch.float64)
    e = edge_barriers(graph, cbf, distance, horizon)
    drift, gain = acceleration_affine(robot, xf)  # (M, d), (M, d, nu)
    # own part of db/dt: -gv . (A_i + B_i s c_i) >= own share, with u = s c
    coef = -(e.grad_v[:, None, :] @ gain[e.receiver])[:, 0] * itf.scale(xf)
    bound = own_share(e, alpha, margin) + (e.grad_v * drift[e.receiver]).sum(-1)
    norm = coef.norm(dim=-1)
    keep = norm > min_authority
    i, coef, bound = e.receiver[keep].cpu(), (coef[keep] / norm[keep, None]).cpu(), (bound[keep] / norm[keep]).cpu()
    lo, hi = (t.to(torch.float64).expand(m, -1).contiguous() for t in itf.state_bounds(xf))
    target = c_ref.reshape(m, -1).detach().to(torch.float64).clamp(lo, hi)
    c, failed = solve_own_qps(target, lo, hi, i, coef, bound, penalty.w1, penalty.w2)
    viol = (bound - (coef * c[i]).sum(-1)).clamp_min(0)
    per_agent = torch.zeros(m, dtype=torch.float64).index_reduce_(0, i, viol, "amax", include_self=True)
    info = {
        "num_slack": int((per_agent > slack_tol).sum()),
        "num_failed": int(failed.sum()),
        "max_slack": float(per_agent.max()) if m else 0.0,
        "rows_dropped": int((~keep).sum()),
    }
    return c.view(b, n, -1).to(c_ref.device), info


def edge_qp_commands(
    graph: SwarmGraph, x: Tensor, itf: AccelInterface, a_ref: Tensor, *, alpha: float, margin: float,
    cbf: CBFNet | None, distance: float, horizon: float, penalty: SlackPenalty | None = None,
    brake_gain: float = BRAKE_GAIN, slack_tol: float = SLACK_TOL, solver: str = "ipm",
) -> tuple[Tensor, dict]:  # fmt: skip
    """Every agent's per-edge QP (module doc) around ``a_ref`` ``(B, N, 3)`` (world accelerations, m/s^2) for the
    swarm states ``x`` ``(B, N, 18)`` whose graph is ``graph``; rows from ``cbf``'s per-edge barriers, or from the
    prior ``d_min - distance`` when ``cbf`` is None (:func:`edge_rows`). ``solver`` (:data:`SOLVERS`): ``"ipm"``
    (default: the learner's target, :func:`egcbf.qp.dense_qp.solve_dense_batch_ipm` on ``a_ref``'s device) or
    ``"active_set"`` (exact, numpy: :func:`egcbf.qp.dense_active_set.solve_dense_batch_active_set`; the filters').

    Returns the accelerations ``(B, N, 3)`` float64 and counts: ``num_slack`` (agents whose QP needed slack above
    ``slack_tol``), ``num_failed`` (agents given the braking fallback ``a = -brake_gain v``), ``max_slack``,
    ``rows_dropped``, and per agent ``slack_mask`` / ``failed_mask`` ``(B, N)`` numpy bool (the agents counted in
    ``num_slack`` / ``num_failed``)."""
    if solver not in SOLVERS:
        raise ValueError(f"edge_qp_commands: solver must be one of {tuple(SOLVERS)}, got {solver!r}")
    penalty = penalty or SlackPenalty()
    b, n = x.shape[:2]
    m = b * n
    rows = edge_rows(graph, alpha, margin, cbf, distance, horizon)
    box = AccelBounds(itf.horizontal, -itf.down, itf.up, polygon=2)  # the interface's yaw-frame box
    rot = x[..., 3:12].reshape(m, 9).detach().to(torch.float64).cpu().numpy()
    bC, blo, bhi = bound_rows(rot, box)
    qps = assemble_decentralized(
        a_ref.reshape(m, 3).detach().to(torch.float64).cpu().numpy(), rows.owner.cpu().numpy(),
        rows.normal.cpu().numpy(), rows.rhs.cpu().numpy(), bC, blo, bhi, penalty,
    )  # fmt: skip
    z, ok, _ = SOLVERS[solver](qps, device=a_ref.device)
    good = verified(qps, z, ok, slack_tol)
    a, slack = z[:, :3].copy(), z[:, 3]
    if not good.all():
        v = x[..., 12:15].reshape(m, 3).detach().to(torch.float64).cpu().numpy()
        a[~good] = brake_acceleration(v[~good], box, brake_gain)
        slack = np.where(good, slack, 0.0)
    info = {
        "num_slack": int((slack > slack_tol).sum()),
        "num_failed": int((~good).sum()),
        "max_slack": float(slack.max(initial=0.0)),
        "rows_dropped": rows.dropped,
        "slack_mask": (slack > slack_tol).reshape(b, n),
        "failed_mask": (~good).reshape(b, n),
    }
    return torch.as_tensor(a, dtype=torch.float64, device=a_ref.device).view(b, n, 3), info
