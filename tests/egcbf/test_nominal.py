"""The equivariant nominal controller (Lee-Leok-McClamroch geometric control, heading held).

Tolerances: equivariance in float64 within 1e-9 (observed ~1e-17 on outputs of size ~1e-2); float32 within 1e-5
relative to the actuator bounds.
"""

from __future__ import annotations

import math

import pytest
import torch
from dyn_helpers import F32, F64, random_states
from hypothesis import given
from hypothesis import strategies as st

from egcbf.robots.quadrotor import nominal as nominal_mod
from egcbf.robots.quadrotor.dynamics import (
    DEFAULT_DT,
    DEFAULT_MAX_STEPS,
    DEFAULT_PARAMS,
    GROUP,
    STATE_TYPE,
    check_state,
    hover_control,
    hover_state,
    state_from_parts,
    step,
    unpack,
)
from egcbf.robots.quadrotor.nominal import GOAL_TYPE, NominalGains, desired_heading, nominal_control
from egcbf.robots.quadrotor.so3 import so3_exp, yaw_rotation
from groupcanon.testing import strategies as gst

B = 32
TMAX = torch.tensor(DEFAULT_PARAMS.max_torque, dtype=F64)


def goals(seed, batch=(B,), dtype=F64, area=4.0):
    return (torch.rand(*batch, 3, generator=torch.Generator().manual_seed(seed + 7), dtype=F64) * area).to(dtype)


def equivariance_error(x, goal, g, **kw):
    u = nominal_control(x, goal, **kw)
    ug = nominal_control(STATE_TYPE.act(g, x), GOAL_TYPE.act(g, goal), **kw)
    return float((ug - u).abs().max())


# --------------------------------------------------------------------------------------------------- equivariance
@given(g=gst.elements(GROUP, batch=(B,)), seed=gst.seeds(), clip=st.booleans(), far=st.booleans())
def test_nominal_controller_is_equivariant(g, seed, clip, far):
    """nominal_control(phi_g x, g . goal) == nominal_control(x, goal): body-frame output is invariant."""
    x = random_states(seed, (B,), rate=5.0)
    goal = goals(seed, area=40.0 if far else 4.0)  # far goals exercise the position-error clip
    assert equivariance_error(x, goal, g, clip=clip) < 1e-9


@given(g=gst.elements(GROUP, batch=(B,), dtype=F32), seed=gst.seeds())
def test_nominal_controller_is_equivariant_float32(g, seed):
    x = random_states(seed, (B,), F32, rate=5.0)
    u = nominal_control(x, goals(seed, dtype=F32))
    ug = nominal_control(STATE_TYPE.act(g, x), GOAL_TYPE.act(g, goals(seed, dtype=F32)))
    scale = torch.cat((TMAX, torch.tensor([DEFAULT_PARAMS.max_thrust], dtype=F64))).to(F32)
    assert float(((ug - u).abs() / scale).max()) < 1e-5


def test_fixed_world_heading_is_not_equivariant(monkeypatch):
    """The textbook choice b1c = world x breaks the rotation symmetry (yaw torques differ after a rotation)."""
    x = random_states(1, (B,), rate=0.0)
    goal = goals(1)
    g = GROUP.sample(B, generator=torch.Generator().manual_seed(1), dtype=F64)
    assert equivariance_error(x, goal, g) < 1e-9
    e1 = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    monkeypatch.setattr(nominal_mod, "desired_heading", lambda R: e1.expand(*R.shape[:-2], 3))
    assert equivariance_error(x, goal, g) > 1e-4


def test_heading_is_equivariant_and_defined_when_body_x_is_vertical():
    yaw = torch.linspace(-3, 3, 7, dtype=F64)
    rz = yaw_rotation(yaw)
    # body x straight up (pitch -90 deg), with any yaw: the fallback uses the body y axis
    pitch_up = so3_exp(torch.tensor([0.0, -math.pi / 2, 0.0], dtype=F64))
    for R in (pitch_up, so3_exp(torch.tensor([0.3, -math.pi / 2, 0.1], dtype=F64)), torch.eye(3, dtype=F64)):
        rs = rz @ R
        h = desired_heading(rs)
        assert torch.isfinite(h).all()
        assert torch.allclose(h.norm(dim=-1), torch.ones(7, dtype=F64))
        assert torch.allclose(h, (rz @ desired_heading(R)[..., None])[..., 0], atol=1e-12)
    # level drone: the heading is its yaw
    assert torch.allclose(desired_heading(rz)[..., :2], torch.stack((yaw.cos(), yaw.sin()), -1), atol=1e-15)


