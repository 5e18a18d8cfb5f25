"""Robots as plug-ins: the robot checks on both robots, the unicycle's dynamics and nominal controller, the planar
swarm and its graph, and the learned planar controller (EGCBF+ SE(2)-equivariant, GCBF+ not)."""

import dataclasses
import functools
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.interface import ControlInterface, make_interface
from egcbf.algo.learner import LearnedController, policy_command
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import build_graph
from egcbf.nn import CBFNet, PolicyNet
from egcbf.robots import ROBOTS, DubinsCar, Quadrotor, Robot, Unicycle, UnicycleParams, make_robot, register_robot
from egcbf.robots.checks import check_robot, generic_states
from groupcanon.groups import SE2
from groupcanon.testing import strategies as gst

F64, F32 = torch.float64, torch.float32


# ----------------------------------------------------------------------------------------------- robot checks
@given(seed=st.integers(0, 2**20), name=st.sampled_from(sorted(ROBOTS)))
@settings(max_examples=20)
def test_robot_claims_hold_float64(seed, name):
    check_robot(make_robot(name), seed=seed, atol=1e-9)


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_robot_claims_hold_float32(name):
    # float32: within 1e-4 (the quadrotor's xdot reaches 6e-5: thrust / mass ~ 10 m/s^2 in single precision)
    for seed in range(5):
        check_robot(make_robot(name), seed=seed, dtype=F32, atol=1e-4)


def test_check_robot_catches_a_broken_robot():
    class Skewed(Unicycle):  # a nominal controller that reads the world x axis: not equivariant
        name = "skewed"

        def nominal_control(self, x, goals):
            return (
                super().nominal_control(x, goals)
                + x[..., 0:1] * 0
                + torch.stack((x[..., 2], torch.zeros_like(x[..., 2])), -1)
            )

    with pytest.raises(AssertionError, match="nominal control equivariant"):
        check_robot(Skewed(), seed=0)


def test_check_robot_catches_a_car_parked_at_speed():
    class Rolling(DubinsCar):  # the reference's freeze: the speed it arrived with stays in the state
        name = "rolling"

        def parked(self, x):
            return x

    with pytest.raises(AssertionError, match="parked: at rest"):
        check_robot(Rolling(), seed=0)


def test_registry():
    assert isinstance(make_robot("quadrotor"), Quadrotor) and isinstance(make_robot("unicycle"), Unicycle)
    with pytest.raises(ValueError, match="unknown robot 'boat'"):
        make_robot("boat")
    with pytest.raises(TypeError):
        register_robot(int)

    @register_robot
    class Other(Unicycle):
        name = "other-unicycle-for-test"

    try:
        assert isinstance(make_robot("other-unicycle-for-test"), Other)
        cfg = EnvConfig.for_robot("other-unicycle-for-test", num_agents=2)
        assert cfg.make_robot().name == "other-unicycle-for-test" and cfg.dim == 2
    finally:
        del ROBOTS["other-unicycle-for-test"]
    assert make_robot("unicycle") == Unicycle() and make_robot("unicycle") != Unicycle(UnicycleParams(k_p=2.0))
    assert issubclass(Quadrotor, Robot)


# ------------------------------------------------------------------------------------------------- unicycle
def test_unicycle_integrates_circles_exactly():
    """Constant turn rate and zero acceleration: a circle of radius v / omega; RK4 with renormalized headings."""
    robot = Unicycle()
    x0 = torch.tensor([[0.3, -0.2, 1.0, 0.0, 0.5]], dtype=F64)
    u = torch.tensor([[2.0, 0.0]], dtype=F64)
    x = x0
    for _ in range(100):
        x = robot.step(x, u, 0.03, 2)
    t = 3.0
    th = 2.0 * t
    expected_p = torch.tensor([0.3 + 0.25 * math.sin(th), -0.2 + 0.25 * (1 - math.cos(th))], dtype=F64)
    assert (x[0, :2] - expected_p).abs().max() < 1e-6
    assert abs(float(x[0, 2:4].norm()) - 1.0) < 1e-12
    assert (x[0, 2:4] - torch.tensor([math.cos(th), math.sin(th)], dtype=F64)).abs().max() < 1e-7  # RK4: O(h^4)
    assert float(x[0, 4]) == pytest.approx(0.5, abs=1e-15)


