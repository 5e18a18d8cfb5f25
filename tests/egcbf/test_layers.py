"""The graph layer's fast pieces equal their plain definitions: EdgeAttention (PyG's TransformerConv),
mlp_on_edges (an MLP on concatenated edge and receiver features) and the in-place SiLU."""

from __future__ import annotations

import subprocess
import sys

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


def _pair(seed: int, dtype, aligned: bool, sorted_: bool = False, n_dst: int = 9, in_dim: int = 8, edge_dim: int = 5):
    gen = torch.Generator().manual_seed(seed)
    num_edges = int(torch.randint(1, 40, (1,), generator=gen))
    dst = torch.randint(0, n_dst - 2, (num_edges,), generator=gen)  # the last two receivers get no edge
    if sorted_:  # as egcbf.env.graph builds them: each receiver's edges contiguous
        dst = dst.sort().values
    n_src = num_edges if aligned else 6
    src = torch.arange(num_edges) if aligned else torch.randint(0, n_src, (num_edges,), generator=gen)
    x_src = 3 * torch.randn(n_src, in_dim, generator=gen, dtype=dtype)
    x_dst = 3 * torch.randn(n_dst, in_dim, generator=gen, dtype=dtype)
    edge_attr = torch.randn(num_edges, edge_dim, generator=gen, dtype=dtype)
    return (x_src, x_dst), torch.stack((src, dst)), edge_attr


def _twins(dtype, heads: int = 3, channels: int = 4, bias: bool = True):
    kw = dict(heads=heads, concat=True, edge_dim=5, root_weight=False, bias=bias)
    fast = EdgeAttention(8, channels, **kw).to(dtype)
    ref = TransformerConv(8, channels, **kw).to(dtype)
    ref.load_state_dict(fast.state_dict())
    return fast, ref


#: the ways EdgeAttention computes (forward picks the receiver-side one on CPU; the per-edge one runs elsewhere)
PATHS = {
    "forward": lambda m, x, ei, ea: m(x, ei, ea),
    "receivers": lambda m, x, ei, ea: m._forward_receivers(x[0], x[1], ei, ea),
    "per_edge": lambda m, x, ei, ea: m._forward_per_edge(x[0], x[1], ei, ea),
}


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    aligned=st.booleans(),
    sorted_=st.booleans(),
    heads=st.integers(1, 4),
    channels=st.integers(1, 5),
    bias=st.booleans(),
)
def test_edge_attention_equals_transformer_conv(dtype, seed, aligned, sorted_, heads, channels, bias):
    """Same outputs and gradients (inputs and parameters) as PyG's TransformerConv on every path, with sources given
    per node or one per edge (canonicalization's pair mode), edges in any order or grouped by receiver, any number
    of heads; receivers without edges get zeros."""
    torch.manual_seed(seed)
    fast, ref = _twins(dtype, heads, channels, bias)
    (x_src, x_dst), edge_index, edge_attr = _pair(seed, dtype, aligned, sorted_)
    inputs = [t.requires_grad_(True) for t in (x_src, x_dst, edge_attr)]
    names = [name for name, _ in fast.named_parameters() if not name.startswith("lin_skip")]  # root_weight=False
    expected = ref((x_src, x_dst), edge_index, edge_attr)
    w = torch.randn(expected.shape, dtype=dtype, generator=torch.Generator().manual_seed(seed))
    grads_ref = torch.autograd.grad((expected * w).sum(), inputs + [ref.get_parameter(n) for n in names])
    for path, run in PATHS.items():
        out = run(fast, (x_src, x_dst), edge_index, edge_attr)
        assert out.shape == expected.shape == (x_dst.shape[0], heads * channels), path
        assert torch.allclose(out, expected, rtol=0.0, atol=TOL[dtype]), (path, (out - expected).abs().max())
        assert torch.all(out[-2:] == 0), path
        grads = torch.autograd.grad((out * w).sum(), inputs + [fast.get_parameter(n) for n in names])
        for name, a, b in zip(["x_src", "x_dst", "edge_attr", *names], grads, grads_ref):
            assert torch.allclose(a, b, rtol=0.0, atol=10 * TOL[dtype]), (path, name, (a - b).abs().max())


@pytest.mark.parametrize("aligned", [True, False], ids=["aligned", "gathered"])
def test_edge_attention_second_derivatives(aligned):
    """The receiver-side path's backward is differentiable again (double backward), numerically checked."""
    fast, _ = _twins(F64, heads=2, channels=3)
    (x_src, x_dst), edge_index, edge_attr = _pair(1, F64, aligned)
    inputs = tuple(t.requires_grad_(True) for t in (x_src, x_dst, edge_attr))

    def f(a, b, e):
        return fast._forward_receivers(a, b, edge_index, e)

    assert torch.autograd.gradcheck(f, inputs)
    assert torch.autograd.gradgradcheck(f, inputs)


def test_edge_attention_falls_back_to_pyg_outside_its_case():
    """Attention weights requested, dropout while training, or no edges: TransformerConv's own forward."""
    fast, ref = _twins(F64)
    x, edge_index, edge_attr = _pair(0, F64, aligned=False)
    out, (ei, alpha) = fast(x, edge_index, edge_attr, return_attention_weights=True)
    out_ref, (ei_ref, alpha_ref) = ref(x, edge_index, edge_attr, return_attention_weights=True)
    assert torch.equal(out, out_ref) and torch.equal(ei, ei_ref) and torch.equal(alpha, alpha_ref)
    empty = edge_index[:, :0]
    assert torch.equal(fast(x, empty, edge_attr[:0]), torch.zeros(x[1].shape[0], 12, dtype=F64))
    fast.dropout = ref.dropout = 0.5
    fast.train()
    ref.train()
    torch.manual_seed(3)
    a = fast(x, edge_index, edge_attr)
    torch.manual_seed(3)
    b = ref(x, edge_index, edge_attr)
    assert torch.equal(a, b)


def test_edge_attention_is_quiet():
    """No warning from torch's sparse support (a fresh process: torch warns about it once per process)."""
    code = (
        "import warnings, torch\n"
        "from egcbf.nn.attention import EdgeAttention\n"
        "warnings.simplefilter('error')\n"
        "m = EdgeAttention(8, 4, heads=2, concat=True, edge_dim=5, root_weight=False)\n"
        "ei = torch.stack((torch.arange(6), torch.tensor([0, 0, 1, 1, 1, 2])))\n"
        "out = m((torch.randn(6, 8), torch.randn(3, 8)), ei, torch.randn(6, 5))\n"
        "out.sum().backward()\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stderr[-2000:]


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
