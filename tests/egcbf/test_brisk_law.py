"""The brisk base law (``Robot.brisk_control``, ``ModelConfig.base_law = "brisk"``): the double integrator's and the
Dubins car's laws cruise at their speed limits and stop at their goals, are equivariant (float64 within 1e-9,
float32 within 1e-5), and a policy on the brisk base acts around it (its command and the teacher's target); the
whole EGCBF+ command stays equivariant."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.interface import make_interface
from egcbf.algo.learner import base_command, policy_command
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.nn.models import ModelConfig, PolicyNet, sensing
from egcbf.robots import DoubleIntegrator, DubinsCar, make_robot
from groupcanon import FieldType
from groupcanon.features import Scalar, Vector

F64 = torch.float64


def _drive(robot, law, goal, steps=256, dt=0.03):
    x = robot.rest_state(torch.zeros(1, robot.dim, dtype=F64), torch.zeros(1, dtype=F64))
    g = torch.tensor([goal], dtype=F64)
    speeds, first = [], None
    for t in range(steps):
        x = robot.step(x, getattr(robot, law)(x, g), dt)
        speeds.append(robot.velocities(x)[0].abs())
        if first is None and float((robot.positions(x) - g).norm()) < 2 * robot.params.radius:
            first = t + 1
    return x, torch.stack(speeds), first


def test_the_double_integrators_brisk_law_drives_straight_at_the_speed_limit_and_stops():
    di = DoubleIntegrator()
    x, speeds, first = _drive(di, "brisk_control", [3.0, 2.0], steps=400)
    assert speeds[:, 0].max() == pytest.approx(0.5)  # the larger axis at the limit
    assert speeds[:, 1].max() == pytest.approx(0.5 * 2 / 3, abs=1e-6)  # straight at the goal: 2 / 3 of it
    assert (di.positions(x) - torch.tensor([3.0, 2.0], dtype=F64)).abs().max() < 1e-6  # no drift, no overshoot
    # the time-optimal arrival at the speed limit: about 3 m at 0.5 m/s is 200 periods less the last 2 r; the nominal
    # LQR brakes from half a metre out and takes longer
    _, _, first_nominal = _drive(di, "nominal_control", [3.0, 2.0], steps=400)
    assert first <= 200 < first_nominal


def test_the_dubins_cars_brisk_law_cruises_at_its_brisk_speed():
    car = DubinsCar()
    _, speeds, first = _drive(car, "brisk_control", [4.0, 0.0], steps=400)
    assert speeds.max() == pytest.approx(car.params.brisk_speed, abs=1e-3) and car.params.brisk_speed > 0.5
    _, nominal_speeds, first_nominal = _drive(car, "nominal_control", [4.0, 0.0], steps=400)
    assert nominal_speeds.max() == pytest.approx(0.46, abs=1e-3)
    assert first is not None and first_nominal is not None and first < first_nominal


def test_robots_without_their_own_brisk_law_use_the_nominal_one():
    robot = make_robot("single_integrator")
    x = torch.rand(5, 2, dtype=F64)
    goals = torch.rand(5, 2, dtype=F64) * 4
    assert torch.equal(robot.brisk_control(x, goals), robot.nominal_control(x, goals))


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
@given(seed=st.integers(0, 2**16))
@settings(max_examples=10, deadline=None)
def test_the_brisk_law_is_equivariant(name, dtype, atol, seed):
    robot = make_robot(name)
    gen = torch.Generator().manual_seed(seed)
    x = robot.rest_state(torch.rand(16, 2, generator=gen, dtype=dtype) * 3, torch.rand(16, generator=gen, dtype=dtype))
    lo, hi = robot.control_bounds(x)
    for _ in range(3):  # moving states, some at the speed limits
        x = robot.step(x, lo + (hi - lo) * torch.rand(16, robot.control_dim, generator=gen, dtype=dtype), 0.05)
    goals = torch.rand(16, 2, generator=gen, dtype=dtype) * 3
    g = robot.group.sample(16, generator=gen, dtype=dtype)
    gx, ggoals = robot.state_type.act(g, x), robot.group.transform(g, goals)
    got = robot.brisk_control(gx, ggoals)
    want = robot.control_type.act(g, robot.brisk_control(x, goals))
    assert (got - want).abs().max() <= atol


def test_the_base_law_is_checked():
    with pytest.raises(ValueError, match="base_law"):
        ModelConfig(robot="dubins_car", group="se2", interface="control", base_law="fast")
    with pytest.raises(ValueError, match="needs interface 'control'"):
        ModelConfig(base_law="brisk", interface="accel")


def _zero_residual_command(cfg, itf, graph, state):
    """``(command, base command)`` of a float64 policy whose weights are all zero (its residual is zero)."""
    pol = PolicyNet(cfg.model).double()
    with torch.no_grad():
        for p in pol.parameters():
            p.zero_()
        return policy_command(pol, cfg.model, itf, graph, state.x, state.goals)


@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
def test_a_policy_on_the_brisk_base_acts_around_it(name):
    """A zero residual commands the brisk law; the teacher's target (base_command) is the brisk law too."""
    cfg = TrainConfig.preset("egcbf+", "gcbfplus", robot=name, model={"base_law": "brisk"})
    env_cfg = EnvConfig.for_robot(name, num_agents=5, num_obstacles=0, num_envs=1, area_size=3.0)
    state = SwarmEnv(env_cfg, dtype=F64).reset(1)
    itf = make_interface("control", env_cfg.make_robot())
    c, c_base = _zero_residual_command(cfg, itf, build_graph(state, env_cfg), state)
    brisk = itf.brisk(state.x, state.goals)
    assert torch.allclose(c_base, brisk) and torch.allclose(c, itf.clip(state.x, brisk))
    assert torch.equal(base_command(cfg.model, itf, state.x, state.goals), brisk)
    assert not torch.allclose(brisk, itf.nominal(state.x, state.goals))  # the test can fail


