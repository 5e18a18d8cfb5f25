"""The environment's geometry in 2-D (discs, the planar LiDAR, sampling, neighbour search), and 3-D pinned to the
numbers of the 3-D-only implementation (commit 71f1fed) so that the quadrotor's results cannot drift."""

import math

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from egcbf.env.lidar import lidar_scan, ray_directions
from egcbf.env.obstacles import Obstacles, sample_obstacles
from egcbf.env.sampling import packing_feasible, sample_separated_points
from egcbf.geometry.neighbors import brute_force_neighbors, radius_neighbors
from groupcanon.groups import SE2
from groupcanon.testing import strategies as gst

G = SE2()  # (cos, sin, tx, ty); translations ~ N(0, 10^2)
F64 = torch.float64
F32 = torch.float32


def _unit(yaw):
    return torch.stack((torch.cos(yaw), torch.sin(yaw)), dim=-1)


@st.composite
def scenes2d(draw, max_envs=2, max_agents=6, max_obs=5, dtype=F64):
    """Agents in [0, 2]^2 with random headings (not unit length: only the direction matters) and discs."""
    b = draw(st.integers(1, max_envs))
    n = draw(st.integers(1, max_agents))
    k = draw(st.integers(0, max_obs))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    pos = torch.rand(b, n, 2, generator=gen, dtype=F64) * 2
    yaw = (torch.rand(b, n, generator=gen, dtype=F64) * 2 - 1) * math.pi
    heading = _unit(yaw) * (0.5 + torch.rand(b, n, 1, generator=gen, dtype=F64))
    centers = torch.rand(b, k, 2, generator=gen, dtype=F64) * 2
    radii = 0.05 + 0.25 * torch.rand(b, k, generator=gen, dtype=F64)
    return pos.to(dtype), heading.to(dtype), Obstacles(centers.to(dtype), radii.to(dtype))


def _brute2d(pos, heading, centers, radii, n_rays, rng):
    """Dense numpy reference: ``(B, N, n_rays)`` distance of every ray of every agent to the closest disc (inf if
    none within ``rng``; 0 from inside a disc), rays at azimuths linspace(-pi, pi - 2 pi / n) from the heading."""
    pos, heading, centers, radii = (np.asarray(t, dtype=np.float64) for t in (pos, heading, centers, radii))
    phi = np.linspace(-np.pi, np.pi - 2 * np.pi / n_rays, n_rays)
    yaw = np.arctan2(heading[..., 1], heading[..., 0])[..., None] + phi  # (B, N, R) world azimuths
    d = np.stack((np.cos(yaw), np.sin(yaw)), -1)  # (B, N, R, 2)
    oc = pos[:, :, None, :] - centers[:, None, :, :]  # (B, N, K, 2)
    proj = np.einsum("bnrx,bnkx->bnrk", d, oc)
    c0 = (oc**2).sum(-1)[:, :, None, :] - radii[:, None, None, :] ** 2
    disc = proj**2 - c0
    sq = np.sqrt(np.clip(disc, 0, None))
    t = np.where(c0 <= 0, 0.0, -proj - sq)
    ok = (c0 <= 0) | ((disc >= 0) & (proj < 0))
    t = np.where(ok & (t <= rng), t, np.inf)
    return np.concatenate((t, np.full((*t.shape[:-1], 1), np.inf)), -1).min(-1)


