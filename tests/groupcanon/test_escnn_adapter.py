"""groupcanon.compat.escnn: escnn representations as batched, differentiable groupcanon feature types.

Needs escnn (numpy<2): run with ``make test-escnn`` (``.venv-escnn``); skipped in the core environment.

Checked for SO(2), O(2), C_n and SO(3) representations (irreps, direct sums, changes of basis, regular ones):
(a) the matrices equal escnn's ``rep(element)`` in float64 to 1e-10 at Haar-random elements; (b) the action laws
hold in float64 (1e-10) and float32 (1e-4), near-singular elements included; (c) one call handles 10_000
elements (timing against a per-element escnn loop is printed, not asserted); (d) gradients with respect to the
group element are finite and equal finite differences along the group.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

pytestmark = pytest.mark.escnn

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message=".*py3nj.*")  # escnn works without py3nj (see requirements/escnn.txt)
    pytest.importorskip("escnn")
    from escnn import group as eg

from groupcanon import FieldType  # noqa: E402
from groupcanon.compat.escnn import EscnnFeature, from_escnn, to_escnn_element  # noqa: E402
from groupcanon.features import Scalar, Vector  # noqa: E402
from groupcanon.groups import O2, SE2, SE3, SO2, SO3, Cyclic, SE2xR, Trivial  # noqa: E402
from groupcanon.testing import check_action_laws  # noqa: E402
from groupcanon.testing import strategies as gst  # noqa: E402

F64, F32 = torch.float64, torch.float32
TOL = {F64: 1e-10, F32: 1e-4}

SO2_E, O2_E, SO3_E = eg.so2_group(8), eg.o2_group(8), eg.so3_group(6)


def _random_basis(n: int, seed: int, orthogonal: bool = False) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(n, n))
    return np.linalg.qr(a)[0] if orthogonal else a + n * np.eye(n)  # well-conditioned either way


def _representations() -> dict:
    so2, o2, so3 = SO2_E, O2_E, SO3_E
    c5, c6 = eg.cyclic_group(5), eg.cyclic_group(6)
    so2_sum = eg.directsum([so2.irrep(0), so2.irrep(2), so2.irrep(1), so2.irrep(2)])
    so3_sum = eg.directsum([so3.irrep(0), so3.irrep(1), so3.irrep(2), so3.irrep(1)])
    return {
        "SO2_irrep0": so2.irrep(0),
        "SO2_irrep1": so2.irrep(1),
        "SO2_irrep3": so2.irrep(3),
        "SO2_sum_basis": eg.change_basis(so2_sum, _random_basis(7, 0), "so2_sum_basis"),
        "SO2_bl_regular3": so2.bl_regular_representation(3),
        "C5_regular": c5.regular_representation,
        "C6_regular": c6.regular_representation,
        "C6_sum_basis": eg.change_basis(
            eg.directsum([c6.irrep(0), c6.irrep(3), c6.irrep(2), c6.irrep(1)]), _random_basis(6, 1), "c6_sum"
        ),
        "O2_irreps": eg.directsum([o2.irrep(0, 0), o2.irrep(1, 0), o2.irrep(1, 1), o2.irrep(1, 3)]),
        "O2_standard": o2.standard_representation(),
        "O2_bl_regular2": o2.bl_regular_representation(2),
        "SO3_l1": so3.irrep(1),
        "SO3_l2": so3.irrep(2),
        "SO3_standard": so3.standard_representation(),
        "SO3_sum_basis": eg.change_basis(so3_sum, _random_basis(12, 2, orthogonal=True), "so3_sum_basis"),
        "SO3_bl_regular2": so3.bl_regular_representation(2),
        "SO3_l3_l5_l6": eg.directsum([so3.irrep(3), so3.irrep(5), so3.irrep(6)]),  # both evaluation paths
    }


REPS = _representations()
NAMES = list(REPS)
CONTINUOUS = [n for n in NAMES if not n.startswith("C") and n != "SO2_irrep0"]  # g-dependent, differentiable
FEATURES: dict[str, EscnnFeature] = {}


def feature(name: str) -> EscnnFeature:
    if name not in FEATURES:
        FEATURES[name] = from_escnn(REPS[name])
    return FEATURES[name]


def escnn_matrices(rep, g: torch.Tensor) -> np.ndarray:
    return np.stack([np.asarray(rep(to_escnn_element(rep.group, gi)), dtype=np.float64) for gi in g])


def test_default_groups():
    expected = {"SO2": SO2(), "C5": Cyclic(5), "C6": Cyclic(6), "O2": O2(), "SO3": SO3()}
    for name in NAMES:
        ft = feature(name)
        assert ft.group == expected[name.split("_")[0]], name
        assert ft.dim == REPS[name].size
    assert feature("SO2_irrep0").invariant and not feature("SO2_irrep1").invariant


# ----------------------------------------------------------------------------------------- (a) equals escnn
@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=8)
@given(seed=gst.seeds())
def test_matches_escnn(name, seed):
    ft, rep = feature(name), REPS[name]
    gen = torch.Generator().manual_seed(seed)
    g = ft.group.sample(6, generator=gen, dtype=F64)  # Haar-random: where escnn itself is exact (see below)
    ref = escnn_matrices(rep, g)
    ours = ft.matrix(g)
    assert ours.shape == (6, ft.dim, ft.dim) and ours.dtype == F64
    np.testing.assert_allclose(ours.numpy(), ref, atol=TOL[F64], rtol=0)
    x = torch.randn(6, ft.dim, generator=gen, dtype=F64)
    np.testing.assert_allclose(ft.act(g, x).numpy(), np.einsum("bij,bj->bi", ref, x.numpy()), atol=TOL[F64], rtol=0)


def test_cyclic_covers_every_element():
    for name in ("C5_regular", "C6_regular", "C6_sum_basis"):
        ft, rep = feature(name), REPS[name]
        g = ft.group.element(torch.arange(ft.group.n), dtype=F64)
        np.testing.assert_allclose(ft.matrix(g).numpy(), escnn_matrices(rep, g), atol=TOL[F64], rtol=0)


@pytest.mark.parametrize("flip", [False, True])
def test_o2_convention(flip):
    """escnn's O(2) element (f, theta) is R(theta) M^f: its standard representation is our matrix itself."""
    theta = torch.linspace(-math.pi, math.pi, 9, dtype=F64)
    g = O2().element(theta, flip)
    np.testing.assert_allclose(escnn_matrices(REPS["O2_standard"], g), g.numpy(), atol=1e-14, rtol=0)
    np.testing.assert_allclose(feature("O2_standard").matrix(g).numpy(), g.numpy(), atol=1e-14, rtol=0)