@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
def test_the_isolated_brisk_base_switches_on_what_an_agent_senses(name):
    """base_law 'brisk_isolated': a zero residual commands the brisk law where an agent senses nothing and the
    nominal law where it senses a neighbour or an obstacle; the teacher's target is the same; no graph, no base."""
    cfg = TrainConfig.preset("egcbf+", "gcbfplus", robot=name, model={"base_law": "brisk_isolated"})
    env_cfg = EnvConfig.for_robot(name, num_agents=8, num_obstacles=2, num_envs=1, area_size=2.5)
    state = SwarmEnv(env_cfg, dtype=F64).reset(3)
    graph = build_graph(state, env_cfg)
    itf = make_interface("control", env_cfg.make_robot())
    c, c_base = _zero_residual_command(cfg, itf, graph, state)
    sensed = sensing(graph).view(1, -1)
    assert sensed.any() and (~sensed).any()  # both kinds of agents: the test can fail
    brisk, nominal = itf.brisk(state.x, state.goals), itf.nominal(state.x, state.goals)
    assert torch.equal(c_base[sensed], nominal[sensed]) and torch.equal(c_base[~sensed], brisk[~sensed])
    assert torch.allclose(c, itf.clip(state.x, c_base))
    assert torch.equal(base_command(cfg.model, itf, state.x, state.goals, graph), c_base)
    with pytest.raises(ValueError, match="needs the agents' graph"):
        base_command(cfg.model, itf, state.x, state.goals)


@pytest.mark.parametrize("law", ["brisk", "brisk_isolated"])
@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
def test_the_brisk_weight_blends_the_base_law_from_the_nominal_towards_the_brisk_one(name, law):
    """base = nominal + w (brisk - nominal) (where the brisk law applies); w = 1 is the brisk law itself."""
    env_cfg = EnvConfig.for_robot(name, num_agents=8, num_obstacles=2, num_envs=1, area_size=2.5)
    state = SwarmEnv(env_cfg, dtype=F64).reset(3)
    graph = build_graph(state, env_cfg)
    itf = make_interface("control", env_cfg.make_robot())
    brisk, nominal = itf.brisk(state.x, state.goals), itf.nominal(state.x, state.goals)
    model = dict(robot=name, group="trivial", interface="control", base_law=law)
    full = base_command(ModelConfig(**model), itf, state.x, state.goals, graph)
    half_cfg = ModelConfig(**model, brisk_weight=0.25)
    half = base_command(half_cfg, itf, state.x, state.goals, graph)
    want = torch.where(full == nominal, nominal, nominal + 0.25 * (brisk - nominal))
    assert torch.allclose(half, want, atol=1e-12) and not torch.allclose(half, full)  # the test can fail