# ------------------------------------------------------------------------------------------------- obstacles
def test_obstacles_2d_shapes_and_errors():
    obs = Obstacles(torch.zeros(2, 3, 2), torch.ones(2, 3))
    assert obs.dim == 2 and obs.num_envs == 2 and obs.num_obstacles == 3
    assert Obstacles(torch.zeros(1, 0, 3), torch.zeros(1, 0)).dim == 3
    with pytest.raises(ValueError, match=r"\(B, K, d\) with d = 3 \(spheres\) or d = 2 \(discs\), got \(2, 3, 4\)"):
        Obstacles(torch.zeros(2, 3, 4), torch.ones(2, 3))
    with pytest.raises(ValueError, match=r"\(B, K, d\)"):
        Obstacles(torch.zeros(3, 2), torch.ones(3))
    for bad in (torch.zeros(2, 5, 3), torch.zeros(5, 2), torch.zeros(3, 5, 2)):
        with pytest.raises(ValueError, match=r"points must be \(B, M, 2\) with B = 2"):
            obs.inside(bad)
        with pytest.raises(ValueError, match=r"points must be \(B, M, 2\)"):
            obs.near_pairs(bad, 0.1)
    with pytest.raises(ValueError, match=r"points must be \(B, M, 2\)"):
        obs.surface_distance(torch.zeros(2, 5, 3))
    with pytest.raises(ValueError, match=r"points must be \(P, 2\)"):
        obs.near_pairs_flat(torch.zeros(5, 3), torch.zeros(5, dtype=torch.long), 0.1)
    with pytest.raises(ValueError, match=r"env must be \(5,\)"):
        obs.near_pairs_flat(torch.zeros(5, 2), torch.zeros(4, dtype=torch.long), 0.1)
    # surface_distance broadcasts over environments (one point set against every environment's obstacles)
    assert obs.surface_distance(torch.zeros(1, 5, 2)).shape == (2, 5, 3)


@given(scene=scenes2d(max_agents=30, max_obs=45), margin=st.floats(0.0, 0.8))
@settings(max_examples=20)
def test_inside_and_surface_distance_2d_match_numpy(scene, margin):
    pos, _, obs = scene
    p, c, r = pos.numpy(), obs.centers.numpy(), obs.radii.numpy()
    ref_sd = np.linalg.norm(p[:, :, None, :] - c[:, None, :, :], axis=-1) - r[:, None, :]  # (B, M, K)
    sd = obs.surface_distance(pos)
    assert sd.shape == ref_sd.shape
    np.testing.assert_allclose(sd.numpy(), ref_sd, rtol=0, atol=1e-12)
    ref_inside = (ref_sd < margin).any(-1)
    for method in ("dense", "cells", "auto"):
        assert np.array_equal(obs.inside(pos, margin, method=method).numpy(), ref_inside)
    dense = obs.near_pairs(pos, margin, method="dense")
    cells = obs.near_pairs(pos, margin, method="cells")
    for a, b in zip(dense, cells):
        assert torch.equal(a, b)
    bi, mi, ki = dense
    assert np.array_equal(np.stack(np.nonzero(ref_sd < margin)), torch.stack((bi, mi, ki)).numpy())


def test_sample_obstacles_2d():
    gen = torch.Generator().manual_seed(3)
    obs = sample_obstacles(4, 7, 2.5, (0.05, 0.3), generator=gen, dim=2)
    assert obs.centers.shape == (4, 7, 2) and obs.radii.shape == (4, 7) and obs.dim == 2
    assert obs.centers.dtype == F64
    assert (obs.centers >= 0).all() and (obs.centers <= 2.5).all()
    assert (obs.radii >= 0.05).all() and (obs.radii <= 0.3).all()
    again = sample_obstacles(4, 7, 2.5, (0.05, 0.3), generator=torch.Generator().manual_seed(3), dim=2)
    assert torch.equal(obs.centers, again.centers) and torch.equal(obs.radii, again.radii)
    with pytest.raises(ValueError, match="dim must be 2"):
        sample_obstacles(1, 1, 1.0, (0.1, 0.2), dim=4)