def test_so3_near_singular_elements_are_exact():
    """At the identity and half turns escnn (Euler angles) loses up to ~1e-7; the adapter stays exact."""
    R = SO3().special_elements(dtype=F64)
    ours = feature("SO3_standard").matrix(R)
    np.testing.assert_allclose(ours.numpy(), R.numpy(), atol=1e-13, rtol=0)  # the standard rep is R itself
    escnn_err = np.abs(escnn_matrices(REPS["SO3_standard"], R) - R.numpy()).max()
    print(
        f"\nSO(3) standard rep at near-singular rotations: adapter error {(ours - R).abs().max():.1e}, "
        f"escnn error {escnn_err:.1e}"
    )


# ----------------------------------------------------------------------------------------- (b) action laws
@pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])
@pytest.mark.parametrize("name", NAMES)
def test_action_laws(name, dtype):
    ft = feature(name)
    check_action_laws(ft.group, ft, dtype=dtype, atol=TOL[dtype])


@pytest.mark.parametrize("name", ["SO2_sum_basis", "C6_sum_basis", "O2_bl_regular2", "SO3_sum_basis"])
@given(data=st.data())
def test_action_laws_hypothesis(name, data):
    ft = feature(name)
    a = data.draw(gst.elements(ft.group, batch=(8,)))  # mixes in near-singular elements
    b = data.draw(gst.elements(ft.group, batch=(8,)))
    check_action_laws(ft.group, ft, elements=(a, b), atol=TOL[F64])


