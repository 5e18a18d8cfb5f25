"""The edge-sum policy head: the command residual as a weighted sum of per-edge geometric vectors.

    r_i = m_node(z_i) + sum_j w_ij ( a_ij dp^_ij + b_ij dv^_ij + c_ij q^_ij )          (agent i's own frame)
    w_ij = softmax_tau( {-d_min,ij}_j  U  {-d_free} )_j
    (a, b, c)_ij = m_edge( [phi_{g_i^-1}(dp_ij, dv_ij, q_ij), |dp_ij|, |dv_ij|, d_min,ij, t_min,ij, kind_j, z_i] )

over agent ``i``'s incoming edges from other agents and LiDAR hits (not its goal). ``dp``, ``dv`` are the sender's
relative position and velocity, ``q = dp + t_min dv`` its relative position at the closest approach within the
horizon (:func:`egcbf.nn.edge_min.closest_approach`), all expressed in the receiver's frame (``phi_{g_i^-1}``: the
network's group; the identity for GCBF); ``x^ = x / sqrt(|x|^2 + eps^2)`` (a unit vector that fades to zero for
a vanishing ``x``). The weights ``w`` are a soft-min over the closest-approach distances (temperature ``tau``),
with a "free" slot at ``d_free``, so the sum reads the neighbours an agent is about to come closest to.

Why (docs/learning.md, "The policy head"): the + methods' teacher is the learned-CBF QP, whose correction of
agent ``i``'s command is ``sum_k lambda_k dh_k/dc_i``; for the soft-min CBF head that gradient is a soft-min
weighted sum over edges of ``d(d_min,ij)/dc_i``, which points along ``-q^_ij`` (scaled by ``t_min``). An MLP on
the graph transformer's pooled features must synthesise that direction from an attention average; this head has
it as a basis vector and learns only invariant coefficients. ``m_edge``'s last layer starts at zero, so an
untrained head adds nothing to ``m_node`` (the paper's head), and the untrained policy is the nominal controller.
Coefficients and basis vectors are invariants of the receiver's frame, so the residual is too, and
``psi_{g_i}`` maps it back to the world as a ``Vector(3)`` (EGCBF+: SE2xR-equivariant, tested).

For an invariant command (``scalar_out = k``: the planar unicycle's turn rate and acceleration) the same sum runs
over learned invariant coefficients directly, ``r_i = m_node(z_i) + sum_j w_ij m_edge(...)`` ``(k,)``: the
correction the QP makes is a soft-min weighted sum over the closest edges there too. In 2-D the vectors are
``Vector(2)`` (``dim``).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from groupcanon import FieldType, Group
from groupcanon.features import Vector

from ..env.graph import KIND_GOAL, KIND_HIT, SwarmGraph
from .edge_min import closest_approach, segment_logsumexp
from .layers import mlp, mlp_on_edges

__all__ = ["EdgeSumHead"]


def _fading_unit(v: Tensor, eps: float) -> Tensor:
    return v / (v.square().sum(-1, keepdim=True) + eps * eps).sqrt()


class EdgeSumHead(nn.Module):
    """``(graph, z (M, hidden), frames) -> r (M, 3)``, the edge part of the residual in each agent's own frame
    (module doc; the caller adds the node MLP ``m_node(z_i)``).

    Args:
        group: the network's group (edge vectors are expressed in the receiver's frame of it).
        hidden: width of ``z``; head_hidden: width of the two hidden layers of ``m_edge``.
        temperature: ``tau`` (m) of the soft-min weights; free_distance: ``d_free`` (m).
        horizon: look-ahead (s) of the closest approach.
        eps: the length (m, m/s) below which a basis vector fades to zero.
        dim: the spatial dimension ``d`` (3 or 2).
        scalar_out: ``None`` (a vector residual in the agent's frame, ``(M, d)``) or ``k`` (``k`` invariant
            coefficients summed directly, ``(M, k)``).
    """

    def __init__(self, group: Group, hidden: int, head_hidden: int, temperature: float, free_distance: float,
                 horizon: float, eps: float = 0.02, dim: int = 3, scalar_out: int | None = None):  # fmt: skip
        super().__init__()
        if not (temperature > 0 and free_distance > 0 and horizon > 0 and eps > 0):
            raise ValueError("EdgeSumHead: temperature, free_distance, horizon and eps must be > 0")
        self.vectors = FieldType(group, [Vector(dim, 3)])
        self.group = group
        self.dim, self.scalar_out = dim, scalar_out
        self.temperature, self.free_distance, self.horizon, self.eps = temperature, free_distance, horizon, eps
        out = 3 if scalar_out is None else scalar_out
        self.edge_mlp = mlp([3 * dim + 5 + hidden, head_hidden, head_hidden, out])
        with torch.no_grad():
            self.edge_mlp[-1].weight.zero_()
            self.edge_mlp[-1].bias.zero_()

    def forward(self, graph: SwarmGraph, z: Tensor, frames: Tensor) -> Tensor:
        sel = graph.edge_kind != KIND_GOAL
        edge_index = graph.edge_index[:, sel]
        dst = edge_index[1]
        d = self.dim
        dp = graph.edge_attr[sel, :d]
        dv = graph.relative_velocity(edge_index).to(dp.dtype)
        approach = closest_approach(dp, dv, self.horizon)
        q = dp + approach[:, 1:2] * dv
        local = self.vectors.act(self.group.inverse(frames).index_select(0, dst), torch.cat((dp, dv, q), -1))
        is_hit = (graph.edge_kind[sel] == KIND_HIT).to(dp.dtype)[:, None]
        norms = torch.cat((dp.norm(dim=-1, keepdim=True), dv.norm(dim=-1, keepdim=True)), -1)
        coef = mlp_on_edges(self.edge_mlp, torch.cat((local, norms, approach, is_hit), -1), z, dst)  # (E', 3 or k)
        if self.scalar_out is None:
            basis = _fading_unit(local.view(-1, 3, d), self.eps)  # (E', [dp, dv, q], xyz)
            vec = (coef[:, :, None] * basis).sum(1)
        else:
            vec = coef
        # soft-min weights over each receiver's edges and its free slot
        score = -approach[:, 0] / self.temperature
        w = torch.exp(
            score
            - segment_logsumexp(score, dst, graph.num_dst, -self.free_distance / self.temperature).index_select(0, dst)
        )
        out = torch.zeros(graph.num_dst, vec.shape[1], dtype=vec.dtype, device=vec.device)
        return out.index_add(0, dst, w[:, None] * vec)

    def extra_repr(self) -> str:
        return f"temperature={self.temperature}, free_distance={self.free_distance}, horizon={self.horizon}"
