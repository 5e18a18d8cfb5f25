"""Clear errors (messages name what is wrong) and documented behaviour on non-finite inputs."""

from __future__ import annotations

import pytest
import torch
from gc_helpers import F64, fixed_graph, in_out_types
from torch import nn
from torch_geometric.nn import GATv2Conv, GCNConv, PointTransformerConv, SAGEConv, TransformerConv

from groupcanon import Canonicalize, FieldType
from groupcanon import groups as gg
from groupcanon.features import Point, Scalar, Vector

G = gg.SE2xR()
T_IN, T_OUT = in_out_types(G)
N = 10


@pytest.fixture
def setup():
    torch.manual_seed(0)
    layer = TransformerConv(T_IN.dim, T_OUT.dim).double()
    eq = Canonicalize(G, T_IN, T_OUT)(layer)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(N, T_IN.dim, generator=gen, dtype=F64)
    frames = G.sample(N, generator=gen, dtype=F64)
    return eq, x, fixed_graph(N), frames


# ------------------------------------------------------------------------------------------------ shapes
def test_wrong_element_shape_for_frames(setup):
    eq, x, ei, frames = setup
    with pytest.raises(ValueError, match=r"frames has shape \(10, 4\).*SE2xR.*\(\*batch, 5\)"):
        eq(x, ei, frames=frames[:, :4])
    so3_frames = gg.SO3().sample(N, dtype=F64)
    with pytest.raises(ValueError, match=r"frames has shape \(10, 3, 3\)"):
        eq(x, ei, frames=so3_frames)
    with pytest.raises(TypeError, match=r"must be a torch\.Tensor"):
        eq(x, ei, frames=frames.tolist())


def test_frames_row_count_must_match_receivers(setup):
    eq, x, ei, frames = setup
    with pytest.raises(ValueError, match=r"frames have batch shape \(9,\), but the graph has 10 receiving nodes"):
        eq(x, ei, frames=frames[:9])
    with pytest.raises(ValueError, match=r"batch shape \(2, 10\)"):
        eq(x, ei, frames=frames.expand(2, N, 5))
    with pytest.raises(ValueError, match="batch shape \\(\\)"):
        eq(x, ei, frames=frames[0])


def test_bipartite_frames_are_per_receiver():
    t_src = FieldType(G, [Point(3)])
    torch.manual_seed(0)
    eq = Canonicalize(G, (t_src, T_IN), T_OUT)(SAGEConv((3, T_IN.dim), T_OUT.dim).double())
    x_src, x_dst = torch.randn(30, 3, dtype=F64), torch.randn(N, T_IN.dim, dtype=F64)
    ei = torch.stack((torch.arange(30), torch.arange(30) % N))
    assert eq((x_src, x_dst), ei, frames=G.sample(N, dtype=F64)).shape == (N, T_OUT.dim)
    with pytest.raises(ValueError, match=r"30.*10 receiving nodes.*x_dst"):
        eq((x_src, x_dst), ei, frames=G.sample(30, dtype=F64))
    with pytest.raises(ValueError, match=r"x \(source\) have shape \(30, 4\)"):
        eq((torch.randn(30, 4, dtype=F64), x_dst), ei, frames=G.sample(N, dtype=F64))
    with pytest.raises(ValueError, match="pair"):
        eq((x_src, x_dst, x_dst), ei, frames=G.sample(N, dtype=F64))


def test_frames_are_required(setup):
    eq, x, ei, _ = setup
    with pytest.raises(TypeError, match="frames are required"):
        eq(x, ei)


def test_wrong_feature_width(setup):
    eq, x, ei, frames = setup
    with pytest.raises(ValueError, match=rf"x have shape \(10, {T_IN.dim - 1}\), expected \(\*batch, {T_IN.dim}\)"):
        eq(x[:, :-1], ei, frames=frames)
    with pytest.raises(TypeError, match=r"x must be a torch\.Tensor, got ndarray"):
        eq(x.numpy(), ei, frames=frames)
    with pytest.raises(ValueError, match=r"x given as a sequence must be a \(source, target\) pair, got 10 items"):
        eq(x.tolist(), ei, frames=frames)