# -------------------------------------------------------------------------------------------------- sampling
@given(
    b=st.integers(1, 3),
    n=st.integers(1, 40),
    k=st.integers(0, 6),
    area=st.floats(1.0, 4.0),
    seed=st.integers(0, 2**31 - 1),
)
@settings(max_examples=20)
def test_sample_separated_points_2d(b, n, k, area, seed):
    sep, clearance = 0.2, 0.1
    assume(packing_feasible(n, area, 2 * sep, dim=2))  # comfortably placeable
    gen = torch.Generator().manual_seed(seed)
    obs = sample_obstacles(b, k, area, (0.05, 0.2), generator=gen, dim=2)
    pts = sample_separated_points(b, 2, n, area, sep, obs, clearance, generator=gen, dim=2)
    assert pts.shape == (b, 2, n, 2) and pts.dtype == F64
    assert (pts >= 0).all() and (pts <= area).all()
    d = (pts[:, :, :, None] - pts[:, :, None, :]).norm(dim=-1) + torch.eye(n, dtype=F64) * 1e9
    assert (d > sep).all()
    if k:
        sd = obs.surface_distance(pts.reshape(b, 2 * n, 2))
        assert (sd >= clearance).all()
    # reproducible
    gen2 = torch.Generator().manual_seed(seed)
    obs2 = sample_obstacles(b, k, area, (0.05, 0.2), generator=gen2, dim=2)
    assert torch.equal(pts, sample_separated_points(b, 2, n, area, sep, obs2, clearance, generator=gen2, dim=2))


def test_sampling_2d_errors():
    flat = Obstacles(torch.zeros(1, 0, 2, dtype=F64), torch.zeros(1, 0, dtype=F64))
    with pytest.raises(ValueError, match=r"\[0, 1\]\^2 .*densest disc packing"):
        sample_separated_points(1, 1, 200, 1.0, 0.2, flat, 0.0, dim=2)
    with pytest.raises(ValueError, match=r"obstacles must be 3-D \(centers \(B, K, 3\)\)"):
        sample_separated_points(1, 1, 2, 1.0, 0.2, flat, 0.0)
    with pytest.raises(ValueError, match="dim must be 2"):
        packing_feasible(2, 1.0, 0.1, dim=1)
    # feasible by the bound but crowded: bounded rounds, then the 2-D message
    with pytest.raises(ValueError, match=r"\[0, 1\]\^2 .*still unplaced after 3 rounds"):
        sample_separated_points(1, 1, 30, 1.0, 0.2, flat, 0.0, dim=2, max_rounds=3)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("area", [0.5, 1.0, 2.7])
@pytest.mark.parametrize("sep", [0.05, 0.2, 0.45])
def test_packing_bound_is_area_in_2d_volume_in_3d(dim, area, sep):
    # the bound: N * (measure of a ball of radius sep/2) <= density * (l + sep)^dim
    ball, density = (
        (math.pi * (sep / 2) ** 2, math.pi / (2 * math.sqrt(3)))
        if dim == 2
        else (
            4 / 3 * math.pi * (sep / 2) ** 3,
            math.pi / (3 * math.sqrt(2)),
        )
    )
    n_max = math.floor(density * (area + sep) ** dim / ball)
    assert packing_feasible(n_max, area, sep, dim=dim) and not packing_feasible(n_max + 1, area, sep, dim=dim)
    # necessary condition: a realizable configuration (grid of spacing sep * (1 + 1e-9)) is never rejected
    per_axis = math.floor(area / (sep * (1 + 1e-9))) + 1
    assert packing_feasible(per_axis**dim, area, sep, dim=dim)
    # a hexagonal 2-D arrangement (rows sep * sqrt(3)/2 apart, alternate rows shifted by sep/2) is not rejected
    if dim == 2:
        s = sep * (1 + 1e-9)
        rows = math.floor(area / (s * math.sqrt(3) / 2)) + 1
        hexa = sum(math.floor((area - (s / 2) * (i % 2)) / s) + 1 for i in range(rows))
        assert packing_feasible(hexa, area, sep, dim=2)
    assert packing_feasible(5, 1.0, 0.1) == packing_feasible(5, 1.0, 0.1, dim=3)  # the default is 3-D


