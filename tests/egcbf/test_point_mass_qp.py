"""The point masses' dCBF-QP (egcbf.robots.point_mass_qp): it commutes with the robots' quarter turns and
translations (float64, 1e-9), keeps the box, returns the nominal control where no row binds, and is refused where it
does not apply."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.control.controllers import make_controller
from egcbf.env import EnvConfig, SwarmEnv
from groupcanon import FieldType
from groupcanon.features import Vector

F64 = torch.float64


@pytest.mark.parametrize("robot", ["single_integrator", "double_integrator", "linear_drone"])
@given(seed=st.integers(0, 2**16), k=st.integers(0, 3), t=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
@settings(max_examples=6, deadline=None)
def test_the_dcbf_qp_is_c4_equivariant(robot, seed, k, t):
    cfg = EnvConfig.for_robot(robot, num_agents=12, num_obstacles=3, num_envs=1, area_size=1.2)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    ctrl = make_controller("dcbf", robot=robot)
    for _ in range(3):
        state, _ = env.step(state, ctrl(state, cfg)[0])
    group, d = cfg.make_robot().group, cfg.dim
    g = torch.cat((group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2], torch.tensor([t[:d]], dtype=F64)), -1)
    u, info = ctrl(state, cfg)
    u_moved, _ = ctrl(state.transform(g), cfg)
    rotate = FieldType(group, [Vector(d)])
    assert (rotate.act(g.expand(12, g.shape[-1]), u[0]) - u_moved[0]).abs().max() <= 1e-9
    lo, hi = cfg.make_robot().control_bounds(u)
    assert bool(((u >= lo - 1e-12) & (u <= hi + 1e-12)).all()) and info["num_failed"] == 0


def test_agents_far_from_everything_keep_their_nominal_control():
    cfg = EnvConfig.for_robot("double_integrator", num_agents=2, num_obstacles=0, num_envs=1, area_size=4.0)
    state = SwarmEnv(cfg, dtype=F64).reset(0)
    state.x[0, 0, :2] = torch.tensor([0.5, 0.5], dtype=F64)
    state.x[0, 1, :2] = torch.tensor([3.5, 3.5], dtype=F64)  # far outside the communication radius
    u, info = make_controller("dcbf", robot="double_integrator")(state, cfg)
    assert torch.allclose(u, info["u_ref"], atol=1e-12)


@pytest.mark.parametrize("name", ["dcbf", "ccbf"])
@given(seed=st.integers(0, 2**16))
@settings(max_examples=8, deadline=None)
def test_commands_stay_in_the_box_that_acts(name, seed):
    """Crowded double integrators, most at a speed limit: every command lies in the box that acts at its agent's
    state (``Robot.effective_control_bounds``), so no row is met on paper by a push the speed clip discards."""
    cfg = EnvConfig.for_robot("double_integrator", num_agents=12, num_obstacles=2, num_envs=1, area_size=1.0,
                              start_separation=2.5)  # fmt: skip
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    g = torch.Generator().manual_seed(seed)
    state.x[0, :, 2:] = 0.5 * torch.sign(torch.randn(12, 2, generator=g, dtype=F64))  # at the limit on both axes
    state.x[0, ::3, 3] = 0.1  # some free on one axis
    u, _ = make_controller(name, robot="double_integrator")(state, cfg)
    lo, hi = env.robot.effective_control_bounds(state.x)
    assert bool((u >= lo - 1e-7).all() and (u <= hi + 1e-7).all())


def test_where_it_does_not_apply():
    from egcbf.robots.point_mass_qp import PointMassDCBF

    quad = EnvConfig(num_agents=2, num_envs=1)
    with pytest.raises(ValueError, match="not a quadrotor"):  # the quadrotor has its own CBF-QPs
        PointMassDCBF()(SwarmEnv(quad, dtype=F64).reset(0), quad)


@pytest.mark.parametrize("robot", ["double_integrator", "linear_drone", "dubins_car", "unicycle"])
def test_the_acceleration_model_matches_the_dynamics(robot):
    """``dv/dt = A + B u`` (egcbf.robots.point_mass_qp.acceleration_affine) against a central difference of the
    world velocity along the control-affine flow, at random states and controls (float64)."""
    from egcbf.robots.point_mass_qp import acceleration_affine

    cfg = EnvConfig.for_robot(robot, num_agents=6, num_obstacles=0, num_envs=2, area_size=2.0)
    rob = cfg.make_robot()
    state = SwarmEnv(cfg, dtype=F64).reset(3)
    x = state.x.reshape(12, -1).clone()
    gen = torch.Generator().manual_seed(0)
    v = rob.velocities(x)
    if rob.name in ("dubins_car", "unicycle"):
        x[:, 4] = 0.5 * torch.rand(12, generator=gen, dtype=F64)  # moving cars: steering acts through the speed
    else:
        x = rob.perturbed(x, torch.zeros_like(v), 0.2 * torch.randn(v.shape, generator=gen, dtype=F64))
    lo, hi = rob.control_bounds(x)
    u = lo + (hi - lo) * torch.rand(12, rob.control_dim, generator=gen, dtype=F64)
    a, b = acceleration_affine(rob, x)
    eps = 1e-6
    xdot = rob.f0(x) + (rob.f1(x) @ u[..., None])[..., 0]
    fd = (rob.velocities(x + eps * xdot) - rob.velocities(x - eps * xdot)) / (2 * eps)
    assert torch.allclose(a + (b @ u[..., None])[..., 0], fd, atol=1e-7)


@pytest.mark.parametrize("robot", ["dubins_car", "unicycle"])
@given(seed=st.integers(0, 2**16), yaw=st.floats(-3.1, 3.1), t=st.lists(st.floats(-3, 3), min_size=2, max_size=2))
@settings(max_examples=5, deadline=None)
def test_the_cars_dcbf_qp_is_se2_invariant(robot, seed, yaw, t):
    """A car's controls (turn rate, acceleration) are invariant: the dCBF-QP gives the same controls in a scene
    rotated and moved by any element of SE(2) (float64, 1e-9), inside the box."""
    import math

    cfg = EnvConfig.for_robot(robot, num_agents=10, num_obstacles=3, num_envs=1, area_size=1.2)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    ctrl = make_controller("dcbf", robot=robot)
    for _ in range(3):
        state, _ = env.step(state, ctrl(state, cfg)[0])
    g = torch.tensor([[math.cos(yaw), math.sin(yaw), *t]], dtype=F64)
    u, _ = ctrl(state, cfg)
    u_moved, _ = ctrl(state.transform(g), cfg)
    assert (u - u_moved).abs().max() <= 1e-9
    lo, hi = cfg.make_robot().control_bounds(u)
    assert bool(((u >= lo - 1e-12) & (u <= hi + 1e-12)).all())


@pytest.mark.parametrize("robot", ["single_integrator", "double_integrator", "dubins_car"])
def test_the_centralized_qp_keeps_whole_pair_rows_and_agrees_with_them(robot):
    """The cCBF-QP's command satisfies every whole barrier row it was given (up to its slack, none here), keeps the
    box, and equals the nominal control where nothing binds; its rows are the dCBF-QP's halves added up."""
    from egcbf.robots.point_mass_qp import barrier_rows

    cfg = EnvConfig.for_robot(robot, num_agents=10, num_obstacles=2, num_envs=2, area_size=1.0)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(5)
    ccbf = make_controller("ccbf", robot=robot)
    for _ in range(3):
        state, _ = env.step(state, ccbf(state, cfg)[0])
    u, info = ccbf(state, cfg)
    assert info["num_failed"] == 0
    rows = barrier_rows(state, cfg, None, pairs="whole")
    flat = u.reshape(20, -1).to(F64)
    lhs = (rows.coef_i * flat[rows.i]).sum(-1) + torch.where(
        rows.j[:, None] >= 0, rows.coef_j * flat[rows.j.clamp_min(0)], torch.zeros_like(rows.coef_j)
    ).sum(-1)
    if info["num_slack"] == 0:
        assert bool((lhs >= rows.bound - 1e-6).all())
    lo, hi = cfg.make_robot().control_bounds(u)
    assert bool(((u >= lo - 1e-9) & (u <= hi + 1e-9)).all())
    halves = barrier_rows(state, cfg, None, pairs="halves")
    pair = rows.j >= 0
    assert int(pair.sum()) * 2 == int((halves.i >= 0).sum()) - int((~pair).sum())  # each pair: two halves


