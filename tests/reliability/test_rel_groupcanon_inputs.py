"""groupcanon on bad or unusual input: a FieldType whose width disagrees with the wrapped layer is refused when
wrapping; empty graphs and empty batches work with every check on; check_finite covers every floating input and
names it; dtype, width and batch-dimension mistakes and wrong argument types raise errors naming the argument,
what was expected and what was given."""

import pytest
import torch
from torch import nn
from torch_geometric.nn import GATv2Conv, GCNConv, PointTransformerConv, SAGEConv, TransformerConv

from groupcanon import Canonicalize, FieldType, frames, localize
from groupcanon import groups as gg
from groupcanon.features import Point, Scalar, Vector
from groupcanon.testing import assert_equivariant, check_action_laws, check_group_axioms

F64, F32 = torch.float64, torch.float32
G = gg.SE2xR()
T_IN = FieldType(G, {"s": Scalar(2), "v": Vector(3), "p": Point(3)})  # dim 8
T_OUT = FieldType(G, {"s": Scalar(3), "v": Vector(3, n=2), "p": Point(3)})  # dim 12
N = 6
EI = torch.tensor([[0, 1, 2, 3, 4, 5, 0], [1, 2, 3, 4, 5, 0, 3]])


def _inputs(dtype=F64, n=N):
    gen = torch.Generator().manual_seed(0)
    return torch.randn(n, T_IN.dim, generator=gen, dtype=dtype), G.sample(n, generator=gen, dtype=dtype)


# ------------------------------------------------------------------------------------ widths when wrapping
@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: TransformerConv(7, 12), ["TransformerConv declares in_channels=7", "in_type", "has dim 8"]),
        (lambda: GCNConv(9, 12), ["GCNConv declares in_channels=9", "has dim 8"]),
        (lambda: TransformerConv((8, 5), 12), ["in_channels=(8, 5)", "has dim 8"]),
        (lambda: TransformerConv(8, 11), ["out_channels=11", "11 output channels", "out_type", "has dim 12"]),
        (lambda: TransformerConv(8, 12, heads=2), ["out_channels=12 x heads=2 (concat=True)", "24 output", "dim 12"]),
        (lambda: nn.Linear(8, 5), ["Linear declares out_features=5", "dim 12"]),
        (lambda: nn.Linear(4, 12), ["Linear declares in_features=4", "dim 8"]),
    ],
    ids=["in", "in-ego", "in-pair", "out", "heads-concat", "linear-out", "linear-in"],
)
def test_width_mismatch_is_refused_when_wrapping(make, words):
    with pytest.raises(ValueError) as info:
        Canonicalize(G, T_IN, T_OUT)(make())
    msg = str(info.value)
    for w in [*words, "FieldType(SE2xR"]:
        assert w in msg, (w, msg)


def test_bipartite_width_mismatch_names_the_side():
    t_src = FieldType(G, [Point(3)])
    with pytest.raises(ValueError, match=r"in_channels=\(4, 8\), but in_type \(source\) FieldType\(.*\) has dim 3"):
        Canonicalize(G, (t_src, T_IN), T_OUT)(SAGEConv((4, 8), 12))
    with pytest.raises(ValueError, match=r"in_channels=8, but in_type \(source\) .* has dim 3"):
        Canonicalize(G, (t_src, T_IN), T_OUT)(SAGEConv(8, 12))


@pytest.mark.parametrize(
    "make",
    [
        lambda: GATv2Conv(-1, 12, add_self_loops=False),  # lazy in_channels
        lambda: TransformerConv((-1, 8), 12),
        lambda: TransformerConv(8, 6, heads=2),  # 6 x 2 heads concatenated = 12
        lambda: TransformerConv(8, 12, heads=3, concat=False),
        lambda: nn.LazyLinear(12),
    ],
    ids=["lazy", "lazy-source", "heads-concat", "heads-mean", "lazy-linear"],
)
def test_matching_and_lazy_widths_are_accepted(make):
    layer = make()
    mode = "node" if isinstance(layer, nn.Linear) else "auto"
    eq = Canonicalize(G, T_IN, T_OUT, mode=mode)(layer.double())
    x, f = _inputs()
    out = eq(x, frames=f) if mode == "node" else eq(x, EI, frames=f)
    assert out.shape == (N, T_OUT.dim)


