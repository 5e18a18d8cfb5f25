"""Quadrotor dynamics: symmetry, control-affine form, integrator, SO(3) preservation, physics sanity, input checks.

Tolerances: float64 identities hold to 1e-10 relative to max(1, |value|) (observed ~1e-16; 1e-9 for step); float32
to 1e-5 relative (1e-4 for step; observed ~1e-7). Symmetry: g = (Rz, t) acts by p -> Rz p + t, R -> Rz R,
v -> Rz v, w -> w and trivially on the body-frame control; on a state derivative it acts without translation
(STATE_TANGENT_TYPE).
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from dyn_helpers import F32, F64, random_controls, random_states, rel_err
from hypothesis import given
from hypothesis import strategies as st

from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.dynamics import (
    CONTROL_TYPE,
    DEFAULT_PARAMS,
    GROUP,
    STATE_TANGENT_TYPE,
    STATE_TYPE,
    check_state,
    clip_control,
    f0,
    f1,
    hover_control,
    hover_state,
    state_from_parts,
    step,
    unpack,
    xdot,
)
from egcbf.robots.quadrotor.so3 import exp_apply, hat, orthonormality_error, rmul_exp, so3_exp, vee
from groupcanon.testing import check_action_laws
from groupcanon.testing import strategies as gst

B = 16
TOL = {F64: 1e-10, F32: 1e-5}
dtypes = pytest.mark.parametrize("dtype", [F64, F32], ids=["f64", "f32"])


# ------------------------------------------------------------------------------------------------ layout and types
def test_layout_matches_field_types():
    assert dyn.STATE_DIM == STATE_TYPE.dim == STATE_TANGENT_TYPE.dim == 18
    assert dyn.CONTROL_DIM == CONTROL_TYPE.dim == 4
    for name, s in (("p", dyn.P), ("R", dyn.ROT), ("v", dyn.V), ("w", dyn.W)):
        assert STATE_TYPE.slice(name) == s == STATE_TANGENT_TYPE.slice(name)
    assert CONTROL_TYPE.slice("tau") == dyn.TAU and CONTROL_TYPE.slice("thrust") == dyn.THRUST
    assert CONTROL_TYPE.invariant  # body-frame control: the action on u is the identity


def test_state_action_is_a_group_action():
    check_action_laws(GROUP, STATE_TYPE, dtype=F64)
    check_action_laws(GROUP, STATE_TANGENT_TYPE, dtype=F64)


def test_unpack_roundtrip_and_broadcast():
    x = random_states(0, (2, 3))
    p, r, v, w = unpack(x)
    assert r.shape == (2, 3, 3, 3)
    assert torch.equal(state_from_parts(p, r, v, w), x)
    assert torch.equal(state_from_parts(p, r.reshape(2, 3, 9), v, w), x)
    y = state_from_parts(p, torch.eye(3, dtype=F64), v, w)  # R broadcast over the batch
    assert y.shape == x.shape


# ------------------------------------------------------------------------------------------------------- symmetry
@given(g=gst.elements(GROUP, batch=(B,)), seed=gst.seeds())
def test_vector_field_is_equivariant(g, seed):
    """f(phi_g x, psi_g u) = dphi_g f(x, u), psi_g = identity, dphi_g = STATE_TANGENT_TYPE (no translation)."""
    x, u = random_states(seed, (B,)), random_controls(seed, (B,))
    lhs = xdot(STATE_TYPE.act(g, x), CONTROL_TYPE.act(g, u))
    rhs = STATE_TANGENT_TYPE.act(g, xdot(x, u))
    assert rel_err(lhs, rhs) < TOL[F64]
    # drift and input matrix separately
    assert rel_err(f0(STATE_TYPE.act(g, x)), STATE_TANGENT_TYPE.act(g, f0(x))) < TOL[F64]
    b = f1(x)  # columns are tangent vectors
    b_g = f1(STATE_TYPE.act(g, x))
    cols = STATE_TANGENT_TYPE.act(g[:, None], b.transpose(-1, -2)).transpose(-1, -2)
    assert rel_err(b_g, cols) < TOL[F64]


def test_naive_translation_of_derivative_is_wrong():
    """Acting on x' with the full action (with translation) is not the differential: the test above needs the
    tangent type."""
    g = GROUP.sample(B, generator=torch.Generator().manual_seed(3), dtype=F64)
    x, u = random_states(3, (B,)), random_controls(3, (B,))
    lhs = xdot(STATE_TYPE.act(g, x), u)
    assert rel_err(lhs, STATE_TYPE.act(g, xdot(x, u))) > 1e-3


@dtypes
@given(g=gst.elements(GROUP, batch=(B,)), seed=gst.seeds())
def test_step_is_equivariant(dtype, g, seed):
    """step(phi_g x, u) = phi_g step(x, u) for the default integrator and for Lie-Euler."""
    g = g.to(dtype)
    x, u = random_states(seed, (B,), dtype), random_controls(seed, (B,), dtype)
    for method in ("rk4", "euler"):
        lhs = step(STATE_TYPE.act(g, x), u, 0.025, substeps=2, method=method)
        rhs = STATE_TYPE.act(g, step(x, u, 0.025, substeps=2, method=method))
        assert rel_err(lhs, rhs) < 10 * TOL[dtype]


def test_step_equivariance_with_shared_g():
    """One global g for a whole (env, agent) batch, as the learner uses it."""
    x, u = random_states(5, (3, 7)), random_controls(5, (3, 7))
    g = GROUP.sample(generator=torch.Generator().manual_seed(5), dtype=F64)
    assert rel_err(step(STATE_TYPE.act(g, x), u), STATE_TYPE.act(g, step(x, u))) < TOL[F64]


def test_world_frame_torque_action_would_be_wrong():
    """The paper's psi_g(u) = (g tau, F3) (rotating the torque) breaks equivariance for body-frame torques."""
    x, u = random_states(7, (B,)), random_controls(7, (B,))
    g = GROUP.sample(B, generator=torch.Generator().manual_seed(7), dtype=F64)
    u_rot = torch.cat((GROUP.rotate(g, u[..., :3]), u[..., 3:]), dim=-1)
    lhs = xdot(STATE_TYPE.act(g, x), u_rot)
    assert rel_err(lhs, STATE_TANGENT_TYPE.act(g, xdot(x, u))) > 1e-3


