"""LiDAR-only obstacle sensing of the hand-crafted dCBF-QP and the dcbf filter (``obstacle_sensing = "lidar"``):
each agent's hits as planes (default) or point obstacles. Point rows equal sphere rows of radius zero; beside a
sphere seen along its normal, the plane row demands at least what the sphere's row does and the point row at most;
the QP stays SE2xR equivariant (hypothesis, float64 within 1e-7 m/s^2) and decentralized (an obstacle beyond an
agent's LiDAR range changes nothing of its command), the controllers declare that they perceive the LiDAR, and the
CLI takes and refuses what it should."""

import json

import numpy as np
import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.control.filters import DCBF_FILTER_BARRIER, FilterConfig, FilteredController
from egcbf.env import EnvConfig, SwarmState
from egcbf.env.graph import GROUP
from egcbf.env.obstacles import Obstacles
from egcbf.evaluate.episodes import fault_support_error
from egcbf.faults import parse_faults
from egcbf.robots.quadrotor.barriers import hit_constraints, obstacle_constraints
from egcbf.robots.quadrotor.cbf_qp import CentralizedCBFQP
from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst


def test_point_hit_rows_are_sphere_rows_of_radius_zero():
    rng = np.random.default_rng(0)
    pos, vel = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    points = pos[:, None] + rng.normal(scale=0.3, size=(4, 2, 3))
    valid = np.array([[True, False], [True, True], [False, False], [False, True]])
    cfg = DCBF_FILTER_BARRIER
    rows = hit_constraints(pos, vel, points, valid, cfg, "point")
    assert rows.i.tolist() == [0, 1, 1, 3] and (rows.j == -1).all()
    for r, (i, k) in enumerate(zip(*np.nonzero(valid))):
        one = obstacle_constraints(pos[i : i + 1], vel[i : i + 1], points[i, k][None], np.zeros(1),
                                   cfg.__class__(**{**cfg.__dict__, "cull_radius": 10.0}))  # fmt: skip
        assert np.allclose(rows.normal[r], one.normal[0]) and np.isclose(rows.rhs[r], one.rhs[0])
        assert np.isclose(rows.D[r], cfg.agent_radius + cfg.margin)
    assert len(hit_constraints(pos, vel, points, np.zeros_like(valid), cfg)) == 0
    with pytest.raises(ValueError, match="model must be one of"):
        hit_constraints(pos, vel, points, valid, cfg, "sphere")


@given(
    radius=st.floats(0.05, 2.0),
    gap=st.floats(0.08, 0.6),
    direction=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    velocity=st.lists(st.floats(-1.5, 1.5), min_size=3, max_size=3),
)
@settings(max_examples=60, deadline=None)
def test_plane_row_demands_at_least_the_sphere_row_and_point_row_at_most(radius, gap, direction, velocity):
    u = np.asarray(direction)
    if np.linalg.norm(u) < 1e-3:
        u = np.array([1.0, 0.0, 0.0])
    u = u / np.linalg.norm(u)
    center = np.zeros(3)
    pos = (radius + gap) * u[None]  # the agent, ``gap`` from the surface
    vel = np.asarray(velocity)[None]
    hit = (radius * u)[None, None]  # the return along the normal: the surface point nearest the agent
    valid = np.ones((1, 1), dtype=bool)
    cfg = DCBF_FILTER_BARRIER.__class__(**{**DCBF_FILTER_BARRIER.__dict__, "cull_radius": 10.0})
    sphere = obstacle_constraints(pos, vel, center[None], np.array([radius]), cfg)
    plane, point = (hit_constraints(pos, vel, hit, valid, cfg, m) for m in ("plane", "point"))
    for rows in (plane, point):  # the same normal, distance and barrier value: only d'' differs
        assert np.allclose(rows.normal, sphere.normal) and np.allclose(rows.h, sphere.h)
    assert plane.rhs[0] >= sphere.rhs[0] - 1e-12 >= point.rhs[0] - 2e-12
    turning = (vel**2).sum() - (vel @ u) ** 2
    assert np.isclose(plane.rhs[0] - point.rhs[0], turning / gap)


def _scene(seed, obstacles=3):
    cfg = EnvConfig(num_agents=6, num_envs=2, area_size=1.2, num_obstacles=obstacles, n_rays=16, lidar_max_hits=8)
    state = moving_scene(cfg, seed)
    x = state.x.clone()
    x[..., 12:15] *= 0.5
    return SwarmState(x, state.goals, state.obstacles), cfg


@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20))
@settings(max_examples=8, deadline=None)
def test_lidar_dcbf_is_equivariant(g, seed):
    state, cfg = _scene(seed)
    qp = DecentralizedCBFQP(obstacle_sensing="lidar")
    u_a, info_a = qp(state, cfg)
    u_b, info_b = qp(state.transform(g), cfg)
    rotate = FieldType(GROUP, [Vector(3)])
    a_a = torch.as_tensor(info_a["a_safe"])
    a_b = torch.as_tensor(info_b["a_safe"])
    assert (rotate.act(g[:, None].expand(2, 6, 5), a_a) - a_b).abs().max() <= 1e-7
    assert (u_a - u_b).abs().max() <= 1e-7 * (1 + u_a.abs().max())