@pytest.mark.parametrize(
    ("name", "group"),
    [
        ("SO2_sum_basis", SE2()),
        ("SO2_sum_basis", SE2xR()),
        ("SO2_sum_basis", Cyclic(7)),
        ("SO2_sum_basis", Trivial()),
        ("SO3_sum_basis", SE3()),
        ("SO3_sum_basis", SE2xR()),
        ("C6_regular", Trivial()),
    ],
    ids=lambda v: v if isinstance(v, str) else repr(v),
)
def test_binds_to_groups_with_the_right_part(name, group):
    ft = FieldType(group, [Scalar(2), feature(name)])
    assert ft.dim == 2 + feature(name).dim
    for dtype in (F64, F32):
        check_action_laws(group, ft, dtype=dtype, atol=TOL[dtype])


def test_so3_standard_rep_acts_like_vector():
    """Through SE(3) the standard representation of SO(3) is exactly the built-in Vector(3)."""
    G = SE3()
    g = G.sample(64, generator=torch.Generator().manual_seed(3), dtype=F64)
    x = torch.randn(64, 3, dtype=F64)
    ours = feature("SO3_standard").bind(G).act(g, x)
    torch.testing.assert_close(ours, FieldType(G, [Vector(3)]).act(g, x), atol=1e-13, rtol=0)


@pytest.mark.parametrize(
    ("name", "group"),
    [("SO3_l1", SO2()), ("SO2_irrep1", SO3()), ("O2_irreps", SO2()), ("C6_regular", Cyclic(5)), ("C6_regular", SO2())],
    ids=str,
)
def test_wrong_group_raises(name, group):
    with pytest.raises(ValueError, match="cannot act on"):
        FieldType(group, [feature(name)])


def test_unsupported_inputs_raise():
    with pytest.raises(TypeError, match="SO\\(2\\), O\\(2\\), C_n"):
        from_escnn(eg.dihedral_group(3).regular_representation)
    with pytest.raises(TypeError, match="Representation"):
        from_escnn(np.eye(2))
    with pytest.raises(ValueError, match="features of shape"):
        feature("SO2_irrep1").act(SO2().identity(3), torch.zeros(3, 5))


# ----------------------------------------------------------------------------------------- (c) batched
@pytest.mark.parametrize("name", ["SO2_sum_basis", "C6_regular", "O2_bl_regular2", "SO3_bl_regular2"])
def test_batched_10k_in_one_call(name):
    ft, rep = feature(name), REPS[name]
    G = ft.group
    gen = torch.Generator().manual_seed(7)
    g = G.sample(10_000, generator=gen, dtype=F64)
    x = torch.randn(10_000, ft.dim, generator=gen, dtype=F64)
    ft.act(g[:10], x[:10])  # warm the constant cache
    t0 = time.perf_counter()
    y = ft.act(g, x)
    t_ours = time.perf_counter() - t0
    assert y.shape == x.shape and torch.isfinite(y).all()
    idx = torch.randint(0, 10_000, (20,), generator=gen)
    ref = escnn_matrices(rep, g[idx])
    np.testing.assert_allclose(y[idx].numpy(), np.einsum("bij,bj->bi", ref, x[idx].numpy()), atol=TOL[F64], rtol=0)
    elements = [to_escnn_element(rep.group, gi) for gi in g[:200]]
    t0 = time.perf_counter()
    loop = [np.asarray(rep(e)) @ xi for e, xi in zip(elements, x[:200].numpy())]
    t_escnn = (time.perf_counter() - t0) / 200
    np.testing.assert_allclose(y[:200].numpy(), np.stack(loop), atol=TOL[F64], rtol=0)
    print(
        f"\n{name} (dim {ft.dim}): adapter {t_ours / 1e4 * 1e6:.2f} us/element (10_000 in one call), "
        f"escnn loop {t_escnn * 1e6:.1f} us/element (200 elements): {t_escnn / (t_ours / 1e4):.0f}x"
    )


