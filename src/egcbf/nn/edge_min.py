"""The soft-min CBF head: ``h_i`` from learned per-edge barrier values, aggregated by a smooth minimum.

    b_ij = (d_min,ij - D) + m( [phi_{g_i^-1}(dp_ij, dv_ij), |dp_ij|, d_min,ij, t_min,ij, kind_j, z_i] )
    h_i  = tanh( softmin_tau( {b_ij}_j  U  {b_free} ) ),   softmin_tau(b) = -tau log sum_j exp(-b_j / tau)

over agent's ``i`` incoming edges from other agents and LiDAR hits (not its goal). ``dp``, ``dv`` are the relative
position and velocity of the sender, expressed in the receiver's frame (``phi_{g_i^-1}``: the group of the
network; the identity for GCBF), ``d_min``, ``t_min`` their closest approach within ``horizon`` seconds
(:func:`closest_approach`, invariant), ``z_i`` the receiver's graph-transformer features (its whole
neighbourhood: how crowded it is). ``m`` is an MLP whose last layer starts at zero, so an untrained CBF is the
soft-min of the closest-approach distances minus ``D``: a barrier whose gradient already points away from the
neighbour that is closing in. ``b_free = 1 - D`` is the value with nothing in range.

Why (docs/learning.md, "Why the learned CBF-QP teacher failed"): a CBF trained on safe/unsafe labels alone is free
to have any gradient in the velocities, and the learned-CBF QP steers along that gradient; this head starts from a
barrier whose gradient is already right (the measurements are in docs/learning.md). Every term is an invariant of
the receiver's frame, so the head keeps the CBF SE2xR-invariant (tested).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from groupcanon import FieldType, Group
from groupcanon.features import Vector

from ..env.graph import KIND_GOAL, KIND_HIT, SwarmGraph
from .layers import mlp, mlp_on_edges

__all__ = ["EdgeMinHead", "closest_approach", "edge_features", "segment_logsumexp"]


def segment_logsumexp(score: Tensor, dst: Tensor, num: int, free: float) -> Tensor:
    """``(num,)``: ``log(exp(free) + sum_{j: dst_j = i} exp(score_j))`` per receiver ``i``, stabilised by the
    (detached) per-receiver maximum. ``free`` is the score of a slot every receiver has (the value with nothing
    in range), so receivers without edges get ``free``."""
    shift = torch.full((num,), free, dtype=score.dtype, device=score.device)
    shift = shift.scatter_reduce(0, dst, score.detach(), "amax", include_self=True)
    total = torch.exp(free - shift).index_add(0, dst, torch.exp(score - shift.index_select(0, dst)))
    return torch.log(total) + shift


def closest_approach(dp: Tensor, dv: Tensor, horizon: float) -> Tensor:
    """``(E, 2)``: the distance ``d_min`` and time ``t_min`` of closest approach of two points at relative
    position ``dp`` and velocity ``dv`` moving straight, within ``[0, horizon]`` seconds:
    ``t_min = clip(-dp . dv / |dv|^2, 0, horizon)``, ``d_min = |dp + t_min dv|``. Invariant under rotations and
    translations (norms and dot products of vectors), so an invariant edge feature."""
    t = (-(dp * dv).sum(-1, keepdim=True) / dv.square().sum(-1, keepdim=True).clamp_min(1e-6)).clamp(0.0, horizon)
    return torch.cat(((dp + t * dv).norm(dim=-1, keepdim=True), t), -1)


def edge_features(
    graph: SwarmGraph,
    frames: Tensor,
    group: Group,
    vectors: FieldType,
    horizon: float,
    dp: Tensor | None = None,
    dv: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Per agent and LiDAR-hit edge: ``[dp, dv (receiver's frame), |dp|, d_min, t_min, is_hit]`` ``(E', 10)``, and
    the receiver of each edge ``(E',)``. All invariant under the group. (The head's MLP also reads the receiver's
    features ``z_i``, appended by :func:`egcbf.nn.layers.mlp_on_edges`.)

    ``dp``, ``dv`` ``(E', d)``: the world-frame relative positions and velocities of these edges (sender minus
    receiver), to differentiate through; by default read from the graph."""
    sel = graph.edge_kind != KIND_GOAL
    edge_index = graph.edge_index[:, sel]
    dst = edge_index[1]
    if dp is None:
        dp = graph.edge_attr[sel]
    if dv is None:
        dv = graph.relative_velocity(edge_index).to(dp.dtype)
    approach = closest_approach(dp, dv, horizon)
    local = vectors.act(group.inverse(frames).index_select(0, dst), torch.cat((dp, dv), -1))
    is_hit = (graph.edge_kind[sel] == KIND_HIT).to(dp.dtype)[:, None]
    return torch.cat((local, dp.norm(dim=-1, keepdim=True), approach, is_hit), -1), dst


