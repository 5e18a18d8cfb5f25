"""Small SO(3) toolkit used by the quadrotor model and the geometric controller.

Every function is batched over leading dimensions, differentiable (finite gradients at the identity too),
dtype/device agnostic and free of data-dependent Python branches. Rotation matrices are ``(*batch, 3, 3)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from groupcanon.groups.so3 import skew

__all__ = [
    "dexpinv",
    "exp_apply",
    "hat",
    "orthonormality_error",
    "orthonormalize",
    "rmul_exp",
    "so3_exp",
    "vee",
    "yaw_rotation",
]


#: skew-symmetric matrix ``[w]x`` ``(*batch, 3, 3)`` of ``w`` ``(*batch, 3)``: ``hat(a) @ b == a x b`` (groupcanon's
#: :func:`~groupcanon.groups.so3.skew`, the one implementation)
hat = skew


def vee(m: Tensor) -> Tensor:
    """Inverse of :func:`hat` on skew-symmetric matrices: ``(m[2,1], m[0,2], m[1,0])``."""
    return torch.stack((m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]), dim=-1)


def _rodrigues_coefficients(phi: Tensor) -> tuple[Tensor, Tensor]:
    """``A = sin t / t`` and ``B = (1 - cos t) / t^2`` of ``t = |phi|``, shapes ``(*batch, 1)``.

    ``t`` is computed as ``sqrt(|phi|^2 + 1e-30)``: ``sin t / t`` and ``B = (sin(t/2) / (t/2))^2 / 2`` are then
    accurate to rounding for every ``t`` (no cancellation, no division by zero, exactly 1 and 1/2 at ``phi = 0``)
    and their gradients are finite at ``phi = 0`` (the chain rule multiplies them by ``phi / t = 0``).
    """
    t = torch.sqrt((phi * phi).sum(-1, keepdim=True) + 1e-30)
    a = torch.sin(t) / t
    half = 0.5 * t
    sh = torch.sin(half) / half
    return a, 0.5 * sh * sh


def so3_exp(phi: Tensor) -> Tensor:
    """Rodrigues' formula ``exp([phi]x) = I + A K + B K^2`` ``(*batch, 3, 3)``, ``K = [phi]x`` (see
    :func:`_rodrigues_coefficients` for ``A``, ``B``)."""
    a, b = _rodrigues_coefficients(phi)
    a, b = a[..., None], b[..., None]
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return eye + a * k + b * (k @ k)


def exp_apply(phi: Tensor, y: Tensor) -> Tensor:
    """``exp([phi]x) y`` ``(*batch, 3)`` without forming the matrix: ``y + A phi x y + B phi x (phi x y)``."""
    if phi.shape != y.shape:
        phi, y = torch.broadcast_tensors(phi, y)
    a, b = _rodrigues_coefficients(phi)
    c = torch.linalg.cross(phi, y, dim=-1)
    return y + a * c + b * torch.linalg.cross(phi, c, dim=-1)


def rmul_exp(r: Tensor, phi: Tensor) -> Tensor:
    """``R exp([phi]x)`` ``(*batch, 3, 3)`` without a matrix product.

    Row ``i`` of ``R [phi]x`` is ``r_i x phi`` (``r_i`` the rows of ``R``), so
    ``R exp([phi]x) = R + A (R x phi) + B ((R x phi) x phi)`` row-wise.
    """
    a, b = _rodrigues_coefficients(phi)
    ph = phi[..., None, :].expand(*torch.broadcast_shapes(r.shape[:-2], phi.shape[:-1]), 3, 3)
    c1 = torch.linalg.cross(r.expand_as(ph), ph, dim=-1)
    c2 = torch.linalg.cross(c1, ph, dim=-1)
    return r + a[..., None] * c1 + b[..., None] * c2


def dexpinv(phi: Tensor, w: Tensor) -> Tensor:
    """``d/dt phi`` for ``R(t) = R0 exp([phi(t)]x)`` driven by a body rate ``w`` (``R' = R [w]x``), truncated.

    ``phi' = w + (1/2) phi x w + (1/12) phi x (phi x w) + O(|phi|^4 |w|)``: the terms Runge–Kutta–Munthe-Kaas needs
    for order 4 (Iserles et al., "Lie-group methods", Acta Numerica 2000, section 4.4).
    """
    c = torch.linalg.cross(phi, w, dim=-1)
    return w + 0.5 * c + torch.linalg.cross(phi, c, dim=-1) / 12


def orthonormalize(r: Tensor) -> Tensor:
    """One Newton step toward the nearest rotation (polar factor): ``R (3 I - R^T R) / 2``.

    Quadratically convergent for ``R`` near SO(3) (an error ``e`` in ``R^T R - I`` becomes ``O(e^2)``) and equivariant
    under left multiplication by any rotation, so it never breaks the symmetry.
    """
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    return r @ (1.5 * eye - 0.5 * (r.transpose(-1, -2) @ r))


def orthonormality_error(r: Tensor) -> Tensor:
    """``max |R^T R - I|`` per matrix ``(*batch,)``, plus ``|det R - 1|`` (catches reflections)."""
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    e = (r.transpose(-1, -2) @ r - eye).abs().amax(dim=(-1, -2))
    return torch.maximum(e, (torch.linalg.det(r) - 1).abs())


def yaw_rotation(yaw: Tensor) -> Tensor:
    """Rotation about the world z axis ``(*batch, 3, 3)`` by angle ``yaw`` ``(*batch,)``."""
    c, s = torch.cos(yaw), torch.sin(yaw)
    o, i = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack(
        (torch.stack((c, -s, o), -1), torch.stack((s, c, o), -1), torch.stack((o, o, i), -1)),
        dim=-2,
    )
