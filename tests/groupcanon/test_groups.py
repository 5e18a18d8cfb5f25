"""Group axioms, exp/log, Haar sampling and the sampling/identity API of every built-in group."""

from __future__ import annotations

import math

import pytest
import torch
from gc_helpers import F32, F64, NEAR_SINGULAR_ANGLES, TOL, all_groups, group_id
from hypothesis import given
from hypothesis import strategies as st

from groupcanon import groups as gg
from groupcanon.testing import check_action_laws, check_group_axioms
from groupcanon.testing import strategies as gst

GROUPS = all_groups()
ELEMENT_SHAPES = {
    "SO2": (2,),
    "SE2": (4,),
    "SE2xR": (5,),
    "SO3": (3, 3),
    "SE3": (3, 4),
    "Trivial": (0,),
    "Cyclic(1)": (2,),
    "Cyclic(5)": (2,),
    "Cyclic(6)": (2,),
    "CyclicSE2(4)": (4,),
    "CyclicSE2xR(4)": (5,),
    "Translation(2)": (2,),
    "Product(SE2, Translation(1))": (5,),
    "Product(SO2, SO3)": (11,),
}


def _key(G) -> str:
    s = group_id(G)
    return s.replace("(translation_scale=10)", "").replace(", translation_scale=10", "")


@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_element_shape_table(G):
    assert tuple(G.element_shape) == ELEMENT_SHAPES[_key(G)]
    assert G.element_numel == math.prod(ELEMENT_SHAPES[_key(G)])


# ------------------------------------------------------------------------------------------------ axioms
@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_group_axioms_hypothesis(G, dtype):
    # float64: 1e-10 (scaled by magnitude by the kit); float32: the stated 1e-4.
    triple = st.tuples(*(gst.elements(G, batch=(16,), dtype=dtype) for _ in range(3)))

    @given(abc=triple)
    def run(abc):
        check_group_axioms(G, elements=abc, dtype=dtype, atol=TOL[dtype])

    run()


@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_group_axioms_default_samples_with_special_elements(G):
    # the kit's own sampler mixes in the near-singular special elements
    check_group_axioms(G, n=48, dtype=F64)
    check_group_axioms(G, n=48, dtype=F32)


