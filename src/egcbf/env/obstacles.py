"""Static obstacles, batched over environments: spheres in 3-D, discs or rotated rectangles in 2-D.

The dimension ``d`` (2 or 3) is read from the shape of the centres ``(B, K, d)``; every point argument must have
the same last dimension. All coordinates are in the world frame.

GCBF+'s CrazyFlie environment uses spheres with radius uniform in ``[0.05, 0.3]`` and centres uniform in the
arena ``[0, l]^3``; that is what :func:`sample_obstacles` draws (``dim=2``: discs with centres uniform in
``[0, l]^2``). GCBF+'s planar environments use rotated rectangles (:meth:`Obstacles.rectangles`,
:func:`sample_rectangle_obstacles`; the geometry is :mod:`egcbf.geometry.rectangles`): ``boxes`` ``(B, K, 4)`` then
holds each rectangle's half sides and orientation ``(cos, sin)``, and ``radii`` its circumradius (the bounding
disc, which the neighbour searches use before the exact distance).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry.neighbors import radius_search

__all__ = ["Obstacles", "sample_obstacles", "sample_rectangle_obstacles"]


@dataclass
class Obstacles:
    """``K`` obstacles per environment: ``centers`` ``(B, K, d)`` (world frame) and ``radii`` ``(B, K)`` (``K`` may
    be 0). ``d = 3``: spheres; ``d = 2``: discs, or rotated rectangles when ``boxes`` ``(B, K, 4)`` (half sides,
    orientation ``(cos, sin)``) is given (``radii`` then their circumradii). The dimension is :attr:`dim`."""

    centers: Tensor
    radii: Tensor
    boxes: Tensor | None = None

    #: ``near_pairs(method="auto")`` computes all distances densely up to this many obstacles per environment.
    DENSE_MAX_OBSTACLES = 32

    def __post_init__(self) -> None:
        c, r = self.centers, self.radii
        if c.dim() != 3 or c.shape[-1] not in (2, 3):
            raise ValueError(
                f"obstacle centers must be (B, K, d) with d = 3 (spheres) or d = 2 (discs), got {tuple(c.shape)}"
            )
        if r.shape != c.shape[:2]:
            raise ValueError(f"obstacle radii must be (B, K) = {tuple(c.shape[:2])}, got {tuple(r.shape)}")
        if self.boxes is not None and (c.shape[-1] != 2 or self.boxes.shape != (*c.shape[:2], 4)):
            raise ValueError(f"obstacle boxes are 2-D rectangles (B, K, 4), got {tuple(self.boxes.shape)} for "
                             f"centers {tuple(c.shape)}")  # fmt: skip

    @classmethod
    def rectangles(cls, centers: Tensor, half_sizes: Tensor, orientations: Tensor) -> Obstacles:
        """Rotated rectangles ``(B, K, 2)`` each: centres, half sides along their own axes, unit orientations."""
        return cls(centers, half_sizes.norm(dim=-1), torch.cat((half_sizes, orientations), -1))

    @property
    def is_rectangles(self) -> bool:
        return self.boxes is not None

    @property
    def packed_boxes(self) -> Tensor:
        """``boxes`` for rectangles, else an empty ``(B, K, 0)`` tensor: what a buffer stores for every kind."""
        return self.boxes if self.boxes is not None else self.centers.new_zeros(*self.centers.shape[:2], 0)

    @classmethod
    def unpack(cls, centers: Tensor, radii: Tensor, boxes: Tensor | None) -> Obstacles:
        """The inverse of :attr:`packed_boxes`: an empty last dimension (or ``None``) means round obstacles."""
        return cls(centers, radii, boxes if boxes is not None and boxes.shape[-1] else None)

    def geometry(self):
        """The rectangles as :class:`egcbf.geometry.rectangles.Rectangles` (rectangle obstacles only)."""
        from ..geometry.rectangles import Rectangles

        if self.boxes is None:
            raise ValueError("these obstacles are round, not rectangles")
        return Rectangles(self.centers, self.boxes[..., :2], self.boxes[..., 2:])

    def _map(self, fn) -> Obstacles:
        return Obstacles(fn(self.centers), fn(self.radii), None if self.boxes is None else fn(self.boxes))

    def detach(self) -> Obstacles:
        return self._map(lambda t: t.detach())

    def expand(self, num_envs: int) -> Obstacles:
        """The obstacles of a one-environment set repeated for ``num_envs`` environments (views: read only)."""
        return self._map(lambda t: t.expand(num_envs, *t.shape[1:]))

    def moved(self, centers: Tensor, rotation: Tensor | None = None) -> Obstacles:
        """The same obstacles with new ``centers`` and, for rectangles, orientations turned by ``rotation``
        ``(B, 1, 2)`` (``(cos, sin)`` of the turn; ``None``: none)."""
        boxes = self.boxes
        if boxes is not None and rotation is not None:
            c, s, o = rotation[..., 0:1], rotation[..., 1:2], boxes[..., 2:]
            turned = torch.cat((c * o[..., :1] - s * o[..., 1:], s * o[..., :1] + c * o[..., 1:]), -1)
            boxes = torch.cat((boxes[..., :2], turned.to(boxes.dtype)), -1)
        return Obstacles(centers, self.radii, boxes)

    @staticmethod
    def cat(items: list[Obstacles]) -> Obstacles:
        """Obstacles of several environment batches stacked along the environments (all of one kind)."""
        kinds = {o.is_rectangles for o in items}
        if len(kinds) != 1:
            raise ValueError("cannot stack round obstacles with rectangles")
        boxes = torch.cat([o.boxes for o in items]) if kinds == {True} else None
        return Obstacles(torch.cat([o.centers for o in items]), torch.cat([o.radii for o in items]), boxes)

    def pair_distance(self, points: Tensor, env: Tensor, k: Tensor) -> Tensor:
        """Signed distance ``(P,)`` of ``points`` ``(P, d)`` to obstacle ``k`` ``(P,)`` of environment ``env``
        ``(P,)``: ``||p - c|| - r`` for round obstacles, the rectangle's signed distance for rectangles."""
        c = self.centers[env, k].to(points.dtype)
        if self.boxes is None:
            return (points - c).norm(dim=-1) - self.radii[env, k].to(points.dtype)
        from ..geometry.rectangles import signed_distance

        box = self.boxes[env, k].to(points.dtype)
        return signed_distance(points, c, box[..., :2], box[..., 2:])

    def validate(self) -> None:
        """Raise ``ValueError`` if a centre is not finite or a radius is not a finite number ``> 0`` (a value check:
        one synchronization; :meth:`egcbf.env.SwarmState.validate` calls it where a state enters the simulator)."""
        c, r = self.centers, self.radii
        if c.numel() and not bool(torch.isfinite(c).all()):
            b, k = (~torch.isfinite(c)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"obstacle centers hold NaN or inf (first: environment {b}, obstacle {k})")
        if self.boxes is not None and self.boxes.numel():
            box = self.boxes
            if not bool(torch.isfinite(box).all()):
                raise ValueError("obstacle boxes hold NaN or inf")
            if not bool((box[..., :2] > 0).all()):
                raise ValueError("rectangle half sides must be > 0")
            if not bool(((box[..., 2:].norm(dim=-1) - 1).abs() <= 1e-6).all()):
                raise ValueError("rectangle orientations must be unit vectors (cos, sin)")
            if not bool((r >= box[..., :2].norm(dim=-1) * (1 - 1e-6)).all()):
                raise ValueError(
                    "rectangle radii must be at least their half diagonals (Obstacles.rectangles sets them)"
                )
        if r.numel() and not bool(((r > 0) & torch.isfinite(r)).all()):
            b, k = (~((r > 0) & torch.isfinite(r))).nonzero()[0].tolist()
            raise ValueError(
                f"obstacle radii must be finite and > 0, got {float(r[b, k])} (environment {b}, obstacle {k})"
            )

    @property
    def dim(self) -> int:
        """The space dimension ``d``: 3 (spheres) or 2 (discs, rectangles)."""
        return self.centers.shape[-1]

    @property
    def num_envs(self) -> int:
        return self.centers.shape[0]

    @property
    def num_obstacles(self) -> int:
        return self.centers.shape[1]

    def to(self, *args, **kwargs) -> Obstacles:
        return self._map(lambda t: t.to(*args, **kwargs))

    def _check_points(self, points: Tensor, batched: bool, broadcast: bool = False) -> None:
        """``batched``: ``points`` must be ``(B, M, d)`` (``broadcast``: ``B`` may also be 1, or anything if the
        obstacles have one environment); else ``(P, d)``."""
        d, b = self.dim, self.num_envs
        if batched:
            ok = points.dim() == 3 and points.shape[-1] == d
            if not (ok and (points.shape[0] == b or (broadcast and 1 in (points.shape[0], b)))):
                raise ValueError(
                    f"points must be (B, M, {d}) with B = {b} (the obstacles' environments) for {d}-D obstacles, "
                    f"got {tuple(points.shape)}"
                )
        elif points.dim() != 2 or points.shape[-1] != d:
            raise ValueError(f"points must be (P, {d}) for {d}-D obstacles, got {tuple(points.shape)}")

    def surface_distance(self, points: Tensor) -> Tensor:
        """Signed distance of ``points`` ``(B, M, d)`` to every obstacle, ``(B, M, K)``: ``||p - c_k|| - r_k`` for
        round ones, the rectangle's signed distance (:func:`egcbf.geometry.rectangles.signed_distance`) for rectangles.

        Dense over obstacles (``K`` is small), linear in the number of points. Broadcasts over environments: ``B``
        may be 1 on either side (the result then has the larger ``B``).
        """
        self._check_points(points, batched=True, broadcast=True)
        if self.boxes is not None:
            from ..geometry.rectangles import signed_distance

            b = max(points.shape[0], self.num_envs)
            box = self.boxes.expand(b, -1, -1)[:, None]
            return signed_distance(points[:, :, None, :], self.centers.expand(b, -1, -1)[:, None], box[..., :2],
                                   box[..., 2:])  # fmt: skip
        d = (points[:, :, None, :] - self.centers[:, None, :, :]).norm(dim=-1)
        return d - self.radii[:, None, :]

    def near_pairs_flat(
        self, points: Tensor, env: Tensor, margin: float, method: str = "auto"
    ) -> tuple[Tensor, Tensor]:
        """Pairs (point, obstacle) closer than ``margin`` to its surface (:meth:`pair_distance`), for flat ``points``
        ``(P, d)`` whose
        environments are ``env`` ``(P,)`` (long, in ``[0, B)``). Returns ``(point index, obstacle index k)``
        sorted by (point, k).

        ``method``: ``"dense"`` computes all ``P x K`` distances, ``"cells"`` uses the cell-list search (linear
        in ``P + K`` at fixed densities), ``"auto"`` picks dense for ``K <= DENSE_MAX_OBSTACLES``. Both give
        identical results.
        """
        self._check_points(points, batched=False)
        if env.shape != points.shape[:1]:
            raise ValueError(f"env must be ({points.shape[0]},) (one environment per point), got {tuple(env.shape)}")
        k = self.num_obstacles
        device = points.device
        none = torch.zeros(0, dtype=torch.long, device=device)
        if k == 0 or points.shape[0] == 0:
            return none, none
        if method not in ("auto", "dense", "cells"):
            raise ValueError(f"method must be 'auto', 'dense' or 'cells', got {method!r}")
        centers = self.centers.to(device=device, dtype=points.dtype)
        radii = self.radii.to(device=device, dtype=points.dtype)
        if method == "dense" or (method == "auto" and k <= self.DENSE_MAX_OBSTACLES):
            sd = (points[:, None, :] - centers[env]).norm(dim=-1) - radii[env]  # (P, K); rectangles: a lower bound
            pi, ki = (sd < margin).nonzero(as_tuple=True)
            return self._exact(points, env, pi, ki, margin)
        b = self.num_envs
        flat_c = centers.reshape(b * k, self.dim)
        flat_r = radii.reshape(b * k)
        env_c = torch.arange(b, device=device).repeat_interleave(k)
        reach = float(margin) + float(radii.max())
        found, pi = radius_search(points, flat_c, reach * (1 + 1e-9) + 1e-12, env, env_c)
        sd = (points[pi] - flat_c[found]).norm(dim=-1) - flat_r[found]
        keep = sd < margin
        return self._exact(points, env, pi[keep], found[keep] % k, margin)

    def _exact(self, points: Tensor, env: Tensor, pi: Tensor, ki: Tensor, margin: float) -> tuple[Tensor, Tensor]:
        """The pairs of the bounding-disc search whose exact distance is below ``margin`` (round: all of them)."""
        if self.boxes is None or pi.numel() == 0:
            return pi, ki
        keep = self.pair_distance(points[pi], env[pi], ki) < margin
        return pi[keep], ki[keep]

    def near_pairs(self, points: Tensor, margin: float, method: str = "auto") -> tuple[Tensor, Tensor, Tensor]:
        """``(b, m, k)`` index triples with ``points[b, m]`` closer than ``margin`` to obstacle ``k``'s surface, for
        ``points`` ``(B, M, d)``, sorted by (b, m, k). Linear in ``M`` (see :meth:`near_pairs_flat`)."""
        self._check_points(points, batched=True)
        b, m, d = points.shape
        k = self.num_obstacles
        dense = method == "dense" or (method == "auto" and k <= self.DENSE_MAX_OBSTACLES)
        if dense and not self.is_rectangles and k > 0 and b * m > 0:
            # the dense case of near_pairs_flat without gathering the obstacles per point: the same distances
            centers = self.centers.to(device=points.device, dtype=points.dtype)
            radii = self.radii.to(device=points.device, dtype=points.dtype)
            sd = (points[:, :, None, :] - centers[:, None, :, :]).norm(dim=-1) - radii[:, None, :]  # (B, M, K)
            return (sd < margin).nonzero(as_tuple=True)
        env = torch.arange(b, device=points.device).repeat_interleave(m)
        pi, k = self.near_pairs_flat(points.reshape(b * m, d), env, margin, method)
        return pi // max(m, 1), pi % max(m, 1), k

    def inside(self, points: Tensor, margin: float = 0.0, method: str = "auto") -> Tensor:
        """``(B, M)`` bool for ``points`` ``(B, M, d)``: the point lies strictly inside some obstacle (sphere, disc or
        rectangle) inflated by ``margin``."""
        self._check_points(points, batched=True)
        b, m, d = points.shape
        out = torch.zeros(b * m, dtype=torch.bool, device=points.device)
        env = torch.arange(b, device=points.device).repeat_interleave(m)
        pi, _ = self.near_pairs_flat(points.reshape(b * m, d), env, margin, method)
        out[pi] = True
        return out.view(b, m)