def test_batch_shapes_broadcast_and_dtype():
    ft = feature("SO3_sum_basis")
    G = ft.group
    g = G.sample(4, 1, generator=torch.Generator().manual_seed(0), dtype=F32)
    x = torch.randn(5, ft.dim, dtype=F32)
    y = ft.act(g, x)
    assert y.shape == (4, 5, ft.dim) and y.dtype == F32
    expected = (ft.matrix(g.double()) @ x.double().unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(y.double(), expected, atol=1e-4, rtol=0)
    assert ft.act(G.identity(dtype=F64), x.double()).shape == (5, ft.dim)


# ----------------------------------------------------------------------------------------- (d) gradients
def _curve(G, name: str, g: torch.Tensor, xi: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """exp(t xi) . g: a curve through g in the group (through the rotation part for O(2))."""
    if isinstance(G, O2):
        return G.compose(G.element(t * xi[..., 0], False), g)
    return G.compose(G.exp(t[..., None] * xi), g)


@pytest.mark.parametrize("name", CONTINUOUS)
def test_gradient_wrt_group_element(name):
    ft = feature(name)
    G = ft.group
    gen = torch.Generator().manual_seed(11)
    g = torch.cat((G.special_elements(dtype=F64), G.sample(16, generator=gen, dtype=F64)))
    n = g.shape[0]
    x = torch.randn(n, ft.dim, generator=gen, dtype=F64)
    w = torch.randn(n, ft.dim, generator=gen, dtype=F64)
    # finite gradient w.r.t. the raw element tensor, near-singular elements included
    gr = g.clone().requires_grad_()
    (ft.act(gr, x) * w).sum().backward()
    assert gr.grad is not None and torch.isfinite(gr.grad).all()
    # and the right derivative along the group: d/dt <w, rho(exp(t xi) g) x> at t = 0 vs central differences
    xi = torch.randn(n, 1 if isinstance(G, (SO2, O2)) else 3, generator=gen, dtype=F64)
    t = torch.zeros(n, dtype=F64, requires_grad=True)
    (ft.act(_curve(G, name, g, xi, t), x) * w).sum().backward()
    h = 1e-5

    def f(s):
        return (ft.act(_curve(G, name, g, xi, torch.full((n,), s, dtype=F64)), x) * w).sum(-1)

    fd = (f(h) - f(-h)) / (2 * h)
    torch.testing.assert_close(t.grad, fd, atol=1e-6, rtol=1e-6)


# --- escnn's SO(3) basis, as docs/escnn.md states it ----------------------------------------------------------


@pytest.mark.parametrize("l", [0, 1, 2, 3, 4, 5, 6])
def test_so3_irrep_l_acts_on_the_stated_real_harmonics(l):
    """escnn's (and so the adapter's) degree-``l`` irrep is ``S_l``: ``y_l(R x) = psi_l(R) y_l(x)`` for the real
    spherical harmonics without the Condon-Shortley phase, ordered ``m = -l..l`` (``real_harmonics``)."""
    from real_harmonics import harmonic_matrix

    g = SO3().sample(5, generator=torch.Generator().manual_seed(l), dtype=F64)
    ours = from_escnn(SO3_E.irrep(l)).matrix(g).numpy()
    for k, rotation in enumerate(SO3().rotation(g).numpy()):
        np.testing.assert_allclose(ours[k], harmonic_matrix(l, rotation), atol=1e-10, rtol=0)


def test_so3_irrep1_is_vector_in_yzx_order():
    """``psi_1(R) = P R P^T`` with ``P`` the rows (e_y, e_z, e_x); ``change_basis(irrep(1), P^T)`` is ``Vector(3)``."""
    from real_harmonics import YZX

    G = SO3()
    g = G.sample(64, generator=torch.Generator().manual_seed(3), dtype=F64)
    P = torch.from_numpy(YZX)
    x = torch.randn(64, 3, dtype=F64)
    vector = FieldType(G, [Vector(3)]).act(g, x)
    torch.testing.assert_close(feature("SO3_l1").act(g, x @ P.T), vector @ P.T, atol=1e-12, rtol=0)
    in_xyz = from_escnn(eg.change_basis(SO3_E.irrep(1), YZX.T, "so3_l1_xyz"))
    torch.testing.assert_close(in_xyz.act(g, x), vector, atol=1e-12, rtol=0)