@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_compose_with_inverse_gives_identity_exactly_shaped(G):
    a = G.sample(2, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    e = G.compose(a, G.inverse(a))
    assert e.shape == (2, 3, *G.element_shape)
    assert torch.allclose(e, G.identity(2, 3, dtype=F64), atol=1e-12)


# ------------------------------------------------------------------------------------------------ exp / log
def _near_singular(dtype=F64) -> torch.Tensor:
    a = torch.tensor(NEAR_SINGULAR_ANGLES, dtype=F64)
    return torch.cat((a, -a, torch.zeros(1, dtype=F64))).to(dtype)


def _wrap(theta: torch.Tensor) -> torch.Tensor:
    """Principal value in (-pi, pi]."""
    return torch.atan2(torch.sin(theta), torch.cos(theta))


@pytest.mark.parametrize("G", [gg.SO2(), gg.SE2(), gg.SE2xR()], ids=_key)
def test_planar_exp_log_near_singular_angles(G):
    theta = _near_singular()
    k = 1 if type(G) is gg.SO2 else 1 + G.space_dim
    u = 10 * torch.randn(theta.shape[0], k - 1, generator=torch.Generator().manual_seed(0), dtype=F64)
    xi = torch.cat((theta[:, None], u), dim=-1)
    g = G.exp(xi)
    assert torch.isfinite(g).all()
    # exp(log(g)) = g everywhere, including theta ~ +-pi and ~ 2 pi
    assert (G.exp(G.log(g)) - g).abs().max() < 1e-10 * 10
    # log returns the principal angle
    assert (G.log(g)[:, 0] - _wrap(theta)).abs().max() < 1e-10
    # log(exp(xi)) = xi on the principal domain |theta| < pi
    dom = theta.abs() < math.pi
    assert (G.log(g)[dom] - xi[dom]).abs().max() < 1e-10 * 10
    # unit complex layout is preserved
    assert (g[:, 0] ** 2 + g[:, 1] ** 2 - 1).abs().max() < 1e-14
    # float32 with the stated tolerance
    g32 = G.exp(xi.to(F32))
    assert (G.exp(G.log(g32)) - g32).abs().max() < 1e-4 * 10


def test_so2_log_at_exact_half_turn_is_plus_pi():
    G = gg.SO2()
    g = torch.tensor([[-1.0, 0.0]], dtype=F64)
    assert G.log(g).item() == pytest.approx(math.pi, abs=1e-15)


@pytest.mark.parametrize("G", [gg.SO3(), gg.SE3()], ids=_key)
def test_spatial_exp_log_near_singular_angles(G):
    theta = _near_singular()
    gen = torch.Generator().manual_seed(1)
    axis = torch.randn(theta.shape[0], 3, generator=gen, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    w = theta[:, None] * axis
    xi = (
        w
        if isinstance(G, gg.SO3)
        else torch.cat((w, 10 * torch.randn(theta.shape[0], 3, generator=gen, dtype=F64)), -1)
    )
    g = G.exp(xi)
    r = G.rotation(g)
    eye = torch.eye(3, dtype=F64)
    assert (r @ r.transpose(-1, -2) - eye).abs().max() < 1e-12
    assert (torch.linalg.det(r) - 1).abs().max() < 1e-12
    assert (G.exp(G.log(g)) - g).abs().max() < 1e-10 * 10
    dom = theta.abs() < math.pi
    assert (G.log(g)[dom] - xi[dom]).abs().max() < 1e-10 * 10
    # the rotation angle recovered by log is the principal one
    assert (G.log(g)[:, :3].norm(dim=-1) - _wrap(theta).abs()).abs().max() < 1e-9
    g32 = G.exp(xi.to(F32))
    assert (G.exp(G.log(g32)) - g32).abs().max() < 1e-4 * 10


@st.composite
def _lie_algebra(draw, G, dtype=F64):
    """Lie-algebra coordinates inside the principal domain (rotation angle < pi)."""
    gen = torch.Generator().manual_seed(draw(gst.seeds()))
    n = 16
    if isinstance(G, gg.Translation):
        return 10 * torch.randn(n, G.space_dim, generator=gen, dtype=dtype)
    theta = (2 * torch.rand(n, generator=gen, dtype=F64) - 1) * (math.pi - 1e-6)
    if type(G) is gg.SO2:
        return theta[:, None].to(dtype)
    if isinstance(G, (gg.SE2, gg.SE2xR)):
        u = 10 * torch.randn(n, G.space_dim, generator=gen, dtype=F64)
        return torch.cat((theta[:, None], u), -1).to(dtype)
    axis = torch.randn(n, 3, generator=gen, dtype=F64)
    w = theta.abs()[:, None] * axis / axis.norm(dim=-1, keepdim=True)
    if isinstance(G, gg.SO3):
        return w.to(dtype)
    return torch.cat((w, 10 * torch.randn(n, 3, generator=gen, dtype=F64)), -1).to(dtype)


@pytest.mark.parametrize("G", [gg.SO2(), gg.SE2(), gg.SE2xR(), gg.SO3(), gg.SE3(), gg.Translation(2)], ids=_key)
def test_exp_log_are_inverse_on_principal_domain(G):
    @given(xi=_lie_algebra(G), g=gst.elements(G, batch=(16,)))
    def run(xi, g):
        scale = max(1.0, float(xi.abs().max()), float(g.abs().max()))
        assert (G.log(G.exp(xi)) - xi).abs().max() <= 1e-10 * scale
        assert (G.exp(G.log(g)) - g).abs().max() <= 1e-10 * scale
        # exp is a one-parameter subgroup: exp(xi) exp(xi) = exp(2 xi) (rotation part 2 theta may wrap; fine)
        assert (G.compose(G.exp(xi), G.exp(xi)) - G.exp(2 * xi)).abs().max() <= 1e-10 * 4 * scale
        # exp(-xi) = exp(xi)^-1
        assert (G.exp(-xi) - G.inverse(G.exp(xi))).abs().max() <= 1e-10 * scale

    run()


def test_trivial_exp_log():
    G = gg.Trivial()
    assert G.exp(torch.zeros(4, 0)).shape == (4, 0)
    assert G.log(G.identity(4)).shape == (4, 0)


@pytest.mark.parametrize("G", [gg.Cyclic(5), gg.Product(gg.SO2(), gg.SO3())], ids=_key)
def test_exp_log_not_implemented(G):
    with pytest.raises(NotImplementedError):
        G.exp(torch.zeros(2, 1))
    with pytest.raises(NotImplementedError):
        G.log(G.identity(2))


# ------------------------------------------------------------------------------------------------ Haar
N_HAAR = 20000


def test_so2_haar_uniform_angles():
    g = gg.SO2().sample(N_HAAR, generator=torch.Generator().manual_seed(123), dtype=F64)
    theta = torch.atan2(g[:, 1], g[:, 0])
    # std of each mean is sqrt(1/2 / 20000) ~ 0.005: 0.03 is a 6-sigma bound
    for k in (1, 2, 3):
        assert abs(float(torch.cos(k * theta).mean())) < 0.03
        assert abs(float(torch.sin(k * theta).mean())) < 0.03
    hist = torch.histc(theta, bins=8, min=-math.pi, max=math.pi) / N_HAAR
    assert (hist - 1 / 8).abs().max() < 0.015
    assert (g.norm(dim=-1) - 1).abs().max() < 1e-15


@pytest.mark.parametrize("G", [gg.SO3(), gg.SE3()], ids=_key)
def test_so3_haar(G):
    g = G.sample(N_HAAR, generator=torch.Generator().manual_seed(7), dtype=F64)
    r = G.rotation(g)
    eye = torch.eye(3, dtype=F64)
    assert (r @ r.transpose(-1, -2) - eye).abs().max() < 1e-12
    assert (torch.linalg.det(r) - 1).abs().max() < 1e-12
    # E[R] = 0 under Haar (each entry has variance 1/3: std of the mean ~0.004)
    assert r.mean(0).abs().max() < 0.03
    # the defining representation is irreducible: E[tr R] = 0, E[(tr R)^2] = 1 (fails e.g. for uniform rotvecs)
    tr = r.diagonal(dim1=-2, dim2=-1).sum(-1)
    assert abs(float(tr.mean())) < 0.05
    assert abs(float((tr**2).mean()) - 1) < 0.05
    if isinstance(G, gg.SE3):
        t = G.translation(g)
        assert abs(float(t.std()) - G.translation_scale) < 0.03 * G.translation_scale
        assert t.mean(0).abs().max() < 0.3


@pytest.mark.parametrize("G", [gg.SE2(), gg.SE2xR(), gg.Translation(2)], ids=_key)
def test_planar_rigid_sampling(G):
    g = G.sample(N_HAAR, generator=torch.Generator().manual_seed(11), dtype=F64)
    t = G.translation(g)
    assert abs(float(t.std()) - G.translation_scale) < 0.03 * G.translation_scale
    if not isinstance(G, gg.Translation):
        theta = torch.atan2(g[:, 1], g[:, 0])
        assert abs(float(torch.cos(theta).mean())) < 0.03
        assert abs(float(torch.sin(theta).mean())) < 0.03


@pytest.mark.parametrize("n", [1, 5, 6])
def test_cyclic_sampling_uniform_and_on_the_group(n):
    G = gg.Cyclic(n)
    g = G.sample(6000, generator=torch.Generator().manual_seed(5), dtype=F64)
    k = G.index(g)
    assert torch.allclose(G.element(k, dtype=F64), g, atol=1e-15)
    counts = torch.bincount(k, minlength=n).to(F64) / k.numel()
    assert (counts - 1 / n).abs().max() < 0.03
    # every element has order dividing n
    p = G.identity(6000, dtype=F64)
    for _ in range(n):
        p = G.compose(p, g)
    assert torch.allclose(p, G.identity(6000, dtype=F64), atol=1e-12)


def test_cyclic_rejects_bad_order():
    for bad in (0, -3, 2.5):
        with pytest.raises(ValueError, match="positive integer"):
            gg.Cyclic(bad)


# ------------------------------------------------------------------------------------------------ SE2xR = SE2 x R
def test_se2xr_matches_product_se2_translation1_exactly():
    A, B = gg.SE2xR(), gg.Product(gg.SE2(), gg.Translation(1))
    assert A.element_shape == B.element_shape
    assert A.space_dim == B.space_dim == 3 and A.has_translation and B.has_translation

    @given(a=gst.elements(A, batch=(16,)), b=gst.elements(A, batch=(16,)), p=gst.seeds())
    def run(a, b, p):
        pts = 5 * torch.randn(16, 3, generator=torch.Generator().manual_seed(p), dtype=F64)
        assert torch.equal(A.compose(a, b), B.compose(a, b))
        assert torch.equal(A.inverse(a), B.inverse(a))
        assert torch.equal(A.transform(a, pts), B.transform(a, pts))
        assert torch.equal(A.rotate(a, pts), B.rotate(a, pts))
        assert torch.equal(A.translation(a), B.translation(a))
        assert torch.equal(A.rotation(a), B.rotation(a))
        assert torch.equal(A.planar_rotation(a), B.planar_rotation(a))

    run()
    assert torch.equal(A.identity(3, dtype=F64), B.identity(3, dtype=F64))


# ------------------------------------------------------------------------------------------------ API
@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_sample_determinism_dtype_device(G):
    a = G.sample(7, generator=torch.Generator().manual_seed(42), dtype=F64)
    b = G.sample(7, generator=torch.Generator().manual_seed(42), dtype=F64)
    assert torch.equal(a, b)
    if G.element_numel and not (isinstance(G, gg.Cyclic) and G.n == 1):
        c = G.sample(7, generator=torch.Generator().manual_seed(43), dtype=F64)
        assert not torch.equal(a, c)
    for dtype in (F32, F64):
        s = G.sample(3, 2, dtype=dtype, device="cpu")
        assert s.dtype == dtype and s.device.type == "cpu" and s.shape == (3, 2, *G.element_shape)
        assert G.identity(2, dtype=dtype, device=torch.device("cpu")).dtype == dtype
        assert G.special_elements(dtype=dtype).dtype == dtype
    # default dtype follows torch's default
    assert G.sample(2).dtype == torch.get_default_dtype()
    assert G.identity(2).dtype == torch.get_default_dtype()


@pytest.mark.parametrize("batch", [(), (1,), (3,), (2, 4)])
@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_sample_shapes(G, batch):
    s = G.sample(*batch, generator=torch.Generator().manual_seed(0), dtype=F64)
    assert s.shape == (*batch, *G.element_shape)
    assert torch.allclose(G.compose(s, G.inverse(s)), G.identity(*batch, dtype=F64), atol=1e-12)


@pytest.mark.parametrize("batch", [(), (1,), (3,), (2, 4)])
@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_identity_shapes(G, batch):
    e = G.identity(*batch, dtype=F64)
    assert e.shape == (*batch, *G.element_shape)
    assert G.batch_shape(e) == batch
    if G.element_numel:
        # the identity acts trivially (on itself) and is its own inverse
        assert torch.equal(G.compose(e, e), e)
        assert torch.allclose(G.inverse(e), e)


@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_special_elements_are_group_elements(G):
    sp = G.special_elements(dtype=F64)
    assert sp.dim() == 1 + len(G.element_shape) and sp.shape[0] >= 1
    e = G.identity(sp.shape[0], dtype=F64)
    assert torch.allclose(G.compose(sp, G.inverse(sp)), e, atol=1e-12)
    if G.space_dim is not None and not isinstance(G, gg.Trivial):
        r = G.rotation(sp)
        eye = torch.eye(G.space_dim, dtype=F64)
        assert (r @ r.transpose(-1, -2) - eye).abs().max() < 1e-12


@pytest.mark.parametrize("G", GROUPS, ids=_key)
def test_check_element_shape(G):
    G.check(G.identity(3))
    bad = torch.zeros(3, G.element_numel + 1)
    with pytest.raises(ValueError, match="shape"):
        G.check(bad, "frames")


def test_product_factor_pack_roundtrip():
    G = gg.Product(gg.SO2(), gg.SO3(), gg.Translation(2))
    assert G.element_shape == (2 + 9 + 2,)
    g = G.sample(4, generator=torch.Generator().manual_seed(0), dtype=F64)
    parts = [G.factor(g, i) for i in range(3)]
    assert parts[1].shape == (4, 3, 3)
    assert torch.equal(G.pack(parts), g)
    # composing in the product = composing factor-wise
    h = G.sample(4, generator=torch.Generator().manual_seed(1), dtype=F64)
    gh = G.compose(g, h)
    for i, H in enumerate(G.groups):
        assert torch.equal(G.factor(gh, i), H.compose(G.factor(g, i), G.factor(h, i)))


def test_product_needs_two_groups():
    with pytest.raises(ValueError, match="at least two"):
        gg.Product(gg.SO2())
    with pytest.raises(TypeError, match="Groups"):
        gg.Product(gg.SO2(), "SO3")


def test_group_equality_and_hash():
    assert gg.SE2() == gg.SE2() and hash(gg.SE2()) == hash(gg.SE2())
    assert gg.SE2(translation_scale=1.0) == gg.SE2()  # the scale only tunes sampling
    assert hash(gg.SE2(translation_scale=1.0)) == hash(gg.SE2()) and gg.CyclicSE2(4, 1.0) == gg.CyclicSE2(4)
    assert gg.Cyclic(5) != gg.Cyclic(6) and gg.Cyclic(5) != gg.SO2()
    assert gg.Product(gg.SO2(), gg.SO3()) == gg.Product(gg.SO2(), gg.SO3())
    assert gg.Product(gg.SO2(), gg.SO3()) != gg.Product(gg.SO3(), gg.SO2())


@pytest.mark.parametrize("G", [gg.SO2(), gg.SE2(), gg.SE2xR(), gg.SO3(), gg.SE3(), gg.Translation(2)], ids=_key)
def test_matrix_is_faithful_homomorphism(G):
    a = G.sample(8, generator=torch.Generator().manual_seed(0), dtype=F64)
    b = G.sample(8, generator=torch.Generator().manual_seed(1), dtype=F64)
    ma, mb = G.matrix(a), G.matrix(b)
    assert torch.allclose(G.matrix(G.compose(a, b)), ma @ mb, atol=1e-11)
    assert torch.allclose(G.matrix(G.inverse(a)), torch.linalg.inv(ma), atol=1e-11)
    assert not torch.allclose(ma, mb)


@pytest.mark.parametrize("G", [gg.SE2(), gg.SE3()], ids=_key)
@pytest.mark.parametrize("angle", [3e-6, 2.7e-4, 1e-3, 3e-2, 0.4, 0.6, 2.0])
def test_exp_and_log_keep_float32_precision_at_small_angles(G, angle):
    """The left Jacobian's coefficients without cancellation: float32 exp/log agree with float64 to float32
    rounding (relative to the translation) at every angle, just above the series' thresholds included."""
    gen = torch.Generator().manual_seed(0)
    d = G.space_dim
    rot_dim = 1 if d == 2 else 3
    axis = torch.randn(64, rot_dim, generator=gen, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    xi = torch.cat((angle * axis, 10.0 * torch.randn(64, d, generator=gen, dtype=F64)), dim=-1)
    g64, g32 = G.exp(xi), G.exp(xi.float())
    assert float((g32.double() - g64).abs().max()) < 1e-5 * 10
    back = G.log(g64.float()).double()
    assert float((back - xi).abs().max()) < 2e-5 * 10


def test_a_trivial_factor_is_not_an_so2_factor():
    from groupcanon.features import SO2Irrep

    G = gg.Product(gg.SO2(), gg.Trivial())
    g = G.sample(5, generator=torch.Generator().manual_seed(0), dtype=F64)
    torch.testing.assert_close(G.planar_rotation(g), gg.SO2().planar_rotation(G.factor(g, 0)))
    assert check_action_laws(G, SO2Irrep(2), dtype=F64) < 1e-12