def test_the_centralized_qp_is_c4_equivariant_and_keeps_the_nominal_control_when_free():
    robot = "double_integrator"
    cfg = EnvConfig.for_robot(robot, num_agents=8, num_obstacles=2, num_envs=1, area_size=1.0)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(11)
    ctrl = make_controller("ccbf", robot=robot)
    for _ in range(2):
        state, _ = env.step(state, ctrl(state, cfg)[0])
    group = cfg.make_robot().group
    quarter = group.rotation_element(torch.tensor([1]), dtype=F64)[:, :2]
    g = torch.cat((quarter, torch.tensor([[0.3, -0.2]], dtype=F64)), -1)
    u, _ = ctrl(state, cfg)
    u_moved, _ = ctrl(state.transform(g), cfg)
    rotate = FieldType(group, [Vector(2)])
    assert (rotate.act(g.expand(8, g.shape[-1]), u[0]) - u_moved[0]).abs().max() <= 1e-6
    far = EnvConfig.for_robot(robot, num_agents=2, num_obstacles=0, num_envs=1, area_size=4.0)
    s = SwarmEnv(far, dtype=F64).reset(0)
    s.x[0, 0, :2] = torch.tensor([0.5, 0.5], dtype=F64)
    s.x[0, 1, :2] = torch.tensor([3.5, 3.5], dtype=F64)
    u, info = ctrl(s, far)
    lo, hi = far.make_robot().control_bounds(u)
    assert torch.allclose(u, info["u_ref"].clamp(lo, hi), atol=1e-12)
