"""``EdgeAttention``: PyG's ``TransformerConv`` with the same parameters and results, computed at the receivers.

The graph layer's attention is ``torch_geometric.nn.TransformerConv(root_weight=False, concat=True, edge_dim=...)``;
per head ``h`` (``C`` channels, ``W_*h`` the head's ``C`` rows of each projection):

    q_ih = (W_qh x_i + b_qh) / sqrt(C),   k_ijh = W_kh x_j + b_kh + W_eh e_ij,   v_ijh = W_vh x_j + b_vh + W_eh e_ij
    out_ih = sum_j w_ijh v_ijh / (S_ih + 1e-16),   w_ijh = exp(s_ijh - max_j s_ijh),   S_ih = sum_j w_ijh,
    s_ijh = q_ih . k_ijh

(``sum_j`` runs over the receiver's incoming edges; ``w / (S + 1e-16)`` is PyG's ``softmax``). PyG computes a key
and a value per edge: with one source row per edge (``groupcanon``'s pair mode, each sender as its receiver sees
it) that is an ``E x in x 2 heads*C`` matrix product, plus ``E x edge_dim x heads*C`` for ``W_e e``. Both
projections are linear, so :class:`EdgeAttention` moves them to the receivers instead:

    s_ijh  = (W_kh^T q_ih) . x_j + (W_eh^T q_ih) . e_ij + q_ih . b_kh
    out_ih = ( W_vh (sum_j w_ijh x_j) + W_eh (sum_j w_ijh e_ij) + b_vh S_ih ) / (S_ih + 1e-16)

(``q_ih . b_kh`` is the same for all ``j`` and cancels in the softmax; it is added anyway, one number per score,
so that the key bias gets PyG's gradient, zero up to rounding, and optimizers treat it as before.)

The dense products run on the ``N`` receivers (the query projections ``W_kh^T q_ih``, ``W_eh^T q_ih`` of width
``in`` and ``edge_dim``, and the output projections); per edge only dot products (scores) and weighted sums over
the ``in + edge_dim`` input channels remain. Both are products with the sparse ``(N heads, E)`` matrix whose row
``(i, h)`` holds receiver ``i``'s edges (:class:`_Pattern`; stored row after row, receiver-major, so one
receiver's edge rows are read once for all its heads):

* scores: the sampled product ``Q X^T`` on the pattern, ``s[(i, h), j] = Q[(i, h)] . X[j]``
  (``torch.sparse.sampled_addmm``; :class:`_SampledDot`);
* weighted sums: the sparse matrix of attention weights times ``X`` (``F.embedding_bag`` with per-sample weights,
  one bag per row; :class:`_RowSums`).

Each is the other's adjoint, with the transpose ``(E, N heads)`` for the gradient of ``X``
(:class:`_ColumnSums`, also ``embedding_bag``), so gradients cost about as much as the forward and are
differentiable again (double backward).

How it compares with the per-edge path kept below, and with the layouts tried and dropped (a padded per-receiver
``(N, max degree, in)`` layout, ``torch.sparse.mm`` for the weighted sums): docs/benchmarks.md.

The results equal ``TransformerConv.forward`` up to float rounding (tested). The receiver-side path runs on CPU in
float32 and float64; on other devices the per-edge path (:meth:`EdgeAttention._forward_per_edge`: keys and values
in one product, no gather when the sources are edge-aligned, the softmax normalized after aggregation). Any call
outside their case (attention weights requested, dropout while training, a root weight, head averaging, a sparse
adjacency, no edge features, no edges, parameters not yet initialized) goes to ``TransformerConv.forward`` itself.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor
from torch.autograd import Function
from torch.nn import functional as F
from torch.nn.parameter import UninitializedParameter
from torch_geometric.nn import TransformerConv

__all__ = ["EdgeAttention"]


def _is_edge_aligned(src: Tensor, num_src: int) -> bool:
    """Whether source row ``e`` is the sender of edge ``e`` (``src == arange(E)``); ``False`` while exporting
    (``torch.export`` records no value-dependent branch; the gather is then always made, with the same result)."""
    if torch.compiler.is_exporting():
        return False
    num_edges = src.shape[0]
    return num_src == num_edges and torch.equal(src, torch.arange(num_edges, device=src.device))


class _Pattern:
    """The receiver-major pattern of the sparse ``(n heads, E)`` matrix: row ``i * heads + h`` holds receiver ``i``'s
    edges in increasing edge order. Values on it (``(heads * E,)``: scores, attention weights) are stored row after
    row.

    Attributes:
        crow: ``(n * heads + 1,)`` row offsets; col: ``(heads * E,)`` the edge of each value; row: ``(heads * E,)``
            the row of each value.
    """

    def __init__(self, dst: Tensor, n: int, heads: int):
        num_edges, device = dst.shape[0], dst.device
        self.dst, self.heads, self.size = dst, heads, (n * heads, num_edges)
        deg = torch.bincount(dst, minlength=n)
        self.first = torch.cumsum(deg, 0) - deg  # each receiver's first position in receiver order
        sorted_ = num_edges < 2 or bool((dst[1:] >= dst[:-1]).all())
        self.order = None if sorted_ else torch.argsort(dst, stable=True)  # edges in receiver order
        lengths = deg.repeat_interleave(heads)
        self.crow = lengths.new_zeros(n * heads + 1)
        torch.cumsum(lengths, 0, out=self.crow[1:])
        rows = torch.arange(n * heads, device=device)
        self.row = torch.repeat_interleave(rows, lengths, output_size=heads * num_edges)
        # the k-th value of row (i, h) is edge number first_i + k in receiver order
        shift = self.crow[:-1] - self.first.repeat_interleave(heads)
        position = torch.arange(heads * num_edges, device=device) - shift.index_select(0, self.row)
        self.col = position if self.order is None else self.order.index_select(0, position)
        self._transpose: tuple[Tensor, Tensor, Tensor] | None = None

    def transpose(self) -> tuple[Tensor, Tensor, Tensor]:
        """The ``(E, n heads)`` transpose (row ``e``: its receiver's ``heads`` rows), built on first use (backward
        passes only): ``(offsets (E + 1,), columns (E * heads,), gather (E * heads,))``, where ``gather`` takes
        values from the pattern's order to the transpose's."""
        if self._transpose is None:
            num_edges, heads, device = self.size[1], self.heads, self.dst.device
            rank = torch.arange(num_edges, device=device)  # each edge's position in receiver order
            if self.order is not None:
                rank = torch.empty_like(rank).index_copy_(0, self.order, rank)
            rank = rank - self.first.index_select(0, self.dst)  # ... among its receiver's edges
            cols = (self.dst[:, None] * heads + torch.arange(heads, device=device)).view(-1)
            gather = (self.crow.index_select(0, cols).view(num_edges, heads) + rank[:, None]).view(-1)
            offsets = torch.arange(0, heads * num_edges + 1, heads, device=device)
            self._transpose = (offsets, cols, gather)
        return self._transpose


def _sampled_dot(pattern: _Pattern, a: Tensor, b: Tensor) -> Tensor:
    """``(heads * E,)``: ``a[row] . b[col]`` on the pattern; ``a`` ``(n heads, d)``, ``b`` ``(E, d)``."""
    with warnings.catch_warnings():  # torch's one-time "sparse CSR support is in beta" notice
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state", category=UserWarning)
        zeros = a.new_zeros(pattern.col.shape[0])
        sparse = torch.sparse_csr_tensor(pattern.crow, pattern.col, zeros, pattern.size, check_invariants=False)
    return torch.sparse.sampled_addmm(sparse, a.contiguous(), b.contiguous().t(), beta=0.0).values()


def _row_sums(pattern: _Pattern, values: Tensor, b: Tensor) -> Tensor:
    """``(n heads, d)``: ``sum_k values[k] b[col[k]]`` over each row's values (the sparse matrix times ``b``)."""
    crow, col = pattern.crow, pattern.col
    return F.embedding_bag(col, b, crow, mode="sum", per_sample_weights=values, include_last_offset=True)