@pytest.mark.parametrize(
    ("bad", "words"),
    [
        (lambda ei: ei.t(), r"\(2, E\) tensor, got \(30, 2\)"),
        (lambda ei: ei[0], r"\(2, E\) tensor, got \(30,\)"),
        (lambda ei: torch.cat((ei, ei[:1])), r"\(2, E\) tensor, got \(3, 30\)"),
        (lambda ei: ei.tolist(), r"\(2, E\) tensor, got list"),
        (lambda ei: ei.int(), "dtype torch.long, got torch.int32"),
        (lambda ei: ei.double(), "dtype torch.long, got torch.float64"),
    ],
)
def test_edge_index_shape_and_dtype(setup, bad, words):
    eq, x, ei, frames = setup
    with pytest.raises(ValueError, match=words):
        eq(x, bad(ei), frames=frames)


def test_edge_index_required_for_graph_layers(setup):
    eq, x, _, frames = setup
    with pytest.raises(TypeError, match="edge_index is required"):
        eq(x, frames=frames)


def test_edge_attr_row_mismatch():
    torch.manual_seed(0)
    eq = Canonicalize(G, T_IN, T_OUT)(TransformerConv(T_IN.dim, T_OUT.dim, edge_dim=2).double())
    ei = fixed_graph(N)
    x, frames = torch.randn(N, T_IN.dim, dtype=F64), G.sample(N, dtype=F64)
    with pytest.raises(ValueError, match=rf"edge_attr has 7 rows, edge_index has {ei.shape[1]} edges"):
        eq(x, ei, frames=frames, edge_attr=torch.randn(7, 2, dtype=F64))


def test_typed_edge_attr_width_mismatch():
    et = FieldType(G, [Vector(3)])
    eq = Canonicalize(G, T_IN, T_OUT, edge_type=et)(TransformerConv(T_IN.dim, T_OUT.dim, edge_dim=3).double())
    ei = fixed_graph(N)
    with pytest.raises(ValueError, match=r"edge_attr have shape \(30, 2\), expected \(\*batch, 3\)"):
        eq(
            torch.randn(N, T_IN.dim, dtype=F64),
            ei,
            frames=G.sample(N, dtype=F64),
            edge_attr=torch.randn(ei.shape[1], 2, dtype=F64),
        )


# ------------------------------------------------------------------------------------------------ construction
@pytest.mark.parametrize(
    "make",
    [
        lambda: GATv2Conv(T_IN.dim, T_OUT.dim),
        lambda: PointTransformerConv(T_IN.dim, T_OUT.dim),
    ],
    ids=["GATv2Conv", "PointTransformerConv"],
)
def test_add_self_loops_rejected_in_pair_mode(make):
    with pytest.raises(ValueError, match=r"adds self loops.*add_self_loops=False.*self_loops=True"):
        Canonicalize(G, T_IN, T_OUT)(make())


def test_add_self_loops_fine_in_ego_mode():
    assert Canonicalize(G, T_IN, T_OUT)(GCNConv(T_IN.dim, T_OUT.dim)).mode == "ego"


def test_fieldtypes_of_different_groups():
    other = FieldType(gg.SE3(), [Scalar(2), Vector(3), Point(3)])
    with pytest.raises(ValueError, match=r"in_type is a FieldType of SE3.*Canonicalize was given SE2xR"):
        Canonicalize(G, other, T_OUT)
    with pytest.raises(ValueError, match=r"out_type is a FieldType of SE3"):
        Canonicalize(G, T_IN, other)
    with pytest.raises(ValueError, match=r"edge_type is a FieldType of SE3"):
        Canonicalize(G, T_IN, T_OUT, edge_type=FieldType(gg.SE3(), [Vector(3)]))
    with pytest.raises(ValueError, match="different groups"):
        T_IN + other
    # the translation scale only tunes sampling: SE2xR(1) is the same group as SE2xR(), so its FieldTypes serve
    other_scale = gg.SE2xR(translation_scale=1.0)
    assert other_scale == gg.SE2xR() and hash(other_scale) == hash(gg.SE2xR()) and other_scale != gg.SE2()
    Canonicalize(other_scale, T_IN, T_OUT)


