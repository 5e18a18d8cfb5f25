"""Frames from geometry: build group elements that transform with the scene.

A frame ``g_v`` must satisfy ``frame(g . scene) = g . frame(scene)`` for the wrapped layers to be equivariant.
Degenerate inputs (a zero heading vector, norm ``<= eps``) have no well-defined frame; these helpers then fall
back to a fixed axis, which is finite and differentiable but not equivariant at that measure-zero configuration.
Non-finite inputs (NaN or inf) are never replaced: the frame they give is NaN, so the error shows downstream (or
at once with ``Canonicalize(..., check_frames=True)``) instead of silently turning into the identity. An argument
that is not a tensor, or whose last dimension is too small, raises an error naming the helper and the argument.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["cyclic_frames", "planar_frame", "rotation_from_vectors", "se2xr_frame", "se3_frame"]


def _check_vectors(fn: str, what: str, v, width: int, exact: bool = True) -> None:
    """Raise a ``TypeError`` / ``ValueError`` naming ``fn``'s argument ``what`` unless ``v`` is a tensor
    ``(*batch, width)`` (``(*batch, >= width)`` when not ``exact``). Shapes only: no device synchronization."""
    if not isinstance(v, Tensor):
        raise TypeError(f"{fn}() argument {what} must be a torch.Tensor, got {type(v).__name__}")
    n = v.shape[-1] if v.dim() else 0
    if n != width if exact else n < width:
        want = f"(*batch, {width})" if exact else f"(*batch, >= {width})"
        raise ValueError(f"{fn}() argument {what} has shape {tuple(v.shape)}, expected {want}")


def _safe_normalize(v: Tensor, fallback: Tensor, eps: float) -> Tensor:
    """``v / |v|``; ``fallback`` where ``|v| <= eps``; NaN where ``v`` is not finite (never the fallback)."""
    n = v.norm(dim=-1, keepdim=True)
    small = n <= eps  # False for a NaN or inf norm: those rows propagate NaN
    denom = torch.where(small, torch.ones_like(n), n)
    unit = v / torch.where(torch.isfinite(n), denom, torch.full_like(n, float("nan")))
    return torch.where(small, fallback.expand_as(v), unit)


def planar_frame(heading: Tensor, eps: float = 1e-12) -> Tensor:
    """SO(2) elements ``(*batch, 2) = (cos, sin)`` from planar heading vectors ``(*batch, 2)`` (first 2 used)."""
    _check_vectors("planar_frame", "heading", heading, 2, exact=False)
    fallback = heading.new_tensor([1.0, 0.0])
    return _safe_normalize(heading[..., :2], fallback, eps)


def se2xr_frame(heading: Tensor, position: Tensor, eps: float = 1e-12) -> Tensor:
    """SE2xR elements ``(*batch, 5)`` from a heading (its horizontal part sets the yaw) and a 3-D position.

    For a quadrotor with attitude ``R`` (body to world), ``heading = R[..., :, 0]`` (the body x axis) gives the
    yaw frame; it is equivariant because a rotation about z rotates the horizontal part of the body x axis.
    """
    _check_vectors("se2xr_frame", "heading", heading, 2, exact=False)
    _check_vectors("se2xr_frame", "position", position, 3)
    return torch.cat((planar_frame(heading, eps), position), dim=-1)


def rotation_from_vectors(a: Tensor, b: Tensor, eps: float = 1e-12) -> Tensor:
    """SO(3) matrices ``(*batch, 3, 3)`` by Gram-Schmidt: first axis along ``a``, second in the ``a, b`` plane.

    The third axis is the cross product, so ``det = +1`` always (never a reflection); the projection is done twice,
    so the result is orthonormal to rounding even when ``b`` is nearly parallel to ``a``. Where the part of ``b``
    orthogonal to ``a`` is at most ``eps`` times ``|b|`` (parallel, or ``b = 0``) the second axis falls back to a
    fixed unit vector orthogonal to ``a``: that configuration is a measure-zero set where the frame cannot be
    equivariant, and near it (``b`` within a small angle of ``a``) the frame turns fast with the inputs (its
    equivariance error in float32 grows like the rounding error over that angle).
    """
    _check_vectors("rotation_from_vectors", "a", a, 3)
    _check_vectors("rotation_from_vectors", "b", b, 3)
    e1 = _safe_normalize(a, a.new_tensor([1.0, 0.0, 0.0]), eps)
    b_perp = b - (b * e1).sum(-1, keepdim=True) * e1
    b_perp = b_perp - (b_perp * e1).sum(-1, keepdim=True) * e1  # again: one pass leaves rounding along e1
    # fallback second axis: any unit vector orthogonal to e1
    helper = torch.where(e1[..., :1].abs() < 0.9, a.new_tensor([1.0, 0.0, 0.0]), a.new_tensor([0.0, 1.0, 0.0]))
    alt = _safe_normalize(torch.linalg.cross(e1, helper), a.new_tensor([0.0, 1.0, 0.0]), eps)
    parallel = b_perp.norm(dim=-1, keepdim=True) <= eps * b.norm(dim=-1, keepdim=True).clamp_min(1.0)
    e2 = torch.where(parallel, alt, _safe_normalize(b_perp, alt, eps))
    e3 = torch.linalg.cross(e1, e2)
    return torch.stack((e1, e2, e3), dim=-1)


def se3_frame(a: Tensor, b: Tensor, position: Tensor, eps: float = 1e-12) -> Tensor:
    """SE3 elements ``(*batch, 3, 4)`` from two direction vectors and a position."""
    _check_vectors("se3_frame", "position", position, 3)
    return torch.cat((rotation_from_vectors(a, b, eps), position.unsqueeze(-1)), dim=-1)


def cyclic_frames(n: int, position: Tensor) -> Tensor:
    """The ``n`` frames of a point at ``position`` ``(*batch, d)``, ``d = 2`` (:class:`~groupcanon.groups.CyclicSE2`)
    or ``d = 3`` (:class:`~groupcanon.groups.CyclicSE2xR`): ``(*batch, n, 2 + d)``, the rotations (about z) by
    ``2 pi k / n`` (``k = 0 .. n-1``) translated to the point.

    For frame averaging: a layer canonicalized in each of these frames and averaged over them is equivariant, since
    ``g`` maps the set of frames of a point onto the set of frames of the moved point (``g . F(p) = F(g . p)`` as
    sets: the rotation index shifts cyclically). No vector is needed, so nothing degenerates at zero velocity.
    """
    if not isinstance(position, Tensor):
        raise TypeError(f"cyclic_frames() argument position must be a torch.Tensor, got {type(position).__name__}")
    if position.dim() == 0 or position.shape[-1] not in (2, 3):
        raise ValueError(
            f"cyclic_frames() argument position has shape {tuple(position.shape)}, expected (*batch, 2 or 3)"
        )
    if int(n) != n or n < 1:
        raise ValueError(f"cyclic_frames() needs a positive integer n, got {n!r}")
    theta = torch.arange(int(n), dtype=torch.float64, device=position.device) * (2 * math.pi / int(n))
    cs = torch.stack((torch.cos(theta), torch.sin(theta)), -1).to(position.dtype)  # (n, 2)
    batch, d = position.shape[:-1], position.shape[-1]
    return torch.cat((cs.expand(*batch, int(n), 2), position[..., None, :].expand(*batch, int(n), d)), -1)
