"""The part of the actuator box that acts (Robot.effective_control_bounds): a robot whose step clips its speed
discards any push beyond the limit, so the learned-CBF QP and the policy's clip work in the narrowed box. Checked:
the narrowed box loses nothing the step keeps (stepping any control or its projection gives the same state), a
component at its limit stays within it without the clip, the narrowing commutes with the robots' symmetries (so
EGCBF+'s command stays equivariant at the speed limit, float64 within 1e-9), and the QP honours one box per agent."""

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.interface import make_interface
from egcbf.algo.learner import policy_command
from egcbf.algo.qp import solve_cbf_qp
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.nn import PolicyNet
from egcbf.robots import make_robot
from groupcanon import FieldType
from groupcanon.features import Vector

F64 = torch.float64
DT = 0.03
#: robot -> (indices of its clipped speed components in the state, the limit)
CLIPPED = {"double_integrator": ([2, 3], 0.5), "linear_drone": ([3, 4, 5], 0.5), "dubins_car": ([4], 0.8)}


def _states(name: str, seed: int, n: int = 64) -> torch.Tensor:
    """``n`` states whose clipped components are at ``+limit``, at ``-limit`` or strictly inside."""
    gen = torch.Generator().manual_seed(seed)
    robot = make_robot(name)
    idx, limit = CLIPPED[name]
    x = torch.randn(n, robot.state_dim, generator=gen, dtype=F64)
    if name == "dubins_car":
        x[:, 2:4] = x[:, 2:4] / x[:, 2:4].norm(dim=-1, keepdim=True)
    choice = torch.randint(0, 3, (n, len(idx)), generator=gen)
    inside = (2 * torch.rand(n, len(idx), generator=gen, dtype=F64) - 1) * 0.9 * limit
    x[:, idx] = torch.where(choice == 0, limit, torch.where(choice == 1, -limit, inside))
    return x


@pytest.mark.parametrize("name", sorted(CLIPPED))
@given(seed=st.integers(0, 2**16))
@settings(max_examples=15, deadline=None)
def test_the_narrowed_box_loses_nothing_the_step_keeps(name, seed):
    """For any control in the box, stepping it or its projection into the effective box gives the same state; and
    from the effective box, a component at its limit stays within it before the clip (the clip is idle)."""
    robot = make_robot(name)
    x = _states(name, seed)
    lo, hi = robot.control_bounds(x)
    gen = torch.Generator().manual_seed(seed + 1)
    u = lo + (hi - lo) * torch.rand(x.shape[0], robot.control_dim, generator=gen, dtype=F64)
    elo, ehi = robot.effective_control_bounds(x)
    assert elo.shape == ehi.shape == u.shape and (elo <= ehi).all() and (elo >= lo).all() and (ehi <= hi).all()
    u_eff = torch.maximum(torch.minimum(u, ehi), elo)
    assert torch.allclose(robot.step(x, u, DT), robot.step(x, u_eff, DT), atol=1e-12, rtol=0)
    idx, limit = CLIPPED[name]
    unclipped = x[:, idx] + DT * robot.xdot(x, u_eff)[:, idx]
    at_limit = x[:, idx].abs() >= limit
    assert (unclipped[at_limit].abs() <= limit + 1e-12).all()


def test_the_box_is_narrowed_only_at_the_limit():
    """Inside the limits the effective box is the box; the double integrator at +0.5 on x keeps only x-pushes <= 0,
    the linear drone the push that balances its damping (D v / 10), the Dubins car at full speed no acceleration."""
    di = make_robot("double_integrator")
    lo, hi = di.effective_control_bounds(torch.tensor([[0.0, 0.0, 0.5, -0.2]], dtype=F64))
    assert lo.tolist() == [[-1.0, -1.0]] and hi.tolist() == [[0.0, 1.0]]
    lo, hi = di.effective_control_bounds(torch.tensor([[0.0, 0.0, 0.3, -0.5]], dtype=F64))
    assert lo.tolist() == [[-1.0, 0.0]] and hi.tolist() == [[1.0, 1.0]]
    drone = make_robot("linear_drone")
    lo, hi = drone.effective_control_bounds(torch.tensor([[0.0, 0.0, 0.0, 0.5, 0.0, -0.5]], dtype=F64))
    assert torch.allclose(hi, torch.tensor([[0.055, 1.0, 1.0]], dtype=F64))
    assert torch.allclose(lo, torch.tensor([[-1.0, -1.0, -0.3]], dtype=F64))
    car = make_robot("dubins_car")
    lo, hi = car.effective_control_bounds(torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.8]], dtype=F64))
    assert lo.tolist() == [[-3.0, -3.0]] and hi.tolist() == [[3.0, 0.0]]
    si = make_robot("single_integrator")
    lo, hi = si.effective_control_bounds(torch.zeros(3, 2, dtype=F64))
    assert (lo == -1).all() and (hi == 1).all() and lo.shape == (3, 2)


