"""Feature types: action laws for every supported (group, type) pair, binding errors, FieldType behaviour."""

from __future__ import annotations

import math

import pytest
import torch
from gc_helpers import F32, F64, TOL, all_groups, group_id
from hypothesis import given, settings
from hypothesis import strategies as st

from groupcanon import FieldType
from groupcanon import groups as gg
from groupcanon.features import FeatureType, OnFactor, Point, Rotation, Scalar, SO2Irrep, Vector
from groupcanon.testing import check_action_laws
from groupcanon.testing import strategies as gst


def _supported_pairs():
    """Every (group, feature type) pair the library supports, with a readable id."""
    pairs = []
    for G in all_groups():
        d = G.space_dim
        types = [Scalar(3)]
        if isinstance(G, gg.Trivial):
            types += [Vector(3), Vector(4, n=2), Point(3, n=2), Rotation(3)]
        else:
            types += [Vector(d), Vector(d, n=3), Point(d), Point(d, n=2), Rotation()]
        has_planar = isinstance(G, (gg.SO2, gg.SE2, gg.SE2xR, gg.Trivial)) or (
            isinstance(G, gg.Product) and any(isinstance(H, (gg.SO2, gg.SE2)) for H in G.groups)
        )
        if has_planar:
            types += [SO2Irrep(k) for k in (-2, 0, 1, 3)]
        if isinstance(G, gg.Product):
            for i, H in enumerate(G.groups):
                types += [
                    OnFactor(i, Scalar(2)),
                    OnFactor(i, Vector(H.space_dim)),
                    OnFactor(i, Point(H.space_dim, n=2)),
                ]
                if isinstance(H, (gg.SO2, gg.SE2)):
                    types.append(OnFactor(i, SO2Irrep(2)))
                else:
                    types.append(OnFactor(i, Rotation()))
        # a named direct sum of everything above
        types.append({f"f{j}": t for j, t in enumerate(types)})
        for t in types:
            ft = FieldType(G, t) if isinstance(t, dict) else FieldType(G, [t])
            tid = "sum" if isinstance(t, dict) else repr(t)
            pairs.append(pytest.param(G, ft, id=f"{group_id(G)}-{tid}"))
    return pairs