# ----------------------------------------------------------------------------------------------------- LiDAR
def test_ray_directions_2d():
    d = ray_directions(8, dim=2, dtype=F64)
    assert d.shape == (8, 2)
    phi = torch.linspace(-math.pi, math.pi - 2 * math.pi / 8, 8, dtype=F64)
    assert torch.allclose(d, _unit(phi), atol=1e-15)
    assert torch.equal(d[4], torch.tensor([1.0, 0.0], dtype=F64))  # azimuth 0: along the heading
    # the same azimuths as the 3-D pattern (its grid rows, projected on the horizontal plane)
    d3 = ray_directions(8, dtype=F64)[: 8 * 4].view(4, 8, 3)[..., :2]
    assert torch.allclose(d3 / d3.norm(dim=-1, keepdim=True), d.expand(4, 8, 2), atol=1e-15)
    assert ray_directions(8, dim=2).dtype == torch.get_default_dtype()
    with pytest.raises(ValueError, match="dim must be 2 or 3"):
        ray_directions(8, dim=4)
    with pytest.raises(ValueError, match="n_rays"):
        ray_directions(1, dim=2)


def test_hand_made_2d_hits_inside_and_out_of_range():
    pos = torch.tensor([[[0.0, 0.0], [5.0, 5.0], [9.0, 0.0]]], dtype=F64)  # second agent inside the second disc
    heading = torch.tensor([[[0.0, 2.0], [1.0, 0.0], [1.0, 0.0]]], dtype=F64)  # first agent faces +y
    obs = Obstacles(torch.tensor([[[0.0, 0.5], [5.0, 5.1]]], dtype=F64), torch.tensor([[0.1, 0.2]], dtype=F64))
    scan = lidar_scan(pos, heading, obs, n_rays=8, max_range=1.0, max_hits=10)
    assert scan.points.shape == (1, 3, 10, 2) and scan.valid.shape == scan.distance.shape == (1, 3, 10)
    # the ray along the heading (+y) hits the disc's bottom at distance 0.4; only it hits (rays 45 deg apart)
    assert scan.valid[0, 0].tolist() == [True] + [False] * 9
    assert scan.distance[0, 0, 0] == pytest.approx(0.4, abs=1e-12)
    assert torch.allclose(scan.points[0, 0, 0], torch.tensor([0.0, 0.4], dtype=F64), atol=1e-12)
    # inside a disc: every ray reports distance 0 at the agent's position; the 2 surplus slots are invalid
    assert scan.valid[0, 1].tolist() == [True] * 8 + [False] * 2
    assert (scan.distance[0, 1, :8] == 0).all() and torch.isinf(scan.distance[0, 1, 8:]).all()
    assert torch.equal(scan.points[0, 1], pos[0, 1].expand(10, 2))
    # nothing in range: invalid slots hold the agent position, distance inf
    assert not scan.valid[0, 2].any() and torch.isinf(scan.distance[0, 2]).all()
    assert torch.equal(scan.points[0, 2], pos[0, 2].expand(10, 2))
    # in range with a longer ray; max_hits keeps the closest
    far = Obstacles(torch.tensor([[[0.0, 1.5]]], dtype=F64), torch.tensor([[0.1]], dtype=F64))
    one = lidar_scan(pos[:, :1], heading[:, :1], far, n_rays=8, max_range=1.4 + 1e-9, max_hits=1)
    assert one.valid.all() and one.distance[0, 0, 0] == pytest.approx(1.4, abs=1e-12)
    empty = Obstacles(torch.zeros(1, 0, 2, dtype=F64), torch.zeros(1, 0, dtype=F64))
    assert not lidar_scan(pos, heading, empty, n_rays=8).valid.any()


def test_lidar_2d_shape_errors():
    pos = torch.zeros(1, 2, 2, dtype=F64)
    obs3 = Obstacles(torch.zeros(1, 1, 3, dtype=F64), torch.ones(1, 1, dtype=F64))
    with pytest.raises(ValueError, match=r"centers \(B, K, 2\), got \(1, 1, 3\)"):
        lidar_scan(pos, pos, obs3)
    with pytest.raises(ValueError, match=r"positions must be \(B, N, d\) with d = 3 or d = 2"):
        lidar_scan(torch.zeros(1, 2, 4), pos, obs3)
    with pytest.raises(ValueError, match="headings"):
        lidar_scan(pos, torch.zeros(1, 2, 1), obs3)