def test_bad_canonicalize_arguments():
    with pytest.raises(TypeError, match="Group"):
        Canonicalize("SE2xR", T_IN, T_OUT)
    with pytest.raises(TypeError, match="in_type must be a FieldType"):
        Canonicalize(G, Scalar(1), T_OUT)
    with pytest.raises(ValueError, match="mode must be one of"):
        Canonicalize(G, T_IN, T_OUT, mode="edge")
    with pytest.raises(ValueError, match=r"\(source, target\) pair, got 3 items"):
        Canonicalize(G, (T_IN, T_IN, T_IN), T_OUT)
    with pytest.raises(TypeError, match=r"wraps a torch\.nn\.Module"):
        Canonicalize(G, T_IN, T_OUT)(lambda x: x)
    t_src = FieldType(G, [Point(3)])
    with pytest.raises(ValueError, match="need mode='pair'"):
        Canonicalize(G, (t_src, T_IN), T_OUT)(GCNConv(T_IN.dim, T_OUT.dim))


def test_out_type_width_mismatch(setup):
    """A layer that declares its width is refused when wrapped (test_rel_groupcanon_inputs.py); one that declares
    nothing (a Sequential) is refused at its first call, naming the widths."""
    _, x, _, frames = setup
    with pytest.raises(ValueError, match=rf"TransformerConv declares out_channels={T_OUT.dim + 1}"):
        Canonicalize(G, T_IN, T_OUT)(TransformerConv(T_IN.dim, T_OUT.dim + 1))
    node = Canonicalize(G, T_IN, T_OUT)(nn.Sequential(nn.Linear(T_IN.dim, 3)).double())
    with pytest.raises(ValueError, match=r"Sequential returned 3 channels, but out_type has dim"):
        node(x, frames=frames)


def test_node_mode_takes_no_edge_index(setup):
    _, x, ei, frames = setup
    node = Canonicalize(G, T_IN, T_OUT)(nn.Linear(T_IN.dim, T_OUT.dim).double())
    with pytest.raises(TypeError, match="mode='node' layers take no edge_index"):
        node(x, ei, frames=frames)


def test_ego_mode_rejects_bipartite_input():
    eq = Canonicalize(G, T_IN, T_OUT)(GCNConv(T_IN.dim, T_OUT.dim).double())
    x = torch.randn(N, T_IN.dim, dtype=F64)
    with pytest.raises(ValueError, match="mode='ego' takes a single node tensor"):
        eq((x, x), fixed_graph(N), frames=G.sample(N, dtype=F64))


def test_pos_width_mismatch():
    torch.manual_seed(0)
    eq = Canonicalize(G, T_IN, T_OUT)(PointTransformerConv(T_IN.dim, T_OUT.dim, add_self_loops=False).double())
    with pytest.raises(ValueError, match=r"pos have shape \(10, 2\), expected \(\*batch, 3\)"):
        eq(
            torch.randn(N, T_IN.dim, dtype=F64),
            fixed_graph(N),
            frames=G.sample(N, dtype=F64),
            pos=torch.randn(N, 2, dtype=F64),
        )


def test_pos_without_group_action():
    """A group without a Euclidean action has no default pos_type: passing pos is an error naming the fix."""
    C = gg.Product(gg.Trivial(), gg.Trivial())
    t = FieldType(C, [Scalar(3)])
    eq = Canonicalize(C, t, t)(PointTransformerConv(3, 3, pos_nn=nn.Linear(1, 3), add_self_loops=False).double())
    with pytest.raises(ValueError, match="no action on positions: give pos_type"):
        eq(
            torch.randn(4, 3, dtype=F64),
            fixed_graph(4, degree=2),
            frames=C.identity(4, dtype=F64),
            pos=torch.randn(4, 1, dtype=F64),
        )