PAIRS = _supported_pairs()


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize(("G", "ft"), PAIRS)
def test_action_laws_hypothesis(G, ft, dtype):
    # float64: 1e-10, float32: 1e-4, both scaled by the magnitude of x and the elements (translations ~10).
    # Single types get a third of the profile's examples; the direct sum of all of a group's types gets them all.
    n_examples = settings.default.max_examples
    if len(ft) == 1:
        n_examples = max(5, n_examples // 3)

    @settings(max_examples=n_examples)
    @given(
        a=gst.elements(G, batch=(12,), dtype=dtype),
        b=gst.elements(G, batch=(12,), dtype=dtype),
        x=gst.features(ft, batch=(12,), dtype=dtype, scale=3.0),
    )
    def run(a, b, x):
        check_action_laws(G, ft, elements=(a, b), x=x, dtype=dtype, atol=TOL[dtype])

    run()


def test_every_pair_is_covered():
    covered = {group_id(p.values[0]) for p in PAIRS}
    assert covered == {group_id(G) for G in all_groups()}
    assert len(PAIRS) > 100


# ------------------------------------------------------------------------------------------------ binding errors
@pytest.mark.parametrize(
    ("ftype", "G", "words"),
    [
        (lambda G: Vector(3, group=G), gg.SO2(), ["SO2()", "Vector(3)", "2-D"]),
        (lambda G: Point(2, group=G), gg.SE3(), ["SE3", "Point(2)", "3-D"]),
        (lambda G: SO2Irrep(1, group=G), gg.SO3(), ["SO3()", "SO2Irrep(1)", "SO(2)"]),
        (lambda G: SO2Irrep(2, group=G), gg.SE3(), ["SE3", "SO2Irrep(2)"]),
        (lambda G: SO2Irrep(1, group=G), gg.Product(gg.SO2(), gg.SE2()), ["2 SO(2) factors", "SO2Irrep(1)"]),
        (lambda G: Rotation(group=G), gg.Product(gg.Trivial(), gg.Trivial()), ["Product", "Rotation()"]),
        (lambda G: Rotation(3, group=G), gg.SO2(), ["SO2()", "Rotation(3)"]),
        (lambda G: OnFactor(0, Vector(2), group=G), gg.SE2(), ["OnFactor", "Product", "SE2"]),
        (lambda G: OnFactor(2, Vector(2), group=G), gg.Product(gg.SO2(), gg.SO3()), ["2 factors", "index 2"]),
        (lambda G: OnFactor(-1, Scalar(1), group=G), gg.Product(gg.SO2(), gg.SO3()), ["index -1"]),
        (lambda G: OnFactor(0, Vector(3), group=G), gg.Product(gg.SE2(), gg.Translation(1)), ["SE2", "Vector(3)"]),
    ],
)
def test_unsupported_type_raises_at_construction(ftype, G, words):
    with pytest.raises(ValueError) as info:
        ftype(G)
    for w in words:
        assert w in str(info.value), (w, str(info.value))


def test_rotation_on_group_without_space_dim_raises():
    # Trivial acts on every type of a given dimension, but Rotation() has no dimension to infer from it.
    with pytest.raises(ValueError, match=r"Trivial\(\) has no action on a Euclidean space.*Rotation\(\)"):
        Rotation(group=gg.Trivial())
    assert FieldType(gg.Trivial(), [Rotation(2)]).dim == 4


def test_unsupported_type_raises_when_bound_in_fieldtype():
    with pytest.raises(ValueError, match=r"SO2\(\).*Vector\(3\)"):
        FieldType(gg.SO2(), [Scalar(1), Vector(3)])
    with pytest.raises(ValueError, match=r"SO3\(\).*SO2Irrep\(3\)"):
        FieldType(gg.SO3(), {"a": SO2Irrep(3)})


def test_bound_type_cannot_be_rebound_to_another_group():
    v = Vector(2, group=gg.SO2())
    assert FieldType(gg.SO2(), [v]).features[0] is v
    with pytest.raises(ValueError, match="already bound"):
        FieldType(gg.SE2(), [v])


def test_unbound_type_cannot_act():
    with pytest.raises(RuntimeError, match="not bound"):
        Vector(2).act(gg.SO2().identity(1), torch.zeros(1, 2))


@pytest.mark.parametrize(
    "make", [lambda: Scalar(0), lambda: Vector(0), lambda: Vector(2, n=0), lambda: Point(2.5), lambda: SO2Irrep(0.5)]
)
def test_bad_constructor_arguments(make):
    with pytest.raises(ValueError):
        make()


# ------------------------------------------------------------------------------------------------ FieldType
def test_fieldtype_errors():
    G = gg.SE2xR()
    ft = FieldType(G, [Scalar(2), Vector(3)])
    g = G.identity(4, dtype=F64)
    with pytest.raises(ValueError, match=r"shape \(4, 4\).*\(\*batch, 5\)"):
        ft.act(g, torch.zeros(4, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"shape \(4, 4\).*elements have shape \(\*batch, 5\)"):
        ft.act(torch.zeros(4, 4, dtype=F64), torch.zeros(4, 5, dtype=F64))
    with pytest.raises(ValueError, match=r"batch shape \(4,\) do not broadcast.*batch shape \(3,\)"):
        ft.act(g, torch.zeros(3, 5, dtype=F64))
    with pytest.raises(ValueError, match="shape"):
        ft.act(g, torch.tensor(1.0))
    with pytest.raises(TypeError, match="Group"):
        FieldType("SE2", [Scalar(1)])
    with pytest.raises(TypeError, match="FeatureType"):
        FieldType(G, [Scalar(1), 3])
    with pytest.raises(TypeError):
        FieldType(G, Scalar(1))


def test_fieldtype_invariant_part_broadcasts_too():
    # even purely invariant types refuse batches that do not broadcast
    G = gg.SO2()
    ft = FieldType(G, [Scalar(2)])
    with pytest.raises(ValueError, match="do not broadcast"):
        ft.act(G.identity(4), torch.zeros(3, 2))
    assert ft.act(G.identity(4, 1), torch.zeros(3, 2)).shape == (4, 3, 2)


def test_fieldtype_slice_get_split_add():
    G = gg.SE2xR()
    a = FieldType(G, {"mass": Scalar(1), "vel": Vector(3), "pos": Point(3, n=2)})
    assert a.dim == 1 + 3 + 6 and len(a) == 3
    assert a.slice("vel") == slice(1, 4) and a.slice(2) == slice(4, 10) and a.slice("mass") == slice(0, 1)
    x = torch.arange(2 * a.dim, dtype=F64).reshape(2, a.dim)
    assert torch.equal(a.get(x, "pos"), x[:, 4:10])
    parts = a.split(x)
    assert list(parts) == ["mass", "vel", "pos"]
    assert torch.equal(torch.cat(list(parts.values()), -1), x)
    with pytest.raises(KeyError, match="no field named 'acc'"):
        a.get(x, "acc")

    b = FieldType(G, [Vector(3), SO2Irrep(2)])
    assert list(b.split(torch.zeros(1, b.dim))) == [0, 1]
    s = a + b  # named + unnamed: unnamed fields get "field<i>" names
    assert s.names == ("mass", "vel", "pos", "field3", "field4")
    assert s.dim == a.dim + b.dim
    u = b + b  # unnamed + unnamed stays unnamed
    assert u.names == (None,) * 4 and u.dim == 2 * b.dim
    with pytest.raises(ValueError, match="duplicate field names"):
        a + a
    with pytest.raises(ValueError, match="different groups"):
        a + FieldType(gg.SE3(), [Vector(3)])
    assert a.__add__(1) is NotImplemented
    with pytest.raises(TypeError):
        a + 1

    # the sum acts field by field
    g = G.sample(2, generator=torch.Generator().manual_seed(0), dtype=F64)
    y = torch.randn(2, s.dim, generator=torch.Generator().manual_seed(1), dtype=F64)
    expected = torch.cat((a.act(g, y[:, : a.dim]), b.act(g, y[:, a.dim :])), -1)
    assert torch.allclose(s.act(g, y), expected, atol=1e-12)
    assert s == FieldType(G, {**dict(zip(a.names, a.features)), "field3": Vector(3), "field4": SO2Irrep(2)})
    assert hash(s) == hash(FieldType(G, dict(zip(s.names, s.features))))


def test_fieldtype_equality():
    G = gg.SO2()
    assert FieldType(G, [Vector(2)]) == FieldType(G, [Vector(2)])
    assert FieldType(G, [Vector(2)]) != FieldType(G, {"v": Vector(2)})
    assert FieldType(G, [Vector(2)]) != FieldType(gg.SE2(), [Vector(2)])
    assert FieldType(G, [Vector(2)]) != FieldType(G, [Point(2)])
    assert FieldType(G, [SO2Irrep(1)]) != FieldType(G, [SO2Irrep(-1)])


# ------------------------------------------------------------------------------------------------ Trivial
@pytest.mark.parametrize(
    "t", [Scalar(2), Vector(7), Vector(2, n=3), Point(4, n=2), Rotation(3), SO2Irrep(3), SO2Irrep(0)], ids=repr
)
def test_trivial_acts_as_identity(t):
    G = gg.Trivial()
    ft = FieldType(G, [t, Vector(5)])
    x = torch.randn(6, ft.dim, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert torch.equal(ft.act(G.identity(6, dtype=F64), x), x)
    assert torch.equal(ft.act(G.sample(6, dtype=F64), x), x)
    assert torch.equal(ft.act(G.identity(dtype=F64), x), x)  # a single (unbatched) element broadcasts


# ------------------------------------------------------------------------------------------------ explicit formulas
RIGID = [gg.SO2(), gg.SE2(), gg.SE2xR(), gg.SO3(), gg.SE3(), gg.Translation(2), gg.Cyclic(6)]
RIGID += [gg.Product(gg.SE2(), gg.Translation(1)), gg.Product(gg.SO2(), gg.SO3())]


@pytest.mark.parametrize("G", RIGID, ids=group_id)
def test_builtin_types_match_matrix_formulas(G):
    d = G.space_dim

    @given(g=gst.elements(G, batch=(10,)), seed=gst.seeds())
    def run(g, seed):
        gen = torch.Generator().manual_seed(seed)
        R, t = G.rotation(g), G.translation(g)
        assert R.shape == (10, d, d) and t.shape == (10, d)
        ft = FieldType(G, {"v": Vector(d, n=3), "p": Point(d, n=2), "r": Rotation()})
        x = torch.randn(10, ft.dim, generator=gen, dtype=F64)
        y = ft.split(ft.act(g, x))
        v = ft.get(x, "v").reshape(10, 3, d)
        p = ft.get(x, "p").reshape(10, 2, d)
        X = ft.get(x, "r").reshape(10, d, d)
        tol = 1e-10 * max(1.0, float(g.abs().max()))
        assert (y["v"].reshape(10, 3, d) - torch.einsum("bij,bnj->bni", R, v)).abs().max() <= tol
        assert (y["p"].reshape(10, 2, d) - (torch.einsum("bij,bnj->bni", R, p) + t[:, None])).abs().max() <= tol
        assert (y["r"].reshape(10, d, d) - R @ X).abs().max() <= tol
        # consistency with the group's own rotate/transform
        assert (G.rotate(g, v[:, 0]) - (R @ v[:, 0, :, None])[..., 0]).abs().max() <= tol
        assert (G.transform(g, p[:, 0]) - (R @ p[:, 0, :, None])[..., 0] - t).abs().max() <= tol

    run()


@pytest.mark.parametrize("k", [-2, -1, 0, 1, 3])
@pytest.mark.parametrize("G", [gg.SO2(), gg.SE2(), gg.SE2xR(), gg.Cyclic(5)], ids=group_id)
def test_so2_irrep_matches_power_of_rotation(G, k):
    g = G.sample(16, generator=torch.Generator().manual_seed(2), dtype=F64)
    x = torch.randn(16, 1 if k == 0 else 2, generator=torch.Generator().manual_seed(3), dtype=F64)
    y = FieldType(G, [SO2Irrep(k)]).act(g, x)
    if k == 0:
        assert torch.equal(y, x)
        return
    R = G.rotation(g)[..., :2, :2]
    Rk = torch.linalg.matrix_power(R if k > 0 else R.transpose(-1, -2), abs(k))
    assert (y - (Rk @ x[..., None])[..., 0]).abs().max() < 1e-12
    if k == 1:  # SO2Irrep(1) is the (horizontal part of the) vector representation
        pad = torch.cat((x, torch.zeros(16, G.space_dim - 2, dtype=F64)), -1)
        assert (y - FieldType(G, [Vector(G.space_dim)]).act(g, pad)[:, :2]).abs().max() < 1e-12


def test_so2_irrep_on_product_uses_the_planar_factor():
    G = gg.Product(gg.SO3(), gg.SE2())
    g = G.sample(8, generator=torch.Generator().manual_seed(0), dtype=F64)
    x = torch.randn(8, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    y = FieldType(G, [SO2Irrep(2)]).act(g, x)
    y_factor = FieldType(gg.SE2(), [SO2Irrep(2)]).act(G.factor(g, 1), x)
    assert torch.equal(y, y_factor)
    assert torch.equal(y, FieldType(G, [OnFactor(1, SO2Irrep(2))]).act(g, x))


def test_onfactor_acts_through_one_factor_only():
    G = gg.Product(gg.SO2(), gg.SO3())
    g = G.sample(8, generator=torch.Generator().manual_seed(0), dtype=F64)
    v = torch.randn(8, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    y = FieldType(G, [OnFactor(1, Vector(3))]).act(g, v)
    assert torch.allclose(y, (G.factor(g, 1) @ v[..., None])[..., 0], atol=1e-14)
    # block-diagonal action of the product on Vector(5) = Vector(2) on factor 0 + Vector(3) on factor 1
    w = torch.randn(8, 5, generator=torch.Generator().manual_seed(2), dtype=F64)
    full = FieldType(G, [Vector(5)]).act(g, w)
    split = FieldType(G, [OnFactor(0, Vector(2)), OnFactor(1, Vector(3))]).act(g, w)
    assert torch.allclose(full, split, atol=1e-14)


def test_point_translation_and_vector_invariance_under_translation_group():
    G = gg.Translation(2)
    g = G.sample(5, generator=torch.Generator().manual_seed(0), dtype=F64)
    x = torch.randn(5, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    ft = FieldType(G, [Vector(2), Point(2)])
    y = ft.act(g, x)
    assert torch.equal(y[:, :2], x[:, :2])
    assert torch.allclose(y[:, 2:], x[:, 2:] + g, atol=1e-14)


def test_user_defined_feature_type():
    class Angle(FeatureType):
        """A planar heading angle (mod 2 pi) under SO(2): theta -> theta + phi."""

        dim = 1

        def act(self, g, x):
            phi = torch.atan2(g[..., 1], g[..., 0])[..., None]
            return torch.remainder(x + phi + math.pi, 2 * math.pi) - math.pi

    G = gg.SO2()
    ft = FieldType(G, [Angle(), Scalar(1)])
    assert ft.features[0].bind(G) is ft.features[0]
    g = G.sample(4, generator=torch.Generator().manual_seed(0), dtype=F64)
    x = torch.zeros(4, 2, dtype=F64)
    assert torch.allclose(ft.act(g, x)[:, 0], torch.atan2(g[:, 1], g[:, 0]), atol=1e-14)


# ------------------------------------------------------------------------------------------ act_gathered
@pytest.mark.parametrize("G", [gg.SE2xR(), gg.SE3(), gg.SO2(), gg.Trivial()], ids=group_id)
@settings(max_examples=10, deadline=None)
@given(seed=gst.seeds())
def test_act_gathered_equals_act_of_gathered_rows(G, seed):
    """The canonicalizer's fast path: act_gathered(g, x, index) is exactly act(g, x[index]), gradients included."""
    d = G.space_dim or 3
    ft = FieldType(G, [Scalar(3), Vector(d), Point(d), Scalar(2), Vector(d, n=2)])
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(7, ft.dim, generator=gen, dtype=F64, requires_grad=True)
    index = torch.randint(0, 7, (20,), generator=gen)
    g = G.sample(20, generator=gen, dtype=F64)
    fast, ref = ft.act_gathered(g, x, index), ft.act(g, x[index])
    assert torch.equal(fast, ref)
    w = torch.randn(fast.shape, generator=gen, dtype=F64)
    (gf,) = torch.autograd.grad((fast * w).sum(), x)
    (gr,) = torch.autograd.grad((ref * w).sum(), x)
    assert torch.allclose(gf, gr, atol=1e-12)


# ------------------------------------------------------------------------------------------ planar fast path
PLANAR_GROUPS = [gg.SO2(), gg.SE2(), gg.SE2xR(), gg.Product(gg.SE2(), gg.Translation(1))]


def _field_by_field(ft: FieldType, g: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """The reference: every field acted on by its own feature type, concatenated."""
    return torch.cat([f.act(g, x[..., ft.slice(i)]) for i, f in enumerate(ft.features)], dim=-1)


@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize("G", PLANAR_GROUPS, ids=group_id)
@settings(max_examples=15, deadline=None)
@given(seed=gst.seeds(), kinds=st.lists(st.sampled_from(["s", "v", "v2", "r"]), min_size=1, max_size=5))
def test_planar_fast_path_equals_field_by_field(G, dtype, seed, kinds):
    """Groups that rotate the first two axes act on sums of scalars, vectors and rotations with one lifted matrix
    product (``FieldType._planar``): the same numbers as acting field by field (float64 1e-12; float32 1e-6, the
    inputs are O(1)), through ``act`` and ``act_gathered``, gradients included."""
    d = G.space_dim
    make = {"s": lambda: Scalar(2), "v": lambda: Vector(d), "v2": lambda: Vector(d, n=2), "r": lambda: Rotation()}
    ft = FieldType(G, [make[k]() for k in kinds])
    assert (ft._planar is not None) == (not ft.invariant)
    gen = torch.Generator().manual_seed(seed)
    tol = 1e-12 if dtype == F64 else 1e-6
    x = torch.randn(7, ft.dim, generator=gen, dtype=dtype, requires_grad=True)
    g = G.sample(7, generator=gen, dtype=dtype)
    out, ref = ft.act(g, x), _field_by_field(ft, g, x)
    assert torch.allclose(out, ref, rtol=0.0, atol=tol)
    index = torch.randint(0, 7, (20,), generator=gen)
    ge = G.sample(20, generator=gen, dtype=dtype)
    gathered = ft.act_gathered(ge, x, index)
    assert torch.allclose(gathered, _field_by_field(ft, ge, x[index]), rtol=0.0, atol=tol)
    w = torch.randn(gathered.shape, generator=gen, dtype=dtype)
    (g_fast,) = torch.autograd.grad((gathered * w).sum(), x)
    (g_ref,) = torch.autograd.grad((_field_by_field(ft, ge, x[index]) * w).sum(), x)
    assert torch.allclose(g_fast, g_ref, rtol=0.0, atol=10 * tol)


@pytest.mark.parametrize(
    ("G", "types"),
    [
        (gg.SO3(), [Scalar(1), Vector(3), Rotation()]),  # rotations about every axis
        (gg.SE3(), [Vector(3), Rotation()]),
        (gg.O2(), [Vector(2)]),  # reflections: no planar rotation
        (gg.SE2xR(), [Vector(3), Point(3)]),  # points are translated too
        (gg.SE2(), [Vector(2), SO2Irrep(2)]),  # frequency 2: not linear in (cos, sin)
        (gg.Trivial(), [Vector(3)]),
    ],
    ids=["SO3", "SE3", "O2", "SE2xR-point", "SE2-irrep2", "trivial"],
)
def test_planar_fast_path_only_where_it_is_exact(G, types):
    ft = FieldType(G, types)
    assert ft._planar is None
    g = G.sample(5, generator=torch.Generator().manual_seed(1), dtype=F64)
    x = torch.randn(5, ft.dim, dtype=F64, generator=torch.Generator().manual_seed(2))
    assert torch.allclose(ft.act(g, x), _field_by_field(ft, g, x), atol=1e-12)
