"""The approach part of the training labels (GCBF+'s "unsafe direction" of its double integrator and Dubins car,
``egcbf.env.swarm.approach_unsafe``): known cases at the cone's edge, agreement with a dense restatement of the
reference's formula (``arctan2`` cone, ``1e-4`` normalizations) on random scenes, invariance of the labels under
the robots' symmetries, the robots' defaults, and the learner's use of them."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.learner import GraphCBFLearner
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.lidar import LidarScan
from egcbf.env.swarm import approach_unsafe
from egcbf.robots import make_robot

F64 = torch.float64
R = 0.05


def _pair(distance: float, angle: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two agents on the x axis, ``distance`` apart; agent 0 moves at ``angle`` from the line to agent 1, agent 1
    moves away from agent 0."""
    pos = torch.tensor([[[0.0, 0.0], [distance, 0.0]]], dtype=F64)
    direction = torch.tensor([[[math.cos(angle), math.sin(angle)], [1.0, 0.0]]], dtype=F64)
    return pos, direction


def test_known_agent_cases():
    cone = math.asin(2 * R / (2.8 * R))  # the half-angle at 2.8 r
    for angle, expected in ((0.0, True), (cone - 1e-2, True), (cone + 1e-2, False), (math.pi / 2, False),
                            (math.pi, False)):  # fmt: skip
        pos, direction = _pair(2.8 * R, angle)
        labels = approach_unsafe(pos, direction, R, 3.0)
        assert labels.tolist() == [[expected, False]], angle
    pos, direction = _pair(3.2 * R, 0.0)  # head-on but beyond 3 r
    assert not approach_unsafe(pos, direction, R, 3.0).any()
    pos, direction = _pair(2.8 * R, 0.0)
    assert not approach_unsafe(pos, direction, R, 0.0).any()  # off
    assert not approach_unsafe(pos, 0 * direction, R, 3.0).any()  # at rest: no direction, no approach


def test_known_obstacle_cases():
    pos = torch.zeros(1, 1, 2, dtype=F64)
    hit = torch.tensor([1.5 * R, 0.0], dtype=F64)
    scan = LidarScan(hit.view(1, 1, 1, 2), torch.ones(1, 1, 1, dtype=torch.bool), torch.full((1, 1, 1), 1.5 * R))
    cone = math.asin(1 / 1.5)
    for angle, expected in ((0.0, True), (cone - 1e-2, True), (cone + 1e-2, False)):
        d = torch.tensor([[[math.cos(angle), math.sin(angle)]]], dtype=F64)
        assert approach_unsafe(pos, d, R, 0.0, scan, 2.0).item() is expected
    far = LidarScan(2.1 / 1.5 * hit.view(1, 1, 1, 2), scan.valid, torch.full((1, 1, 1), 2.1 * R))
    head_on = torch.tensor([[[1.0, 0.0]]], dtype=F64)
    assert not approach_unsafe(pos, head_on, R, 0.0, far, 2.0).any()  # beyond 2 r
    invalid = LidarScan(scan.points, torch.zeros_like(scan.valid), torch.full((1, 1, 1), math.inf))
    assert not approach_unsafe(pos, head_on, R, 0.0, invalid, 2.0).any()


def _dense_reference(pos, vel, hits, hit_valid):
    """The reference's dense formula for one environment: ``pos`` ``(N, 2)``, ``vel`` ``(N, 2)`` (directions from
    a velocity, normalized with ``+ 1e-4``), ``hits`` ``(N, H, 2)``."""
    n = pos.shape[0]
    heading = vel / (vel.norm(dim=-1, keepdim=True) + 1e-4)
    diff = pos[None, :, :] - pos[:, None, :]  # [i, j] = p_j - p_i
    dist = diff.norm(dim=-1) + torch.eye(n, dtype=F64) * (2 * R + 1)
    cos = (diff / (diff.norm(dim=-1, keepdim=True) + 1e-4) * heading[:, None, :]).sum(-1)
    theta = torch.arctan2(torch.full_like(dist, 2 * R), torch.sqrt(dist**2 - 4 * R**2))
    agent = ((dist < 3 * R) & (cos > torch.cos(theta))).any(1)
    hdiff = hits - pos[:, None, :]
    hdist = hdiff.norm(dim=-1)
    hcos = (hdiff / (hdist[..., None] + 1e-4) * heading[:, None, :]).sum(-1)
    htheta = torch.arctan2(torch.full_like(hdist, R), torch.sqrt(hdist**2 - R**2))
    obstacle = (hit_valid & (hdist < 2 * R) & (hcos > torch.cos(htheta))).any(1)
    return agent | obstacle


@given(seed=st.integers(0, 2**16), n=st.integers(2, 12))
@settings(max_examples=40, deadline=None)
def test_matches_the_dense_reference_formula(seed, n):
    """Away from the collisions (where the reference's square root is NaN and the collision label decides)."""
    g = torch.Generator().manual_seed(seed)
    pos = 0.4 * torch.rand(1, n, 2, generator=g, dtype=F64)
    vel = torch.randn(1, n, 2, generator=g, dtype=F64)
    hits = pos[:, :, None, :] + 0.15 * (2 * torch.rand(1, n, 5, 2, generator=g, dtype=F64) - 1)
    valid = torch.rand(1, n, 5, generator=g) < 0.7
    hdist = torch.where(valid, (hits - pos[:, :, None, :]).norm(dim=-1), torch.full((1, n, 5), math.inf, dtype=F64))
    pair = (pos[0, :, None] - pos[0, None, :]).norm(dim=-1) + torch.eye(n, dtype=F64)
    keep = (pair > 2 * R + 1e-6).all(1) & ((hdist[0] > R + 1e-6) | ~valid[0]).all(1)
    heading = vel / (vel.norm(dim=-1, keepdim=True) + 1e-4)
    ours = approach_unsafe(pos, heading, R, 3.0, LidarScan(hits, valid, hdist), 2.0)[0]
    reference = _dense_reference(pos[0], vel[0], hits[0], valid[0])
    isolated = keep & (pair > 2 * R + 1e-6).all(0)
    assert torch.equal(ours[isolated], reference[isolated])


