"""GCBF+'s single and double integrators (egcbf.robots.integrators): one step, the LQR gains and the nominal law
match the reference's conventions (../shared/reference/gcbfplus-facts.md), the nominal controller reaches its goals
within the box, the whole pipeline (environment, graph, training, evaluation) runs on them, and EGCBF+, averaged
over each agent's four frames, is equivariant under C4 x| R^2 at every state."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.robots import DoubleIntegrator, IntegratorParams, LinearDrone, SingleIntegrator, make_robot
from groupcanon import FieldType
from groupcanon.features import Vector

F64 = torch.float64


def test_lqr_gains_are_the_references():
    """K from the discrete Riccati equation of the reference's A, B, Q, R (values read from its code; the linear
    drone's mixes the exactly discretized A with the continuous B, as the reference does)."""
    k = LinearDrone()._gain
    expected = torch.zeros(3, 6, dtype=F64)
    expected[0, 0] = expected[1, 1] = 0.6312
    expected[2, 2] = 0.6365
    expected[0, 3] = expected[1, 4] = 0.1146
    expected[2, 5] = 0.1003
    assert torch.allclose(k, expected, atol=1e-4)
    assert torch.allclose(SingleIntegrator()._gain, 1.3845 * torch.eye(2, dtype=F64), atol=1e-4)
    k = DoubleIntegrator()._gain
    expected = torch.tensor([[1.585, 0, 1.706, 0], [0, 1.585, 0, 1.706]], dtype=F64)
    assert torch.allclose(k, expected, atol=1e-3)


def test_one_euler_step_is_the_references():
    """Double: p + dt v (the old velocity), v + dt u / m, then v clipped to +-0.5 per axis. Single: p + dt u."""
    di = DoubleIntegrator()
    x = torch.tensor([[0.1, 0.2, 0.4, -0.3]], dtype=F64)
    u = torch.tensor([[1.0, -0.5]], dtype=F64)
    got = di.step(x, u, 0.03)
    assert torch.allclose(got, torch.tensor([[0.112, 0.191, 0.5, -0.45]], dtype=F64), atol=1e-15, rtol=0)
    si = SingleIntegrator()
    got = si.step(torch.tensor([[1.0, 2.0]], dtype=F64), torch.tensor([[1.0, -0.25]], dtype=F64), 0.03)
    assert torch.allclose(got, torch.tensor([[1.03, 1.9925]], dtype=F64), atol=1e-15, rtol=0)
    with pytest.raises(ValueError, match="unknown integrator"):
        di.step(x, u, 0.03, integrator="midpoint")
    drone = LinearDrone()  # v + dt (-D v + 10 u), D = diag(1.1, 1.1, 6), then clipped; p + dt v (the old v)
    x = torch.tensor([[0.0, 0.0, 0.0, 0.4, -0.3, 0.1]], dtype=F64)
    got = drone.step(x, torch.tensor([[1.0, 0.5, -1.0]], dtype=F64), 0.03)
    want = torch.tensor([[0.012, -0.009, 0.003, 0.5, -0.3 + 0.03 * (0.33 + 5), 0.1 + 0.03 * (-0.6 - 10)]], dtype=F64)
    assert torch.allclose(got, want, atol=1e-15, rtol=0)


def test_the_nominal_law():
    """u = clip(K e), e = goal_state - x scaled to norm <= 0.5 (velocities included; the goal is at rest)."""
    di = DoubleIntegrator()
    x = torch.tensor([[0.0, 0.0, 0.1, 0.0]], dtype=F64)
    goal = torch.tensor([[0.02, 0.01]], dtype=F64)  # |e| < 0.5: not scaled
    e = torch.tensor([[0.02, 0.01, -0.1, 0.0]], dtype=F64)
    assert torch.allclose(di.nominal_control(x, goal), e @ di._gain.T, atol=1e-15)
    far = torch.tensor([[3.0, 4.0]], dtype=F64)  # scaled to norm 0.5, then clipped to the box
    e = torch.tensor([[3.0, 4.0, -0.1, 0.0]], dtype=F64)
    e = e * 0.5 / e.norm()
    assert torch.allclose(di.nominal_control(x, far), (e @ di._gain.T).clamp(-1, 1), atol=1e-15)
    assert torch.isfinite(di.nominal_control(x.new_zeros(1, 4), x.new_zeros(1, 2))).all()  # e = 0: no NaN