def _check_against_reference(scan, pos, heading, obs, n_rays, rng, hits):
    ref = np.sort(_brute2d(pos, heading, obs.centers, obs.radii, n_rays, rng), -1)[..., :hits]
    ref = np.concatenate((ref, np.full((*ref.shape[:-1], max(hits - ref.shape[-1], 0)), np.inf)), -1)
    dist = scan.distance.numpy()
    assert np.array_equal(np.isinf(dist), np.isinf(ref))
    fin = np.isfinite(ref)
    np.testing.assert_allclose(dist[fin], ref[fin], rtol=0, atol=1e-12)


@given(scene=scenes2d(), n_rays=st.sampled_from([2, 7, 16, 32]), hits=st.sampled_from([1, 5, 16, 40]))
def test_lidar_2d_matches_dense_reference_and_hits_lie_on_discs(scene, n_rays, hits):
    pos, heading, obs = scene
    scan = lidar_scan(pos, heading, obs, n_rays=n_rays, max_range=0.8, max_hits=hits)
    assert scan.points.shape == (*pos.shape[:2], hits, 2)
    _check_against_reference(scan, pos, heading, obs, n_rays, 0.8, hits)
    assert (scan.distance.diff(dim=-1)[scan.valid[..., 1:]] >= 0).all()  # closest first
    # every hit lies at the reported distance from the agent ...
    gap = (scan.points - pos[:, :, None]).norm(dim=-1)
    assert torch.allclose(gap[scan.valid], scan.distance[scan.valid], rtol=0, atol=1e-12)
    assert (scan.distance[scan.valid] <= 0.8).all()
    assert torch.equal(scan.points[~scan.valid], pos[:, :, None].expand_as(scan.points)[~scan.valid])
    if obs.num_obstacles == 0:
        assert not scan.valid.any()
        return
    # ... and on the boundary of a disc, or (distance 0) at an agent inside a disc
    b, n, h = scan.valid.shape
    sd = obs.surface_distance(scan.points.reshape(b, n * h, 2)).amin(-1).reshape(b, n, h)
    inside = obs.inside(pos)[:, :, None].expand(b, n, h)
    on = scan.valid & ~inside
    assert (sd[on].abs() < 1e-12).all()
    assert (scan.distance[scan.valid & inside] == 0).all()


@given(scene=scenes2d(max_envs=1, max_agents=4, max_obs=45))
@settings(max_examples=10)
def test_lidar_2d_many_obstacles_uses_cells_and_matches_reference(scene):
    pos, heading, obs = scene  # more than DENSE_MAX_OBSTACLES discs: near_pairs takes the cell list
    scan = lidar_scan(pos, heading, obs, n_rays=16, max_range=1.0, max_hits=6)
    _check_against_reference(scan, pos, heading, obs, 16, 1.0, 6)


def _moved(g, pos, heading, obs):
    """The scene moved by ``g`` ``(B, 4)``: positions and centres as points, headings as vectors."""
    return (
        G.transform(g[:, None], pos),
        G.rotate(g[:, None], heading),
        Obstacles(G.transform(g[:, None], obs.centers), obs.radii),
    )


@given(scene=scenes2d(), g=gst.elements(G, batch=(2,)))
def test_lidar_2d_equivariant_under_se2_float64(scene, g):
    pos, heading, obs = scene
    g = g[: pos.shape[0]]
    kw = {"n_rays": 16, "max_range": 1.0, "max_hits": 12}
    s1 = lidar_scan(pos, heading, obs, **kw)
    s2 = lidar_scan(*_moved(g, pos, heading, obs), **kw)
    assert torch.equal(s1.valid, s2.valid)
    assert torch.allclose(s1.distance[s1.valid], s2.distance[s2.valid], rtol=0, atol=1e-9)
    assert torch.allclose(G.transform(g[:, None, None], s1.points), s2.points, rtol=0, atol=1e-9)


# float32: translations ~ N(0, 10^2) put coordinates at |x| ~ 30, where float32 spacing is ~2e-6; hits of rays
# that are not within MARGIN of grazing a disc, of max_range, or of an agent on a disc's boundary move by a few
# 1e-5 (measured: at most 2.2e-5 on 1552 accepted random scenes, 4.4e-5 on 2000 unfiltered ones); the stated
# tolerance is 2e-4 on distances and hit points.
F32_TOL = 2e-4
MARGIN = 1e-3