# ------------------------------------------------------------------------------------ empty graphs / batches
@pytest.mark.parametrize(
    ("make", "canon"),
    [
        (lambda: TransformerConv(8, 12), {}),
        (lambda: GCNConv(8, 12), {}),
        (lambda: PointTransformerConv(8, 12, add_self_loops=False), {"self_loops": True}),
        (lambda: nn.Linear(8, 12), {}),
    ],
    ids=["pair", "ego", "pair-pos-self_loops", "node"],
)
@pytest.mark.parametrize("group", [G, gg.Trivial()], ids=["SE2xR", "Trivial"])
def test_zero_node_graph_with_every_check(make, canon, group):
    t_in = FieldType(group, [Scalar(2), Vector(3), Point(3)])
    t_out = FieldType(group, [Scalar(3), Vector(3, n=2), Point(3)])
    layer = make().double()
    eq = Canonicalize(group, t_in, t_out, check_frames=True, check_finite=True, **canon)(layer)
    x, f = torch.zeros(0, 8, dtype=F64), group.identity(0, dtype=F64)
    if eq.mode == "node":
        out = eq(x, frames=f)
    else:
        kw = {"pos": torch.zeros(0, 3, dtype=F64)} if isinstance(layer, PointTransformerConv) else {}
        out = eq(x, torch.zeros(2, 0, dtype=torch.long), frames=f, **kw)
    assert out.shape == (0, 12) and out.dtype == F64


@pytest.mark.parametrize(
    "group",
    [gg.SO2(), gg.SE2xR(), gg.SO3(), gg.SE3(), gg.O2(), gg.Cyclic(4), gg.Translation(2), gg.Trivial(),
     gg.Product(gg.SO2(), gg.Translation(2))],
    ids=repr,
)  # fmt: skip
def test_check_member_of_an_empty_batch(group):
    empty = group.identity(0, dtype=F64)
    group.check_member(empty)
    assert group.membership_residual(empty).shape == (0,)
    assert group.compose(empty, group.inverse(empty)).shape == empty.shape


# ------------------------------------------------------------------------------------ check_finite
def _edge_layer(**canon):
    torch.manual_seed(0)
    return Canonicalize(G, T_IN, T_OUT, check_finite=True, **canon)(TransformerConv(8, 12, edge_dim=4).double())


@pytest.mark.parametrize("typed", [False, True], ids=["invariant", "typed"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_check_finite_covers_edge_attr(typed, value):
    et = FieldType(G, [Scalar(1), Vector(3)]) if typed else None
    eq = _edge_layer(edge_type=et)
    x, f = _inputs()
    ea = torch.randn(EI.shape[1], 4, dtype=F64)
    eq(x, EI, frames=f, edge_attr=ea)  # finite: passes
    ea[5, 2] = value
    words = r"^edge_attr contains NaN or inf \(1 of 28 entries, the first at index \(5, 2\)\)$"
    with pytest.raises(ValueError, match=words):
        eq(x, EI, frames=f, edge_attr=ea)


def test_check_finite_covers_extra_keyword_tensors():
    eq = Canonicalize(G, T_IN, T_OUT, check_finite=True)(GCNConv(8, 12, normalize=False).double())
    x, f = _inputs()
    w = torch.ones(EI.shape[1], dtype=F64)
    eq(x, EI, frames=f, edge_weight=w)
    w[3] = float("nan")
    with pytest.raises(ValueError, match=r"^edge_weight contains NaN or inf"):
        eq(x, EI, frames=f, edge_weight=w)


def test_check_finite_names_the_side_of_a_pair():
    t_src = FieldType(G, [Point(3)])
    eq = Canonicalize(G, (t_src, T_IN), T_OUT, check_finite=True)(
        PointTransformerConv((3, 8), 12, add_self_loops=False).double()
    )
    x, f = _inputs()
    x_src, pos = torch.randn(4, 3, dtype=F64), (torch.randn(4, 3, dtype=F64), torch.randn(N, 3, dtype=F64))
    ei = torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]])
    eq((x_src, x), ei, frames=f, pos=pos)
    pos[0][2, 0] = float("inf")
    with pytest.raises(ValueError, match=r"^pos \(source\) contains NaN or inf"):
        eq((x_src, x), ei, frames=f, pos=pos)