def test_unicycle_nominal_reaches_its_goal_and_respects_the_box():
    robot = Unicycle()
    gen = torch.Generator().manual_seed(3)
    x, goals = generic_states(robot, 32, gen)
    x = torch.cat((x[:, :4], torch.zeros_like(x[:, 4:])), -1)  # at rest
    lo, hi = robot.control_bounds(x)
    for _ in range(600):
        u = robot.nominal_control(x, goals)
        assert bool(((u >= lo - 1e-12) & (u <= hi + 1e-12)).all())
        x = robot.step(x, u, 0.03)
    assert float((x[:, :2] - goals).norm(dim=-1).max()) < 0.1  # within the reach radius 2 r


def test_unicycle_params_are_checked():
    with pytest.raises(ValueError, match="max_turn_rate"):
        UnicycleParams(max_turn_rate=0.0)
    with pytest.raises(ValueError, match="unit vector"):
        Unicycle().check_state(torch.tensor([[0.0, 0.0, 2.0, 0.0, 0.0]]))


# ---------------------------------------------------------------------------------------------- the planar swarm
def test_planar_env_config_and_round_trip():
    cfg = EnvConfig.for_robot("unicycle", num_agents=16, area_size=4.0)
    assert cfg.dim == 2 and cfg.dt == 0.03 and isinstance(cfg.params, UnicycleParams)
    assert cfg.density == pytest.approx(16 / 16.0)
    assert EnvConfig.from_dict(cfg.to_dict()) == cfg
    assert EnvConfig().robot == "quadrotor" and EnvConfig().dim == 3
    with pytest.raises(ValueError, match="params"):
        EnvConfig(robot="unicycle", params=EnvConfig().params)
    with pytest.raises(ValueError, match="unknown robot"):
        EnvConfig(robot="boat")


def test_planar_swarm_steps_and_its_masks_are_invariant():
    cfg = EnvConfig.for_robot("unicycle", num_agents=12, area_size=1.5, num_obstacles=3, num_envs=2)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(5)
    assert state.x.shape == (2, 12, 5) and state.goals.shape == (2, 12, 2) and state.obstacles.dim == 2
    g = SE2().sample(2, generator=torch.Generator().manual_seed(1), dtype=F64)
    moved = state.transform(g)
    for _ in range(20):
        u = env.robot.nominal_control(state.x, state.goals)
        u_moved = env.robot.nominal_control(moved.x, moved.goals)
        assert (u - u_moved).abs().max() < 1e-9  # the control is invariant
        state, info = env.step(state, u)
        moved, info_moved = env.step(moved, u_moved)
        for f in ("collision", "unsafe", "reached"):
            assert torch.equal(getattr(info, f), getattr(info_moved, f))
    assert (state.transform(g).x - moved.x).abs().max() < 1e-9
    with pytest.raises(ValueError, match=r"\(2, 12, 2\)"):
        env.step(state, torch.zeros(2, 12, 4, dtype=F64))


def test_planar_graph_is_two_dimensional():
    cfg = EnvConfig.for_robot("unicycle", num_agents=10, area_size=1.0, num_obstacles=2, num_envs=2)
    state = SwarmEnv(cfg, dtype=F64).reset(0)
    graph = build_graph(state, cfg)
    assert graph.x_src.shape[1] == 7 and graph.edge_attr.shape[1] == 2 and graph.frames.shape == (20, 4)
    assert graph.pos_src.shape[1] == 2 and graph.num_hits > 0
    with pytest.raises(ValueError, match="quadrotor graphs"):
        graph.reflect_z()