@pytest.mark.parametrize("name", ["single_integrator", "double_integrator", "linear_drone"])
@given(seed=st.integers(0, 2**16))
@settings(max_examples=5, deadline=None)
def test_the_nominal_controller_reaches_its_goals_within_the_box(name, seed):
    cfg = EnvConfig.for_robot(name, num_agents=8, num_obstacles=0, num_envs=2)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    robot = cfg.make_robot()
    lo, hi = robot.control_bounds(state.x)
    for _ in range(600):
        u = robot.nominal_control(state.x, state.goals)
        assert bool(((u >= lo) & (u <= hi)).all())
        state, _ = env.step(state, u)
        if name != "single_integrator":
            assert float(robot.velocities(state.x).abs().max()) <= 0.5
    assert float((robot.positions(state.x) - state.goals).norm(dim=-1).max()) < 2 * cfg.agent_radius


def test_the_reference_environment_defaults():
    for name, dim in (("single_integrator", 2), ("double_integrator", 2), ("linear_drone", 3)):
        cfg = EnvConfig.for_robot(name, num_agents=4)
        assert (cfg.dt, cfg.integrator, cfg.agent_radius, cfg.comm_radius) == (0.03, "euler", 0.05, 0.5)
        assert (cfg.n_rays, cfg.max_steps, cfg.dim) == (32, 256, dim)
    assert EnvConfig.for_robot("linear_drone", num_agents=4).obstacle_radius_range == (0.075, 0.15)
    robot = make_robot("double_integrator")
    x = torch.rand(5, 4, dtype=F64)
    assert torch.equal(robot.heading(x), torch.tensor([1.0, 0.0], dtype=F64).expand(5, 2))  # world-fixed rays
    with pytest.raises(ValueError, match="mass"):
        IntegratorParams(mass=0.0)
    with pytest.raises(ValueError, match="n_rays"):  # world-fixed rays must be invariant under quarter turns
        EnvConfig.for_robot("double_integrator", num_agents=4, n_rays=6)


def test_gcbf_plus_networks_do_not_average_frames():
    """The world-frame networks ignore the frame sets: one pass, the same output (no wasted work)."""
    from egcbf.nn import PolicyNet

    model = TrainConfig.preset("gcbf+", "cpu", robot="double_integrator").model
    pol = PolicyNet(model).double()
    cfg = EnvConfig.for_robot("double_integrator", num_agents=5, num_obstacles=1, num_envs=1, area_size=1.0)
    graph = build_graph(SwarmEnv(cfg, dtype=F64).reset(0), cfg)
    seen = []
    hook = pol.encoder.register_forward_hook(lambda _m, args, _out: seen.append(args[0].num_dst))
    with torch.no_grad():
        pol(graph), pol.raw(graph)
    hook.remove()
    assert seen == [5, 5]


@pytest.mark.parametrize("name", ["single_integrator", "double_integrator", "linear_drone"])
def test_the_pipeline_runs(name, tmp_path):
    from egcbf.algo import GraphCBFLearner
    from egcbf.evaluate.episodes import evaluate

    cfg = TrainConfig.preset("gcbf+", "tiny", robot=name)
    learner = GraphCBFLearner(cfg)
    for _ in range(2):
        info = learner.update()
    assert all(torch.isfinite(torch.as_tensor(v)).all() for v in info.values() if isinstance(v, (int, float)))
    env_cfg = EnvConfig.for_robot(name, num_agents=6, num_obstacles=2, num_envs=1, max_steps=20)
    graph = build_graph(SwarmEnv(env_cfg).reset(0), env_cfg)
    assert graph.edge_attr.shape[1] == env_cfg.dim
    rows, _ = evaluate(lambda _cfg: learner.controller(), [6], area_size=1.5, num_obstacles=2, episodes=1,
                       max_steps=20, show_progress=False, robot=name)  # fmt: skip
    assert 0.0 <= rows[0]["safe_rate"] <= 1.0 and rows[0]["num_agents"] == 6