# ------------------------------------------------------------------------------------ dtypes
@pytest.mark.parametrize("dtype", [F64, torch.float16], ids=["f64", "f16"])
@pytest.mark.parametrize("mode", ["pair", "ego", "node"])
@pytest.mark.parametrize("group", [G, gg.Trivial()], ids=["SE2xR", "Trivial"])
def test_features_of_another_dtype_than_the_layer(dtype, mode, group):
    t_in = FieldType(group, [Scalar(2), Vector(3), Point(3)])
    t_out = FieldType(group, [Scalar(3), Vector(3, n=2), Point(3)])
    layer = {"pair": lambda: TransformerConv(8, 12), "ego": lambda: GCNConv(8, 12), "node": lambda: nn.Linear(8, 12)}
    eq = Canonicalize(group, t_in, t_out)(layer[mode]())  # float32 parameters
    x, f = torch.randn(N, 8, dtype=dtype), group.identity(N, dtype=dtype)
    with pytest.raises(TypeError, match=rf"^x has dtype {dtype}, but the parameters of \w+ have dtype torch.float32"):
        eq(x, frames=f) if mode == "node" else eq(x, EI, frames=f)


def test_invariant_edge_attr_of_another_dtype_than_the_layer():
    eq = Canonicalize(G, T_IN, T_OUT)(TransformerConv(8, 12, edge_dim=4))
    x, f = _inputs(F32)
    with pytest.raises(TypeError, match=r"^edge_attr has dtype torch.float64, but the parameters .* torch.float32"):
        eq(x, EI, frames=f, edge_attr=torch.randn(EI.shape[1], 4, dtype=F64))


def test_typed_inputs_must_have_the_dtype_of_x():
    eq = _edge_layer(edge_type=FieldType(G, [Scalar(1), Vector(3)]))
    x, f = _inputs()
    with pytest.raises(TypeError, match=r"^edge_attr has dtype torch.float32 but x has torch.float64"):
        eq(x, EI, frames=f, edge_attr=torch.randn(EI.shape[1], 4))
    pt = Canonicalize(G, T_IN, T_OUT)(PointTransformerConv(8, 12, add_self_loops=False).double())
    with pytest.raises(TypeError, match=r"^pos has dtype torch.float32 but x has torch.float64"):
        pt(x, EI, frames=f, pos=torch.randn(N, 3))


# ------------------------------------------------------------------------------------ batch dimensions
@pytest.mark.parametrize(
    ("arg", "words"),
    [
        ("x", r"^x has shape \(2, 6, 8\), expected \(N, 8\): one row per node and no batch dimension"),
        ("pos", r"^pos has shape \(1, 6, 3\), expected \(N, 3\)"),
        ("edge_attr", r"^edge_attr has shape \(1, 7, 4\), expected \(E, 4\): one row per edge"),
    ],
)
def test_an_extra_batch_dimension_is_named(arg, words):
    torch.manual_seed(0)
    layer = PointTransformerConv(8, 12, add_self_loops=False) if arg == "pos" else TransformerConv(8, 12, edge_dim=4)
    eq = Canonicalize(G, T_IN, T_OUT, edge_type=FieldType(G, [Scalar(1), Vector(3)]))(layer.double())
    x, f = _inputs()
    kw = {"pos": torch.randn(N, 3, dtype=F64)} if arg == "pos" else {"edge_attr": torch.randn(7, 4, dtype=F64)}
    if arg == "x":
        x = torch.stack((x, x))
    else:
        kw[arg] = kw[arg][None]
    with pytest.raises(ValueError, match=words):
        eq(x, EI, frames=f, **kw)


def test_an_extra_batch_dimension_in_node_mode():
    eq = Canonicalize(G, T_IN, T_OUT)(nn.Linear(8, 12).double())
    x, f = _inputs()
    with pytest.raises(ValueError, match=r"^x has shape \(1, 6, 8\), expected \(N, 8\)"):
        eq(x[None], frames=f[None])