# ------------------------------------------------------------------------------------------------ non-finite
@pytest.mark.parametrize("what", ["x", "frames", "pos"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")], ids=["nan", "inf", "-inf"])
def test_check_finite_raises(what, value):
    torch.manual_seed(0)
    layer = PointTransformerConv(T_IN.dim, T_OUT.dim, add_self_loops=False).double()
    eq = Canonicalize(G, T_IN, T_OUT, check_finite=True)(layer)
    gen = torch.Generator().manual_seed(0)
    args = {
        "x": torch.randn(N, T_IN.dim, generator=gen, dtype=F64),
        "frames": G.sample(N, generator=gen, dtype=F64),
        "pos": torch.randn(N, 3, generator=gen, dtype=F64),
    }
    ei = fixed_graph(N)
    eq(args["x"], ei, frames=args["frames"], pos=args["pos"])  # finite inputs pass
    args[what][3, 1] = value
    with pytest.raises(ValueError, match=rf"{what}\w* contains NaN or inf"):
        eq(args["x"], ei, frames=args["frames"], pos=args["pos"])


def test_check_finite_in_node_mode():
    node = Canonicalize(G, T_IN, T_OUT, check_finite=True)(nn.Linear(T_IN.dim, T_OUT.dim).double())
    x, frames = torch.randn(N, T_IN.dim, dtype=F64), G.sample(N, dtype=F64)
    frames[2, 0] = float("nan")
    with pytest.raises(ValueError, match="frames contains NaN or inf"):
        node(x, frames=frames)


@pytest.mark.parametrize(
    "make",
    [
        lambda: TransformerConv(T_IN.dim, T_OUT.dim),
        lambda: GATv2Conv(T_IN.dim, T_OUT.dim, add_self_loops=False),
        lambda: SAGEConv(T_IN.dim, T_OUT.dim),
    ],
    ids=["TransformerConv", "GATv2Conv", "SAGEConv"],
)
def test_without_check_finite_nan_propagates_only_to_receivers(make):
    """Documented behaviour: non-finite values are never replaced. A NaN in node k's features reaches exactly the
    outputs of k itself and of the nodes that receive messages from k; every other output stays finite.
    A non-finite frame of node k only affects k's output (the frame is used only for k's neighbourhood)."""
    torch.manual_seed(0)
    eq = Canonicalize(G, T_IN, T_OUT)(make().double())
    ei = fixed_graph(N, degree=2)
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(N, T_IN.dim, generator=gen, dtype=F64)
    frames = G.sample(N, generator=gen, dtype=F64)
    k = 0
    affected = torch.zeros(N, dtype=torch.bool)
    affected[ei[1][ei[0] == k]] = True
    affected[k] = True
    assert 1 < int(affected.sum()) < N  # the graph makes the check meaningful
    x_bad = x.clone()
    x_bad[k, 0] = float("nan")
    out = eq(x_bad, ei, frames=frames)
    assert torch.equal(~torch.isfinite(out).all(-1), affected)
    clean = eq(x, ei, frames=frames)
    assert torch.equal(out[~affected], clean[~affected])  # the others are untouched, bit for bit

    f_bad = frames.clone()
    f_bad[4, 2] = float("inf")
    out = eq(x, ei, frames=f_bad)
    bad_rows = ~torch.isfinite(out).all(-1)
    assert bad_rows.nonzero().flatten().tolist() == [4]


class _Returns(nn.Module):
    """A node layer that returns ``make(out)`` of a linear map's output."""

    def __init__(self, make):
        super().__init__()
        self.lin, self.make = nn.Linear(T_IN.dim, T_OUT.dim).double(), make

    def forward(self, x):
        return self.make(self.lin(x))


@pytest.mark.parametrize(
    "make, says",
    [
        (lambda y: [y], "returned list"),
        (lambda y: {"out": y}, "returned dict"),
        (lambda y: None, "returned NoneType"),
        (lambda y: (None, y), "returned a tuple whose first item is NoneType"),
        (lambda y: (), "returned tuple"),
    ],
    ids=["list", "dict", "None", "tuple-of-None", "empty-tuple"],
)
def test_a_layer_output_that_is_not_a_tensor_is_named(setup, make, says):
    _, x, _, frames = setup
    node = Canonicalize(G, T_IN, T_OUT)(_Returns(make))
    with pytest.raises(TypeError, match=rf"_Returns {says}; a wrapped layer must return a tensor"):
        node(x, frames=frames)
    ok = Canonicalize(G, T_IN, T_OUT)(_Returns(lambda y: (y, "extra")))(x, frames=frames)
    assert isinstance(ok, tuple) and ok[1] == "extra"
