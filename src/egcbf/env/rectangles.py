"""Rotated rectangle obstacles in the plane, as the GCBF+ benchmark's 2-D environments use them (issue 26, part 2).

A rectangle is its centre ``c`` (world frame), its half sides ``(a, b)`` along its own axes, and its orientation
``(cos theta, sin theta)`` (the direction of its first axis). ``B`` environments of ``K`` rectangles each:
``centers (B, K, 2)``, ``half_sizes (B, K, 2)``, ``orientations (B, K, 2)``.

Geometry (GCBF+'s conventions, ``../shared/reference/gcbfplus-facts.md``):

* **inside with inflation r** (:meth:`Rectangles.contains`): with ``d = p - c`` in the rectangle's axes,
  ``x = |d . e1| - a``, ``y = |d . e2| - b``, a point is inside iff ``(x < r and y < 0) or (x < 0 and y < r) or
  (x > 0 and y > 0 and x^2 + y^2 < r^2)``: the rectangle grown by a disc of radius ``r`` (strict inequalities).
  :meth:`Rectangles.distance` is the matching Euclidean distance to the rectangle (0 inside).
* **ray casting** (:meth:`Rectangles.raycast`): the distance along a unit direction from a point to the first
  rectangle boundary it meets within ``max_range`` (``inf`` for a miss), by the slab method in each rectangle's axes;
  a ray starting inside a rectangle hits at distance 0 (GCBF+ puts every hit of such an agent at the agent).
* **sampling** (:func:`sample_rectangles`): centres uniform in ``[0, l]^2``, each side drawn independently from
  ``side_range``, ``theta`` uniform in ``[0, 2 pi)``.

Everything is a function of relative geometry, so a rigid motion ``g`` of the plane (``groupcanon.groups.SE2``)
moving points, rays and rectangles together leaves ``contains``, ``distance`` and ``raycast`` unchanged (tested).
Not yet wired into the environment: the swarm, its LiDAR and the collision metrics read round obstacles today.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Rectangles", "sample_rectangles"]


@dataclass
class Rectangles:
    """``K`` rotated rectangles per environment (module doc): ``centers``, ``half_sizes`` and ``orientations``
    ``(B, K, 2)`` (orientations unit vectors, half sizes > 0)."""

    centers: Tensor
    half_sizes: Tensor
    orientations: Tensor

    def __post_init__(self) -> None:
        c, h, o = self.centers, self.half_sizes, self.orientations
        if c.dim() != 3 or c.shape[-1] != 2 or h.shape != c.shape or o.shape != c.shape:
            raise ValueError(
                "rectangles need centers, half_sizes and orientations of one shape (B, K, 2), got "
                f"{tuple(c.shape)}, {tuple(h.shape)}, {tuple(o.shape)}"
            )
        if c.numel() and not bool((h > 0).all()):
            raise ValueError("rectangle half sizes must be > 0")

    @property
    def num_obstacles(self) -> int:
        return self.centers.shape[1]

    def _local(self, points: Tensor) -> Tensor:
        """``(B, N, K, 2)``: each point relative to each rectangle, in the rectangle's axes."""
        d = points[:, :, None, :] - self.centers[:, None, :, :]
        e1 = self.orientations[:, None, :, :]
        along = (d * e1).sum(-1)
        across = d[..., 1] * e1[..., 0] - d[..., 0] * e1[..., 1]
        return torch.stack((along, across), -1)

    def contains(self, points: Tensor, inflation: float = 0.0) -> Tensor:
        """``(B, N)`` bool: the point lies inside some rectangle grown by ``inflation`` (module doc; strict)."""
        q = self._local(points).abs() - self.half_sizes[:, None]
        x, y = q[..., 0], q[..., 1]
        r = float(inflation)
        corner = (x > 0) & (y > 0) & (x * x + y * y < r * r)
        inside = ((x < r) & (y < 0)) | ((x < 0) & (y < r)) | corner
        return inside.any(-1) if self.num_obstacles else inside.new_zeros(points.shape[:2])

    def distance(self, points: Tensor) -> Tensor:
        """``(B, N)``: Euclidean distance from each point to the nearest rectangle (0 inside; ``inf`` without
        rectangles)."""
        if not self.num_obstacles:
            return points.new_full(points.shape[:2], math.inf)
        q = self._local(points).abs() - self.half_sizes[:, None]
        return torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1).amin(-1)

    def raycast(self, points: Tensor, directions: Tensor, max_range: float) -> Tensor:
        """``(B, N, R)``: the distance from each point ``(B, N, 2)`` along each unit direction ``(B, N, R, 2)``
        (world frame) to the first rectangle it meets, ``inf`` if none within ``max_range``; 0 from inside."""
        b, n, r = directions.shape[:3]
        if not self.num_obstacles:
            return points.new_full((b, n, r), math.inf)
        local = self._local(points)[:, :, None]  # (B, N, 1, K, 2)
        e1 = self.orientations[:, None, None]  # (B, 1, 1, K, 2)
        dirs = directions[:, :, :, None, :]
        u = torch.stack(((dirs * e1).sum(-1), dirs[..., 1] * e1[..., 0] - dirs[..., 0] * e1[..., 1]), -1)
        half = self.half_sizes[:, None, None]
        # slab method: the ray is inside slab i for t between (-h_i - p_i) / u_i and (h_i - p_i) / u_i
        safe_u = torch.where(u.abs() > 1e-12, u, torch.full_like(u, 1e-12))
        t1, t2 = (-half - local) / safe_u, (half - local) / safe_u
        parallel_out = (u.abs() <= 1e-12) & (local.abs() >= half)  # parallel to a slab and outside it: no hit
        t_enter = torch.minimum(t1, t2).amax(-1)
        t_exit = torch.maximum(t1, t2).amin(-1)
        hit = (t_enter <= t_exit) & (t_exit >= 0) & ~parallel_out.any(-1)
        t = torch.where(hit, t_enter.clamp_min(0.0), torch.full_like(t_enter, math.inf))
        t = t.amin(-1)
        return torch.where(t <= max_range, t, torch.full_like(t, math.inf))


def sample_rectangles(
    num_envs: int,
    num_obstacles: int,
    area: float,
    side_range: tuple[float, float],
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> Rectangles:
    """GCBF+'s rectangles (module doc): ``num_obstacles`` per environment in the arena ``[0, area]^2``, sides from
    ``side_range`` (m), orientations uniform."""
    lo, hi = side_range
    if not 0 < lo <= hi:
        raise ValueError(f"side_range must satisfy 0 < low <= high, got {side_range}")
    shape = (num_envs, num_obstacles)
    centers = area * torch.rand(*shape, 2, generator=generator, dtype=torch.float64)
    sides = lo + (hi - lo) * torch.rand(*shape, 2, generator=generator, dtype=torch.float64)
    theta = 2 * math.pi * torch.rand(*shape, generator=generator, dtype=torch.float64)
    orientations = torch.stack((torch.cos(theta), torch.sin(theta)), -1)
    return Rectangles(centers.to(dtype), (sides / 2).to(dtype), orientations.to(dtype))
