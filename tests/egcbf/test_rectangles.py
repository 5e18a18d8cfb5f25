"""egcbf.geometry.rectangles: GCBF+'s rotated rectangle obstacles. The inflated inside test is the distance test, ray
casting finds the first boundary point (against a brute-force march), everything is invariant under rigid motions
of the plane, and the sampling follows GCBF+'s ranges. In the swarm (EnvConfig(obstacle_shape="rectangle")):
the obstacle queries, the sampling clearance, the collision mask and the LiDAR agree with that geometry."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from egcbf.env.swarm import safety_masks
from egcbf.geometry.rectangles import Rectangles, sample_rectangles

F64 = torch.float64


def _scene(seed: int, k: int = 3, n: int = 40):
    g = torch.Generator().manual_seed(seed)
    rects = sample_rectangles(1, k, 2.0, (0.1, 0.6), generator=g, dtype=F64)
    points = 2.4 * torch.rand(1, n, 2, generator=g, dtype=F64) - 0.2
    return rects, points, g


def _rigid(rects: Rectangles, points: Tensor, dirs: Tensor, angle: float, shift: Tensor):
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, -s], [s, c]], dtype=F64)
    moved = Rectangles(rects.centers @ rot.T + shift, rects.half_sizes, rects.orientations @ rot.T)
    return moved, points @ rot.T + shift, dirs @ rot.T


@given(seed=st.integers(0, 2**16), r=st.floats(0.0, 0.2))
@settings(max_examples=30, deadline=None)
def test_inflated_inside_is_within_distance_r(seed, r):
    rects, points, _ = _scene(seed)
    dist = rects.distance(points)
    inside = rects.contains(points, r)
    clear = (dist - r).abs() > 1e-9  # away from the boundary, where strict and non-strict agree
    if r > 0:
        assert torch.equal(inside[clear], (dist < r)[clear])
    q = rects._local(points).abs() - rects.half_sizes[:, None]
    strictly = ((q < 0).all(-1)).any(-1)
    if r == 0:
        assert torch.equal(inside, strictly)
    assert bool((dist[strictly] == 0).all())


@given(seed=st.integers(0, 2**16))
@settings(max_examples=15, deadline=None)
def test_raycast_finds_the_first_boundary_point(seed):
    rects, points, g = _scene(seed, n=12)
    angles = 2 * math.pi * torch.rand(1, 12, 8, generator=g, dtype=F64)
    dirs = torch.stack((torch.cos(angles), torch.sin(angles)), -1)
    t = rects.raycast(points, dirs, 0.5)
    steps = torch.linspace(0, 0.5, 2001, dtype=F64)  # brute force: march in 0.25 mm steps
    along = points[:, :, None, None, :] + steps[:, None] * dirs[:, :, :, None, :]
    touched = rects.distance(along.reshape(1, -1, 2)).reshape(along.shape[:-1]) <= 1e-12
    first = torch.where(touched.any(-1), steps[touched.int().argmax(-1)], torch.full_like(t, math.inf))
    hit = torch.isfinite(t)
    assert not bool((~hit & torch.isfinite(first)).any())  # no boundary point on a ray said to miss
    both = hit & torch.isfinite(first)
    assert bool(((t - first).abs()[both] <= 3e-4).all())
    ends = points[:, :, None, :] + torch.where(hit, t, torch.zeros_like(t))[..., None] * dirs
    assert bool((rects.distance(ends.reshape(1, -1, 2)).reshape(t.shape)[hit] <= 1e-9).all())  # on the boundary


def test_known_cases():
    square = Rectangles(torch.tensor([[[1.0, 0.0]]], dtype=F64), torch.full((1, 1, 2), 0.5, dtype=F64),
                        torch.tensor([[[1.0, 0.0]]], dtype=F64))  # fmt: skip
    origin = torch.zeros(1, 1, 2, dtype=F64)
    dirs = torch.tensor([[[[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]]], dtype=F64)
    t = square.raycast(origin, dirs, 1.0)[0, 0]
    assert t[0] == 0.5 and math.isinf(t[1]) and math.isinf(t[2])
    assert math.isinf(square.raycast(origin, dirs, 0.4)[0, 0, 0])  # beyond the range
    inside = torch.tensor([[[1.2, 0.1]]], dtype=F64)
    assert bool((square.raycast(inside, dirs, 1.0) == 0).all()) and bool(square.contains(inside)[0, 0])
    corner = torch.tensor([[[1.55, 0.55]]], dtype=F64)  # 0.0707 from the corner (1.5, 0.5)
    assert bool(square.contains(corner, 0.08)[0, 0]) and not bool(square.contains(corner, 0.07)[0, 0])
    rotated = Rectangles(square.centers, torch.tensor([[[0.5, 0.1]]], dtype=F64),
                         torch.tensor([[[0.0, 1.0]]], dtype=F64))  # fmt: skip  # long side along y
    assert rotated.raycast(origin, dirs, 2.0)[0, 0, 0] == pytest.approx(0.9)


@given(seed=st.integers(0, 2**16), angle=st.floats(-math.pi, math.pi), tx=st.floats(-3, 3), ty=st.floats(-3, 3))
@settings(max_examples=30, deadline=None)
def test_invariant_under_rigid_motions(seed, angle, tx, ty):
    rects, points, g = _scene(seed, n=16)
    angles = 2 * math.pi * torch.rand(1, 16, 6, generator=g, dtype=F64)
    dirs = torch.stack((torch.cos(angles), torch.sin(angles)), -1)
    moved, p2, d2 = _rigid(rects, points, dirs, angle, torch.tensor([tx, ty], dtype=F64))
    t, t2 = rects.raycast(points, dirs, 0.5), moved.raycast(p2, d2, 0.5)
    assert torch.equal(torch.isfinite(t), torch.isfinite(t2))
    assert bool(((t - t2).abs()[torch.isfinite(t)] <= 1e-9).all())
    assert bool(((rects.distance(points) - moved.distance(p2)).abs() <= 1e-9).all())


def test_sampling_follows_the_reference_ranges():
    g = torch.Generator().manual_seed(0)
    rects = sample_rectangles(4, 200, 3.0, (0.1, 0.5), generator=g)
    assert rects.centers.shape == (4, 200, 2) and float(rects.centers.min()) >= 0 and float(rects.centers.max()) <= 3
    sides = 2 * rects.half_sizes
    assert float(sides.min()) >= 0.1 - 1e-6 and float(sides.max()) <= 0.5 + 1e-6
    assert torch.allclose(rects.orientations.norm(dim=-1), torch.ones(4, 200), atol=1e-6)
    again = sample_rectangles(4, 200, 3.0, (0.1, 0.5), generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.centers, rects.centers)
    with pytest.raises(ValueError, match="side_range"):
        sample_rectangles(1, 1, 1.0, (0.5, 0.1))
    with pytest.raises(ValueError, match="one shape"):
        Rectangles(torch.zeros(1, 2, 2), torch.ones(1, 3, 2), torch.ones(1, 2, 2))
    empty = sample_rectangles(1, 0, 1.0, (0.1, 0.2))
    pts = torch.zeros(1, 3, 2)
    assert not bool(empty.contains(pts).any()) and bool(torch.isinf(empty.distance(pts)).all())


# ----------------------------------------------------------------------------------- rectangles in the swarm
def _rect_env(seed: int, n: int = 10, k: int = 6, **kw):
    from egcbf.env import EnvConfig, SwarmEnv

    cfg = EnvConfig.for_robot("double_integrator", num_agents=n, num_obstacles=k, num_envs=2, area_size=2.0, **kw)
    env = SwarmEnv(cfg, dtype=F64)
    return cfg, env, env.reset(seed)


@given(seed=st.integers(0, 2**16))
@settings(max_examples=8, deadline=None)
def test_obstacle_queries_on_rectangles_are_the_geometry(seed):
    """Obstacles.rectangles: near pairs (dense and cell list alike), the inflated inside test and the surface
    distance agree with egcbf.geometry.rectangles."""
    from egcbf.env.obstacles import sample_rectangle_obstacles

    g = torch.Generator().manual_seed(seed)
    obs = sample_rectangle_obstacles(2, 5, 2.0, (0.1, 0.6), generator=g)
    geo = obs.geometry()
    pts = 2.4 * torch.rand(2, 30, 2, generator=g, dtype=F64) - 0.2
    for margin in (0.0, 0.05, 0.2):
        assert torch.equal(obs.inside(pts, margin, method="dense"), geo.contains(pts, margin))
        assert torch.equal(obs.inside(pts, margin, method="cells"), geo.contains(pts, margin))
    sd = obs.surface_distance(pts)
    assert torch.allclose(sd.clamp_min(0).amin(-1), geo.distance(pts), atol=1e-12)


@given(seed=st.integers(0, 2**16))
@settings(max_examples=6, deadline=None)
def test_the_swarm_samples_senses_and_collides_with_rectangles(seed):
    """Starts and goals 4 r clear of every rectangle; the collision mask is "within r of a rectangle" (or of another
    agent); every LiDAR hit lies on a rectangle's boundary, at the distance a brute-force ray cast gives."""
    cfg, env, state = _rect_env(seed)
    obs, r = state.obstacles, cfg.agent_radius
    assert obs.is_rectangles and obs.num_obstacles == 6
    robot = cfg.make_robot()
    for pts in (robot.positions(state.x), state.goals):
        assert not bool(obs.inside(pts, 4 * r).any())
    for _ in range(25):  # drive through the obstacles with the nominal controller
        state, _ = env.step(state, robot.nominal_control(state.x, state.goals))
    pos = robot.positions(state.x)
    m = safety_masks(pos, state.goals, obs, r)
    assert torch.equal(m["obstacle_collision"], obs.geometry().distance(pos) < r)
    scan = env.lidar(state)
    geo = obs.geometry()
    hit_d = geo.distance(scan.points.reshape(2, -1, 2)).reshape(scan.valid.shape)
    assert bool((hit_d[scan.valid] <= 1e-9).all())
    # each valid hit is the first boundary point along its ray: a brute-force march in 0.25 mm steps
    bi, ni, hi = scan.valid.nonzero(as_tuple=True)
    dirs = torch.nn.functional.normalize(scan.points[bi, ni, hi] - pos[bi, ni], dim=-1)
    inside = scan.distance[bi, ni, hi] == 0  # from inside a rectangle: distance 0, no direction to march
    steps = torch.linspace(0, cfg.comm_radius, 2001, dtype=F64)
    along = pos[bi, ni][:, None] + steps[:, None] * dirs[:, None]  # (P, S, 2)
    env_of = bi[:, None].expand(-1, steps.shape[0]).reshape(-1)
    obs_sd = obs.surface_distance(along.reshape(1, -1, 2).expand(2, -1, -1)).amin(-1)  # (2, P * S)
    touched = (obs_sd[env_of, torch.arange(env_of.shape[0])] <= 1e-12).view(-1, steps.shape[0])
    first = steps[touched.int().argmax(-1)]
    assert bool(touched[~inside].any(-1).all())
    assert bool(((first - scan.distance[bi, ni, hi]).abs()[~inside] <= 3e-4).all())