def test_lidar_rows_read_the_scan_and_only_the_agents_own():
    state, cfg = _scene(3)
    lidar, mapped = DecentralizedCBFQP(obstacle_sensing="lidar"), DecentralizedCBFQP()
    a_l = lidar(state, cfg)[1]["a_safe"]
    assert not np.allclose(a_l, mapped(state, cfg)[1]["a_safe"])  # the obstacles are read another way
    free, _ = _scene(3, obstacles=0)
    assert np.array_equal(lidar(free, cfg)[1]["a_safe"], mapped(free, cfg)[1]["a_safe"])
    # an obstacle moved beyond every agent's LiDAR range: no agent's command changes
    c = state.obstacles.centers.clone()
    far = state.obstacles.centers.new_tensor([50.0, 50.0, 50.0])
    base = SwarmState(state.x, state.goals, Obstacles(torch.cat((c, far.expand(2, 1, 3)), 1),
                                                      torch.cat((state.obstacles.radii, torch.full((2, 1), 0.1,
                                                      dtype=c.dtype)), 1)))  # fmt: skip
    moved = SwarmState(state.x, state.goals, Obstacles(torch.cat((c, (far + 7).expand(2, 1, 3)), 1),
                                                       base.obstacles.radii))  # fmt: skip
    assert np.abs(lidar(base, cfg)[1]["a_safe"] - lidar(moved, cfg)[1]["a_safe"]).max() <= 1e-12


def test_what_the_controllers_perceive_and_refuse():
    assert "lidar" in DecentralizedCBFQP(obstacle_sensing="lidar").reads_sensing
    assert "lidar" not in DecentralizedCBFQP().reads_sensing
    lidar_faults = parse_faults("lidar_drop=0.2")
    nominal_lidar = FilteredController(None, None, FilterConfig.for_kind("dcbf", obstacle_sensing="lidar"))
    assert fault_support_error(nominal_lidar, lidar_faults) is None
    assert fault_support_error(FilteredController(None, None, FilterConfig.for_kind("dcbf")), lidar_faults)
    assert FilterConfig.for_kind("dcbf", obstacle_sensing="lidar").settings()["obstacle_sensing"] == "lidar"
    assert "obstacle_sensing" not in FilterConfig.for_kind("dcbf").settings()  # earlier results' keys unchanged
    with pytest.raises(ValueError, match="obstacle_sensing"):
        FilterConfig.for_kind("dcbf", obstacle_sensing="sonar")
    with pytest.raises(ValueError, match="centralized"):
        CentralizedCBFQP(obstacle_sensing="lidar")
    assert FilterConfig.for_kind("dcbf", obstacle_sensing="lidar", lidar_hits="point").settings()["lidar_hits"] == (
        "point"
    )
    with pytest.raises(ValueError, match="lidar_hits = 'point' needs obstacle_sensing = 'lidar'"):
        FilterConfig.for_kind("dcbf", lidar_hits="point")
    with pytest.raises(ValueError, match="lidar_hits must be one of"):
        DecentralizedCBFQP(obstacle_sensing="lidar", lidar_hits="sphere")


def test_the_hit_model_reaches_the_qp():
    """``lidar_hits`` reaches the QP: in a scene of agents moving past obstacles, point and plane rows (which differ
    by the turning term only) give different commands."""
    state, cfg = _scene(3)
    u_plane, _ = DecentralizedCBFQP(obstacle_sensing="lidar")(state, cfg)
    u_point, _ = DecentralizedCBFQP(obstacle_sensing="lidar", lidar_hits="point")(state, cfg)
    assert not torch.equal(u_plane, u_point)


def test_eval_flag(tmp_path):
    runner = CliRunner()
    common = ["eval", "--num-agents", "4", "--area", "1.5", "--obstacles", "2", "--episodes", "1", "--max-steps",
              "8", "--no-progress"]  # fmt: skip
    res = runner.invoke(app, [*common, "--controller", "dcbf", "--obstacle-sensing", "lidar", "--out",
                              str(tmp_path / "d")])  # fmt: skip
    assert res.exit_code == 0, res.output
    run = json.loads((tmp_path / "d" / "run.json").read_text())
    assert run["obstacle_sensing"] == "lidar" and run["lidar_hits"] == "plane"
    res = runner.invoke(app, [*common, "--controller", "dcbf", "--lidar-hits", "point", "--out", str(tmp_path / "p")])
    assert res.exit_code == 2 and "--obstacle-sensing lidar" in res.output
    res = runner.invoke(app, [*common, "--controller", "ccbf", "--obstacle-sensing", "lidar", "--out",
                              str(tmp_path / "c")])  # fmt: skip
    assert res.exit_code == 2 and "centralized" in res.output
    res = runner.invoke(app, [*common, "--obstacle-sensing", "sonar", "--out", str(tmp_path / "s")])
    assert res.exit_code == 2 and "--obstacle-sensing" in res.output