def _perturbed_nets(algo: str, name: str = "double_integrator"):
    from egcbf.nn import CBFNet, PolicyNet

    model = TrainConfig.preset(algo, "cpu", robot=name).model
    torch.manual_seed(0)
    cbf, pol = CBFNet(model).double(), PolicyNet(model).double()
    with torch.no_grad():  # equivariance holds for any weights: move the zero-initialized last layers off their priors
        for p in (*cbf.parameters(), *pol.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    return cbf, pol


@pytest.mark.parametrize("name", ["single_integrator", "double_integrator", "linear_drone"])
@given(seed=st.integers(0, 2**16), k=st.integers(0, 3), t=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
       moving=st.booleans())  # fmt: skip
@settings(max_examples=12, deadline=None)
def test_egcbf_plus_is_c4_equivariant_at_every_state(name, seed, k, t, moving):
    """EGCBF+ averaged over each agent's four frames: the CBF is invariant and the policy's command (a world-frame
    vector) rotates with the scene, under every quarter turn (about z) and translation, float64 within 1e-9, at rest
    (zero velocity: no vector to build a frame from) and moving."""
    cbf, pol = _perturbed_nets("egcbf+", name)
    env_cfg = EnvConfig.for_robot(name, num_agents=6, num_obstacles=2, num_envs=1, area_size=1.2)
    env = SwarmEnv(env_cfg, dtype=F64)
    state = env.reset(seed)
    robot = env_cfg.make_robot()
    for _ in range(4 if moving else 0):
        state, _ = env.step(state, robot.nominal_control(state.x, state.goals))
    group, d = robot.group, robot.dim
    g = torch.cat((group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2], torch.tensor([t[:d]], dtype=F64)), -1)
    moved = state.transform(g)
    with torch.no_grad():
        a, b = build_graph(state, env_cfg), build_graph(moved, env_cfg)
        assert a.frames_per_agent == 4
        assert (cbf(a) - cbf(b)).abs().max() <= 1e-9
        rotate = FieldType(group, [Vector(d)])
        pa, pb = pol(a).view(6, d), pol(b).view(6, d)
        assert (rotate.act(g.expand(6, g.shape[-1]), pa) - pb).abs().max() <= 1e-9


def test_gcbf_plus_is_not_c4_equivariant():
    """The same test fails for GCBF+ (the world-frame networks) under a quarter turn: the test can fail."""
    from groupcanon.groups import CyclicSE2

    pol = _perturbed_nets("gcbf+")[1]
    env_cfg = EnvConfig.for_robot("double_integrator", num_agents=6, num_obstacles=2, num_envs=1, area_size=1.2)
    state = SwarmEnv(env_cfg, dtype=F64).reset(3)
    g = CyclicSE2(4).rotation_element(torch.tensor([1]), dtype=F64)
    with torch.no_grad():
        pa = pol(build_graph(state, env_cfg)).view(6, 2)
        pb = pol(build_graph(state.transform(g), env_cfg)).view(6, 2)
    assert (FieldType(CyclicSE2(4), [Vector(2)]).act(g.expand(6, 4), pa) - pb).abs().max() > 1e-4


def test_a_wrong_frame_set_is_caught():
    from egcbf.robots.checks import check_robot

    class Shifted(DoubleIntegrator):
        name = "shifted-double-integrator-for-test"

        def frames(self, x):
            f = super().frames(x)
            return torch.cat((f[..., :2], f[..., 2:] + torch.tensor([0.1, 0.0], dtype=x.dtype)), -1)  # world-fixed

    with pytest.raises(AssertionError, match="frames"):
        check_robot(Shifted(), seed=0)


@pytest.mark.parametrize("name", ["double_integrator", "quadrotor"])
@given(seed=st.integers(0, 2**16), travel=st.floats(0.3, 2.0))
@settings(max_examples=6, deadline=None)
def test_max_travel_keeps_each_goal_near_its_start(name, seed, travel):
    """GCBF+'s --max-travel: every goal within max_travel of its own start, inside the arena, still separated from
    the other goals and clear of the obstacles (the sampler's rules)."""
    cfg = EnvConfig.for_robot(name, num_agents=24, num_envs=2, num_obstacles=3, area_size=3.0, max_travel=travel)
    state = SwarmEnv(cfg, dtype=F64).reset(seed)
    robot = cfg.make_robot()
    start, goal = robot.positions(state.x), state.goals
    assert float((goal - start).norm(dim=-1).max()) <= travel + 1e-12
    assert float(goal.min()) >= 0 and float(goal.max()) <= 3.0
    gap = (goal[:, :, None] - goal[:, None]).norm(dim=-1) + 10 * torch.eye(24, dtype=F64)
    assert float(gap.min()) > cfg.start_separation * cfg.agent_radius
    assert not bool(state.obstacles.inside(goal, cfg.obstacle_clearance * cfg.agent_radius).any())


def test_max_travel_is_checked():
    with pytest.raises(ValueError, match="max_travel"):
        EnvConfig.for_robot("double_integrator", num_agents=4, max_travel=0.0)
    with pytest.raises(ValueError, match="max_travel"):
        EnvConfig.for_robot("double_integrator", num_agents=4, max_travel=1.0, scene="crossing")