def _well_conditioned(pos, heading, obs, n_rays, rng):
    """No ray of the float64 scene is within MARGIN of a tangent, of the range limit, or of a disc boundary (the
    cases where float32 rounding may flip a hit on or off)."""
    p, h, c, r = (x.numpy() for x in (pos, heading, obs.centers, obs.radii))
    phi = np.linspace(-np.pi, np.pi - 2 * np.pi / n_rays, n_rays)
    yaw = np.arctan2(h[..., 1], h[..., 0])[..., None] + phi
    d = np.stack((np.cos(yaw), np.sin(yaw)), -1)  # (B, N, R, 2)
    oc = c[:, None, :, :] - p[:, :, None, :]  # agent -> centre (B, N, K, 2)
    dist = np.linalg.norm(oc, axis=-1)
    if (np.abs(dist - r[:, None]) < MARGIN).any():
        return False
    along = np.einsum("bnrx,bnkx->bnrk", d, oc)
    miss = np.sqrt(np.clip((dist**2)[:, :, None] - along**2, 0, None))  # distance of the ray's line to the centre
    ahead = along > 0
    rr = r[:, None, None, :]
    if (ahead & (np.abs(miss - rr) < MARGIN)).any():
        return False
    t = along - np.sqrt(np.clip(rr**2 - miss**2, 0, None))
    return not (ahead & (miss < rr) & (np.abs(t - rng) < MARGIN)).any()


@given(scene=scenes2d(), g=gst.elements(G, batch=(2,)))
@settings(max_examples=40)
def test_lidar_2d_equivariant_under_se2_float32(scene, g):
    pos, heading, obs = scene
    kw = {"n_rays": 16, "max_range": 1.0, "max_hits": 16}  # every hit is kept: no near-tie at the cut-off
    assume(_well_conditioned(pos, heading, obs, kw["n_rays"], kw["max_range"]))
    g = g[: pos.shape[0]]
    moved = _moved(g, pos, heading, obs)
    f32 = [
        (p.to(F32), h.to(F32), Obstacles(o.centers.to(F32), o.radii.to(F32)))
        for p, h, o in ((pos, heading, obs), moved)
    ]
    s1, s2 = lidar_scan(*f32[0], **kw), lidar_scan(*f32[1], **kw)
    assert s1.points.dtype == F32
    assert torch.equal(s1.valid.sum(-1), s2.valid.sum(-1))  # same number of hits per agent
    v = s1.valid  # hits are sorted and valid slots come first, so equal counts mean equal masks
    assert torch.equal(v, s2.valid)
    assert torch.allclose(s1.distance[v], s2.distance[v], rtol=0, atol=F32_TOL)  # sorting is 1-Lipschitz
    # hit points as sets per agent (near-equal distances may swap slots): each moved hit has a partner within tol
    a = G.transform(g.to(F32)[:, None, None], s1.points)
    gap = torch.cdist(a.double(), s2.points.double())  # (B, N, H, H)
    both = v[..., :, None] & v[..., None, :]
    gap = torch.where(both, gap, torch.full_like(gap, math.inf))
    assert (gap.amin(-1)[v] <= F32_TOL).all() and (gap.amin(-2)[v] <= F32_TOL).all()


def test_lidar_2d_differentiable_float32():
    pos = torch.tensor([[[0.0, 0.0]]], requires_grad=True)
    obs = Obstacles(torch.tensor([[[0.5, 0.1]]]), torch.tensor([[0.2]]))
    scan = lidar_scan(pos, torch.tensor([[[1.0, 0.0]]]), obs, n_rays=16, max_hits=4)
    assert scan.points.dtype == F32 and scan.valid.any()
    scan.distance[scan.valid].sum().backward()
    assert torch.isfinite(pos.grad).all() and pos.grad.abs().sum() > 0


