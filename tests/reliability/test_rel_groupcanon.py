"""groupcanon: elements of the wrong shape, frames that are not group elements, non-finite headings, bad
edge indices and dtypes give a clear error naming the input (or, for NaN headings, a NaN frame)."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from groupcanon import Canonicalize, FieldType, frames
from groupcanon import groups as gg
from groupcanon.features import Scalar, Vector

F64 = torch.float64
GROUPS = {
    "SO2": gg.SO2(),
    "SE2": gg.SE2(),
    "SE2xR": gg.SE2xR(),
    "SO3": gg.SO3(),
    "SE3": gg.SE3(),
    "O2": gg.O2(),
    "Cyclic4": gg.Cyclic(4),
    "Translation3": gg.Translation(3),
    "SO2xT2": gg.Product(gg.SO2(), gg.Translation(2)),
}


def _wrong(G):
    """An element-shaped tensor with one trailing entry too many."""
    shape = list(G.element_shape)
    shape[-1] += 1
    return torch.zeros(3, *shape, dtype=F64)


@pytest.mark.parametrize("name", sorted(GROUPS))
def test_compose_checks_the_element_shape(name):
    G = GROUPS[name]
    with pytest.raises(ValueError, match=r"compose\(\) argument 2 .* elements have shape"):
        G.compose(G.identity(3, dtype=F64), _wrong(G))


@pytest.mark.parametrize("name", sorted(GROUPS))
def test_inverse_checks_the_element_shape(name):
    G = GROUPS[name]
    with pytest.raises(ValueError, match=r"inverse\(\) argument 1"):
        G.inverse(_wrong(G))


@pytest.mark.parametrize("name", ["SO2", "SE2xR", "SO3", "SE3", "O2"])
def test_rotate_checks_the_element_shape(name):
    G = GROUPS[name]
    with pytest.raises(ValueError, match=r"rotate\(\) argument 1"):
        G.rotate(_wrong(G), torch.zeros(3, G.space_dim, dtype=F64))


@pytest.mark.parametrize("name", ["SE2", "SE3"])
def test_transform_checks_the_element_shape(name):
    G = GROUPS[name]
    with pytest.raises(ValueError, match=r"transform\(\) argument 1"):
        G.transform(_wrong(G), torch.zeros(3, G.space_dim, dtype=F64))


def test_field_act_checks_the_element_shape():
    G = gg.SE2xR()
    ft = FieldType(G, [Vector(3)])
    with pytest.raises(ValueError, match=r"\(\*batch, 5\)"):
        ft.act(torch.zeros(4, 4, dtype=F64), torch.zeros(4, 3, dtype=F64))


def test_a_non_tensor_element_is_a_type_error():
    with pytest.raises(TypeError, match=r"torch\.Tensor"):
        gg.SO2().inverse([1.0, 0.0])


# ------------------------------------------------------------------------------------------------ membership
@pytest.mark.parametrize("name", sorted(GROUPS))
def test_sampled_elements_are_members(name):
    G = GROUPS[name]
    G.check_member(G.sample(16, generator=torch.Generator().manual_seed(0), dtype=F64), atol=1e-9)


@pytest.mark.parametrize(
    "name, bad",
    [
        ("SO2", torch.tensor([[2.0, 0.0]], dtype=F64)),  # not unit
        ("SE2xR", torch.tensor([[0.5, 0.5, 0.0, 0.0, 1.0]], dtype=F64)),
        ("SO3", torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64))[None]),  # a reflection
        ("SO3", torch.tensor([[[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]], dtype=F64)),  # sheared
        ("SE3", torch.cat((2 * torch.eye(3, dtype=F64), torch.zeros(3, 1, dtype=F64)), -1)[None]),
        ("O2", torch.tensor([[[1.0, 0.0], [0.0, 2.0]]], dtype=F64)),
        ("SO2", torch.tensor([[float("nan"), 0.0]], dtype=F64)),
        ("SO2xT2", torch.tensor([[1.0, 1.0, 0.0, 0.0]], dtype=F64)),
        ("Translation3", torch.tensor([[float("inf"), 0.0, 0.0]], dtype=F64)),
    ],
)
def test_non_members_are_reported(name, bad):
    with pytest.raises(ValueError, match=r"frames: 1 of 1 are not elements of"):
        GROUPS[name].check_member(bad, atol=1e-4, what="frames")


def test_o2_reflections_are_members():
    gg.O2().check_member(torch.diag(torch.tensor([1.0, -1.0], dtype=F64))[None], atol=1e-12)


def test_membership_tolerance_is_respected():
    G = gg.SO2()
    g = torch.tensor([[1.0 + 1e-6, 0.0]], dtype=F64)
    G.check_member(g, atol=1e-4)
    with pytest.raises(ValueError, match="atol=1e-08"):
        G.check_member(g, atol=1e-8)


# ------------------------------------------------------------------------------------------------ Canonicalize
class _Lin(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(3, 3, dtype=F64)

    def forward(self, x):
        return self.lin(x)


def _node_layer(**kw):
    G = gg.SE2xR()
    ft = FieldType(G, [Vector(3)])
    return G, Canonicalize(G, ft, ft, **kw)(_Lin())


def test_check_frames_refuses_non_unit_planar_frames():
    G, layer = _node_layer(check_frames=True)
    f = G.identity(4, dtype=F64)
    f[2, :2] = torch.tensor([0.6, 0.6], dtype=F64)
    with pytest.raises(ValueError, match="frames: 1 of 4 are not elements of SE2xR"):
        layer(torch.zeros(4, 3, dtype=F64), frames=f)


def test_check_frames_accepts_valid_frames():
    G, layer = _node_layer(check_frames=True, frame_atol=1e-9)
    out = layer(torch.ones(4, 3, dtype=F64), frames=G.sample(4, dtype=F64))
    assert out.shape == (4, 3)


def test_frame_atol_must_be_non_negative():
    with pytest.raises(ValueError, match="frame_atol"):
        _node_layer(check_frames=True, frame_atol=-1.0)


def test_frames_of_another_dtype_are_a_type_error():
    G, layer = _node_layer()
    with pytest.raises(TypeError, match=r"frames have dtype torch.float32 but x has torch.float64"):
        layer(torch.zeros(4, 3, dtype=F64), frames=G.identity(4, dtype=torch.float32))


class _Sum(nn.Module):
    """A minimal ego-mode message-passing layer: sums source features into targets."""

    def forward(self, x, edge_index):
        out = torch.zeros(x.shape[0], x.shape[1], dtype=x.dtype)
        return out.index_add(0, edge_index[1], x.index_select(0, edge_index[0]))


@pytest.mark.parametrize("check", [False, True])
def test_edge_index_out_of_range_names_it(check):
    G = gg.SO2()
    ft = FieldType(G, [Scalar(2)])
    layer = Canonicalize(G, ft, ft, mode="ego", check_frames=check)(_Sum())
    ei = torch.tensor([[0, 1, 7], [1, 2, 0]])
    with pytest.raises(ValueError, match=r"edge_index row 0 \(sources\).*outside \[0, 3\)"):
        layer(torch.ones(3, 2, dtype=F64), ei, frames=G.identity(3, dtype=F64))


def test_negative_edge_index_names_it():
    G = gg.SO2()
    ft = FieldType(G, [Scalar(2)])
    layer = Canonicalize(G, ft, ft, mode="ego", check_frames=True)(_Sum())
    ei = torch.tensor([[0, 1], [1, -1]])
    with pytest.raises(ValueError, match=r"edge_index row 1 \(targets\)"):
        layer(torch.ones(3, 2, dtype=F64), ei, frames=G.identity(3, dtype=F64))


def test_float_edge_index_names_it():
    G = gg.SO2()
    ft = FieldType(G, [Scalar(2)])
    layer = Canonicalize(G, ft, ft, mode="ego")(_Sum())
    with pytest.raises(ValueError, match=r"edge_index must have dtype torch\.long"):
        layer(torch.ones(3, 2, dtype=F64), torch.zeros(2, 2), frames=G.identity(3, dtype=F64))


# ------------------------------------------------------------------------------------------------ frame helpers
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_planar_frame_propagates_non_finite_headings(value):
    f = frames.planar_frame(torch.tensor([[value, 0.0], [0.0, 2.0]], dtype=F64))
    assert torch.isnan(f[0]).all()
    assert torch.allclose(f[1], torch.tensor([0.0, 1.0], dtype=F64))


def test_zero_heading_falls_back_to_the_identity():
    f = frames.planar_frame(torch.zeros(1, 2, dtype=F64))
    assert torch.equal(f, torch.tensor([[1.0, 0.0]], dtype=F64))


def test_rotation_from_vectors_propagates_nan():
    a = torch.tensor([[float("nan"), 0.0, 0.0]], dtype=F64)
    r = frames.rotation_from_vectors(a, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64))
    assert torch.isnan(r).any()
    with pytest.raises(ValueError, match="not elements of SO3"):
        gg.SO3().check_member(r)


def test_se2xr_frame_of_a_nan_heading_is_not_the_identity():
    f = frames.se2xr_frame(torch.tensor([[float("nan"), 1.0, 0.0]], dtype=F64), torch.zeros(1, 3, dtype=F64))
    assert not torch.equal(f, gg.SE2xR().identity(1, dtype=F64))
    assert math.isnan(float(f[0, 0]))


@given(n=st.integers(1, 12), k=st.integers(-30, 30), frac=st.floats(0.05, 0.95))
@settings(max_examples=60, deadline=None)
def test_cyclic_membership_is_a_multiple_of_its_angle(n, k, frac):
    """C_n holds the rotations by multiples of 2 pi / n and no other unit vector (float64, atol 1e-9)."""
    G = gg.Cyclic(n)
    G.check_member(G.element(torch.tensor([k]), dtype=F64), atol=1e-9)
    G.check_member(G.element(torch.tensor([k]), dtype=torch.float32), atol=1e-6)  # float32: stated tolerance
    between = 2 * math.pi * (k + frac) / n  # strictly between two elements of C_n, at least 0.05 steps from both
    g = torch.tensor([[math.cos(between), math.sin(between)]], dtype=F64)
    gg.SO2().check_member(g, atol=1e-9)  # a unit vector: in SO(2) ...
    with pytest.raises(ValueError, match=r"not elements of Cyclic"):
        G.check_member(g, atol=1e-3)  # ... but not in C_n