def _column_sums(pattern: _Pattern, values: Tensor, a: Tensor) -> Tensor:
    """``(E, d)``: ``sum_k values[k] a[row[k]]`` over each column's values (the transposed matrix times ``a``)."""
    offsets, cols, gather = pattern.transpose()
    weights = values.index_select(0, gather)
    return F.embedding_bag(cols, a, offsets, mode="sum", per_sample_weights=weights, include_last_offset=True)


class _SampledDot(Function):
    """``(heads * E,)`` scores ``a[row] . b[col]``; ``a`` ``(n heads, d)``, ``b`` ``(E, d)``."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, pattern: _Pattern) -> Tensor:
        ctx.save_for_backward(a, b)
        ctx.pattern = pattern
        return _sampled_dot(pattern, a, b)

    @staticmethod
    def backward(ctx, grad: Tensor):
        a, b = ctx.saved_tensors
        da = _RowSums.apply(grad, b, ctx.pattern) if ctx.needs_input_grad[0] else None
        db = _ColumnSums.apply(grad, a, ctx.pattern) if ctx.needs_input_grad[1] else None
        return da, db, None


class _RowSums(Function):
    """``(n heads, d)``: the sparse matrix with ``values`` ``(heads * E,)`` times ``b`` ``(E, d)``."""

    @staticmethod
    def forward(ctx, values: Tensor, b: Tensor, pattern: _Pattern) -> Tensor:
        ctx.save_for_backward(values, b)
        ctx.pattern = pattern
        return _row_sums(pattern, values, b)

    @staticmethod
    def backward(ctx, grad: Tensor):
        values, b = ctx.saved_tensors
        dv = _SampledDot.apply(grad, b, ctx.pattern) if ctx.needs_input_grad[0] else None
        db = _ColumnSums.apply(values, grad, ctx.pattern) if ctx.needs_input_grad[1] else None
        return dv, db, None


class _ColumnSums(Function):
    """``(E, d)``: the transposed sparse matrix with ``values`` ``(heads * E,)`` times ``a`` ``(n heads, d)``."""

    @staticmethod
    def forward(ctx, values: Tensor, a: Tensor, pattern: _Pattern) -> Tensor:
        ctx.save_for_backward(values, a)
        ctx.pattern = pattern
        return _column_sums(pattern, values, a)

    @staticmethod
    def backward(ctx, grad: Tensor):
        values, a = ctx.saved_tensors
        dv = _SampledDot.apply(a, grad, ctx.pattern) if ctx.needs_input_grad[0] else None
        da = _RowSums.apply(values, grad, ctx.pattern) if ctx.needs_input_grad[1] else None
        return dv, da, None


class EdgeAttention(TransformerConv):
    """``TransformerConv`` (same constructor and parameters) with a faster forward for the graph layer's case.

    Call as ``attn((x_src (N_src, in), x_dst (N_dst, in)), edge_index (2, E), edge_attr (E, edge_dim))``; returns
    ``(N_dst, heads * out_channels)``. Receivers without incoming edges get zeros, as in PyG.

    ``receiver_side = False`` (an instance attribute) keeps it on the per-edge path on every device: dense and
    scatter operations only, which tracing and ONNX export can record (:mod:`egcbf.deploy.export`).
    """

    receiver_side: bool = True

    def _fast_path(self, edge_index, edge_attr, return_attention_weights) -> bool:
        linears = (self.lin_query, self.lin_key, self.lin_value, self.lin_edge)
        return (
            return_attention_weights is None
            and isinstance(edge_index, Tensor)
            and edge_index.layout == torch.strided  # not a sparse adjacency
            and edge_index.shape[1] > 0
            and edge_attr is not None
            and self.lin_edge is not None
            and self.concat
            and not self.root_weight
            and not (self.training and self.dropout > 0)
            and not any(isinstance(lin.weight, UninitializedParameter) for lin in linears)
        )

    def forward(self, x, edge_index, edge_attr=None, return_attention_weights=None):
        if not self._fast_path(edge_index, edge_attr, return_attention_weights):
            return super().forward(x, edge_index, edge_attr, return_attention_weights)
        x_src, x_dst = (x, x) if isinstance(x, Tensor) else x
        if self.receiver_side and x_dst.device.type == "cpu" and x_dst.dtype in (torch.float32, torch.float64):
            return self._forward_receivers(x_src, x_dst, edge_index, edge_attr)
        return self._forward_per_edge(x_src, x_dst, edge_index, edge_attr)

    def _forward_receivers(self, x_src: Tensor, x_dst: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        """The receiver-side computation (module doc). ``x_src`` ``(N_src, in)``, ``x_dst`` ``(n, in)``,
        ``edge_index`` ``(2, E)``, ``edge_attr`` ``(E, edge_dim)``; returns ``(n, heads * C)``."""
        heads, channels = self.heads, self.out_channels
        src, dst = edge_index[0], edge_index[1]
        n = x_dst.shape[0]
        if not _is_edge_aligned(src, x_src.shape[0]):
            x_src = x_src.index_select(0, src)  # (E, in)
        pattern = _Pattern(dst, n, heads)

        def per_head(lin):  # (heads, C, width) rows of a projection
            return lin.weight.view(heads, channels, -1)

        q = self.lin_query(x_dst).view(n, heads, channels).transpose(0, 1) / math.sqrt(channels)  # (heads, n, C)
        q_key = torch.bmm(q, per_head(self.lin_key)).transpose(0, 1).reshape(n * heads, -1)  # W_kh^T q_ih
        q_edge = torch.bmm(q, per_head(self.lin_edge)).transpose(0, 1).reshape(n * heads, -1)  # W_eh^T q_ih
        score = _SampledDot.apply(q_key, x_src, pattern) + _SampledDot.apply(q_edge, edge_attr, pattern)
        row = pattern.row
        if self.lin_key.bias is not None:  # q_ih . b_kh (module doc)
            shift = (q * self.lin_key.bias.view(heads, 1, channels)).sum(-1).t().reshape(n * heads)
            score = score + shift.index_select(0, row)

        top = score.new_full((n * heads,), -math.inf)
        top = top.scatter_reduce(0, row, score.detach(), "amax", include_self=True)
        weight = torch.exp(score - top.index_select(0, row))  # (heads * E,)
        total = score.new_zeros(n * heads).index_add(0, row, weight).view(n, heads, 1)  # S_ih

        sum_x = _RowSums.apply(weight, x_src, pattern).view(n, heads, -1).transpose(0, 1)  # (heads, n, in)
        sum_e = _RowSums.apply(weight, edge_attr, pattern).view(n, heads, -1).transpose(0, 1)
        out = torch.bmm(sum_x, per_head(self.lin_value).transpose(1, 2))
        out = out.baddbmm(sum_e, per_head(self.lin_edge).transpose(1, 2)).transpose(0, 1)  # (n, heads, C)
        if self.lin_value.bias is not None:
            out = out + self.lin_value.bias.view(heads, channels) * total
        return (out / (total + 1e-16)).reshape(n, heads * channels)

    def _forward_per_edge(self, x_src: Tensor, x_dst: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        """PyG's per-edge computation in fewer passes: keys and values in one product, the edge term ``W_e e``
        added to both in place, no gather when the sources are edge-aligned, the softmax normalized at the
        receivers. Shapes as :meth:`_forward_receivers`."""
        heads, channels = self.heads, self.out_channels
        width = heads * channels
        src, dst = edge_index[0], edge_index[1]
        n_dst = x_dst.shape[0]

        weight = torch.cat((self.lin_key.weight, self.lin_value.weight))
        bias = None if self.lin_key.bias is None else torch.cat((self.lin_key.bias, self.lin_value.bias))
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
