"""The testing kit itself: its checks fail on broken groups / actions / functions, its strategies and frames."""

from __future__ import annotations

import pytest
import torch
from gc_helpers import F32, F64, all_groups, group_id
from hypothesis import Phase, assume, given, settings
from hypothesis import strategies as st

from groupcanon import FieldType, frames
from groupcanon import groups as gg
from groupcanon.features import FeatureType, Point, Scalar, Vector
from groupcanon.groups._util import angle_to_cs, complex_mul
from groupcanon.testing import (
    assert_equivariant,
    assert_invariant,
    check_action_laws,
    check_group_axioms,
    default_atol,
    equivariance_error,
)
from groupcanon.testing import strategies as gst


# ------------------------------------------------------------------------------------------------ broken groups
class NonUnitSO2(gg.SO2):
    """compose forgets to renormalize after adding a tiny error: fails identity by 1e-7."""

    def compose(self, a, b):
        return complex_mul(a, b) * (1 + 1e-7)


class WrongInverseSO2(gg.SO2):
    def inverse(self, a):
        return a  # the identity map is not the inverse


class NonAssociativeSO2(gg.SO2):
    """Angles add with a twist that vanishes when either factor is the identity or they are inverse to each
    other: identity and inverse laws hold, associativity does not."""

    def compose(self, a, b):
        ta, tb = torch.atan2(a[..., 1], a[..., 0]), torch.atan2(b[..., 1], b[..., 0])
        return angle_to_cs(ta + tb + 0.1 * torch.sin(ta) * torch.sin(tb) * (ta + tb))


class OppositeSO3(gg.SO3):
    """a.b = b a as matrices: a perfectly good group (the opposite group), but matrix() is no longer a
    homomorphism and transform is a right action: the affine checks catch it."""

    def compose(self, a, b):
        return b @ a


class WrongTransformSE3(gg.SE3):
    """p -> R^T p + t is not an action."""

    def transform(self, g, p):
        return (g[..., :3].transpose(-1, -2) @ p.unsqueeze(-1)).squeeze(-1) + g[..., 3]


class MinusTranslationSE2(gg.SE2):
    """p -> R p - t is an action of the group, but not the one its translation() and matrix() describe."""

    def transform(self, g, p):
        return self.rotate(g, p) - self.translation(g)


class TransposedRotateSO2(gg.SO2):
    """Vectors turned the opposite way from what matrix() says (and from points)."""

    def rotate(self, g, v):
        c, s = g[..., :1], g[..., 1:]
        return torch.cat((c * v[..., :1] + s * v[..., 1:], -s * v[..., :1] + c * v[..., 1:]), dim=-1)

    def rotation(self, g):
        return super().rotation(g).transpose(-1, -2)


@pytest.mark.parametrize(
    ("G", "law"),
    [
        (NonUnitSO2(), "identity"),
        (WrongInverseSO2(), "inverse"),
        (NonAssociativeSO2(), "associativity"),
        (OppositeSO3(), "matrix"),
        (WrongTransformSE3(), "transform"),
        (MinusTranslationSE2(), "translation"),
        (TransposedRotateSO2(), "rotate"),
    ],
    ids=lambda v: type(v).__name__ if not isinstance(v, str) else v,
)
def test_check_group_axioms_fails_on_broken_groups(G, law):
    with pytest.raises(AssertionError, match=law):
        check_group_axioms(G, dtype=F64)


def test_check_group_axioms_tolerance_is_dtype_aware():
    # a 1e-7 error: caught in float64 (1e-10), inside float32's stated 1e-4
    check_group_axioms(NonUnitSO2(), dtype=F32)
    with pytest.raises(AssertionError, match=r"max error .* > tolerance 1\.0e-10"):
        check_group_axioms(NonUnitSO2(), dtype=F64)
    assert default_atol(F64) == 1e-10 and default_atol(F32) == 1e-4


def test_check_group_axioms_fails_with_hypothesis_elements():
    G = WrongInverseSO2()
    triple = st.tuples(*(gst.elements(gg.SO2(), batch=(8,)) for _ in range(3)))

    @settings(max_examples=5, phases=(Phase.generate,), database=None)  # no shrinking: we only need the failure
    @given(abc=triple)
    def run(abc):
        check_group_axioms(G, elements=abc)

    with pytest.raises(AssertionError, match="inverse"):
        run()


def test_check_group_axioms_passes_and_returns_worst_error():
    worst = check_group_axioms(gg.SE3(), dtype=F64)
    assert 0 < worst < 1e-12