# ---------------------------------------------------------------------------------------- neighbour search
@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("spread", [1.0, 1e4])  # dense cell table / sparse occupancy (binary search)
def test_radius_neighbors_2d(dtype, spread):
    gen = torch.Generator().manual_seed(11)
    pos = torch.rand(1500, 2, generator=gen, dtype=F64) * 6
    pos[:20] *= spread  # far outliers make the grid sparse
    pos = pos.to(dtype)
    batch = torch.randint(0, 3, (1500,), generator=gen)
    ref = brute_force_neighbors(pos, 0.3, batch)
    assert ref.shape[1] > 1000
    for k in (1, 2):
        for chunk in (997, 2**21):
            got = radius_neighbors(pos, 0.3, batch, cells_per_radius=k, max_candidates=chunk)
            assert torch.equal(got, ref)


# ------------------------------------------------------------------------------------------- 3-D, pinned
# Produced by running the pre-2-D implementation (``git show 71f1fed:src/egcbf/env/{obstacles,sampling,lidar}.py``)
# on exactly the calls below (torch 2.x, CPU, float64) and printing the values with ``.tolist()`` (repr
# round-trips float64 exactly); the new code must reproduce them bit for bit.
def test_3d_sampling_stream_is_unchanged():
    gen = torch.Generator().manual_seed(20240611)
    obs = sample_obstacles(2, 3, 4.0, (0.05, 0.3), generator=gen, dtype=F64)
    pts = sample_separated_points(2, 2, 6, 4.0, 0.5, obs, 0.3, generator=gen, dtype=F64)
    nxt = torch.rand(2, generator=gen, dtype=F64)  # the generator ends in the same state
    assert obs.centers[0].flatten().tolist() == [
        1.892034168396168, 1.7378404641794867, 3.9529804521842, 1.4549210284951402, 1.3887757497044797,
        0.26378766090454153, 0.3924028461581699, 1.0010967008019462, 1.2266873488768333,
    ]  # fmt: skip
    assert obs.radii.flatten().tolist() == [
        0.13825075950169136, 0.24665978741184214, 0.22271082107523016, 0.21745723198183442, 0.21511203508918614,
        0.2074511752804074,
    ]  # fmt: skip
    assert pts.shape == (2, 2, 6, 3)
    assert pts[0, 0, :2].flatten().tolist() == [
        1.7289752516660157, 3.6535944072052495, 3.7199491958681676, 1.4016497738488, 3.151834292982307,
        2.07150693165357,
    ]  # fmt: skip
    assert pts[1, 1, -1].tolist() == [1.879514827290829, 1.3660299129172464, 3.737452285091701]
    assert pts.sum().item() == 134.3223287614367
    assert nxt.tolist() == [0.4258235657632452, 0.42942818872725885]


def test_3d_lidar_is_unchanged():
    gen = torch.Generator().manual_seed(7)
    pos = torch.rand(1, 4, 3, generator=gen, dtype=F64) * 2
    heading = torch.randn(1, 4, 3, generator=gen, dtype=F64)
    centers = torch.rand(1, 6, 3, generator=gen, dtype=F64) * 2
    radii = 0.1 + 0.3 * torch.rand(1, 6, generator=gen, dtype=F64)
    s = lidar_scan(pos, heading, Obstacles(centers, radii), n_rays=16, max_range=1.0, max_hits=8)
    assert s.points.shape == (1, 4, 8, 3)
    assert s.valid.sum().item() == 23
    assert s.distance[0, :, 0].tolist() == [
        0.13091805558824426, 0.48604449907227876, 0.19948026622844417, 0.44411828629629757,
    ]  # fmt: skip
    assert s.points[0, 0, 0].tolist() == [0.6227507133500964, 0.65947636095537, 1.7461155118892373]
    # sums of the pinned values: their last bit depends on the CPU's reduction order (AVX2 / AVX-512), so 1e-14
    assert s.distance[s.valid].sum().item() == pytest.approx(6.933500587485406, rel=1e-14, abs=0)
    assert s.points.sum().item() == pytest.approx(104.07276720235602, rel=1e-14, abs=0)
