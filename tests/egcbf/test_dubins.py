"""GCBF+'s Dubins car (egcbf.robots.dubins): one Euler step and the nominal law match the reference's conventions
(../shared/reference/gcbfplus-facts.md), agents at their goals freeze, the nominal controller reaches its goals, and
EGCBF+ on it is SE(2)-equivariant (float64, 1e-9)."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.robots import DubinsCar
from groupcanon import FieldType
from groupcanon.features import Scalar
from groupcanon.groups import SE2
from groupcanon.testing import strategies as gst

F64 = torch.float64


def test_one_euler_step_is_the_references():
    """theta + dt 20 omega_cmd, p + dt v (cos, sin) theta (the old ones), v + dt a clipped to +-0.8."""
    car = DubinsCar()
    x = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.5], [1.0, 2.0, 0.0, 1.0, 0.79]], dtype=F64)
    u = torch.tensor([[1.0, 2.0], [-0.5, 3.0]], dtype=F64)
    got = car.step(x, u, 0.03)
    th = torch.tensor([0.6, math.pi / 2 - 0.3], dtype=F64)
    want = torch.tensor([[0.015, 0.0, 0, 0, 0.56], [1.0, 2.0 + 0.03 * 0.79, 0, 0, 0.8]], dtype=F64)
    want[:, 2], want[:, 3] = torch.cos(th), torch.sin(th)
    assert torch.allclose(got, want, atol=1e-15, rtol=0)


def _reference_u(x: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """The reference's law written as its code reads (arccos of the bearing and its sign rule, the soft distance)."""
    p, th, v = x[:2], math.atan2(float(x[3]), float(x[2])) % (2 * math.pi), float(x[4])
    e = goal - p
    d = float(e.norm())
    theta_t = math.atan2(float(e[1]), float(e[0])) % (2 * math.pi)
    between = math.acos(
        max(-1.0, min(1.0, float(e @ torch.tensor([math.cos(th), math.sin(th)], dtype=F64)) / (d + 1e-4)))
    )
    if th <= math.pi:
        sign = 1.0 if 0 <= theta_t - th < math.pi else -1.0
    else:
        sign = -1.0 if -math.pi < theta_t - th <= 0 else 1.0
    soft = math.sqrt(d * d + 1e-6)
    dist = d * (0.5 / soft if soft > 0.5 else 1.0)
    return torch.tensor([sign * between, -2.5 * v + 2.3 * dist], dtype=F64)


@given(seed=st.integers(0, 2**16))
@settings(max_examples=20, deadline=None)
def test_the_nominal_law_is_the_references(seed):
    g = torch.Generator().manual_seed(seed)
    yaw = 2 * math.pi * torch.rand(8, generator=g, dtype=F64)
    x = torch.cat((2 * torch.rand(8, 2, generator=g, dtype=F64), torch.stack((yaw.cos(), yaw.sin()), -1),
                   torch.rand(8, 1, generator=g, dtype=F64) - 0.5), -1)  # fmt: skip
    goals = 2 * torch.rand(8, 2, generator=g, dtype=F64)
    ours = DubinsCar().nominal_control(x, goals)
    for i in range(8):
        assert torch.allclose(ours[i], _reference_u(x[i], goals[i]), atol=1e-9)


def test_agents_at_their_goals_freeze_and_the_nominal_controller_arrives():
    cfg = EnvConfig.for_robot("dubins_car", num_agents=12, num_obstacles=0, num_envs=2, area_size=2.0)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(4)
    car = cfg.make_robot()
    for _ in range(400):
        frozen = (car.positions(state.x) - state.goals).norm(dim=-1) < 0.5 * cfg.agent_radius
        before = state.x.clone()
        state, _ = env.step(state, car.clip_control(car.nominal_control(state.x, state.goals)))
        assert torch.equal(state.x[frozen][:, :4], before[frozen][:, :4])  # position and heading kept
        assert torch.equal(state.x[frozen][:, 4], torch.zeros_like(state.x[frozen][:, 4]))  # parked: speed 0
    assert float((car.positions(state.x) - state.goals).norm(dim=-1).max()) < 0.5 * cfg.agent_radius


@given(scene_seed=st.integers(0, 2**16), g=gst.elements(SE2(), batch=(1,)))
@settings(max_examples=10, deadline=None)
def test_egcbf_plus_is_se2_equivariant(scene_seed, g):
    from egcbf.nn import CBFNet, PolicyNet

    model = TrainConfig.preset("egcbf+", "cpu", robot="dubins_car").model
    torch.manual_seed(0)
    cbf, pol = CBFNet(model).double(), PolicyNet(model).double()
    with torch.no_grad():
        for p in (*cbf.parameters(), *pol.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    cfg = EnvConfig.for_robot("dubins_car", num_agents=6, num_obstacles=2, num_envs=1, area_size=1.2)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(scene_seed)
    car = cfg.make_robot()
    for _ in range(3):
        state, _ = env.step(state, car.clip_control(car.nominal_control(state.x, state.goals)))
    with torch.no_grad():
        a, b = build_graph(state, cfg), build_graph(state.transform(g.to(F64)), cfg)
        assert (cbf(a) - cbf(b)).abs().max() <= 1e-9
        invariant = FieldType(SE2(), [Scalar(2)])
        assert (invariant.act(g.expand(6, 4), pol(a)) - pol(b)).abs().max() <= 1e-9


def test_the_pipeline_runs():
    from egcbf.algo import GraphCBFLearner
    from egcbf.evaluate.episodes import evaluate

    learner = GraphCBFLearner(TrainConfig.preset("egcbf+", "tiny", robot="dubins_car"))
    learner.update()
    rows, _ = evaluate(lambda _cfg: learner.controller(), [6], area_size=1.5, num_obstacles=2, episodes=1,
                       max_steps=20, show_progress=False, robot="dubins_car")  # fmt: skip
    assert 0.0 <= rows[0]["safe_rate"] <= 1.0
    with pytest.raises(ValueError, match="euler"):
        DubinsCar().step(torch.zeros(1, 5), torch.zeros(1, 2), 0.03, integrator="rk4")