# ------------------------------------------------------------------------------------------- control-affine form
@dtypes
@given(seed=gst.seeds())
def test_control_affine_decomposition(dtype, seed):
    x, u = random_states(seed, (B,), dtype), random_controls(seed, (B,), dtype)
    affine = f0(x) + (f1(x) @ u[..., None])[..., 0]
    assert rel_err(affine, xdot(x, u)) < TOL[dtype]
    assert rel_err(f0(x), xdot(x, torch.zeros_like(u))) < TOL[dtype]


@given(seed=gst.seeds())
def test_input_matrix_is_the_autograd_jacobian(seed):
    x, u = random_states(seed, (4,)), random_controls(seed, (4,))
    for i in range(4):
        jac = torch.autograd.functional.jacobian(lambda uu, xi=x[i]: xdot(xi, uu), u[i])
        assert jac.shape == (18, 4)
        assert rel_err(jac, f1(x[i])) < 1e-12


def test_shapes_broadcast():
    x = random_states(1, (2, 5))
    assert f0(x).shape == (2, 5, 18) and f1(x).shape == (2, 5, 18, 4)
    u = random_controls(1, (5,))
    assert xdot(x, u).shape == (2, 5, 18) and step(x, u, 0.02).shape == (2, 5, 18)


# ----------------------------------------------------------------------------------------------------- integrator
def test_rk4_converges_at_order_four():
    x, u = random_states(11, (32,)), random_controls(11, (32,))
    ref = step(x, u, 0.1, substeps=1024, project=False)
    errs = [float((step(x, u, 0.1, substeps=s, project=False) - ref).abs().max()) for s in (2, 4, 8)]
    for a, b in itertools.pairwise(errs):
        assert 12 < a / b < 20, errs  # 2^4 = 16


def test_euler_converges_at_order_one():
    x, u = random_states(12, (32,)), random_controls(12, (32,))
    ref = step(x, u, 0.1, substeps=512, project=False)
    errs = [float((step(x, u, 0.1, substeps=s, method="euler", project=False) - ref).abs().max()) for s in (8, 16)]
    assert 1.7 < errs[0] / errs[1] < 2.3, errs


@dtypes
def test_rotation_stays_orthonormal(dtype):
    """float64: 10^4 steps; float32: 2 * 10^3 steps here (docs/dynamics.md records 10^4: same bound)."""
    n = 10_000 if dtype == F64 else 2_000
    x = random_states(13, (4,), dtype, rate=10.0)
    u = torch.zeros(4, 4, dtype=dtype)  # torque-free tumbling: w precesses, R sweeps SO(3)
    for _ in range(n):
        x = step(x, u, dyn.DEFAULT_DT, substeps=1)
    err = float(orthonormality_error(unpack(x)[1]).max())
    assert err < 1e-6, err
    check_state(x)


def test_step_is_differentiable():
    x = random_states(14, (3,)).requires_grad_(True)
    u = random_controls(14, (3,)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: step(a, b, 0.025), (x, u))
    # finite gradients at w = 0 (the small-angle branch of the exponential map)
    x0 = hover_state(torch.zeros(2, 3, dtype=F64)).requires_grad_(True)
    u0 = hover_control(DEFAULT_PARAMS, 2, dtype=F64).requires_grad_(True)
    y = step(x0, u0, 0.025)
    y.sum().backward()
    assert torch.isfinite(x0.grad).all() and torch.isfinite(u0.grad).all()