# ------------------------------------------------------------------------------------------------ broken actions
class TransposedVector(FeatureType):
    """v -> R^T v: a right action, so act(a, act(b, x)) != act(a.b, x) for non-commuting rotations."""

    dim = 3

    def act(self, g, x):
        return (g.transpose(-1, -2) @ x.unsqueeze(-1)).squeeze(-1)


class ShiftedScalar(FeatureType):
    """x -> x + 1: not even identity-preserving."""

    dim = 2

    def act(self, g, x):
        return x + 1


class DoubleAngle(FeatureType):
    """Rotation by 2 theta computed as R(g) R(g) v: a valid action (SO2Irrep(2)), for contrast."""

    dim = 2

    def act(self, g, x):
        G = gg.SO2()
        return G.rotate(g, G.rotate(g, x))


class NoBroadcastVector(FeatureType):
    """Correct for matching batches, but ignores the element batch: act(a_0, x) applies a_0 to row 0 only."""

    dim = 2

    def act(self, g, x):
        if g.dim() == 1:
            g = torch.cat((g[None], gg.SO2().identity(x.shape[0] - 1, dtype=x.dtype)))
        return gg.SO2().rotate(g, x)


@pytest.mark.parametrize(
    ("G", "ft", "law"),
    [
        (gg.SO3(), TransposedVector(), "compatibility"),
        (gg.SO2(), ShiftedScalar(), "identity"),
        (gg.SO2(), NoBroadcastVector(), "broadcast"),
    ],
    ids=["transposed", "shifted", "no-broadcast"],
)
def test_check_action_laws_fails_on_broken_types(G, ft, law):
    with pytest.raises(AssertionError, match=law):
        check_action_laws(G, ft, dtype=F64)


def test_check_action_laws_passes_on_a_user_type():
    assert check_action_laws(gg.SO2(), DoubleAngle(), dtype=F64) < 1e-12
    check_action_laws(gg.SO2(), FieldType(gg.SO2(), [DoubleAngle(), Scalar(1)]), dtype=F32)


def test_check_action_laws_rejects_fieldtype_of_other_group():
    with pytest.raises(ValueError, match="FieldType is over"):
        check_action_laws(gg.SO3(), FieldType(gg.SO2(), [Vector(2)]))


# ------------------------------------------------------------------------------------------------ equivariance
def _vec_fn(v):
    return v * (v * v).sum(-1, keepdim=True)  # |v|^2 v: SO(3)-equivariant


def test_assert_equivariant_passes_on_equivariant_function():
    G = gg.SO3()
    v = torch.randn(8, 3, dtype=F64)
    err = assert_equivariant(_vec_fn, G, (v,), in_types={0: Vector(3)}, out_types=Vector(3))
    assert err < 1e-12
    assert_invariant(lambda v: v.norm(dim=-1, keepdim=True), G, (v,), in_types={0: Vector(3)})


@pytest.mark.parametrize(
    "fn",
    [
        lambda v: v + torch.tensor([1.0, 0.0, 0.0], dtype=v.dtype),  # a fixed direction
        lambda v: v * v,  # componentwise
        lambda v: v[:, [1, 0, 2]],  # axis swap
    ],
    ids=["shift", "square", "swap"],
)
def test_assert_equivariant_fails_on_non_equivariant_function(fn):
    G = gg.SO3()
    v = torch.randn(8, 3, dtype=F64)
    assert equivariance_error(fn, G, (v,), in_types={0: Vector(3)}, out_types=Vector(3)) > 1e-3
    with pytest.raises(AssertionError, match="is not equivariant under SO3"):
        assert_equivariant(fn, G, (v,), in_types={0: Vector(3)}, out_types=Vector(3))


def test_assert_invariant_fails_on_equivariant_output():
    v = torch.randn(8, 3, dtype=F64)
    with pytest.raises(AssertionError, match="is not invariant"):
        assert_invariant(_vec_fn, gg.SO3(), (v,), in_types={0: Vector(3)})


def test_point_vs_vector_is_distinguished_by_translations():
    """Declaring a point as a vector is caught under SE(3) (the translation part matters)."""
    G = gg.SE3()
    p = torch.randn(8, 3, dtype=F64)
    centroid = lambda p: p.mean(0, keepdim=True).expand_as(p)  # noqa: E731
    assert_equivariant(centroid, G, (p,), in_types={0: Point(3)}, out_types=Point(3))
    with pytest.raises(AssertionError):
        assert_equivariant(centroid, G, (p,), in_types={0: Point(3)}, out_types=Vector(3))


