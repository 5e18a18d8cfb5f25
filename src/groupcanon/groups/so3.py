"""SO(3) and SE(3): rotations and rigid motions of 3-D space.

Element layouts:
    SO3: ``(*batch, 3, 3)``, a rotation matrix (orthonormal, det +1).
    SE3: ``(*batch, 3, 4) = [R | t]``, acting on points by ``p -> R p + t``.
"""

from __future__ import annotations

import roma
import torch
from torch import Tensor

from ..group import Group, default_dtype
from ._util import SPECIAL_ANGLES, gaussian

__all__ = ["SE3", "SO3", "skew"]


def skew(w: Tensor) -> Tensor:
    """``[w]_x`` ``(*batch, 3, 3)`` with ``[w]_x v = w x v``."""
    z = torch.zeros_like(w[..., 0])
    x, y, zz = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack((torch.stack((z, -zz, y), -1), torch.stack((zz, z, -x), -1), torch.stack((-y, x, z), -1)), -2)


def _quat_to_rotmat(q: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` in (w, x, y, z) order to rotation matrices."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)), -1),
            torch.stack((2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)), -1),
            torch.stack((2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def _haar_rotations(batch, generator, dtype, device) -> Tensor:
    # uniform unit quaternions -> Haar-distributed rotations; roma.random_rotmat does the same but takes no
    # torch.Generator, which reproducible sampling (and the property tests) need
    q = torch.randn(*batch, 4, generator=generator, dtype=default_dtype(dtype), device=device)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    return _quat_to_rotmat(q)


def _special_rotations(dtype, device) -> Tensor:
    axes = torch.tensor([[1.0, 0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]], dtype=torch.float64, device=device)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.tensor(SPECIAL_ANGLES, dtype=torch.float64, device=device)
    rotvec = (angles[:, None, None] * axes[None]).reshape(-1, 3)
    return roma.rotvec_to_rotmat(rotvec).to(default_dtype(dtype))


def _left_jacobian_coeffs(theta: Tensor) -> tuple[Tensor, Tensor]:
    """``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` without cancellation: the first as ``2 sin^2(t/2) / t^2``,
    the second by its Taylor series below ``t = 0.5`` (five terms: error < 2e-13 relative to 1/6)."""
    tiny = theta < 1e-6
    t = torch.where(tiny, torch.ones_like(theta), theta)
    a = torch.where(tiny, 0.5 - theta**2 / 24, 2 * torch.sin(t / 2) ** 2 / t**2)
    near = theta < 0.5
    t = torch.where(near, torch.ones_like(theta), theta)
    t2 = theta * theta
    series = 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72 * (1 - t2 / 110)))
    b = torch.where(near, series, (t - torch.sin(t)) / t**3)
    return a, b


class SO3(Group):
    """Rotations of 3-D space. Layout ``(*batch, 3, 3)`` rotation matrices; Haar sampling via Gaussian quaternions."""

    space_dim = 3

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (3, 3)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return torch.eye(3, dtype=default_dtype(dtype), device=device).expand(*batch, 3, 3).clone()

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        return a @ b

    def inverse(self, a: Tensor) -> Tensor:
        return a.transpose(-1, -2)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        return _haar_rotations(batch, generator, dtype, device)

    def exp(self, xi: Tensor) -> Tensor:
        """``xi`` ``(*batch, 3)``: rotation vector (axis times angle)."""
        return roma.rotvec_to_rotmat(xi)

    def log(self, g: Tensor) -> Tensor:
        return roma.rotmat_to_rotvec(g)

    def matrix(self, g: Tensor) -> Tensor:
        return g

    def special_elements(self, dtype=None, device=None) -> Tensor:
        return _special_rotations(dtype, device)

    def rotation(self, g: Tensor) -> Tensor:
        return g

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return (g @ v.unsqueeze(-1)).squeeze(-1)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return self.rotate(g, p)


class SE3(Group):
    """Rigid motions of 3-D space. Layout ``(*batch, 3, 4) = [R | t]``."""

    space_dim = 3
    has_translation = True

    def __init__(self, translation_scale: float = 10.0):
        if not translation_scale >= 0:
            raise ValueError(f"translation_scale must be >= 0, got {translation_scale!r}")
        self.translation_scale = float(translation_scale)

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (3, 4)

    @staticmethod
    def from_parts(rotation: Tensor, translation: Tensor) -> Tensor:
        """Build ``[R | t]`` from ``R`` ``(*batch, 3, 3)`` and ``t`` ``(*batch, 3)``."""
        return torch.cat((rotation, translation.unsqueeze(-1)), dim=-1)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        g = torch.zeros(*batch, 3, 4, dtype=default_dtype(dtype), device=device)
        g[..., 0, 0] = g[..., 1, 1] = g[..., 2, 2] = 1
        return g

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        ra, ta = a[..., :3], a[..., 3:]
        return torch.cat((ra @ b[..., :3], ra @ b[..., 3:] + ta), dim=-1)

    def inverse(self, a: Tensor) -> Tensor:
        rt = a[..., :3].transpose(-1, -2)
        return torch.cat((rt, -(rt @ a[..., 3:])), dim=-1)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        r = _haar_rotations(batch, generator, dtype, device)
        t = gaussian(batch, 3, self.translation_scale, generator, dtype, device)
        return self.from_parts(r, t)

    def exp(self, xi: Tensor) -> Tensor:
        """``xi = (w, u)`` ``(*batch, 6)``: rotation vector then translational velocity."""
        w, u = xi[..., :3], xi[..., 3:]
        theta = w.norm(dim=-1)
        a, b = _left_jacobian_coeffs(theta)
        k = skew(w)
        eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
        v = eye + a[..., None, None] * k + b[..., None, None] * (k @ k)
        return self.from_parts(roma.rotvec_to_rotmat(w), (v @ u.unsqueeze(-1)).squeeze(-1))

    def log(self, g: Tensor) -> Tensor:
        w = roma.rotmat_to_rotvec(g[..., :3])
        theta = w.norm(dim=-1)
        a, b = _left_jacobian_coeffs(theta)
        k = skew(w)
        eye = torch.eye(3, dtype=g.dtype, device=g.device)
        v = eye + a[..., None, None] * k + b[..., None, None] * (k @ k)
        u = torch.linalg.solve(v, g[..., 3])
        return torch.cat((w, u), dim=-1)

    def matrix(self, g: Tensor) -> Tensor:
        bottom = torch.zeros(*g.shape[:-2], 1, 4, dtype=g.dtype, device=g.device)
        bottom[..., 0, 3] = 1
        return torch.cat((g, bottom), dim=-2)

    def special_elements(self, dtype=None, device=None) -> Tensor:
        r = _special_rotations(dtype, device)
        t = torch.zeros(r.shape[0], 3, dtype=r.dtype, device=device)
        t[:, 2] = torch.linspace(-1, 1, r.shape[0], dtype=r.dtype, device=device) * self.translation_scale
        return self.from_parts(r, t)

    def rotation(self, g: Tensor) -> Tensor:
        return g[..., :3]

    def translation(self, g: Tensor) -> Tensor:
        return g[..., 3]

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return (g[..., :3] @ v.unsqueeze(-1)).squeeze(-1)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return (g[..., :3] @ p.unsqueeze(-1)).squeeze(-1) + g[..., 3]

    def __repr__(self) -> str:
        return f"SE3(translation_scale={self.translation_scale:g})"