@pytest.mark.parametrize("name", ["double_integrator", "linear_drone"])
@given(seed=st.integers(0, 2**16), k=st.integers(0, 3), t=st.lists(st.floats(-3, 3), min_size=3, max_size=3))
@settings(max_examples=10, deadline=None)
def test_egcbf_plus_command_is_c4_equivariant_at_the_speed_limit(name, seed, k, t):
    """EGCBF+'s applied command ``clip(c_nom + 2 pi)`` (the gcbfplus recipe, the narrowed box) rotates with the
    scene under every quarter turn and translation, float64 within 1e-9, with agents at their speed limits."""
    cfg = TrainConfig.preset("egcbf+", "gcbfplus", robot=name)
    torch.manual_seed(seed)
    pol = PolicyNet(cfg.model).double()
    with torch.no_grad():
        for p in pol.parameters():
            p.add_(0.3 * torch.randn_like(p))
    env_cfg = EnvConfig.for_robot(name, num_agents=6, num_obstacles=2, num_envs=1, area_size=1.2)
    state = SwarmEnv(env_cfg, dtype=F64).reset(seed)
    robot = env_cfg.make_robot()
    d = robot.dim
    v = torch.randn(6, d, generator=torch.Generator().manual_seed(seed), dtype=F64).sign() * 0.5
    v[::2, 0] = 0.1  # some axes inside the limit
    state = dataclasses.replace(state, x=torch.cat((state.x[..., :d], v[None]), -1))
    group = robot.group
    g = torch.cat((group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2], torch.tensor([t[:d]], dtype=F64)), -1)
    moved = state.transform(g)
    itf = make_interface("control", robot)
    with torch.no_grad():
        ca, _ = policy_command(pol, cfg.model, itf, build_graph(state, env_cfg), state.x, state.goals)
        cb, _ = policy_command(pol, cfg.model, itf, build_graph(moved, env_cfg), moved.x, moved.goals)
    assert (ca.abs() > 1e-6).any()
    rotate = FieldType(group, [Vector(d)])
    assert (rotate.act(g.expand(6, g.shape[-1]), ca[0]) - cb[0]).abs().max() <= 1e-9


@given(seed=st.integers(0, 2**16))
@settings(max_examples=15, deadline=None)
def test_the_qp_honours_one_box_per_agent(seed):
    """solve_cbf_qp with ``(B, N, k)`` boxes: the solution lies in each agent's own box; with every agent's box
    equal it is the solution of the shared ``(k,)`` box."""
    gen = torch.Generator().manual_seed(seed)
    b, n, k = 3, 4, 2
    h = torch.randn(b, n, generator=gen, dtype=F64)
    lf = torch.randn(b, n, generator=gen, dtype=F64)
    lg = torch.randn(b, n, n, k, generator=gen, dtype=F64)
    u_ref = torch.randn(b, n, k, generator=gen, dtype=F64)
    lo = -torch.rand(b, n, k, generator=gen, dtype=F64)
    hi = torch.rand(b, n, k, generator=gen, dtype=F64)
    res = solve_cbf_qp(h, lf, lg, u_ref, lo, hi, alpha=1.0, chunk=2)
    assert (res.u >= lo - 1e-9).all() and (res.u <= hi + 1e-9).all()
    box_lo, box_hi = -torch.ones(k, dtype=F64), torch.ones(k, dtype=F64)
    shared = solve_cbf_qp(h, lf, lg, u_ref, box_lo, box_hi, alpha=1.0)
    per_agent = solve_cbf_qp(h, lf, lg, u_ref, box_lo.expand(b, n, k), box_hi.expand(b, n, k), alpha=1.0)
    assert torch.allclose(shared.u, per_agent.u, atol=1e-9, rtol=0)


def test_the_straight_through_clip_passes_the_gradient_of_a_clipped_command():
    """At a speed limit the policy's command is clipped to 0; the imitation term must still push it towards a
    braking reference: the straight-through command has the clipped value and the raw command's gradient."""
    from egcbf.algo.learner import straight_through

    raw = torch.tensor([[0.4, -0.2]], dtype=F64, requires_grad=True)
    lo, hi = torch.tensor([[-1.0, -1.0]], dtype=F64), torch.tensor([[0.0, 1.0]], dtype=F64)
    clipped = torch.maximum(torch.minimum(raw, hi), lo)
    target = torch.tensor([[-0.5, -0.2]], dtype=F64)
    (grad_clipped,) = torch.autograd.grad((clipped - target).square().sum(), raw)
    st_cmd = straight_through(raw, clipped)
    (grad_st,) = torch.autograd.grad((st_cmd - target).square().sum(), raw)
    assert torch.equal(st_cmd.detach(), clipped.detach())
    assert grad_clipped[0, 0] == 0 and grad_st[0, 0] == 2 * (0.0 + 0.5)
    assert grad_st[0, 1] == grad_clipped[0, 1] == 0