# ------------------------------------------------------------------------------------ wrong argument types
@pytest.mark.parametrize(
    ("call", "kind", "words"),
    [
        (lambda: FieldType(T_IN, [Scalar(1)]), TypeError, "FieldType(group, features): group must be a groupcanon "
         "Group, got FieldType (pass its .group"),
        (lambda: FieldType(G, {"a": Scalar(1), "b": 3}), TypeError, "features['b'] must be a FeatureType, got int"),
        (lambda: Vector(3, group=T_IN), TypeError, "Vector(group=...) must be a groupcanon Group, got FieldType"),
        (lambda: Canonicalize(T_IN, T_IN, T_OUT), TypeError, "Canonicalize(group, ...): group must be a groupcanon"),
        (lambda: Canonicalize(G, T_IN, T_OUT, edge_type=Vector(3)), TypeError, "edge_type must be a FieldType, got "
         "Vector"),
        (lambda: Canonicalize(G, T_IN, T_OUT, pos_type="xyz"), TypeError, "pos_type must be a FeatureType or "
         "FieldType, got str"),
        (lambda: localize(G, G.identity(2), torch.zeros(2, 8)), TypeError, "localize() argument field_type must be a "
         "FieldType, got SE2xR"),
        (lambda: localize(T_IN, [[1.0, 0, 0, 0, 0]], torch.zeros(1, 8)), TypeError, "localize() argument frames for "
         "SE2xR(translation_scale=10) must be a torch.Tensor, got list"),
        (lambda: T_IN.act(G.identity(2), [[0.0] * 8] * 2), TypeError, "act() argument x must be a torch.Tensor"),
        (lambda: G.check_member([[1.0, 0, 0, 0, 0]], what="frames"), TypeError, "frames for SE2xR"),
        (lambda: check_group_axioms(T_IN), TypeError, "check_group_axioms() argument group must be a groupcanon "
         "Group, got FieldType"),
        (lambda: check_action_laws(G, [Scalar(1)]), TypeError, "argument feature_type must be a FeatureType or "
         "FieldType, got list"),
        (lambda: assert_equivariant(lambda x: x, G, (torch.zeros(2, 8),), in_types={0: "T_IN"}), TypeError,
         "in_types[0] must be a FieldType, FeatureType, Group or None, got str"),
        (lambda: frames.planar_frame([1.0, 0.0]), TypeError, "planar_frame() argument heading must be a torch.Tensor"),
        (lambda: frames.se2xr_frame(torch.ones(4, 3), torch.ones(4, 2)), ValueError, "se2xr_frame() argument "
         "position has shape (4, 2), expected (*batch, 3)"),
        (lambda: frames.rotation_from_vectors(torch.ones(4, 3), torch.ones(4)), ValueError, "rotation_from_vectors() "
         "argument b has shape (4,), expected (*batch, 3)"),
    ],
    ids=lambda v: "" if callable(v) or isinstance(v, type) else v[:28],
)  # fmt: skip
def test_wrong_argument_types_name_the_argument(call, kind, words):
    with pytest.raises(kind) as info:
        call()
    assert words in str(info.value), str(info.value)


def test_edge_attr_that_is_not_a_tensor():
    eq = _edge_layer()
    x, f = _inputs()
    with pytest.raises(TypeError, match=r"^edge_attr must be a torch\.Tensor, got list"):
        eq(x, EI, frames=f, edge_attr=[[0.0] * 4] * EI.shape[1])


# ------------------------------------------------------------------------------------ Trivial as a drop-in
def test_trivial_is_a_drop_in_for_a_layer_with_positions():
    """A working SE2xR model switched to ``groups.Trivial()`` with nothing else changed (no ``pos_type``) runs with
    positions, and computes the unwrapped layer: the docs' "the same code with groups.Trivial()"."""

    def model(group):
        t_in = FieldType(group, [Scalar(2), Vector(3), Point(3)])
        t_out = FieldType(group, [Scalar(3), Vector(3, n=2), Point(3)])
        torch.manual_seed(0)
        return Canonicalize(group, t_in, t_out)(PointTransformerConv(8, 12, add_self_loops=False).double())

    x, f = _inputs()
    pos = torch.randn(N, 3, dtype=F64)
    model(G)(x, EI, frames=f, pos=pos)  # the working equivariant model
    T = gg.Trivial()
    eq = model(T)
    out = eq(x, EI, frames=T.identity(N, dtype=F64), pos=pos)
    assert out.shape == (N, 12)
    assert torch.allclose(out, eq.layer(x=x, edge_index=EI, pos=pos), atol=1e-12, rtol=0)
