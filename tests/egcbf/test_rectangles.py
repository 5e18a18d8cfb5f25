"""egcbf.env.rectangles: GCBF+'s rotated rectangle obstacles. The inflated inside test is the distance test, ray
casting finds the first boundary point (against a brute-force march), everything is invariant under rigid motions
of the plane, and the sampling follows GCBF+'s ranges."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from egcbf.env.rectangles import Rectangles, sample_rectangles

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
