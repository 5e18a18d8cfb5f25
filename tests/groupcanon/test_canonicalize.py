"""Acceptance test: Canonicalize makes unmodified torch_geometric layers equivariant (and the raw layers are not).

Tolerances: float64 errors must be below 1e-9 (observed ~1e-14 with translations ~10); float32 errors below
1e-4 * (1 + max|output|) (observed ~1e-5 for outputs of magnitude ~40).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import pytest
import torch
from gc_helpers import F32, F64, LAYER_TOL_F64, fixed_graph, graph_inputs, group_id, in_out_types
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn
from torch_geometric.nn import EdgeConv, GATv2Conv, GCNConv, GraphConv, PointTransformerConv, SAGEConv, TransformerConv

from groupcanon import Canonicalize, FieldType
from groupcanon import groups as gg
from groupcanon.features import Point, Scalar, Vector
from groupcanon.testing import assert_equivariant, equivariance_error
from groupcanon.testing import strategies as gst

GROUPS = [gg.SE2xR(), gg.SE3(), gg.SO2()]
F32_ATOL, F32_RTOL = 1e-4, 1e-4


def edge_type_for(G) -> FieldType:
    """A typed edge attribute: a length (invariant) and a displacement (a vector, rotated into the receiver frame)."""
    return FieldType(G, {"dist": Scalar(1), "disp": Vector(G.space_dim)})


@dataclass
class LayerSpec:
    make: Any  # (in_dim, out_dim, space_dim, edge_dim) -> nn.Module
    mode: str
    pos: bool = False
    typed_edges: bool = False
    canon: dict = field(default_factory=dict)


def _mlp(i, o, h=16):
    return nn.Sequential(nn.Linear(i, h), nn.Tanh(), nn.Linear(h, o))


LAYERS = {
    "TransformerConv": LayerSpec(lambda i, o, d, e: TransformerConv(i, o, heads=2, concat=False), "pair"),
    "TransformerConv+edge_dim": LayerSpec(
        lambda i, o, d, e: TransformerConv(i, o, heads=2, concat=False, edge_dim=e), "pair", typed_edges=True
    ),
    "GATv2Conv": LayerSpec(lambda i, o, d, e: GATv2Conv(i, o, heads=2, concat=False, add_self_loops=False), "pair"),
    "GATv2Conv+self_loops": LayerSpec(
        lambda i, o, d, e: GATv2Conv(i, o, heads=2, concat=False, add_self_loops=False),
        "pair",
        canon={"self_loops": True},
    ),
    "PointTransformerConv": LayerSpec(
        lambda i, o, d, e: PointTransformerConv(i, o, pos_nn=nn.Linear(d, o), add_self_loops=False), "pair", pos=True
    ),
    "PointTransformerConv+self_loops": LayerSpec(
        lambda i, o, d, e: PointTransformerConv(i, o, pos_nn=nn.Linear(d, o), add_self_loops=False),
        "pair",
        pos=True,
        canon={"self_loops": True},
    ),
    "EdgeConv": LayerSpec(lambda i, o, d, e: EdgeConv(_mlp(2 * i, o)), "pair"),
    "SAGEConv": LayerSpec(lambda i, o, d, e: SAGEConv(i, o), "pair"),
    "GraphConv": LayerSpec(lambda i, o, d, e: GraphConv(i, o), "pair"),
    "GCNConv": LayerSpec(lambda i, o, d, e: GCNConv(i, o), "ego"),
}


def build(name: str, G, dtype=F64, seed: int = 0, **canon):
    """(raw layer, wrapped layer, t_in, t_out, edge FieldType or None) with deterministic weights."""
    spec = LAYERS[name]
    t_in, t_out = in_out_types(G)
    et = edge_type_for(G) if spec.typed_edges else None
    torch.manual_seed(seed)
    raw = spec.make(t_in.dim, t_out.dim, G.space_dim, None if et is None else et.dim).to(dtype)
    eq = Canonicalize(G, t_in, t_out, edge_type=et, **{**spec.canon, **canon})(raw)
    assert eq.mode == spec.mode
    return raw, eq, t_in, t_out, et


def call_kwargs(inp, frames=True):
    kw = {}
    if frames:
        kw["frames"] = inp.frames
    if inp.pos is not None:
        kw["pos"] = inp.pos
    if inp.edge_attr is not None:
        kw["edge_attr"] = inp.edge_attr
    return kw


def type_map(G, t_in, inp, et=None, frames=True):
    it = {0: t_in}
    if frames:
        it["frames"] = G
    if inp.pos is not None:
        it["pos"] = Point(G.space_dim)
    if et is not None:
        it["edge_attr"] = et
    return it


def _n_examples(dtype):
    n = settings.default.max_examples
    return n if dtype == F64 else max(5, n // 3)


# ------------------------------------------------------------------------------------------------ acceptance
@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize("G", GROUPS, ids=group_id)
@pytest.mark.parametrize("name", list(LAYERS))
def test_wrapped_layer_is_equivariant(name, G, dtype):
    _, eq, t_in, t_out, et = build(name, G, dtype)
    spec = LAYERS[name]
    strategy = graph_inputs(G, t_in, dtype=dtype, pos=spec.pos, edge_type=et)

    @settings(max_examples=_n_examples(dtype))
    @given(inp=strategy)
    def run(inp):
        kw = call_kwargs(inp)
        tol = dict(atol=LAYER_TOL_F64) if dtype == F64 else dict(atol=F32_ATOL, rtol=F32_RTOL)
        assert_equivariant(
            eq, G, (inp.x, inp.edge_index), kw, in_types=type_map(G, t_in, inp, et), out_types=t_out, g=inp.g, **tol
        )
        out = eq(inp.x, inp.edge_index, **kw)
        assert out.shape == (inp.num_nodes, t_out.dim) and out.dtype == dtype
        assert torch.isfinite(out).all()

    run()


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
@pytest.mark.parametrize("name", list(LAYERS))
def test_raw_layer_is_not_equivariant(name, G):
    """The same check on the unwrapped layer fails by a wide margin: the acceptance test has teeth."""
    raw, eq, t_in, t_out, et = build(name, G, F64)
    n = 12
    ei = fixed_graph(n, seed=1, degree=3)
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    kw, it = {}, {0: t_in}
    if LAYERS[name].pos:
        kw["pos"], it["pos"] = torch.randn(n, G.space_dim, generator=gen, dtype=F64), Point(G.space_dim)
    if et is not None:
        kw["edge_attr"], it["edge_attr"] = torch.randn(ei.shape[1], et.dim, generator=gen, dtype=F64), et
    g = G.sample(3, generator=gen, dtype=F64)

    def raw_fn(x, edge_index, **kwargs):
        return raw(x=x, edge_index=edge_index, **kwargs)

    raw_err = equivariance_error(raw_fn, G, (x, ei), kw, in_types=it, out_types=t_out, g=g)
    assert raw_err > 1e-3
    with pytest.raises(AssertionError, match="is not equivariant"):
        assert_equivariant(raw_fn, G, (x, ei), kw, in_types=it, out_types=t_out, g=g, atol=1e-3)
    # ... while the wrapped layer passes on the very same inputs
    frames = G.sample(n, generator=gen, dtype=F64)
    wrapped_err = equivariance_error(
        eq, G, (x, ei), {**kw, "frames": frames}, in_types={**it, "frames": G}, out_types=t_out, g=g
    )
    assert wrapped_err < LAYER_TOL_F64


def test_dropping_frames_from_the_check_breaks_equivariance():
    """Frames must transform with the scene: holding them fixed is (correctly) detected as non-equivariant."""
    G = gg.SE2xR()
    _, eq, t_in, t_out, _ = build("TransformerConv", G)
    n = 10
    ei = fixed_graph(n)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    frames = G.sample(n, generator=gen, dtype=F64)
    err = equivariance_error(eq, G, (x, ei), {"frames": frames}, in_types={0: t_in}, out_types=t_out)
    assert err > 1e-3


# ------------------------------------------------------------------------------------------------ edge features
@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_typed_edge_attr_needs_its_type(G):
    """TransformerConv with a typed edge_attr (a displacement vector): equivariant when declared as edge_type."""
    _, eq, t_in, t_out, et = build("TransformerConv+edge_dim", G)

    @settings(max_examples=_n_examples(F32))  # the main matrix covers this layer; here the negative check matters
    @given(inp=graph_inputs(G, t_in, edge_type=et))
    def run(inp):
        kw = call_kwargs(inp)
        assert_equivariant(
            eq,
            G,
            (inp.x, inp.edge_index),
            kw,
            in_types=type_map(G, t_in, inp, et),
            out_types=t_out,
            g=inp.g,
            atol=LAYER_TOL_F64,
        )
        # treating the typed edge_attr as invariant would break equivariance (unless there are no edges)
        if inp.edge_index.shape[1]:
            it = type_map(G, t_in, inp, None)
            err = equivariance_error(eq, G, (inp.x, inp.edge_index), kw, in_types=it, out_types=t_out, g=inp.g)
            assert err > 1e-6

    run()


def test_edge_attr_rotated_into_receiver_frame():
    """What the layer sees as edge_attr is exactly rho(g_v^-1) edge_attr for edge u -> v."""
    G = gg.SE2xR()
    et = edge_type_for(G)
    seen = {}

    class Spy(nn.Module):
        def forward(self, x, edge_index, edge_attr=None):
            seen["edge_attr"], seen["edge_index"] = edge_attr, edge_index
            return x[1]

    t = FieldType(G, [Scalar(2)])
    eq = Canonicalize(G, t, t, edge_type=et, mode="pair")(Spy())
    ei = fixed_graph(8)
    gen = torch.Generator().manual_seed(0)
    frames = G.sample(8, generator=gen, dtype=F64)
    ea = torch.randn(ei.shape[1], et.dim, generator=gen, dtype=F64)
    eq(torch.randn(8, 2, generator=gen, dtype=F64), ei, frames=frames, edge_attr=ea)
    expected = et.act(G.inverse(frames)[ei[1]], ea)
    assert torch.allclose(seen["edge_attr"], expected, atol=1e-14)
    assert torch.equal(seen["edge_index"][0], torch.arange(ei.shape[1]))  # one source row per edge
    assert torch.equal(seen["edge_index"][1], ei[1])


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
@pytest.mark.parametrize("name", ["TransformerConv", "GATv2Conv"])
def test_invariant_edge_attr_passthrough(name, G):
    t_in, t_out = in_out_types(G)
    torch.manual_seed(0)
    if name == "TransformerConv":
        raw = TransformerConv(t_in.dim, t_out.dim, edge_dim=3).double()
    else:
        raw = GATv2Conv(t_in.dim, t_out.dim, edge_dim=3, add_self_loops=False).double()
    seen = {}
    raw.register_forward_pre_hook(lambda m, a, kw: seen.update(kw), with_kwargs=True)
    eq = Canonicalize(G, t_in, t_out)(raw)

    @settings(max_examples=_n_examples(F32))  # the main matrix already covers edge attributes: a third suffices
    @given(inp=graph_inputs(G, t_in, edge_dim=3))
    def run(inp):
        kw = call_kwargs(inp)
        assert_equivariant(
            eq,
            G,
            (inp.x, inp.edge_index),
            kw,
            in_types=type_map(G, t_in, inp),
            out_types=t_out,
            g=inp.g,
            atol=LAYER_TOL_F64,
        )
        eq(inp.x, inp.edge_index, **kw)
        assert seen["edge_attr"] is inp.edge_attr  # passed through untouched (no copy, no transform)

    run()


# ------------------------------------------------------------------------------------------------ bipartite
@st.composite
def bipartite_inputs(draw, G, t_src, t_dst, n_src=30, n_dst=10, max_degree=5, dtype=F64):
    gen = torch.Generator().manual_seed(draw(gst.seeds()))
    deg = torch.randint(0, max_degree + 1, (n_dst,), generator=gen)
    src = torch.cat([torch.randperm(n_src, generator=gen)[: int(k)] for k in deg])
    dst = torch.repeat_interleave(torch.arange(n_dst), deg)
    x_src = torch.randn(n_src, t_src.dim, generator=gen, dtype=dtype)
    x_dst = torch.randn(n_dst, t_dst.dim, generator=gen, dtype=dtype)
    pos = (
        3 * torch.randn(n_src, G.space_dim, generator=gen, dtype=dtype),
        3 * torch.randn(n_dst, G.space_dim, generator=gen, dtype=dtype),
    )
    frames = draw(gst.elements(G, batch=(n_dst,), dtype=dtype))
    g = draw(gst.elements(G, batch=(3,), dtype=dtype))
    return x_src, x_dst, torch.stack((src, dst)), pos, frames, g


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
@pytest.mark.parametrize("name", ["TransformerConv", "SAGEConv", "PointTransformerConv"])
def test_bipartite_receivers_only_have_frames(name, G):
    """10 agents receive from 30 frame-less senders (e.g. LiDAR hits as points); frames exist for receivers only."""
    d = G.space_dim
    t_src = FieldType(G, {"hit": Point(d), "kind": Scalar(1)})
    t_dst, t_out = in_out_types(G)
    torch.manual_seed(0)
    dims = (t_src.dim, t_dst.dim)
    raw = {
        "TransformerConv": lambda: TransformerConv(dims, t_out.dim, heads=2),
        "SAGEConv": lambda: SAGEConv(dims, t_out.dim),
        "PointTransformerConv": lambda: PointTransformerConv(
            dims, t_out.dim, pos_nn=nn.Linear(d, t_out.dim), add_self_loops=False
        ),
    }[name]()
    if name == "TransformerConv":  # heads are concatenated: project back with a node-mode linear map
        raw = _Chain(raw, nn.Linear(2 * t_out.dim, t_out.dim))
    raw = raw.double()
    eq = Canonicalize(G, (t_src, t_dst), t_out, mode="pair")(raw)
    use_pos = name == "PointTransformerConv"

    def fn(x_src, x_dst, edge_index, frames, pos=None):
        kw = {"pos": pos} if pos is not None else {}
        return eq((x_src, x_dst), edge_index, frames=frames, **kw)

    @given(inp=bipartite_inputs(G, t_src, t_dst))
    def run(inp):
        x_src, x_dst, ei, pos, frames, g = inp
        kwargs = {"frames": frames}
        in_types = {0: t_src, 1: t_dst, "frames": G}
        if use_pos:
            kwargs["pos"], in_types["pos"] = pos, Point(d)
        out = fn(x_src, x_dst, ei, **kwargs)
        assert out.shape == (10, t_out.dim)
        assert_equivariant(fn, G, (x_src, x_dst, ei), kwargs, in_types=in_types, out_types=t_out, g=g, atol=1e-9)

    run()


class _Chain(nn.Module):
    """A graph layer followed by a per-node map (keeps the graph layer's pair signature)."""

    def __init__(self, conv, post):
        super().__init__()
        self.conv, self.post = conv, post

    def forward(self, x: tuple, edge_index, **kwargs):
        return self.post(self.conv(x, edge_index, **kwargs))


# ------------------------------------------------------------------------------------------------ isolated nodes
@pytest.mark.parametrize("name", list(LAYERS))
def test_no_edges_at_all(name):
    G = gg.SE2xR()
    _, eq, t_in, t_out, et = build(name, G)
    n = 6
    gen = torch.Generator().manual_seed(0)
    ei = torch.zeros(2, 0, dtype=torch.long)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    kw, it = {"frames": G.sample(n, generator=gen, dtype=F64)}, {0: t_in, "frames": G}
    if LAYERS[name].pos:
        kw["pos"], it["pos"] = torch.randn(n, 3, generator=gen, dtype=F64), Point(3)
    if et is not None:
        kw["edge_attr"], it["edge_attr"] = torch.zeros(0, et.dim, dtype=F64), et
    out = eq(x, ei, **kw)
    assert out.shape == (n, t_out.dim) and torch.isfinite(out).all()
    assert_equivariant(eq, G, (x, ei), kw, in_types=it, out_types=t_out, atol=LAYER_TOL_F64)


def test_isolated_nodes_see_only_themselves():
    """SAGEConv on a graph with isolated nodes: their output is rho(g_v) (lin_r(rho(g_v^-1) x_v) + lin_l.bias),
    whatever the other nodes hold."""
    G = gg.SE3()
    raw, eq, t_in, t_out, _ = build("SAGEConv", G)
    n = 10
    ei = fixed_graph(n)
    ei = ei[:, ei[1] >= 3]  # nodes 0, 1, 2 receive nothing
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    frames = G.sample(n, generator=gen, dtype=F64)
    out = eq(x, ei, frames=frames)
    local = t_in.act(G.inverse(frames[:3]), x[:3])
    expected = t_out.act(frames[:3], raw.lin_r(local) + raw.lin_l.bias)
    assert torch.allclose(out[:3], expected, atol=1e-12)
    x2 = x.clone()
    x2[3:] = torch.randn(n - 3, t_in.dim, generator=gen, dtype=F64)
    assert torch.equal(eq(x2, ei, frames=frames)[:3], out[:3])


# ------------------------------------------------------------------------------------------------ tuple outputs
@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_attention_weights_are_invariant(G):
    t_in, t_out = in_out_types(G)
    torch.manual_seed(0)
    raw = TransformerConv(t_in.dim, t_out.dim, heads=2, concat=False).double()
    eq = Canonicalize(G, t_in, t_out)(raw)

    @given(inp=graph_inputs(G, t_in, min_nodes=4, min_edges=3))
    def run(inp):
        y, (ei_out, alpha) = eq(inp.x, inp.edge_index, frames=inp.frames, return_attention_weights=True)
        e = inp.edge_index.shape[1]
        assert alpha.shape == (e, 2)
        # attention is reported on the caller's graph, row for row (not the internal canonicalized one)
        assert torch.equal(ei_out, inp.edge_index)
        # softmax over each receiver's incoming edges
        sums = torch.zeros(inp.num_nodes, 2, dtype=F64).index_add_(0, inp.edge_index[1], alpha)
        has_in = torch.bincount(inp.edge_index[1], minlength=inp.num_nodes) > 0
        assert torch.allclose(sums[has_in], torch.ones_like(sums[has_in]), atol=1e-12)
        for gi in inp.g:
            y2, (_, alpha2) = eq(
                t_in.act(gi, inp.x), inp.edge_index, frames=G.compose(gi, inp.frames), return_attention_weights=True
            )
            assert (alpha2 - alpha).abs().max() < 1e-9
            assert (y2 - t_out.act(gi, y)).abs().max() < LAYER_TOL_F64

    run()


# ------------------------------------------------------------------------------------------------ node mode
@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize("G", [*GROUPS, gg.Product(gg.SE2(), gg.Translation(1)), gg.Cyclic(6)], ids=group_id)
def test_node_mode_mlp(G, dtype):
    t_in, t_out = in_out_types(G)
    torch.manual_seed(0)
    mlp = _mlp(t_in.dim, t_out.dim, 32).to(dtype)
    eq = Canonicalize(G, t_in, t_out)(mlp)
    assert eq.mode == "node"
    assert torch.equal(
        Canonicalize(G, t_in, t_out, mode="node")(mlp)(
            torch.zeros(1, t_in.dim, dtype=dtype), frames=G.identity(1, dtype=dtype)
        ),
        eq(torch.zeros(1, t_in.dim, dtype=dtype), frames=G.identity(1, dtype=dtype)),
    )

    @settings(max_examples=_n_examples(dtype))
    @given(
        x=gst.features(t_in, batch=(12,), dtype=dtype),
        f=gst.elements(G, (12,), dtype=dtype),
        g=gst.elements(G, (3,), dtype=dtype),
    )
    def run(x, f, g):
        tol = dict(atol=LAYER_TOL_F64) if dtype == F64 else dict(atol=F32_ATOL, rtol=F32_RTOL)
        assert_equivariant(eq, G, (x,), {"frames": f}, in_types={0: t_in, "frames": G}, out_types=t_out, g=g, **tol)
        # node mode is exactly f_v = rho(g_v) M(rho(g_v^-1) x_v)
        expected = t_out.act(f, mlp(t_in.act(G.inverse(f), x)))
        assert torch.equal(eq(x, frames=f), expected)

    run()


# ------------------------------------------------------------------------------------------------ Trivial
@pytest.mark.parametrize("name", list(LAYERS))
def test_trivial_group_is_exactly_the_raw_layer(name):
    T = gg.Trivial()
    spec = LAYERS[name]
    t_in = FieldType(T, [Scalar(2), Vector(3), Point(3)])
    t_out = FieldType(T, [Scalar(3), Vector(3, n=2), Point(3)])
    et = FieldType(T, [Scalar(1), Vector(3)]) if spec.typed_edges else None
    torch.manual_seed(0)
    raw = spec.make(t_in.dim, t_out.dim, 3, None if et is None else et.dim).double()
    eq = Canonicalize(T, t_in, t_out, edge_type=et, pos_type=Point(3), **spec.canon)(raw)
    n = 14
    ei = fixed_graph(n, degree=4)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    kw = {}
    if spec.pos:
        kw["pos"] = torch.randn(n, 3, generator=gen, dtype=F64)
    if et is not None:
        kw["edge_attr"] = torch.randn(ei.shape[1], et.dim, generator=gen, dtype=F64)
    got = eq(x, ei, frames=T.identity(n, dtype=F64), **kw)
    if spec.canon.get("self_loops"):
        # self_loops=True is honoured under Trivial too: the result is the raw layer with add_self_loops=True
        raw.add_self_loops = True
        assert torch.allclose(got, raw(x=x, edge_index=ei, **kw), atol=1e-12)
        raw.add_self_loops = False
        assert not torch.allclose(got, raw(x=x, edge_index=ei, **kw), atol=1e-6)
    elif eq.mode == "ego":
        # ego mode keeps its ego-graph path under Trivial (so GCBF and EGCBF are the same model): it equals the raw
        # layer on the disjoint union of ego graphs, which for degree-normalizing layers differs from the raw graph
        src, dst = ei
        union = torch.cat((x, x[src]))
        ego_edges = torch.stack((n + torch.arange(src.shape[0]), dst))
        assert torch.equal(got, raw(x=union, edge_index=ego_edges, **kw)[:n])
        assert not torch.allclose(got, raw(x=x, edge_index=ei, **kw), atol=1e-6)
    else:
        assert torch.equal(got, raw(x=x, edge_index=ei, **kw))


def _model(G, d: int, name: str):
    """The construction code of a user model: dimensions spelled out, group as a parameter, no pos_type."""
    spec = LAYERS[name]
    t_in = FieldType(G, {"s": Scalar(2), "v": Vector(d), "p": Point(d)})
    t_out = FieldType(G, {"s": Scalar(3), "v": Vector(d, n=2), "p": Point(d)})
    et = FieldType(G, {"dist": Scalar(1), "disp": Vector(d)}) if spec.typed_edges else None
    torch.manual_seed(0)
    raw = spec.make(t_in.dim, t_out.dim, d, None if et is None else et.dim).double()
    return raw, Canonicalize(G, t_in, t_out, edge_type=et, **spec.canon)(raw), t_in, et


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
@pytest.mark.parametrize("name", list(LAYERS))
def test_trivial_is_a_drop_in_replacement(name, G):
    """The code of a working G model with G replaced by Trivial() (positions included, no pos_type) runs, and gives
    the G model's output at identity frames; in pair mode that is the unwrapped layer's output (with its own self
    loops where the wrapper adds them), in ego mode the layer on the ego graphs (documented)."""
    d, n = G.space_dim, 14
    T = gg.Trivial()
    _, eq_g, t_in, et = _model(G, d, name)
    raw, eq, _, _ = _model(T, d, name)
    ei = fixed_graph(n, degree=4)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(n, t_in.dim, generator=gen, dtype=F64)
    kw = {}
    if LAYERS[name].pos:
        kw["pos"] = torch.randn(n, d, generator=gen, dtype=F64)
    if et is not None:
        kw["edge_attr"] = torch.randn(ei.shape[1], et.dim, generator=gen, dtype=F64)
    got = eq(x, ei, frames=T.identity(n, dtype=F64), **kw)
    expected = eq_g(x, ei, frames=G.identity(n, dtype=F64), **kw)
    assert got.shape == expected.shape == (n, eq.spec.out_type.dim)
    assert torch.allclose(got, expected, atol=1e-12, rtol=0)
    if eq.mode == "pair":
        if LAYERS[name].canon.get("self_loops"):
            raw.add_self_loops = True  # the wrapper's self_loops=True is the layer's own add_self_loops=True
        assert torch.allclose(got, raw(x=x, edge_index=ei, **kw), atol=1e-12, rtol=0)


def test_trivial_node_mode_is_exactly_the_raw_module():
    T = gg.Trivial()
    t = FieldType(T, [Vector(4)])
    mlp = _mlp(4, 4).double()
    x = torch.randn(5, 4, dtype=F64)
    assert torch.equal(Canonicalize(T, t, t)(mlp)(x, frames=T.identity(5)), mlp(x))


# ------------------------------------------------------------------------------------------------ identity frames
@pytest.mark.parametrize("G", [gg.SE2xR(), gg.SE3()], ids=group_id)
@pytest.mark.parametrize(
    "name", ["TransformerConv", "TransformerConv+edge_dim", "SAGEConv", "GraphConv", "EdgeConv", "PointTransformerConv"]
)
def test_identity_frames_pair_mode_equals_raw_layer(name, G):
    """With identity frames the edge-expanded bipartite graph is the same computation as the original graph."""
    raw, eq, t_in, _, et = build(name, G)

    @given(inp=graph_inputs(G, t_in, pos=LAYERS[name].pos, edge_type=et))
    def run(inp):
        kw = call_kwargs(inp, frames=False)
        expected = raw(x=inp.x, edge_index=inp.edge_index, **kw)
        got = eq(inp.x, inp.edge_index, frames=G.identity(inp.num_nodes, dtype=F64), **kw)
        assert (got - expected).abs().max() <= 1e-12 * max(1.0, float(expected.detach().abs().max()))

    run()


def test_identity_frames_gatv2_self_loops_equals_add_self_loops():
    """Canonicalize(self_loops=True) on GATv2Conv(add_self_loops=False) = GATv2Conv(add_self_loops=True)."""
    G = gg.SE2xR()
    t_in, t_out = in_out_types(G)
    torch.manual_seed(0)
    raw = GATv2Conv(t_in.dim, t_out.dim, heads=2, concat=False, add_self_loops=True).double()
    inner = copy.deepcopy(raw)
    inner.add_self_loops = False
    eq = Canonicalize(G, t_in, t_out, self_loops=True)(inner)

    @given(inp=graph_inputs(G, t_in))
    def run(inp):
        expected = raw(inp.x, inp.edge_index)
        got = eq(inp.x, inp.edge_index, frames=G.identity(inp.num_nodes, dtype=F64))
        assert (got - expected).abs().max() <= 1e-12 * max(1.0, float(expected.detach().abs().max()))

    run()


def test_ego_mode_gcn_degrees():
    """Ego mode: GCNConv(normalize=False) equals the raw layer at identity frames; with normalization the ego
    graphs' degrees (each source copy has degree 1) differ from the original graph's (documented caveat)."""
    G = gg.SE2xR()
    t_in, t_out = in_out_types(G)
    n = 10
    ei = fixed_graph(n)
    x = torch.randn(n, t_in.dim, generator=torch.Generator().manual_seed(0), dtype=F64)
    frames = G.identity(n, dtype=F64)
    torch.manual_seed(0)
    raw = GCNConv(t_in.dim, t_out.dim, normalize=False).double()
    eq = Canonicalize(G, t_in, t_out)(raw)
    assert eq.mode == "ego"
    assert torch.allclose(eq(x, ei, frames=frames), raw(x, ei), atol=1e-12)
    raw_n = GCNConv(t_in.dim, t_out.dim).double()
    eq_n = Canonicalize(G, t_in, t_out)(raw_n)
    assert not torch.allclose(eq_n(x, ei, frames=frames), raw_n(x, ei), atol=1e-6)


@pytest.mark.parametrize("G", GROUPS, ids=group_id)
def test_ego_mode_with_edge_weight(G):
    """Extra invariant kwargs (edge_weight) are passed through; the ego graph keeps the original edge order."""
    t_in, t_out = in_out_types(G)
    torch.manual_seed(0)
    eq = Canonicalize(G, t_in, t_out)(GCNConv(t_in.dim, t_out.dim).double())

    @given(inp=graph_inputs(G, t_in), seed=gst.seeds())
    def run(inp, seed):
        w = torch.rand(inp.edge_index.shape[1], generator=torch.Generator().manual_seed(seed), dtype=F64)
        kw = {"frames": inp.frames, "edge_weight": w}
        assert_equivariant(
            eq,
            G,
            (inp.x, inp.edge_index),
            kw,
            in_types={0: t_in, "frames": G},
            out_types=t_out,
            g=inp.g,
            atol=LAYER_TOL_F64,
        )

    run()


def test_mode_detection():
    G = gg.SE2xR()
    t_in, t_out = in_out_types(G)
    c = Canonicalize(G, t_in, t_out)
    for name, spec in LAYERS.items():
        if spec.canon:
            continue
        layer = spec.make(t_in.dim, t_out.dim, 3, 4)
        assert c(layer).mode == spec.mode, name
    assert c(_mlp(t_in.dim, t_out.dim)).mode == "node"
    assert Canonicalize(G, t_in, t_out, mode="ego")(SAGEConv(t_in.dim, t_out.dim)).mode == "ego"


# ------------------------------------------------------------------------------------------ PyG conventions
def test_frames_are_keyword_only():
    G = gg.SO2()
    t = FieldType(G, [Vector(2)])
    eq = Canonicalize(G, t, t)(TransformerConv(2, 2).double())
    x, ei = torch.randn(3, 2, dtype=F64), torch.tensor([[0, 1], [1, 2]])
    with pytest.raises(TypeError):
        eq(x, ei, G.identity(3, dtype=F64))  # third positional is edge_attr in PyG; frames must be named
    assert eq(x, ei, frames=G.identity(3, dtype=F64)).shape == (3, 2)


def test_reset_parameters_reaches_the_wrapped_layer():
    G = gg.SO2()
    t = FieldType(G, [Vector(2)])
    raw = TransformerConv(2, 2).double()
    eq = Canonicalize(G, t, t)(raw)
    torch.manual_seed(3)
    eq.reset_parameters()
    after = [p.detach().clone() for p in raw.parameters()]
    torch.manual_seed(3)
    raw.reset_parameters()
    assert all(torch.equal(a, p) for a, p in zip(after, raw.parameters()))
    with pytest.raises(AttributeError, match="reset_parameters"):
        Canonicalize(G, t, t)(nn.Identity()).reset_parameters()


def test_an_unannotated_graph_layer_needs_an_explicit_mode():
    class Plain(torch.nn.Module):
        def forward(self, x, edge_index):
            return x

    G = gg.SO2()
    t = FieldType(G, [Vector(2)])
    with pytest.raises(ValueError, match="mode='pair'"):
        Canonicalize(G, t, t)(Plain())
    assert Canonicalize(G, t, t, mode="ego")(Plain()).mode == "ego"


def test_attention_weights_with_self_loops_list_the_loops_after_the_callers_edges():
    G = gg.SO2()
    t = FieldType(G, [Vector(2)])
    raw = TransformerConv(2, 2, heads=1).double()
    eq = Canonicalize(G, t, t, self_loops=True)(raw)
    ei = torch.tensor([[0, 1, 2], [1, 2, 0]])
    _, (ei_out, alpha) = eq(torch.randn(3, 2, dtype=F64), ei, frames=G.sample(3, dtype=F64),
                            return_attention_weights=True)  # fmt: skip
    loops = torch.arange(3).repeat(2, 1)
    assert torch.equal(ei_out, torch.cat((ei, loops), 1)) and alpha.shape == (6, 1)


def test_a_wrapped_layer_compiles():
    G = gg.SE2xR()
    t = FieldType(G, [Vector(3), Scalar(1)])
    torch.manual_seed(0)
    eq = Canonicalize(G, t, t)(TransformerConv(t.dim, t.dim, heads=2, concat=False).double())
    x = torch.randn(5, t.dim, dtype=F64)
    ei = torch.tensor([[0, 1, 2, 3, 4, 0], [1, 2, 3, 4, 0, 2]])
    f = G.sample(5, dtype=F64, generator=torch.Generator().manual_seed(1))
    compiled = torch.compile(eq, backend="aot_eager", fullgraph=False)  # traced through dynamo and AOTAutograd
    assert torch.allclose(compiled(x, ei, frames=f), eq(x, ei, frames=f), atol=1e-12, rtol=0)
