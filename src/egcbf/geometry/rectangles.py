"""Rotated rectangle obstacles in the plane, as the GCBF+ benchmark's 2-D environments use them.

A rectangle is its centre ``c`` (world frame), its half sides ``(a, b)`` along its own axes, and its orientation
``(cos theta, sin theta)`` (the direction of its first axis). ``B`` environments of ``K`` rectangles each:
``centers (B, K, 2)``, ``half_sizes (B, K, 2)``, ``orientations (B, K, 2)``.

Geometry (GCBF+'s conventions, docs/robots.md):

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
The swarm uses them through :class:`egcbf.env.obstacles.Obstacles` (``EnvConfig(obstacle_shape="rectangle")``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["Rectangles", "nearest_point", "ray_distances", "sample_rectangles", "signed_distance"]


def _to_local(d: Tensor, orientation: Tensor) -> Tensor:
    """Vectors ``d`` in the axes of rectangles oriented ``(cos, sin)`` (broadcasting)."""
    c, s = orientation[..., 0], orientation[..., 1]
    return torch.stack((c * d[..., 0] + s * d[..., 1], c * d[..., 1] - s * d[..., 0]), -1)


def signed_distance(points: Tensor, centers: Tensor, half_sizes: Tensor, orientations: Tensor) -> Tensor:
    """Signed distance of ``points`` to rectangles (all ``(..., 2)``, broadcasting): the Euclidean distance outside,
    minus the depth inside. A point is inside the rectangle grown by ``r`` (GCBF+'s test) iff this is ``< r``."""
    q = _to_local(points - centers, orientations).abs() - half_sizes
    outside = torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1)
    return outside + q.amax(-1).clamp_max(0.0)


def nearest_point(points: Tensor, centers: Tensor, half_sizes: Tensor, orientations: Tensor) -> Tensor:
    """The point of each rectangle nearest to ``points`` (all ``(..., 2)``, broadcasting; the point itself inside)."""
    local = _to_local(points - centers, orientations)
    clamped = torch.maximum(torch.minimum(local, half_sizes), -half_sizes)
    c, s = orientations[..., 0:1], orientations[..., 1:2]
    return centers + c * clamped + s * torch.stack((-clamped[..., 1], clamped[..., 0]), -1)


def ray_distances(origins: Tensor, directions: Tensor, centers: Tensor, half_sizes: Tensor,
                  orientations: Tensor) -> Tensor:  # fmt: skip
    """Distance along unit ``directions`` ``(P, R, 2)`` from ``origins`` ``(P, 2)`` to the rectangle of each row
    (``centers``, ``half_sizes``, ``orientations`` ``(P, 2)``): ``(P, R)``, ``inf`` for a miss, 0 from inside (the
    slab method in the rectangle's axes)."""
    local = _to_local(origins - centers, orientations)[:, None]  # (P, 1, 2)
    u = _to_local(directions, orientations[:, None])  # (P, R, 2)
    half = half_sizes[:, None]
    tiny = torch.full_like(u, 1e-12)
    safe_u = torch.where(u.abs() > 1e-12, u, tiny)
    t1, t2 = (-half - local) / safe_u, (half - local) / safe_u
    parallel_out = ((u.abs() <= 1e-12) & (local.abs() >= half)).any(-1)  # parallel to a slab and outside it
    t_enter, t_exit = torch.minimum(t1, t2).amax(-1), torch.maximum(t1, t2).amin(-1)
    hit = (t_enter <= t_exit) & (t_exit >= 0) & ~parallel_out
    return torch.where(hit, t_enter.clamp_min(0.0), torch.full_like(t_enter, math.inf))


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
        return _to_local(points[:, :, None, :] - self.centers[:, None, :, :], self.orientations[:, None])

    def contains(self, points: Tensor, inflation: float = 0.0) -> Tensor:
        """``(B, N)`` bool: the point lies inside some rectangle grown by ``inflation`` (module doc; strict)."""
        if not self.num_obstacles:
            return torch.zeros(points.shape[:2], dtype=torch.bool, device=points.device)
        q = self._local(points).abs() - self.half_sizes[:, None]
        x, y = q[..., 0], q[..., 1]
        r = float(inflation)
        corner = (x > 0) & (y > 0) & (x * x + y * y < r * r)
        return (((x < r) & (y < 0)) | ((x < 0) & (y < r)) | corner).any(-1)

    def distance(self, points: Tensor) -> Tensor:
        """``(B, N)``: Euclidean distance from each point to the nearest rectangle (0 inside; ``inf`` without
        rectangles)."""
        if not self.num_obstacles:
            return points.new_full(points.shape[:2], math.inf)
        sd = signed_distance(points[:, :, None], self.centers[:, None], self.half_sizes[:, None],
                             self.orientations[:, None])  # fmt: skip
        return sd.clamp_min(0.0).amin(-1)

    def raycast(self, points: Tensor, directions: Tensor, max_range: float) -> Tensor:
        """``(B, N, R)``: the distance from each point ``(B, N, 2)`` along each unit direction ``(B, N, R, 2)``
        (world frame) to the first rectangle it meets, ``inf`` if none within ``max_range``; 0 from inside."""
        b, n, r = directions.shape[:3]
        k = self.num_obstacles
        if not k:
            return points.new_full((b, n, r), math.inf)
        rows = (b, n, k)
        t = ray_distances(
            points[:, :, None].expand(*rows, 2).reshape(-1, 2),
            directions[:, :, None].expand(b, n, k, r, 2).reshape(-1, r, 2),
            self.centers[:, None].expand(*rows, 2).reshape(-1, 2),
            self.half_sizes[:, None].expand(*rows, 2).reshape(-1, 2),
            self.orientations[:, None].expand(*rows, 2).reshape(-1, 2),
        ).view(b, n, k, r)
        t = t.amin(2)
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