class EdgeMinHead(nn.Module):
    """``(graph, z (M, hidden), frames) -> h (M,)`` (module doc).

    Args:
        group: the network's group (edge vectors are expressed in the receiver's frame of it).
        hidden: width of ``z``; head_hidden: width of the two hidden layers of ``m``.
        distance: ``D`` (m), the closest-approach distance at which the prior barrier is 0.
        temperature: ``tau`` (m) of the smooth minimum.
        horizon: look-ahead (s) of the closest approach.
        dim: the spatial dimension ``d`` of the edge vectors (3: quadrotor, 2: planar robots).
        correction_bound: ``None`` (the correction ``m`` as is) or ``B > 0`` (m): ``m`` replaced by
            ``B tanh(m / B)``, so every ``b_ij`` stays within ``B`` of its prior.
    """

    def __init__(self, group: Group, hidden: int, head_hidden: int, distance: float, temperature: float,
                 horizon: float, dim: int = 3, correction_bound: float | None = None):  # fmt: skip
        super().__init__()
        if not (distance > 0 and temperature > 0 and horizon > 0):
            raise ValueError("EdgeMinHead: distance, temperature and horizon must be > 0")
        if correction_bound is not None and not correction_bound > 0:
            raise ValueError("EdgeMinHead: correction_bound must be > 0 or None")
        self.correction_bound = correction_bound
        self.vectors = FieldType(group, [Vector(dim, 2)])
        self.group = group
        self.dim = dim
        self.distance, self.temperature, self.horizon = distance, temperature, horizon
        # per edge: dp and dv in the receiver's frame (2 d), |dp|, closest approach (d_min, t_min), is-a-hit
        self.edge_mlp = mlp([2 * dim + 3 + 1 + hidden, head_hidden, head_hidden, 1])
        with torch.no_grad():
            self.edge_mlp[-1].weight.zero_()
            self.edge_mlp[-1].bias.zero_()

    def edge_values(
        self, graph: SwarmGraph, z: Tensor, frames: Tensor, dp: Tensor | None = None, dv: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """The per-edge barrier values ``b_ij`` ``(E',)`` (m) over the agent and LiDAR-hit edges (the graph's
        edges of kind other than goal, in order) and their receivers ``(E',)``; ``dp``, ``dv`` as in
        :func:`edge_features` (pass tensors that require grad to get ``db/d dp``, ``db/d dv``)."""
        feats, dst = edge_features(graph, frames, self.group, self.vectors, self.horizon, dp, dv)
        approach = feats[:, 2 * self.dim + 1 : 2 * self.dim + 3]
        correction = mlp_on_edges(self.edge_mlp, feats, z, dst).squeeze(-1)
        if self.correction_bound is not None:
            correction = self.correction_bound * torch.tanh(correction / self.correction_bound)
        return approach[:, 0] - self.distance + correction, dst

    def forward(self, graph: SwarmGraph, z: Tensor, frames: Tensor) -> Tensor:
        b, dst = self.edge_values(graph, z, frames)
        tau = self.temperature
        return -tau * segment_logsumexp(-b / tau, dst, graph.num_dst, -(1.0 - self.distance) / tau)

    def extra_repr(self) -> str:
        bound = "" if self.correction_bound is None else f", correction_bound={self.correction_bound}"
        return f"distance={self.distance}, temperature={self.temperature}, horizon={self.horizon}{bound}"