def test_body_x_vertical_gives_finite_control_and_gradient():
    R = so3_exp(torch.tensor([[0.0, -math.pi / 2, 0.0], [0.0, math.pi / 2, 0.0]], dtype=F64))
    x = state_from_parts(torch.ones(2, 3, dtype=F64), R, torch.zeros(2, 3, dtype=F64), torch.zeros(2, 3, dtype=F64))
    x.requires_grad_(True)
    u = nominal_control(x, torch.zeros(2, 3, dtype=F64))
    assert torch.isfinite(u).all()
    u.sum().backward()
    assert torch.isfinite(x.grad).all()
    g = GROUP.sample(2, generator=torch.Generator().manual_seed(2), dtype=F64)
    assert equivariance_error(x.detach(), torch.zeros(2, 3, dtype=F64), g) < 1e-9


# ------------------------------------------------------------------------------------------------ basic behaviour
def test_hover_at_goal_is_a_fixed_point():
    goal = goals(3)
    x = hover_state(goal, torch.rand(B, dtype=F64) * 6)
    u = nominal_control(x, goal)
    assert torch.allclose(u, hover_control(DEFAULT_PARAMS, B, dtype=F64), atol=1e-15)


@given(seed=gst.seeds())
def test_output_is_bounded_and_finite_for_wild_states(seed):
    x = random_states(seed, (B,), pos=100.0, vel=30.0, rate=100.0)  # any attitude, incl. upside down
    u = nominal_control(x, goals(seed, area=100.0))
    assert torch.isfinite(u).all()
    assert (u[..., :3].abs() <= TMAX).all()
    assert (u[..., 3] >= 0).all() and (u[..., 3] <= DEFAULT_PARAMS.max_thrust).all()


def test_thrust_points_toward_goal_and_yaw_is_held():
    """A level drone below-left of its goal: thrust above hover, torques tilt it toward the goal, no yaw torque."""
    x = hover_state(torch.zeros(1, 3, dtype=F64))
    u = nominal_control(x, torch.tensor([[0.5, 0.0, 0.5]], dtype=F64))
    assert u[0, 3] > DEFAULT_PARAMS.hover_thrust
    # to accelerate along +x the body must pitch nose-down about +y: a positive y torque (R' = R [w]x)
    assert u[0, 1] > 0 and abs(float(u[0, 0])) < 1e-15 and abs(float(u[0, 2])) < 1e-15


def test_gains_validation_and_bad_input():
    with pytest.raises(ValueError, match="equal x and y"):
        NominalGains(kx=(6.5, 6.0, 15.0))
    with pytest.raises(ValueError, match="max_tilt"):
        NominalGains(max_tilt=2.0)
    x = random_states(0, (2,))
    with pytest.raises(ValueError, match="goal has shape"):
        nominal_control(x, torch.zeros(2, 2, dtype=F64))
    with pytest.raises(ValueError, match="state x has shape"):
        nominal_control(x[..., :10], torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ValueError, match="max_position_error"):
        nominal_control(x, torch.zeros(2, 3, dtype=F64), max_position_error=0.0)


# ---------------------------------------------------------------------------------------------------- acceptance
def test_reaches_any_goal_in_the_area_and_hovers():
    """From rest at a random point of [0, 4]^3 (random yaw) to a random goal there: 200 episodes as one batch,
    DEFAULT_MAX_STEPS steps of DEFAULT_DT. Reached = distance < 2 r = 0.1 m at some step (GCBF+); it must also
    stay within 2 r for the last second and end nearly still."""
    gen = torch.Generator().manual_seed(2024)
    n = 200
    p0 = torch.rand(n, 3, generator=gen, dtype=F64) * 4
    goal = torch.rand(n, 3, generator=gen, dtype=F64) * 4
    x = hover_state(p0, (torch.rand(n, generator=gen, dtype=F64) * 2 - 1) * math.pi)
    reached = torch.zeros(n, dtype=torch.bool)
    last_second = round(1.0 / DEFAULT_DT)
    stays = torch.ones(n, dtype=torch.bool)
    radius = DEFAULT_PARAMS.radius
    for k in range(DEFAULT_MAX_STEPS):
        x = step(x, nominal_control(x, goal))
        d = (x[..., :3] - goal).norm(dim=-1)
        reached |= d < 2 * radius
        if k >= DEFAULT_MAX_STEPS - last_second:
            stays &= d < 2 * radius
    check_state(x)  # finite and on SO(3)
    assert float(reached.double().mean()) >= 0.99
    assert float(stays.double().mean()) >= 0.99
    _, _, v, w = unpack(x)
    assert float((x[..., :3] - goal).norm(dim=-1).max()) < 0.01
    assert float(v.norm(dim=-1).max()) < 0.05 and float(w.norm(dim=-1).max()) < 0.1
