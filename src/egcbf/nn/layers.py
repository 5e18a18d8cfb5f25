"""The graph transformer layer of the paper (its "Graphormer" block), written as a plain, unconstrained layer.

    f_v' = mu( f_v + A(F)_v ),   A(F)_v = sum_{u in N(v)} softmax_u( q_v . k_{uv} ) v_{uv}

One layer reads the bipartite graph of :mod:`egcbf.env.graph` (senders: agents, goals, LiDAR hits; receivers:
agents) and returns one feature vector per receiver:

* node encoder: an MLP on the raw 18 node channels (kind one-hot, v, R, w), shared by senders and receivers;
* edge encoder: an MLP on ``[dp, |dp|]`` (the relative position of the sender and its length), or on
  ``[dp, dv, |dp|]`` with the relative velocity (so that one edge's message can read how fast it closes in);
* local multi-head attention over each receiver's incoming edges: ``torch_geometric.nn.TransformerConv`` with the
  encoded edge as ``edge_dim`` input (keys and values see the edge), no root weight (the residual is explicit),
  computed by :class:`egcbf.nn.attention.EdgeAttention` (the same parameters and results, with the projections
  moved to the receivers: no matrix product per edge);
* residual ``z = f_v + A(F)_v`` and a feed-forward block with its own residual, ``out = z + FF(LayerNorm(z))``.

The layer has no notion of a group: equivariance is added from outside by :class:`groupcanon.Canonicalize`,
which feeds it every neighbourhood already expressed in the receiver's frame (see :mod:`egcbf.nn.models`).
Its ``forward`` takes a ``(x_src, x_dst)`` pair, as Canonicalize's ``pair`` mode calls it.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .attention import EdgeAttention

__all__ = ["GraphTransformerLayer", "SiLU", "mlp", "mlp_on_edges"]


class SiLU(nn.SiLU):
    """``nn.SiLU`` that overwrites its input when no gradient flows through it (inference, rollouts).

    On CPU, allocating the output of an activation over ``E`` edges costs several times the activation itself; in
    :func:`mlp` every activation follows a ``Linear`` whose output nothing else holds, so overwriting it is safe.
    With autograd recording (training) it is the ordinary out-of-place SiLU."""

    def forward(self, x: Tensor) -> Tensor:
        return F.silu(x, inplace=not (torch.is_grad_enabled() and x.requires_grad))


def mlp(sizes: list[int], act: type[nn.Module] = SiLU, last_act: bool = False) -> nn.Sequential:
    """A plain MLP ``sizes[0] -> ... -> sizes[-1]`` with ``act`` between layers (and after the last if asked)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or last_act:
            layers.append(act())
    return nn.Sequential(*layers)


def mlp_on_edges(net: nn.Sequential, edge_features: Tensor, node_features: Tensor, dst: Tensor) -> Tensor:
    """``net(cat(edge_features, node_features[dst]))`` ``(E, out)`` for an :func:`mlp` ``net``, without building the
    ``(E, k + d)`` concatenation: the first layer's node block runs once per node and is gathered to the edges
    (``W [a; b_dst] + c = W_a a + (W_b b + c)_dst``), so a per-node context costs ``N``, not ``E``, matrix rows.

    Args:
        net: an MLP whose first module is an ``nn.Linear`` over ``k + d`` inputs.
        edge_features: ``(E, k)``; node_features: ``(N, d)``; dst: ``(E,)`` long, the node of each edge.
    """
    first = net[0]
    k = edge_features.shape[-1]
    if first.in_features != k + node_features.shape[-1]:
        raise ValueError(
            f"mlp_on_edges: the first layer takes {first.in_features} inputs, got {k} edge + "
            f"{node_features.shape[-1]} node features"
        )
    hidden = F.linear(node_features, first.weight[:, k:], first.bias).index_select(0, dst)
    hidden = torch.addmm(hidden, edge_features, first.weight[:, :k].t())
    return net[1:](hidden)


class GraphTransformerLayer(nn.Module):
    """Encoders + local attention + residual + feed-forward (module doc).

    Args:
        node_dim: raw node channels (18 for :data:`egcbf.env.graph.NODE_TYPE`).
        edge_dim: raw edge channels (3: the relative position ``dp``; 6: ``dp`` and the relative velocity ``dv``);
            the length of the first three (``|dp|``) is appended inside.
        hidden: width of every hidden representation and of the output.
        heads: attention heads (``hidden`` must be divisible by ``heads``).
    """

    def __init__(self, node_dim: int, edge_dim: int, hidden: int = 64, heads: int = 4):
        super().__init__()
        if hidden % heads:
            raise ValueError(f"hidden ({hidden}) must be divisible by heads ({heads})")
        self.node_dim, self.edge_dim, self.hidden, self.heads = node_dim, edge_dim, hidden, heads
        self.node_enc = mlp([node_dim, hidden, hidden], last_act=True)
        self.edge_enc = mlp([edge_dim + 1, hidden, hidden], last_act=True)
        self.attn = EdgeAttention(hidden, hidden // heads, heads=heads, concat=True, edge_dim=hidden, root_weight=False)
        self.norm = nn.LayerNorm(hidden)
        self.ff = mlp([hidden, 2 * hidden, hidden])

    def forward(self, x: tuple[Tensor, Tensor], edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        x_src, x_dst = x
        h_src, h_dst = self.node_enc(x_src), self.node_enc(x_dst)
        e = self.edge_enc(torch.cat((edge_attr, edge_attr[:, :3].norm(dim=-1, keepdim=True)), dim=-1))
        z = h_dst + self.attn((h_src, h_dst), edge_index, edge_attr=e)
        return z + self.ff(self.norm(z))