# ------------------------------------------------------------------------------------- the learned controller
@functools.cache
def _planar_nets(algo: str):
    torch.manual_seed(0)
    mcfg = TrainConfig.preset(algo, "tiny", robot="unicycle").model
    cbf, pol = CBFNet(mcfg).double(), PolicyNet(mcfg).double()
    with torch.no_grad():  # equivariance holds for any weights: move zero-initialized layers off their priors
        for p in (*cbf.parameters(), *pol.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    return cbf, pol, mcfg


def _moving_planar_scene(cfg: EnvConfig, seed: int):
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    gen = torch.Generator().manual_seed(seed + 1)
    lo, hi = env.robot.control_bounds(state.x)
    for _ in range(3):  # some speed and turning, so that every feature is non-trivial
        u = lo + (hi - lo) * torch.rand(*state.x.shape[:2], 2, generator=gen, dtype=F64)
        state, _ = env.step(state, u)
    return state


def _planar_outputs(algo, state, cfg):
    cbf, pol, mcfg = _planar_nets(algo)
    graph = build_graph(state, cfg)
    with torch.no_grad():
        u, _ = LearnedController(pol, mcfg)(state, cfg)
        itf = make_interface(mcfg.interface, cfg.make_robot())
        c, _ = policy_command(pol, mcfg, itf, graph, state.x, state.goals)
        return cbf(graph), pol.encoder(graph), u, c


@st.composite
def planar_scenes(draw):
    cfg = EnvConfig.for_robot(
        "unicycle",
        num_agents=draw(st.integers(1, 6)),
        num_envs=draw(st.integers(1, 2)),
        area_size=draw(st.floats(0.8, 1.5)),
        num_obstacles=draw(st.integers(0, 3)),
        n_rays=8,
        lidar_max_hits=4,
    )
    return cfg, draw(st.integers(0, 2**20))


@given(scene=planar_scenes(), g=gst.elements(SE2(), batch=(2,)))
@settings(max_examples=20)
def test_planar_egcbf_plus_is_se2_equivariant_and_gcbf_plus_is_not(scene, g):
    cfg, seed = scene
    state = _moving_planar_scene(cfg, seed)
    g = g[: cfg.num_envs]
    a = _planar_outputs("egcbf+", state, cfg)
    b = _planar_outputs("egcbf+", state.transform(g), cfg)
    for name, x, y in zip(("h", "features", "control", "command"), a, b):
        assert (x - y).abs().max() <= 1e-9, name  # all invariant: the unicycle's control is a body-frame scalar
    quarter = torch.tensor([[0.0, 1.0, 0.5, -0.5]], dtype=F64).expand(cfg.num_envs, 4)
    a = _planar_outputs("gcbf+", state, cfg)
    b = _planar_outputs("gcbf+", state.transform(quarter), cfg)
    assert (a[1] - b[1]).abs().max() > 1e-4  # GCBF+'s features see the world's axes


def test_planar_learned_control_float32_tolerance():
    cfg = EnvConfig.for_robot("unicycle", num_agents=5, num_envs=2, area_size=1.0, num_obstacles=2, n_rays=8,
                              lidar_max_hits=4)  # fmt: skip
    state = _moving_planar_scene(cfg, 4)
    g = SE2().sample(2, generator=torch.Generator().manual_seed(2), dtype=F64)
    mcfg = _planar_nets("egcbf+")[2]
    ctrl = LearnedController(PolicyNet(mcfg).float(), mcfg)
    u0, _ = ctrl(state.to(dtype=F32), cfg)
    u1, _ = ctrl(state.transform(g).to(dtype=F32), cfg)
    assert (u0 - u1).abs().max() <= 1e-4  # float32: within 1e-4 of a control bounded by 5 rad/s and 3 m/s^2


def test_control_interface_matches_the_dynamics():
    """``Lf h + Lg h . c`` is the derivative of ``h`` along the robot's dynamics (finite differences)."""
    cfg = EnvConfig.for_robot("unicycle", num_agents=4, num_envs=1, area_size=0.8, num_obstacles=0, n_rays=8,
                              lidar_max_hits=4)  # fmt: skip
    state = _moving_planar_scene(cfg, 7)
    step_cfg = dataclasses.replace(cfg, dt=1e-6)  # a short step: the closest-approach time has kinks
    cbf = _planar_nets("egcbf+")[0]
    itf = make_interface("control", cfg.make_robot())
    assert isinstance(itf, ControlInterface)
    graph = build_graph(state, cfg)
    c = 0.5 * torch.ones(1, 4, 2, dtype=F64)
    h, lf, lg = itf.lie_derivatives(cbf, graph, state.x)
    hdot = lf + torch.einsum("bijk,bjk->bi", lg, c)
    from egcbf.env.graph import refresh_graph

    x1 = itf.model_step(state.x, c, step_cfg)
    fd = (cbf(refresh_graph(graph, x1)).view(1, 4) - h) / step_cfg.dt
    assert (fd - hdot).abs().max() < 1e-3 * max(1.0, float(hdot.abs().max()))
    with pytest.raises(ValueError, match="unicycle"):
        make_interface("accel", cfg.make_robot())


def test_hand_crafted_qps_refuse_another_robot():
    from egcbf.control.controllers import make_controller

    cfg = EnvConfig.for_robot("unicycle", num_agents=3, area_size=1.0, num_obstacles=0)
    state = SwarmEnv(cfg).reset(0)
    for name in ("ccbf", "dcbf"):
        with pytest.raises(ValueError, match="quadrotor, not a unicycle"):
            make_controller(name)(state, cfg)
    u, _ = make_controller("nominal")(state, cfg)  # the nominal controller is the robot's own
    assert torch.equal(u, cfg.make_robot().nominal_control(state.x, state.goals))


def test_planar_episodes_render(tmp_path):
    from egcbf.viz.render import render_comparison_gif, render_gif, render_topdown

    traj = torch.rand(5, 3, 2) * 2
    goals, centers, radii = torch.rand(3, 2), torch.rand(2, 2), torch.full((2,), 0.1)
    coll = torch.zeros(5, 3, dtype=torch.bool)
    render_gif(tmp_path / "a.gif", traj, goals, centers, radii, coll, area_size=2.0, max_frames=3)
    render_topdown(tmp_path / "a.png", traj, goals, centers, radii, coll, area_size=2.0)
    render_comparison_gif(tmp_path / "b.gif", {"x": (traj, coll)}, goals, centers, radii, area_size=2.0, max_frames=3)
    assert all((tmp_path / n).stat().st_size > 0 for n in ("a.gif", "a.png", "b.gif"))
    with pytest.raises(ValueError, match=r"goals must be \(N, 2\)"):
        render_topdown(tmp_path / "c.png", traj, torch.rand(3, 3), area_size=2.0)


def test_demo_refuses_a_planar_checkpoint(tmp_path):
    """The demo compares quadrotor controllers: a unicycle checkpoint is a usage error, never a mixed comparison."""
    from pathlib import Path

    from typer.testing import CliRunner

    from egcbf.cli import app

    planar = Path(__file__).resolve().parents[2] / "checkpoints" / "unicycle"
    res = CliRunner().invoke(app, ["demo", "--checkpoints", str(planar), "--compare", "nominal", "--out",
                                   str(tmp_path / "demo")])  # fmt: skip
    assert res.exit_code == 2 and "drives a unicycle" in res.output


@pytest.mark.parametrize("robot", ["single_integrator", "double_integrator", "dubins_car", "linear_drone"])
def test_gcbfplus_preset_trains_each_benchmark_robot(robot, tmp_path):
    """GCBF+'s training setting (8 agents, its obstacles and arena, 0.7x the arena every other update) builds and
    runs an update for each of its benchmark robots; the other robots refuse it by name."""
    from egcbf.algo.config import GCBFPLUS_TRAINING, TrainConfig
    from egcbf.train.loop import train

    cfg = TrainConfig.preset("egcbf+", "gcbfplus", robot=robot)
    obstacles, side = GCBFPLUS_TRAINING[robot]
    got = (cfg.num_agents, cfg.num_obstacles, cfg.area_size, cfg.area_sizes)
    assert got == (8, obstacles, side, [0.7 * side, side])
    assert cfg.max_cpu_minutes == 30.0 and cfg.max_wall_minutes is None and cfg.eval_num_obstacles == 0
    small = cfg.replace(steps=1, rollout_envs=1, rollout_steps=8, horizon=4, train_graphs=None, unsafe_samples=4,
                        batch_size=4, epochs=1, eval_episodes=1, eval_max_steps=4)  # fmt: skip
    learner = train(small, tmp_path, progress=False, log=lambda s: None)
    assert learner.step == 1 and (tmp_path / "best" / "model.safetensors").exists()
    with pytest.raises(ValueError, match="gcbfplus"):
        TrainConfig.preset("egcbf+", "gcbfplus", robot="unicycle")
    with pytest.raises(ValueError, match="benchmark robots"):
        TrainConfig.preset("egcbf+", "gcbfplus")
