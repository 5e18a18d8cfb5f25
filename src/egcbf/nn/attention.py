"""``EdgeAttention``: PyG's ``TransformerConv`` with the same parameters and math, restructured for speed.

The graph layer's attention is ``torch_geometric.nn.TransformerConv(root_weight=False, concat=True, edge_dim=...)``:

    q_i = W_q x_i + b_q,   k_ij = W_k x_j + b_k + W_e e_ij,   v_ij = W_v x_j + b_v + W_e e_ij
    a_ij = softmax_j( q_i . k_ij / sqrt(C) )   (per head, over the receiver's incoming edges)
    out_i = sum_j a_ij v_ij

PyG computes keys and values at the sources, gathers them to the edges (one copy each), projects the edge features
once more per edge, normalizes the attention weights per edge and scatters. :class:`EdgeAttention` subclasses it
(the same ``lin_query``, ``lin_key``, ``lin_value``, ``lin_edge`` parameters, so state dicts are interchangeable)
and computes the same quantities with fewer passes over the ``E`` edges:

* keys and values in one matrix product, the edge term ``W_e e`` computed once and added to both in place;
* no gather at all when the sources are already one row per edge in edge order (``groupcanon``'s pair mode hands
  the layer exactly that: each sender as its receiver sees it);
* the softmax normalized after aggregation, at the receivers (``sum_j exp(s_ij - m_i) v_ij / sum_j exp(s_ij - m_i)``
  with the same ``+1e-16`` in the denominator as PyG's ``softmax``).

The results equal ``TransformerConv.forward`` up to float rounding (tested); any call outside the fast path
(attention weights requested, dropout while training, a root weight, head averaging, a sparse adjacency, no edge
features) goes to ``TransformerConv.forward`` itself.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.nn import functional as F
from torch_geometric.nn import TransformerConv

__all__ = ["EdgeAttention"]


def _is_edge_aligned(src: Tensor, num_src: int) -> bool:
    """Whether source row ``e`` is the sender of edge ``e`` (``src == arange(E)``)."""
    num_edges = src.shape[0]
    return num_src == num_edges and torch.equal(src, torch.arange(num_edges, device=src.device))


class EdgeAttention(TransformerConv):
    """``TransformerConv`` (same constructor and parameters) with a faster forward for the graph layer's case.

    Call as ``attn((x_src (N_src, in), x_dst (N_dst, in)), edge_index (2, E), edge_attr (E, edge_dim))``; returns
    ``(N_dst, heads * out_channels)``. Receivers without incoming edges get zeros, as in PyG.
    """

    def _fast_path(self, edge_index, edge_attr, return_attention_weights) -> bool:
        return (
            return_attention_weights is None
            and isinstance(edge_index, Tensor)
            and edge_attr is not None
            and self.lin_edge is not None
            and self.concat
            and not self.root_weight
            and not (self.training and self.dropout > 0)
        )

    def forward(self, x, edge_index, edge_attr=None, return_attention_weights=None):
        if not self._fast_path(edge_index, edge_attr, return_attention_weights):
            return super().forward(x, edge_index, edge_attr, return_attention_weights)
        x_src, x_dst = (x, x) if isinstance(x, Tensor) else x
        heads, channels = self.heads, self.out_channels
        width = heads * channels
        src, dst = edge_index[0], edge_index[1]
        n_dst = x_dst.shape[0]

        weight = torch.cat((self.lin_key.weight, self.lin_value.weight))
        bias = torch.cat((self.lin_key.bias, self.lin_value.bias))
        kv = F.linear(x_src, weight, bias)  # (N_src, 2 * width): keys | values
        if not _is_edge_aligned(src, x_src.shape[0]):
            kv = kv.index_select(0, src)
        edge_term = self.lin_edge(edge_attr)  # (E, width), added to keys and values alike
        kv = kv.view(-1, 2, width).add_(edge_term[:, None, :]).view(-1, 2 * width)  # no backward reads kv
        key, value = kv[:, :width], kv[:, width:]

        query = self.lin_query(x_dst).index_select(0, dst)  # (E, width)
        score = (query * key).view(-1, heads, channels).sum(-1) / math.sqrt(channels)  # (E, heads)
        index = dst[:, None].expand_as(score)
        top = score.new_full((n_dst, heads), -math.inf)
        top = top.scatter_reduce(0, index, score.detach(), "amax", include_self=True)
        weight_e = torch.exp(score - top.index_select(0, dst))  # (E, heads)
        denominator = score.new_zeros(n_dst, heads).index_add(0, dst, weight_e) + 1e-16
        messages = value.view(-1, heads, channels) * weight_e[..., None]
        out = value.new_zeros(n_dst, heads, channels).index_add(0, dst, messages)
        return (out / denominator[..., None]).view(n_dst, width)