def sample_obstacles(
    num_envs: int,
    num_obstacles: int,
    area_size: float,
    radius_range: tuple[float, float],
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    dim: int = 3,
) -> Obstacles:
    """``num_obstacles`` obstacles per environment: centres ``(num_envs, num_obstacles, dim)`` uniform in
    ``[0, l]^dim`` (world frame), radii ``(num_envs, num_obstacles)`` uniform in ``radius_range`` (CPU tensors;
    move them with ``.to``). ``dim = 3``: spheres, ``dim = 2``: discs.

    Draws the centres, then the radii, from ``generator`` (``dim = 3`` consumes exactly the stream it always has).
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 (discs) or 3 (spheres), got {dim!r}")
    lo, hi = radius_range
    centers = torch.rand(num_envs, num_obstacles, dim, generator=generator, dtype=dtype) * area_size
    radii = lo + (hi - lo) * torch.rand(num_envs, num_obstacles, generator=generator, dtype=dtype)
    return Obstacles(centers, radii)


def sample_rectangle_obstacles(
    num_envs: int,
    num_obstacles: int,
    area_size: float,
    side_range: tuple[float, float],
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> Obstacles:
    """GCBF+'s planar obstacles: rotated rectangles, centres uniform in ``[0, l]^2``, each side from ``side_range``,
    orientations uniform (:func:`egcbf.geometry.rectangles.sample_rectangles`)."""
    from ..geometry.rectangles import sample_rectangles

    r = sample_rectangles(num_envs, num_obstacles, area_size, side_range, generator=generator, dtype=dtype)
    return Obstacles.rectangles(r.centers, r.half_sizes, r.orientations)
