"""LiDAR: analytic hits, the closest-k selection, and equivariance under SE2xR (rays in each agent's yaw frame)."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.env.lidar import lidar_scan, ray_directions
from egcbf.env.obstacles import Obstacles
from groupcanon.groups import SE2xR
from groupcanon.testing import strategies as gst

G = SE2xR()
F64 = torch.float64


def _heading(yaw):
    return torch.stack((torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw)), dim=-1)


def _brute(pos, yaw, centers, radii, n_rays, rng, hits):
    """Dense reference: every agent x ray x obstacle, sorted distances of the closest `hits` rays."""
    d = ray_directions(n_rays, dtype=F64)
    c, s = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
    dw = torch.stack((c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2].expand_as(c * d[:, 0])), -1)
    oc = pos[:, :, None, :] - centers[:, None, :, :]  # B N K 3
    proj = torch.einsum("bnrx,bnkx->bnrk", dw, oc)
    c0 = oc.square().sum(-1)[:, :, None, :] - radii[:, None, None, :].square()
    disc = proj.square() - c0
    sq = disc.clamp(min=0).sqrt()
    t = (-proj - sq).clamp(min=0)
    ok = (disc >= 0) & (-proj + sq >= 0) & (t <= rng)
    t = torch.where(ok, t, torch.full_like(t, math.inf))
    t = torch.cat((t, t.new_full((*t.shape[:-1], 1), math.inf)), -1).amin(-1)  # B N R (K may be 0)
    return t.sort(-1).values[..., :hits]


@st.composite
def scenes(draw, max_envs=2, max_agents=6, max_obs=5):
    b = draw(st.integers(1, max_envs))
    n = draw(st.integers(1, max_agents))
    k = draw(st.integers(0, max_obs))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    pos = torch.rand(b, n, 3, generator=gen, dtype=F64) * 2
    yaw = (torch.rand(b, n, generator=gen, dtype=F64) * 2 - 1) * math.pi
    centers = torch.rand(b, k, 3, generator=gen, dtype=F64) * 2
    radii = 0.05 + 0.25 * torch.rand(b, k, generator=gen, dtype=F64)
    return pos, yaw, Obstacles(centers, radii)


def test_ray_pattern():
    d = ray_directions(32, dtype=F64)
    assert d.shape == (32 * 16 + 2, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(d.shape[0], dtype=F64))
    assert torch.equal(d[-2], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    assert torch.equal(d[-1], torch.tensor([0.0, 0.0, -1.0], dtype=F64))
    with pytest.raises(ValueError, match="n_rays"):
        ray_directions(1)


def test_hand_made_hit_straight_up_and_inside():
    pos = torch.zeros(1, 2, 3, dtype=F64)
    pos[0, 1] = torch.tensor([5.0, 5.0, 0.5])  # second agent inside the second sphere
    obs = Obstacles(
        torch.tensor([[[0.0, 0.0, 0.5], [5.0, 5.0, 0.5]]], dtype=F64), torch.tensor([[0.1, 0.2]], dtype=F64)
    )
    scan = lidar_scan(pos, _heading(torch.zeros(1, 2, dtype=F64)), obs, n_rays=32, max_range=1.0, max_hits=16)
    assert scan.points.shape == (1, 2, 16, 3) and scan.valid.shape == (1, 2, 16)
    # the up ray hits the bottom of the first sphere at distance 0.4, the closest of all hits
    assert scan.distance[0, 0, 0] == pytest.approx(0.4, abs=1e-12)
    assert torch.allclose(scan.points[0, 0, 0], torch.tensor([0.0, 0.0, 0.4], dtype=F64), atol=1e-12)
    assert scan.valid[0, 0].all()  # many rays hit: 16 kept
    assert (scan.distance[0, 0].diff() >= 0).all()
    # inside an obstacle: every ray reports distance 0
    assert scan.valid[0, 1].all() and (scan.distance[0, 1] == 0).all()
    assert torch.equal(scan.points[0, 1], pos[0, 1].expand(16, 3))


def test_out_of_range_and_no_obstacles():
    pos = torch.zeros(1, 1, 3, dtype=F64)
    obs = Obstacles(torch.tensor([[[0.0, 0.0, 2.0]]], dtype=F64), torch.tensor([[0.5]], dtype=F64))
    h = _heading(torch.zeros(1, 1, dtype=F64))
    scan = lidar_scan(pos, h, obs, n_rays=8, max_range=1.0, max_hits=4)
    assert not scan.valid.any() and torch.isinf(scan.distance).all()
    assert torch.equal(scan.points, pos[:, :, None].expand(1, 1, 4, 3))  # invalid slots hold the agent position
    scan = lidar_scan(pos, h, obs, n_rays=8, max_range=1.6, max_hits=4)
    assert scan.valid[0, 0, 0] and scan.distance[0, 0, 0] == pytest.approx(1.5)
    empty = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    assert not lidar_scan(pos, h, empty, n_rays=8).valid.any()
    # more hits requested than rays: padded with invalid slots
    few = lidar_scan(
        pos, h, Obstacles(torch.zeros(1, 1, 3, dtype=F64), torch.ones(1, 1, dtype=F64)), n_rays=2, max_hits=8
    )
    assert few.valid.shape == (1, 1, 8) and few.valid.sum() == 4  # 2 azimuths x 1 elevation + up + down


@given(scene=scenes())
def test_matches_dense_reference(scene):
    pos, yaw, obs = scene
    scan = lidar_scan(pos, _heading(yaw), obs, n_rays=16, max_range=0.8, max_hits=10)
    ref = _brute(pos, yaw, obs.centers, obs.radii, 16, 0.8, 10)
    assert torch.equal(torch.isinf(scan.distance), torch.isinf(ref))
    fin = torch.isfinite(ref)
    assert torch.allclose(scan.distance[fin], ref[fin], atol=1e-12)
    # every valid hit lies on (or, for an agent inside, within) the surface of some sphere, within range
    if obs.num_obstacles:
        sd = obs.surface_distance(scan.points.reshape(pos.shape[0], -1, 3)).amin(-1).reshape(scan.valid.shape)
        assert (sd[scan.valid] < 1e-9).all()
    assert ((scan.points - pos[:, :, None]).norm(dim=-1)[scan.valid] <= 0.8 + 1e-12).all()


@given(scene=scenes(), g=gst.elements(G, batch=(2,)))
def test_equivariant_under_se2xr(scene, g):
    pos, yaw, obs = scene
    b = pos.shape[0]
    g = g[:b]
    theta = torch.atan2(g[:, 1], g[:, 0])
    pos2 = G.transform(g[:, None], pos)
    obs2 = Obstacles(G.transform(g[:, None], obs.centers), obs.radii)
    kw = {"n_rays": 16, "max_range": 1.0, "max_hits": 12}
    s1 = lidar_scan(pos, _heading(yaw), obs, **kw)
    s2 = lidar_scan(pos2, _heading(yaw + theta[:, None]), obs2, **kw)
    assert torch.equal(s1.valid, s2.valid)
    assert torch.allclose(s1.distance[s1.valid], s2.distance[s2.valid], atol=1e-9)
    moved = G.transform(g[:, None, None], s1.points)
    assert torch.allclose(moved, s2.points, atol=1e-9)


def test_world_fixed_rays_would_not_be_equivariant():
    """Sanity check of the design choice: rotating the scene but not the ray pattern changes the hits."""
    pos = torch.zeros(1, 1, 3, dtype=F64)
    obs = Obstacles(torch.tensor([[[0.6, 0.1, 0.05]]], dtype=F64), torch.tensor([[0.2]], dtype=F64))
    h0 = _heading(torch.zeros(1, 1, dtype=F64))
    g = torch.tensor([[math.cos(0.1), math.sin(0.1), 0.0, 0.0, 0.0]], dtype=F64)
    obs2 = Obstacles(G.transform(g[:, None], obs.centers), obs.radii)
    s1 = lidar_scan(pos, h0, obs, n_rays=16)
    s2 = lidar_scan(pos, h0, obs2, n_rays=16)  # heading not rotated
    assert not torch.allclose(G.transform(g[:, None, None], s1.points)[s1.valid], s2.points[s2.valid], atol=1e-6)


def test_differentiable_and_float32():
    pos = torch.tensor([[[0.0, 0.0, 0.0]]], requires_grad=True)
    obs = Obstacles(torch.tensor([[[0.0, 0.0, 0.5]]]), torch.tensor([[0.1]]))
    scan = lidar_scan(pos, _heading(torch.zeros(1, 1)), obs, n_rays=8, max_hits=4)
    assert scan.points.dtype == torch.float32
    scan.distance[scan.valid].sum().backward()
    assert torch.isfinite(pos.grad).all() and pos.grad.abs().sum() > 0


@given(scene=scenes(max_obs=45), margin=st.floats(0.0, 1.0))
@settings(max_examples=15)
def test_near_pairs_cells_equal_dense(scene, margin):
    pos, _, obs = scene
    dense = obs.near_pairs(pos, margin, method="dense")
    cells = obs.near_pairs(pos, margin, method="cells")
    for a, b in zip(dense, cells):
        assert torch.equal(a, b)
    inside = obs.inside(pos, margin, method="cells")
    ref = (obs.surface_distance(pos) < margin).any(-1) if obs.num_obstacles else torch.zeros_like(inside)
    assert torch.equal(inside, ref)


@given(scene=scenes(max_envs=1, max_agents=4, max_obs=45))
@settings(max_examples=10)
def test_many_obstacles_matches_dense_reference(scene):
    pos, yaw, obs = scene  # more than DENSE_MAX_OBSTACLES: the cell-list path finds the pairs
    scan = lidar_scan(pos, _heading(yaw), obs, n_rays=8, max_range=1.0, max_hits=6)
    ref = _brute(pos, yaw, obs.centers, obs.radii, 8, 1.0, 6)
    assert torch.equal(torch.isinf(scan.distance), torch.isinf(ref))
    fin = torch.isfinite(ref)
    assert torch.allclose(scan.distance[fin], ref[fin], atol=1e-12)


@given(scene=scenes(), cut=st.floats(0.0, 0.8))
def test_ray_faults_act_before_the_closest_hits_are_kept(scene, cut):
    """``ray_faults`` sees every ray that hits (agent rows, ray indices, distances) before the selection: losing
    the returns closer than ``cut`` gives the clean scan of all rays without them, its first ``max_hits``."""
    pos, yaw, obs = scene
    b, n = pos.shape[:2]
    seen = []

    def lose_close(agent, ray, t):
        seen.append((agent, ray))
        assert agent.shape == ray.shape == t.shape and (agent < b * n).all() and (ray < 16 * 8 + 2).all()
        return t, t >= cut

    scan = lidar_scan(pos, _heading(yaw), obs, n_rays=16, max_range=0.8, max_hits=4, ray_faults=lose_close)
    every = lidar_scan(pos, _heading(yaw), obs, n_rays=16, max_range=0.8, max_hits=16 * 8 + 2)
    far = torch.where(every.distance >= cut, every.distance, torch.full_like(every.distance, math.inf))
    ref = far.sort(-1).values[..., :4]
    assert torch.equal(torch.isinf(scan.distance), torch.isinf(ref))
    assert torch.equal(scan.distance[torch.isfinite(ref)], ref[torch.isfinite(ref)])
    if seen:  # each (agent, ray) at most once
        agent, ray = seen[0]
        assert torch.unique(agent * 1000 + ray).numel() == agent.numel()


@st.composite
def scenes_to_compare(draw):
    """Scenes for :func:`test_scan_equals_the_previous_implementation`: spheres (3-D) or discs or rectangles (2-D),
    ``K`` up to past the dense near-pair search, agents anywhere (some inside an obstacle, some on its surface, some
    a hair outside it), headings of any yaw (and pitch, in 3-D), float32 or float64, any ray pattern and range."""
    from egcbf.env.obstacles import sample_rectangle_obstacles

    dim = draw(st.sampled_from([2, 3]))
    rectangles = dim == 2 and draw(st.booleans())
    b, n, k = draw(st.integers(1, 3)), draw(st.integers(1, 40)), draw(st.sampled_from([0, 1, 3, 8, 40]))
    dtype = draw(st.sampled_from([torch.float32, F64]))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    side = draw(st.floats(0.5, 3.0))
    if rectangles:
        obs = sample_rectangle_obstacles(b, k, side, (0.05, 0.6), generator=gen, dtype=F64)
    else:
        centers = torch.rand(b, k, dim, generator=gen, dtype=F64) * side
        obs = Obstacles(centers, 0.05 + 0.3 * torch.rand(b, k, generator=gen, dtype=F64))
    pos = torch.rand(b, n, dim, generator=gen, dtype=F64) * side
    if k and not rectangles:  # a third of the agents on (or a relative 1e-7 off) a sphere's surface
        which = torch.randint(0, k, (b, n), generator=gen)
        c = torch.gather(obs.centers, 1, which[..., None].expand(b, n, dim))
        r = torch.gather(obs.radii, 1, which)
        u = torch.randn(b, n, dim, generator=gen, dtype=F64)
        s = 1 + (torch.randint(-1, 2, (b, n), generator=gen) * 1e-7)
        on = c + u / u.norm(dim=-1, keepdim=True) * (r * s)[..., None]
        pos = torch.where((torch.rand(b, n, 1, generator=gen) < 1 / 3), on, pos)
    heading = torch.randn(b, n, dim, generator=gen, dtype=F64)
    n_rays = draw(st.sampled_from([2, 4, 8, 16, 32]))
    kw = {"n_rays": n_rays, "max_range": draw(st.floats(0.1, 1.5)), "max_hits": draw(st.sampled_from([1, 4, 16]))}
    return pos.to(dtype), heading.to(dtype), obs.to(dtype), kw


@settings(max_examples=150, deadline=None)
@given(scene=scenes_to_compare(), faults=st.booleans())
def test_scan_equals_the_previous_implementation(scene, faults):
    """The scan (the angular-window candidates of each agent-sphere pair, the packed closest-hit sorts, the points
    of the valid slots alone) equals the previous implementation's, which tests every ray of every pair
    (``previous_env.lidar_scan``), bit for bit: points, validity and distances; also with ray faults."""
    from previous_env import lidar_scan as previous_lidar_scan

    pos, heading, obs, kw = scene

    def drop_every_third(agent, ray, t):
        return t * 0.9, (agent + ray) % 3 != 0

    if faults:
        kw = {**kw, "ray_faults": drop_every_third}
    new, old = lidar_scan(pos, heading, obs, **kw), previous_lidar_scan(pos, heading, obs, **kw)
    for a, b in ((new.points, old.points), (new.valid, old.valid), (new.distance, old.distance)):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)


@pytest.mark.parametrize("robot", ["quadrotor", "unicycle"])
def test_scan_of_swarm_episodes_equals_the_previous_implementation(robot):
    """Along episodes of the simulator (nominal controller, obstacles of Table I's density) the scan equals the
    previous implementation's at every step, in float32 and float64."""
    from previous_env import lidar_scan as previous_lidar_scan

    from egcbf.env import EnvConfig, SwarmEnv

    for dtype in (torch.float32, F64):
        area = {"quadrotor": 2.0, "unicycle": 4.0}[robot]
        cfg = EnvConfig.for_robot(robot, num_agents=64, num_envs=2, area_size=area, num_obstacles=6, max_steps=40)
        env = SwarmEnv(cfg, dtype=dtype)
        state = env.reset(3)
        kw = {"n_rays": cfg.n_rays, "max_range": cfg.resolved_lidar_range, "max_hits": cfg.lidar_max_hits}
        hits = 0
        for _ in range(12):
            state, _ = env.step(state, env.robot.nominal_control(state.x, state.goals))
            args = (state.positions, env.robot.heading(state.x), state.obstacles)
            new, old = lidar_scan(*args, **kw), previous_lidar_scan(*args, **kw)
            assert torch.equal(new.points, old.points) and torch.equal(new.valid, old.valid)
            assert torch.equal(new.distance, old.distance)
            hits += int(new.valid.sum())
        assert hits > 100  # the scenes are not empty


def test_gradients_equal_the_previous_implementation():
    """With autograd (positions or headings that require grad) the scan, and the gradients through its points and
    distances, equal the previous implementation's."""
    from previous_env import lidar_scan as previous_lidar_scan

    gen = torch.Generator().manual_seed(7)
    for dim in (2, 3):
        centers = torch.rand(2, 5, dim, generator=gen, dtype=F64) * 1.5
        obs = Obstacles(centers, 0.1 + 0.2 * torch.rand(2, 5, generator=gen, dtype=F64))
        pos0 = torch.rand(2, 30, dim, generator=gen, dtype=F64) * 1.5
        heading0 = torch.randn(2, 30, dim, generator=gen, dtype=F64)
        grads = []
        for scan_fn in (lidar_scan, previous_lidar_scan):
            pos, heading = pos0.clone().requires_grad_(True), heading0.clone().requires_grad_(True)
            scan = scan_fn(pos, heading, obs, n_rays=16, max_range=1.0, max_hits=8)
            (scan.points.sum() + scan.distance[scan.valid].sum()).backward()
            grads.append((scan.points.detach(), scan.valid, scan.distance.detach(), pos.grad, heading.grad))
        assert grads[0][1].any()
        for a, b in zip(*grads):
            assert torch.equal(a, b)