def test_a_dubins_car_on_a_blended_base_cruises_between_the_nominal_and_brisk_speeds():
    """The car's laws are affine in the speed gain: weight w cruises at 0.46 + w (brisk_speed - 0.46) m/s."""
    car = DubinsCar()
    cfg = ModelConfig(robot="dubins_car", group="se2", interface="control", base_law="brisk", brisk_weight=0.5)
    itf = make_interface("control", car)
    x = car.rest_state(torch.zeros(1, 1, 2, dtype=F64), torch.zeros(1, 1, dtype=F64))
    g = torch.tensor([[[4.0, 0.0]]], dtype=F64)
    top = 0.0
    for _ in range(400):
        x = car.step(x, itf.apply(x, itf.clip(x, base_command(cfg, itf, x, g))), 0.03)
        top = max(top, float(car.velocities(x).abs().max()))
    nominal_speed = car.params.k_v * car.params.max_position_error / car.params.k_a
    assert top == pytest.approx(nominal_speed + 0.5 * (car.params.brisk_speed - nominal_speed), abs=1e-3)


def test_the_brisk_weight_is_checked():
    with pytest.raises(ValueError, match="brisk_weight must be in"):
        ModelConfig(robot="dubins_car", group="se2", interface="control", base_law="brisk", brisk_weight=1.5)
    with pytest.raises(ValueError, match="base_law 'nominal' has none"):
        ModelConfig(robot="dubins_car", group="se2", interface="control", brisk_weight=0.5)


@pytest.mark.parametrize("law, weight", [("brisk", 1.0), ("brisk_isolated", 1.0), ("brisk", 0.6)])
@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
@given(seed=st.integers(0, 2**16), k=st.integers(0, 3), angle=st.floats(-math.pi, math.pi), t=st.floats(-2, 2))
@settings(max_examples=8, deadline=None)
def test_the_whole_egcbf_plus_command_on_the_brisk_base_is_equivariant(name, law, weight, seed, k, angle, t):
    """clip(base + scale pi) around the brisk law (always, or while isolated, or blended with the nominal law) under
    a group element (a quarter turn for the double integrator, any rotation for the car, and a translation):
    float64 within 1e-9."""
    model = {"base_law": law, "brisk_weight": weight}
    cfg = TrainConfig.preset("egcbf+", "gcbfplus", robot=name, model=model)
    torch.manual_seed(0)
    pol = PolicyNet(cfg.model).double()
    with torch.no_grad():
        for p in pol.parameters():
            p.add_(0.05 * torch.randn_like(p))
    env_cfg = EnvConfig.for_robot(name, num_agents=6, num_obstacles=2, num_envs=1, area_size=1.2)
    env = SwarmEnv(env_cfg, dtype=F64)
    state = env.reset(seed)
    robot = env_cfg.make_robot()
    for _ in range(3):
        state, _ = env.step(state, robot.brisk_control(state.x, state.goals))
    if name == "double_integrator":
        rot = robot.group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2]
        g = torch.cat((rot, torch.tensor([[t, -t]], dtype=F64)), -1)
        out = FieldType(robot.group, [Vector(2)])
    else:
        g = torch.tensor([[math.cos(angle), math.sin(angle), t, -t]], dtype=F64)
        out = FieldType(robot.group, [Scalar(2)])
    moved = state.transform(g)
    itf = make_interface("control", robot)
    with torch.no_grad():
        ca, _ = policy_command(pol, cfg.model, itf, build_graph(state, env_cfg), state.x, state.goals)
        cb, _ = policy_command(pol, cfg.model, itf, build_graph(moved, env_cfg), moved.x, moved.goals)
    assert (out.act(g.expand(6, g.shape[-1]), ca[0]) - cb[0]).abs().max() <= 1e-9
