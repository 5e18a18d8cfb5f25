"""Static round obstacles, batched over environments: spheres in 3-D, discs in 2-D.

The dimension ``d`` (2 or 3) is read from the shape of the centres ``(B, K, d)``; every point argument must have
the same last dimension. All coordinates are in the world frame.

GCBF+'s CrazyFlie environment uses spheres with radius uniform in ``[0.05, 0.3]`` and centres uniform in the
arena ``[0, l]^3``; that is what :func:`sample_obstacles` draws (``dim=2``: discs with centres uniform in
``[0, l]^2``). (Boxes are not implemented: spheres and discs are the paper's setting and make ray casting
analytic.)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..neighbors import radius_search

__all__ = ["Obstacles", "sample_obstacles"]


@dataclass
class Obstacles:
    """``K`` round obstacles per environment: ``centers`` ``(B, K, d)`` (world frame) and ``radii`` ``(B, K)``
    (``K`` may be 0). ``d = 3``: spheres; ``d = 2``: discs. The dimension is :attr:`dim`."""

    centers: Tensor
    radii: Tensor

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
    def dim(self) -> int:
        """The space dimension ``d``: 3 (spheres) or 2 (discs)."""
        return self.centers.shape[-1]

    @property
    def num_envs(self) -> int:
        return self.centers.shape[0]

    @property
    def num_obstacles(self) -> int:
        return self.centers.shape[1]

    def to(self, *args, **kwargs) -> Obstacles:
        return Obstacles(self.centers.to(*args, **kwargs), self.radii.to(*args, **kwargs))

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
        """Signed distance ``||p - c_k|| - r_k`` of ``points`` ``(B, M, d)`` to every obstacle: ``(B, M, K)``.

        Dense over obstacles (``K`` is small), linear in the number of points. Broadcasts over environments: ``B``
        may be 1 on either side (the result then has the larger ``B``).
        """
        self._check_points(points, batched=True, broadcast=True)
        d = (points[:, :, None, :] - self.centers[:, None, :, :]).norm(dim=-1)
        return d - self.radii[:, None, :]

    def near_pairs_flat(
        self, points: Tensor, env: Tensor, margin: float, method: str = "auto"
    ) -> tuple[Tensor, Tensor]:
        """Pairs (point, obstacle) with ``||p - c_k|| - r_k < margin``, for flat ``points`` ``(P, d)`` whose
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
            sd = (points[:, None, :] - centers[env]).norm(dim=-1) - radii[env]  # (P, K)
            return (sd < margin).nonzero(as_tuple=True)
        b = self.num_envs
        flat_c = centers.reshape(b * k, self.dim)
        flat_r = radii.reshape(b * k)
        env_c = torch.arange(b, device=device).repeat_interleave(k)
        reach = float(margin) + float(radii.max())
        found, pi = radius_search(points, flat_c, reach * (1 + 1e-9) + 1e-12, env, env_c)
        sd = (points[pi] - flat_c[found]).norm(dim=-1) - flat_r[found]
        keep = sd < margin
        return pi[keep], found[keep] % k

    def near_pairs(self, points: Tensor, margin: float, method: str = "auto") -> tuple[Tensor, Tensor, Tensor]:
        """``(b, m, k)`` index triples with ``||points[b, m] - c[b, k]|| - r[b, k] < margin`` for ``points``
        ``(B, M, d)``, sorted by (b, m, k). Linear in ``M`` (see :meth:`near_pairs_flat`)."""
        self._check_points(points, batched=True)
        b, m, d = points.shape
        env = torch.arange(b, device=points.device).repeat_interleave(m)
        pi, k = self.near_pairs_flat(points.reshape(b * m, d), env, margin, method)
        return pi // max(m, 1), pi % max(m, 1), k

    def inside(self, points: Tensor, margin: float = 0.0, method: str = "auto") -> Tensor:
        """``(B, M)`` bool for ``points`` ``(B, M, d)``: the point lies strictly inside some obstacle (sphere or
        disc) inflated by ``margin``."""
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
