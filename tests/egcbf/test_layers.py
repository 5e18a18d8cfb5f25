"""The graph layer's fast pieces equal their plain definitions: EdgeAttention (PyG's TransformerConv),
mlp_on_edges (an MLP on concatenated edge and receiver features) and the in-place SiLU."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn
from torch_geometric.nn import TransformerConv

from egcbf.nn.attention import EdgeAttention
from egcbf.nn.layers import SiLU, mlp, mlp_on_edges

F64, F32 = torch.float64, torch.float32
#: float64: rounding only (observed ~1e-15); float32: outputs O(1-10), observed ~5e-7
TOL = {F64: 1e-12, F32: 2e-5}


def _pair(seed: int, dtype, aligned: bool, n_dst: int = 9, in_dim: int = 8, edge_dim: int = 5):
    gen = torch.Generator().manual_seed(seed)
    num_edges = int(torch.randint(1, 40, (1,), generator=gen))
    dst = torch.randint(0, n_dst - 2, (num_edges,), generator=gen)  # the last two receivers get no edge
    n_src = num_edges if aligned else 6
    src = torch.arange(num_edges) if aligned else torch.randint(0, n_src, (num_edges,), generator=gen)
    x_src = 3 * torch.randn(n_src, in_dim, generator=gen, dtype=dtype)
    x_dst = 3 * torch.randn(n_dst, in_dim, generator=gen, dtype=dtype)
    edge_attr = torch.randn(num_edges, edge_dim, generator=gen, dtype=dtype)
    return (x_src, x_dst), torch.stack((src, dst)), edge_attr


def _twins(dtype, heads: int = 3, channels: int = 4):
    fast = EdgeAttention(8, channels, heads=heads, concat=True, edge_dim=5, root_weight=False).to(dtype)
    ref = TransformerConv(8, channels, heads=heads, concat=True, edge_dim=5, root_weight=False).to(dtype)
    ref.load_state_dict(fast.state_dict())
    return fast, ref


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), aligned=st.booleans())
def test_edge_attention_equals_transformer_conv(dtype, seed, aligned):
    """Same outputs and parameter gradients as PyG's TransformerConv, with sources given per node or one per edge
    (canonicalization's pair mode); receivers without edges get zeros."""
    torch.manual_seed(seed)
    fast, ref = _twins(dtype)
    x, edge_index, edge_attr = _pair(seed, dtype, aligned)
    out, expected = fast(x, edge_index, edge_attr), ref(x, edge_index, edge_attr)
    assert out.shape == expected.shape == (x[1].shape[0], 12)
    assert torch.allclose(out, expected, rtol=0.0, atol=TOL[dtype])
    assert torch.all(out[-2:] == 0)
    w = torch.randn(out.shape, dtype=dtype, generator=torch.Generator().manual_seed(seed))
    used = [name for name, _ in fast.named_parameters() if not name.startswith("lin_skip")]  # root_weight=False
    grads = torch.autograd.grad((out * w).sum(), [fast.get_parameter(n) for n in used])
    grads_ref = torch.autograd.grad((expected * w).sum(), [ref.get_parameter(n) for n in used])
    for a, b in zip(grads, grads_ref):
        assert torch.allclose(a, b, rtol=0.0, atol=10 * TOL[dtype])


def test_edge_attention_falls_back_to_pyg_outside_its_case():
    """Attention weights requested, or dropout while training: TransformerConv's own forward."""
    fast, ref = _twins(F64)
    x, edge_index, edge_attr = _pair(0, F64, aligned=False)
    out, (ei, alpha) = fast(x, edge_index, edge_attr, return_attention_weights=True)
    out_ref, (ei_ref, alpha_ref) = ref(x, edge_index, edge_attr, return_attention_weights=True)
    assert torch.equal(out, out_ref) and torch.equal(ei, ei_ref) and torch.equal(alpha, alpha_ref)
    fast.dropout = ref.dropout = 0.5
    fast.train()
    ref.train()
    torch.manual_seed(3)
    a = fast(x, edge_index, edge_attr)
    torch.manual_seed(3)
    b = ref(x, edge_index, edge_attr)
    assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
def test_mlp_on_edges_equals_mlp_of_concatenation(dtype):
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    net = mlp([4 + 6, 16, 16, 3]).to(dtype)
    edge, node = torch.randn(30, 4, generator=gen, dtype=dtype), torch.randn(7, 6, generator=gen, dtype=dtype)
    dst = torch.randint(0, 7, (30,), generator=gen)
    expected = net(torch.cat((edge, node[dst]), -1))
    assert torch.allclose(mlp_on_edges(net, edge, node, dst), expected, rtol=0.0, atol=TOL[dtype])
    with pytest.raises(ValueError, match="first layer takes 10 inputs"):
        mlp_on_edges(net, edge[:, :3], node, dst)


def test_silu_overwrites_only_without_autograd():
    x = torch.randn(5, 4)
    expected = nn.functional.silu(x)
    with torch.no_grad():
        y = x.clone()
        assert SiLU()(y) is y and torch.equal(y, expected)  # in place: the inference path
    leaf = x.clone().requires_grad_(True)
    y = SiLU()(leaf)
    assert y is not leaf and torch.equal(leaf.detach(), x)  # out of place when autograd records
    (g,) = torch.autograd.grad(y.sum(), leaf)
    sig = torch.sigmoid(x)
    assert torch.allclose(g, sig * (1 + x * (1 - sig)))