def test_step_zero_dt_substeps_validation():
    x, u = random_states(0, (2,)), random_controls(0, (2,))
    with pytest.raises(ValueError, match="dt"):
        step(x, u, 0.0)
    with pytest.raises(ValueError, match="substeps"):
        step(x, u, 0.02, substeps=0)
    with pytest.raises(ValueError, match="integrator"):
        step(x, u, 0.02, method="rk45")


# -------------------------------------------------------------------------------------------------------- physics
def test_hover_control_keeps_a_drone_still():
    x0 = hover_state(torch.rand(5, 3, dtype=F64) * 4, torch.rand(5, dtype=F64) * 6)
    u = hover_control(DEFAULT_PARAMS, 5, dtype=F64)
    assert torch.equal(xdot(x0, u), torch.zeros_like(x0))
    x = x0
    for _ in range(200):
        x = step(x, u)
    assert float((x - x0).abs().max()) < 1e-12


def test_free_fall():
    """u = 0: v' = (0, 0, -g) exactly, the same for every attitude; RK4 is exact for the parabola."""
    x = state_from_parts(
        torch.zeros(4, 3, dtype=F64), unpack(random_states(2, (4,)))[1], *torch.zeros(2, 4, 3, dtype=F64)
    )
    y = step(x, torch.zeros(4, 4, dtype=F64), 0.1, substeps=1)
    g = DEFAULT_PARAMS.gravity
    assert torch.allclose(y[..., dyn.V], torch.tensor([0, 0, -g * 0.1], dtype=F64).expand(4, 3), atol=1e-14)
    assert torch.allclose(y[..., dyn.P], torch.tensor([0, 0, -g * 0.005], dtype=F64).expand(4, 3), atol=1e-14)


def test_thrust_acts_along_body_z_and_torque_through_inertia():
    x = random_states(3, (B,))
    x = state_from_parts(*unpack(x)[:3], torch.zeros(B, 3, dtype=F64))  # w = 0: no gyroscopic term
    r = unpack(x)[1]
    u = torch.tensor([1e-3, -2e-3, 5e-4, 0.4], dtype=F64).expand(B, 4)
    xd = xdot(x, u)
    m, j = DEFAULT_PARAMS.mass, torch.tensor(DEFAULT_PARAMS.inertia, dtype=F64)
    acc = xd[..., dyn.V] - torch.tensor([0, 0, -DEFAULT_PARAMS.gravity], dtype=F64)
    assert rel_err(acc, r[..., :, 2] * 0.4 / m) < 1e-12
    assert rel_err(xd[..., dyn.W], u[..., :3] / j) < 1e-12
    assert torch.equal(xd[..., dyn.P], x[..., dyn.V])


def test_torque_free_rotation_conserves_energy_and_momentum():
    """Without torque: rotational energy w.Jw/2, |J w| and R J w are conserved (RK4 x2, |w| ~ 5 rad/s, 4 s: ~1e-7)."""
    x = random_states(4, (8,), rate=5.0)
    j = torch.tensor(DEFAULT_PARAMS.inertia, dtype=F64)
    w0 = x[..., dyn.W]
    e0, l0 = (w0 * j * w0).sum(-1), (j * w0).norm(dim=-1)
    # world-frame angular momentum R J w is conserved too
    h0 = (unpack(x)[1] @ (j * w0)[..., None])[..., 0]
    u = torch.zeros(8, 4, dtype=F64)
    for _ in range(160):
        x = step(x, u)
    w = x[..., dyn.W]
    assert float(((w * j * w).sum(-1) / e0 - 1).abs().max()) < 1e-6
    assert float(((j * w).norm(dim=-1) / l0 - 1).abs().max()) < 1e-6
    h = (unpack(x)[1] @ (j * w)[..., None])[..., 0]
    assert float((h - h0).norm(dim=-1).max() / l0.max()) < 1e-6


def test_translational_energy_without_thrust():
    """u = 0 from any state: m |v|^2 / 2 + m g z is conserved (exactly, up to rounding, with RK4)."""
    x = random_states(5, (8,))
    g = DEFAULT_PARAMS.gravity
    e0 = 0.5 * (x[..., dyn.V] ** 2).sum(-1) + g * x[..., 2]
    for _ in range(40):
        x = step(x, torch.zeros(8, 4, dtype=F64))
    e = 0.5 * (x[..., dyn.V] ** 2).sum(-1) + g * x[..., 2]
    assert float((e - e0).abs().max()) < 1e-9


