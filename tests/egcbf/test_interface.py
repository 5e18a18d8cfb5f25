"""Control interfaces: the acceleration command's frames, bounds and attitude loop, and the Lie derivatives the
learned-CBF QP uses (checked against finite differences of each model's ``hdot``)."""

import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.interface import AccelInterface, TorqueInterface, make_interface
from egcbf.env import EnvConfig
from egcbf.env.graph import GROUP, build_graph, refresh_graph
from egcbf.nn import CBFNet, ModelConfig
from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.nominal import nominal_acceleration, nominal_control
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

F64, F32 = torch.float64, torch.float32
VEC = FieldType(GROUP, [Vector(3)])
CFG = EnvConfig(num_agents=5, num_envs=2, area_size=1.2, num_obstacles=2, n_rays=8, lidar_max_hits=4)


def _commands(seed: int, shape, dtype=F64) -> torch.Tensor:
    return 1.5 * torch.randn(*shape, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@given(seed=st.integers(0, 2**16), g=gst.elements(GROUP, batch=(2,)))
@settings(max_examples=25)
def test_accel_interface_is_equivariant(seed, g):
    """Clip, nominal command and local coordinates commute with SE2xR; the body control is invariant."""
    itf = AccelInterface()
    state = moving_scene(CFG, seed)
    moved = state.transform(g)
    ga = g[:, None].expand(2, CFG.num_agents, 5)
    c = _commands(seed, (2, CFG.num_agents))
    x, xg = state.x, moved.x
    assert (VEC.act(ga, itf.clip(x, c)) - itf.clip(xg, VEC.act(ga, c))).abs().max() <= 1e-9
    assert (itf.to_local(x, c) - itf.to_local(xg, VEC.act(ga, c))).abs().max() <= 1e-9
    assert (VEC.act(ga, itf.nominal(x, state.goals)) - itf.nominal(xg, moved.goals)).abs().max() <= 1e-9
    assert (itf.apply(x, c) - itf.apply(xg, VEC.act(ga, c))).abs().max() <= 1e-9


@given(seed=st.integers(0, 2**16))
@settings(max_examples=25)
def test_accel_local_coordinates_and_bounds(seed):
    itf = AccelInterface()
    x = moving_scene(CFG, seed).x
    c = _commands(seed, (2, CFG.num_agents))
    z = itf.to_local(x, c)
    assert (itf.from_local(x, z) - c).abs().max() <= 1e-12
    assert torch.allclose(z.norm(dim=-1), c.norm(dim=-1), atol=1e-12)  # a rotation
    lo, hi = itf.bounds(c)
    zc = itf.to_local(x, itf.clip(x, c))
    assert (zc >= lo - 1e-12).all() and (zc <= hi + 1e-12).all()
    inside = ((z >= lo) & (z <= hi)).all(-1)
    assert torch.allclose(itf.clip(x, c)[inside], c[inside], atol=1e-12)  # commands inside are left alone
    # float32 agrees within 1e-5
    assert torch.allclose(itf.clip(x.float(), c.float()), itf.clip(x, c).float(), atol=1e-5)


def test_accel_nominal_command_is_the_nominal_controller_where_unclipped():
    itf = AccelInterface()
    state = moving_scene(CFG, 3)
    goals = state.x[..., dyn.P] + 0.1 * _commands(1, (2, CFG.num_agents))
    raw = itf.to_local(state.x, nominal_acceleration(state.x, goals) / itf.accel_unit)
    lo, hi = itf.bounds(raw)
    inside = ((raw > lo) & (raw < hi)).all(-1)
    assert inside.any() and not inside.all()  # both cases occur
    u = itf.apply(state.x, itf.nominal(state.x, goals))
    assert torch.allclose(u[inside], nominal_control(state.x, goals)[inside], atol=1e-12)
    torque = TorqueInterface()
    assert torch.allclose(torque.apply(state.x, torque.nominal(state.x, goals)), nominal_control(state.x, goals))


def _cbf(group: str = "se2xr", **kw) -> CBFNet:
    torch.manual_seed(0)
    cfg = ModelConfig(group=group, hidden=16, heads=2, head_hidden=16, **kw)
    return CBFNet(cfg).double()


@pytest.mark.parametrize("group", ["se2xr", "trivial"])
def test_ideal_model_lie_derivatives_match_finite_differences(group):
    """``Lf h + sum_j Lg_j h . c_j`` is ``hdot`` along the double integrator ``p' = v, v' = A c``."""
    itf = AccelInterface(model="ideal")
    net = _cbf(group, cbf_body_rates=False, cbf_attitude=False, edge_velocity=True, edge_closest_approach=True)
    state = moving_scene(CFG, 7)
    graph = build_graph(state, CFG)
    h, lf, lg = itf.lie_derivatives(net, graph, state.x)
    c = _commands(2, (2, CFG.num_agents))
    xdot = torch.zeros_like(state.x)
    xdot[..., dyn.P] = state.x[..., dyn.V]
    xdot[..., dyn.V] = itf.accel_unit * c
    eps = 1e-6
    with torch.no_grad():
        hp = net(refresh_graph(graph, state.x + eps * xdot)).view_as(h)
        hm = net(refresh_graph(graph, state.x - eps * xdot)).view_as(h)
    fd = (hp - hm) / (2 * eps)
    model = lf + torch.einsum("bijk,bjk->bi", lg, c)
    assert (fd - model).abs().max() <= 1e-7 * (1 + fd.abs().max())
    assert (lg.abs().sum(-1) > 0).any()


def test_closed_loop_lie_derivatives_match_finite_differences():
    """``Lg_j h`` of the closed-loop model is ``d h(x'(c)) / d c_j / dt`` at the linearization point."""
    itf = AccelInterface(model="closed_loop")
    net = _cbf("se2xr", cbf_body_rates=False)
    state = moving_scene(CFG, 8)
    graph = build_graph(state, CFG)
    c0 = itf.nominal(state.x, state.goals)
    h, lf, lg = itf.lie_derivatives(net, graph, state.x, CFG, c0)

    def hdot(c):
        with torch.no_grad():
            return (net(refresh_graph(graph, itf.model_step(state.x, c, CFG))).view_as(h) - h) / CFG.dt

    assert torch.allclose(lf + torch.einsum("bijk,bjk->bi", lg, c0), hdot(c0), atol=1e-9)
    eps = 1e-6
    for j, k in ((0, 0), (1, 1), (3, 2)):
        e = torch.zeros_like(c0)
        e[:, j, k] = eps
        fd = (hdot(c0 + e) - hdot(c0 - e)) / (2 * eps)
        assert (fd - lg[:, :, j, k]).abs().max() <= 1e-6 * (1 + fd.abs().max()), (j, k)


def test_torque_lie_derivatives_match_finite_differences():
    itf = TorqueInterface()
    net = _cbf("se2xr")
    state = moving_scene(CFG, 9)
    graph = build_graph(state, CFG)
    h, lf, lg = itf.lie_derivatives(net, graph, state.x)
    c = itf.nominal(state.x, state.goals)
    xdot = dyn.xdot(state.x, itf.apply(state.x, c))
    eps = 1e-6
    with torch.no_grad():
        fd = net(refresh_graph(graph, state.x + eps * xdot)) - net(refresh_graph(graph, state.x - eps * xdot))
    fd = fd.view_as(h) / (2 * eps)
    assert (fd - lf - torch.einsum("bijk,bjk->bi", lg, c)).abs().max() <= 1e-6 * (1 + fd.abs().max())


def test_make_interface_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown control interface"):
        make_interface("velocity")
    with pytest.raises(ValueError, match="model"):
        AccelInterface(model="two_steps")
    with pytest.raises(ValueError, match="interface"):
        ModelConfig(interface="velocity")