def test_equivariance_error_argument_checks():
    v = torch.randn(4, 3, dtype=F64)
    with pytest.raises(ValueError, match="positional argument 1"):
        equivariance_error(_vec_fn, gg.SO3(), (v,), in_types={1: Vector(3)})
    with pytest.raises(ValueError, match="keyword 'w'"):
        equivariance_error(_vec_fn, gg.SO3(), (v,), in_types={"w": Vector(3)})
    with pytest.raises(ValueError, match="2 entries"):
        equivariance_error(_vec_fn, gg.SO3(), (v,), in_types={0: Vector(3)}, out_types=[Vector(3), None])
    with pytest.raises(ValueError, match="shape"):
        equivariance_error(_vec_fn, gg.SO3(), (v,), in_types={0: Vector(3)}, g=torch.eye(2, dtype=F64))


def test_equivariance_error_uses_given_elements():
    """With g = identity the error is exactly zero, even for a non-equivariant function."""
    v = torch.randn(4, 3, dtype=F64)
    err = equivariance_error(
        lambda v: v * v, gg.SO3(), (v,), in_types={0: Vector(3)}, out_types=Vector(3), g=gg.SO3().identity(dtype=F64)
    )
    assert err == 0.0


# ------------------------------------------------------------------------------------------------ strategies
@pytest.mark.parametrize("G", all_groups(), ids=group_id)
def test_elements_strategy_shapes_dtypes(G):
    @settings(max_examples=10)
    @given(
        a=gst.elements(G, batch=(5, 2)),
        b=gst.elements(G, batch=(), dtype=F32),
        c=gst.elements(G, batch=(3,), special=False),
    )
    def run(a, b, c):
        assert a.shape == (5, 2, *G.element_shape) and a.dtype == F64
        assert b.shape == tuple(G.element_shape) and b.dtype == F32
        assert c.shape == (3, *G.element_shape)
        for t in (a, b, c):  # genuine group elements: g g^-1 = e
            e = G.compose(t, G.inverse(t))
            assert torch.allclose(e, G.identity(*G.batch_shape(t), dtype=t.dtype), atol=1e-5)

    run()


def test_elements_strategy_mixes_in_special_elements():
    G = gg.SO2()
    sp = G.special_elements(dtype=F64)
    found = []

    @settings(max_examples=30)
    @given(a=gst.elements(G, batch=(8,)))
    def run(a):
        found.append(bool((a[:, None, :] == sp[None]).all(-1).any()))

    run()
    assert any(found)


def test_features_strategy():
    ft = FieldType(gg.SE3(), [Scalar(2), Point(3)])

    @settings(max_examples=10)
    @given(x=gst.features(ft, batch=(4, 3), dtype=F32, scale=5.0), y=gst.features(ft))
    def run(x, y):
        assert x.shape == (4, 3, 5) and x.dtype == F32 and torch.isfinite(x).all()
        assert y.shape == (8, 5) and y.dtype == F64

    run()


@pytest.mark.parametrize("max_degree", [0, 1, 3])
@pytest.mark.parametrize("min_edges", [0, 10])
def test_graphs_strategy(max_degree, min_edges):
    @settings(max_examples=30)
    @given(g=gst.graphs(2, 20, max_degree=max_degree, min_edges=min_edges))
    def run(g):
        ei = g.edge_index
        assert 2 <= g.num_nodes <= 20
        assert ei.dtype == torch.long and ei.dim() == 2 and ei.shape[0] == 2
        if ei.numel():
            assert 0 <= int(ei.min()) and int(ei.max()) < g.num_nodes
        assert (ei[0] != ei[1]).all(), "self loops by default"
        indeg = torch.bincount(ei[1], minlength=g.num_nodes)
        assert int(indeg.max()) <= max_degree
        assert torch.unique(ei, dim=1).shape[1] == ei.shape[1], "duplicate edges"
        possible = g.num_nodes * min(max_degree, g.num_nodes - 1)
        assert ei.shape[1] >= min(min_edges, possible)

    run()


def test_graphs_strategy_self_loops_and_isolated_nodes():
    seen_loop, seen_isolated = [], []

    @settings(max_examples=30)
    @given(g=gst.graphs(3, 12, max_degree=4, self_loops=True))
    def run(g):
        ei = g.edge_index
        seen_loop.append(bool((ei[0] == ei[1]).any()))
        seen_isolated.append(bool((torch.bincount(ei[1], minlength=g.num_nodes) == 0).any()))
        assert int(torch.bincount(ei[1], minlength=g.num_nodes).max()) <= 4

    run()
    assert any(seen_loop) and any(seen_isolated)