# ---------------------------------------------------------------------------------------------------- control box
@given(seed=gst.seeds(), scale=st.floats(0.1, 100.0))
def test_clip_control(seed, scale):
    u = torch.randn(B, 4, generator=torch.Generator().manual_seed(seed), dtype=F64) * scale
    c = clip_control(u)
    tmax = torch.tensor(DEFAULT_PARAMS.max_torque, dtype=F64)
    assert (c[..., :3].abs() <= tmax).all()
    assert (c[..., 3] >= 0).all() and (c[..., 3] <= DEFAULT_PARAMS.max_thrust).all()
    inside = (u[..., :3].abs() <= tmax).all(-1) & (u[..., 3] >= 0) & (u[..., 3] <= DEFAULT_PARAMS.max_thrust)
    assert torch.equal(c[inside], u[inside])
    assert torch.equal(clip_control(c), c)


def test_hover_within_bounds_and_params_validation():
    assert 0 < DEFAULT_PARAMS.hover_thrust < DEFAULT_PARAMS.max_thrust
    assert DEFAULT_PARAMS.max_thrust / DEFAULT_PARAMS.hover_thrust == pytest.approx(2.0, abs=0.1)
    # per-axis torque bounds follow from the rotor geometry (docstring of QuadrotorParams)
    fmax = DEFAULT_PARAMS.max_thrust / 4
    assert DEFAULT_PARAMS.max_torque[0] == pytest.approx(2 * fmax * DEFAULT_PARAMS.arm_length / math.sqrt(2), rel=0.01)
    assert DEFAULT_PARAMS.max_torque[2] == pytest.approx(2 * fmax * DEFAULT_PARAMS.torque_coefficient, rel=0.01)
    with pytest.raises(ValueError, match="mass"):
        dyn.QuadrotorParams(mass=-1.0)
    with pytest.raises(ValueError, match="inertia"):
        dyn.QuadrotorParams(inertia=(1.0, 1.0))


# ------------------------------------------------------------------------------------------------------ SO(3) kit
@given(seed=gst.seeds(), scale=st.sampled_from([1e-9, 1e-5, 1e-3, 0.5, 3.0]))
def test_so3_helpers(seed, scale):
    gen = torch.Generator().manual_seed(seed)
    phi = torch.randn(B, 3, generator=gen, dtype=F64) * scale
    r = so3_exp(torch.randn(B, 3, generator=gen, dtype=F64))
    assert rel_err(so3_exp(phi), torch.linalg.matrix_exp(hat(phi))) < 1e-13
    assert rel_err(rmul_exp(r, phi), r @ so3_exp(phi)) < 1e-13
    y = torch.randn(B, 3, generator=gen, dtype=F64)
    assert rel_err(exp_apply(phi, y), (so3_exp(phi) @ y[..., None])[..., 0]) < 1e-13
    assert rel_err(vee(hat(phi)), phi) == 0
    assert float(orthonormality_error(so3_exp(phi)).max()) < 1e-14


# ----------------------------------------------------------------------------------------------------- bad input
def test_wrong_shapes_raise_clear_errors():
    x, u = random_states(0, (3,)), random_controls(0, (3,))
    for fn, args in ((f0, (x[..., :17],)), (f1, (x[..., :17],)), (xdot, (x[..., :12], u)), (step, (x[..., :17], u))):
        with pytest.raises(ValueError, match=r"state x has shape \(3, \d+\), expected \(\*batch, 18\)"):
            fn(*args)
    for fn, args in ((xdot, (x, u[..., :3])), (step, (x, u[..., :3], 0.02)), (clip_control, (u[..., :2],))):
        with pytest.raises(ValueError, match=r"control u has shape"):
            fn(*args)
    with pytest.raises(TypeError, match="floating"):
        f0(x.long())


def test_check_state_names_the_agent():
    x = random_states(0, (2, 5))
    check_state(x)
    bad = x.clone()
    bad[1, 3, 13] = float("nan")
    with pytest.raises(ValueError, match=r"batch index \(1, 3\).*non-finite values in v.*1 invalid agent"):
        check_state(bad)
    bad = x.clone()
    bad[0, 2, 0] = float("inf")
    bad[1, 4, 16] = float("nan")
    with pytest.raises(ValueError, match=r"batch index \(0, 2\).*in p.*2 invalid agents"):
        check_state(bad)
    bad = x.clone()
    bad[0, 1, dyn.ROT] *= 1.01  # scaled attitude
    with pytest.raises(ValueError, match=r"batch index \(0, 1\).*R is not a rotation"):
        check_state(bad)
    refl = x.clone()
    refl[1, 0, dyn.ROT] = -refl[1, 0, dyn.ROT]  # det = -1: orthogonal but a reflection
    with pytest.raises(ValueError, match=r"batch index \(1, 0\).*not a rotation"):
        check_state(refl)
    with pytest.raises(ValueError, match="expected"):
        check_state(x[..., :9])