def test_rectangles_turn_with_the_scene():
    """A rotated world (scene_yaw) and a group transform turn the rectangles with the scene."""
    from groupcanon.groups import CyclicSE2

    _, _, state = _rect_env(1)
    g = CyclicSE2(4).rotation_element(torch.tensor([1, 1]), dtype=F64)
    g[:, 2:] = torch.tensor([0.3, -0.2], dtype=F64)
    moved = state.transform(g)
    pts = 2.4 * torch.rand(2, 20, 2, generator=torch.Generator().manual_seed(0), dtype=F64) - 0.2
    moved_pts = CyclicSE2(4).transform(g[:, None].expand(2, 20, 4), pts)
    assert torch.allclose(
        state.obstacles.surface_distance(pts), moved.obstacles.surface_distance(moved_pts), atol=1e-12
    )
    _, _, turned = _rect_env(1, scene_yaw=90.0)
    c = turned.obstacles.boxes[..., 2:]
    o = state.obstacles.boxes[..., 2:]
    assert torch.allclose(c, torch.stack((-o[..., 1], o[..., 0]), -1), atol=1e-12)
    with pytest.raises(ValueError, match="obstacle_shape"):
        from egcbf.env import EnvConfig

        EnvConfig(num_agents=4, obstacle_shape="rectangle")  # the quadrotor: 3-D