@pytest.mark.parametrize("name", ["double_integrator", "dubins_car"])
@given(seed=st.integers(0, 2**16), k=st.integers(0, 3), angle=st.floats(-math.pi, math.pi),
       t=st.lists(st.floats(-3, 3), min_size=2, max_size=2))  # fmt: skip
@settings(max_examples=10, deadline=None)
def test_labels_are_invariant_under_the_robots_symmetry(name, seed, k, angle, t):
    """Quarter turns for the double integrator (world-fixed rays), any rotation for the car; and translations."""
    cfg = EnvConfig.for_robot(
        name,
        num_agents=10,
        num_obstacles=3,
        area_size=1.0,
        start_separation=2.2,
        obstacle_clearance=1.5,
        **make_robot(name).reference_labels,
    )  # dense: approaches on most draws
    env = SwarmEnv(cfg, dtype=F64)
    robot = env.robot
    state = env.reset(seed)
    for _ in range(6):  # moving, so that there are directions to test
        state, _ = env.step(state, robot.nominal_control(state.x, state.goals))
    turn = k * math.pi / 2 if name == "double_integrator" else angle
    if name == "double_integrator":
        rot = robot.group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2]
    else:
        rot = torch.tensor([[math.cos(turn), math.sin(turn)]], dtype=F64)
    g = torch.cat((rot, torch.tensor([t], dtype=F64)), -1)
    assert torch.equal(env.approach_unsafe(state), env.approach_unsafe(state.transform(g)))


def test_motion_directions():
    di, car = make_robot("double_integrator"), make_robot("dubins_car")
    x = torch.tensor([[0.0, 0.0, 0.3, -0.4]], dtype=F64)
    assert torch.allclose(di.motion_direction(x), torch.tensor([[0.3, -0.4]], dtype=F64) / (0.5 + 1e-4))
    assert di.motion_direction(torch.zeros(1, 4, dtype=F64)).abs().max() == 0
    rest = car.rest_state(torch.zeros(1, 2, dtype=F64), torch.tensor([0.7], dtype=F64))  # speed 0: still the heading
    assert torch.allclose(car.motion_direction(rest), torch.tensor([[math.cos(0.7), math.sin(0.7)]], dtype=F64))


def test_the_robots_name_the_references_labels():
    """The reference's labels are named by the robots (EnvConfig fields); the defaults stay the distance labels."""
    expect = {"double_integrator": (2.0, 1.0, 3.0, 2.0), "dubins_car": (2.0, 1.5, 3.0, 2.0)}
    for name, values in expect.items():
        c = EnvConfig.for_robot(name, **make_robot(name).reference_labels)
        got = (c.unsafe_agent_distance, c.unsafe_obstacle_distance, c.unsafe_approach_agent_distance,
               c.unsafe_approach_obstacle_distance)  # fmt: skip
        assert got == values, name
    for name in ("double_integrator", "dubins_car", "single_integrator", "linear_drone"):
        c = EnvConfig.for_robot(name)
        assert (c.unsafe_agent_distance, c.unsafe_obstacle_distance) == (2.5, 1.5)
        assert c.unsafe_approach_agent_distance == c.unsafe_approach_obstacle_distance == 0
    with pytest.raises(ValueError, match="unsafe_approach_agent_distance"):
        EnvConfig.for_robot("double_integrator", unsafe_approach_agent_distance=1.5)
    with pytest.raises(ValueError, match="unsafe_approach_obstacle_distance"):
        EnvConfig.for_robot("double_integrator", unsafe_approach_obstacle_distance=-1.0)
    off = EnvConfig.for_robot("single_integrator", num_envs=2, num_agents=3)
    env = SwarmEnv(off)
    assert not env.approach_unsafe(env.reset(0)).any()


def test_the_learner_labels_approaches_unsafe(monkeypatch):
    """A head-on pair 2.8 r apart, closing, is unsafe by the approach labels (the distance labels alone, 2 r, call it
    safe), and the learner's rollouts take their labels from them."""
    cfg = TrainConfig.preset("gcbf+", "tiny", robot="double_integrator")
    labels = make_robot("double_integrator").reference_labels
    env = SwarmEnv(EnvConfig.for_robot("double_integrator", num_agents=3, num_obstacles=0, **labels))
    state = env.reset(0)
    x = state.x.clone()
    x[0, 0] = torch.tensor([1.0, 1.0, 0.5, 0.0])
    x[0, 1] = torch.tensor([1.0 + 2.8 * R, 1.0, -0.5, 0.0])
    closing = type(state)(x, state.goals, state.obstacles, 0, state.robot)
    assert env.approach_unsafe(closing)[0, :2].tolist() == [True, True]
    assert not env.info(closing).unsafe[0, :2].any()

    def everyone(self, state, scan=None):
        return torch.ones(state.num_envs, state.num_agents, dtype=torch.bool)

    monkeypatch.setattr(SwarmEnv, "approach_unsafe", everyone)
    samples = GraphCBFLearner(cfg).collect(0)
    assert samples.unsafe.all() and not samples.safe.any()