# ------------------------------------------------------------------------------------------------ frames
def _vectors(n=16, d=3):
    return gst.features(FieldType(gg.Trivial(), [Vector(d)]), batch=(n,))


def test_planar_frame_is_equivariant():
    G = gg.SO2()

    @given(h=_vectors(d=2), g=gst.elements(G))
    def run(h, g):
        f = frames.planar_frame(h)
        assert torch.allclose(f.norm(dim=-1), torch.ones(16, dtype=F64), atol=1e-12)
        assert (frames.planar_frame(G.rotate(g, h)) - G.compose(g, f)).abs().max() < 1e-10
        # the frame's first axis is the heading direction: canonicalized heading is (|h|, 0)
        local = G.rotate(G.inverse(f), h)
        assert local[:, 1].abs().max() < 1e-10 and (local[:, 0] >= 0).all()

    run()


def test_se2xr_frame_is_equivariant():
    G = gg.SE2xR()

    @given(h=_vectors(), p=_vectors(), g=gst.elements(G))
    def run(h, p, g):
        f = frames.se2xr_frame(h, 10 * p)
        assert f.shape == (16, 5)
        expected = G.compose(g, f)
        got = frames.se2xr_frame(G.rotate(g, h), G.transform(g, 10 * p))
        assert (got - expected).abs().max() < 1e-10 * 40

    run()


def test_rotation_from_vectors_is_an_equivariant_rotation():
    G = gg.SO3()

    @given(a=_vectors(), b=_vectors(), g=gst.elements(G))
    def run(a, b, g):
        sin = torch.linalg.cross(a, b).norm(dim=-1) / (a.norm(dim=-1) * b.norm(dim=-1))
        assume(bool((sin > 1e-3).all()))  # (anti)parallel a, b have no well-defined frame (see the next test)
        r = frames.rotation_from_vectors(a, b)
        eye = torch.eye(3, dtype=F64)
        assert (r @ r.transpose(-1, -2) - eye).abs().max() < 1e-12
        assert (torch.linalg.det(r) - 1).abs().max() < 1e-12  # never a reflection
        # first axis along a, second in the (a, b) plane
        assert (r[..., 0] - a / a.norm(dim=-1, keepdim=True)).abs().max() < 1e-12
        assert (r[..., 2] * a).sum(-1).abs().max() < 1e-9 and (r[..., 2] * b).sum(-1).abs().max() < 1e-9
        got = frames.rotation_from_vectors(G.rotate(g, a), G.rotate(g, b))
        assert (got - g @ r).abs().max() < 1e-10
        # se3_frame adds the position
        p = 10 * b
        f = frames.se3_frame(a, b, p)
        H = gg.SE3()
        gt = H.from_parts(g, 10 * a[0])
        assert (
            frames.se3_frame(H.rotate(gt, a), H.rotate(gt, b), H.transform(gt, p)) - H.compose(gt, f)
        ).abs().max() < 1e-9

    run()


def test_frames_degenerate_inputs_are_finite():
    z = torch.zeros(2, 3, dtype=F64)
    assert torch.equal(frames.planar_frame(z), torch.tensor([[1.0, 0.0]] * 2, dtype=F64))
    for a, b in (
        (z, z),
        (torch.tensor([[0.0, 0.0, 2.0]] * 2, dtype=F64), z),
        (torch.tensor([[1.0, 2.0, 3.0]] * 2, dtype=F64), torch.tensor([[2.0, 4.0, 6.0]] * 2, dtype=F64)),
    ):
        r = frames.rotation_from_vectors(a, b)
        assert torch.isfinite(r).all()
        assert (r @ r.transpose(-1, -2) - torch.eye(3, dtype=F64)).abs().max() < 1e-12
        assert (torch.linalg.det(r) - 1).abs().max() < 1e-12


@pytest.mark.parametrize("angle", [1e-2, 1e-3, 1e-5, 1e-7])
def test_rotation_from_nearly_parallel_vectors_is_a_rotation_in_float32(angle):
    """Two Gram-Schmidt passes: orthonormal to float32 rounding however close ``b`` comes to ``a``."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(4096, 3, generator=gen, dtype=F64)
    side = torch.linalg.cross(a, torch.randn(4096, 3, generator=gen, dtype=F64))
    b = a / a.norm(dim=-1, keepdim=True) + angle * side / side.norm(dim=-1, keepdim=True)
    r = frames.rotation_from_vectors(a.float(), (3.0 * b).float())
    assert float(gg.SO3().membership_residual(r).max()) < 1e-5
    assert bool((torch.linalg.det(r) > 0.9999).all())
