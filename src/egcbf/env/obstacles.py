"""Static sphere obstacles, batched over environments.

GCBF+'s CrazyFlie environment uses spheres with radius uniform in ``[0.05, 0.3]`` and centres uniform in the
arena ``[0, l]^3``; that is what :func:`sample_obstacles` draws. (Boxes are not implemented: spheres are the
paper's setting and make ray casting analytic.)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..neighbors import radius_search

__all__ = ["Obstacles", "sample_obstacles"]


@dataclass
class Obstacles:
    """``K`` spheres per environment: ``centers`` ``(B, K, 3)`` and ``radii`` ``(B, K)`` (``K`` may be 0)."""

    centers: Tensor
    radii: Tensor

    #: ``near_pairs(method="auto")`` computes all distances densely up to this many obstacles per environment.
    DENSE_MAX_OBSTACLES = 32

    def __post_init__(self) -> None:
        c, r = self.centers, self.radii
        if c.dim() != 3 or c.shape[-1] != 3:
            raise ValueError(f"obstacle centers must be (B, K, 3), got {tuple(c.shape)}")
        if r.shape != c.shape[:2]:
            raise ValueError(f"obstacle radii must be (B, K) = {tuple(c.shape[:2])}, got {tuple(r.shape)}")

    def validate(self) -> None:
        """Raise ``ValueError`` if a centre is not finite or a radius is not a finite number ``> 0`` (a value check:
        one synchronization; :meth:`egcbf.env.SwarmState.validate` calls it where a state enters the simulator)."""
        c, r = self.centers, self.radii
        if c.numel() and not bool(torch.isfinite(c).all()):
            b, k = (~torch.isfinite(c)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"obstacle centers hold NaN or inf (first: environment {b}, obstacle {k})")
        if r.numel() and not bool(((r > 0) & torch.isfinite(r)).all()):
            b, k = (~((r > 0) & torch.isfinite(r))).nonzero()[0].tolist()
            raise ValueError(
                f"obstacle radii must be finite and > 0, got {float(r[b, k])} (environment {b}, obstacle {k})"
            )

    @property
    def num_envs(self) -> int:
        return self.centers.shape[0]

    @property
    def num_obstacles(self) -> int:
        return self.centers.shape[1]

    def to(self, *args, **kwargs) -> Obstacles:
        return Obstacles(self.centers.to(*args, **kwargs), self.radii.to(*args, **kwargs))

    def surface_distance(self, points: Tensor) -> Tensor:
        """Signed distance ``||p - c_k|| - r_k`` of ``points`` ``(B, M, 3)`` to every sphere: ``(B, M, K)``.

        Dense over obstacles (``K`` is small), linear in the number of points.
        """
        d = (points[:, :, None, :] - self.centers[:, None, :, :]).norm(dim=-1)
        return d - self.radii[:, None, :]

    def near_pairs_flat(
        self, points: Tensor, env: Tensor, margin: float, method: str = "auto"
    ) -> tuple[Tensor, Tensor]:
        """Pairs (point, obstacle) with ``||p - c_k|| - r_k < margin``, for flat ``points`` ``(P, 3)`` whose
        environments are ``env`` ``(P,)``. Returns ``(point index, obstacle index k)`` sorted by (point, k).

        ``method``: ``"dense"`` computes all ``P x K`` distances, ``"cells"`` uses the cell-list search (linear
        in ``P + K`` at fixed densities), ``"auto"`` picks dense for ``K <= DENSE_MAX_OBSTACLES``. Both give
        identical results.
        """
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
            sd = (points[:, None, :] - centers[env]).norm(dim=-1) - radii[env]  # (P, K)
            return (sd < margin).nonzero(as_tuple=True)
        b = self.num_envs
        flat_c = centers.reshape(b * k, 3)
        flat_r = radii.reshape(b * k)
        env_c = torch.arange(b, device=device).repeat_interleave(k)
        reach = float(margin) + float(radii.max())
        found, pi = radius_search(points, flat_c, reach * (1 + 1e-9) + 1e-12, env, env_c)
        sd = (points[pi] - flat_c[found]).norm(dim=-1) - flat_r[found]
        keep = sd < margin
        return pi[keep], found[keep] % k

    def near_pairs(self, points: Tensor, margin: float, method: str = "auto") -> tuple[Tensor, Tensor, Tensor]:
        """``(b, m, k)`` index triples with ``||points[b, m] - c[b, k]|| - r[b, k] < margin`` for ``points``
        ``(B, M, 3)``, sorted by (b, m, k). Linear in ``M`` (see :meth:`near_pairs_flat`)."""
        b, m, _ = points.shape
        env = torch.arange(b, device=points.device).repeat_interleave(m)
        pi, k = self.near_pairs_flat(points.reshape(b * m, 3), env, margin, method)
        return pi // max(m, 1), pi % max(m, 1), k

    def inside(self, points: Tensor, margin: float = 0.0, method: str = "auto") -> Tensor:
        """``(B, M)`` bool: the point lies strictly inside some sphere inflated by ``margin``."""
        b, m, _ = points.shape
        out = torch.zeros(b * m, dtype=torch.bool, device=points.device)
        env = torch.arange(b, device=points.device).repeat_interleave(m)
        pi, _ = self.near_pairs_flat(points.reshape(b * m, 3), env, margin, method)
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
) -> Obstacles:
    """Centres uniform in ``[0, l]^3``, radii uniform in ``radius_range`` (CPU tensors; move them with ``.to``)."""
    lo, hi = radius_range
    centers = torch.rand(num_envs, num_obstacles, 3, generator=generator, dtype=dtype) * area_size
    radii = lo + (hi - lo) * torch.rand(num_envs, num_obstacles, generator=generator, dtype=dtype)
    return Obstacles(centers, radii)
