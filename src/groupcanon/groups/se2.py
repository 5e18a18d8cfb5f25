"""SE(2) and SE(2) x R: planar rotations (about z) with 2-D or 3-D translations; CyclicSE2(n) and CyclicSE2xR(n),
their subgroups of rotations by multiples of 2 pi / n.

Element layouts:
    SE2, CyclicSE2:       ``(*batch, 4) = (cos theta, sin theta, tx, ty)``
    SE2xR, CyclicSE2xR:   ``(*batch, 5) = (cos theta, sin theta, tx, ty, tz)``

``g = (theta, t)`` acts on points by ``p -> R_z(theta) p + t`` and on vectors by ``v -> R_z(theta) v``.
SE2xR is the paper's symmetry group G-bar of a quadrotor under gravity: rotations about the world z axis and
all 3-D translations (a subgroup of SE(3), isomorphic to SE(2) x R).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..group import Group
from ._util import (
    angle_to_cs,
    complex_conj,
    complex_mul,
    gaussian,
    identity_cs,
    rotate2d,
    rotmat2d,
    special_cs,
    uniform_angle,
)

__all__ = ["SE2", "CyclicSE2", "CyclicSE2xR", "SE2xR"]


class _PlanarRigid(Group):
    """Rotation about z stored as ``(cos, sin)``, followed by a ``space_dim``-vector translation."""

    has_translation = True

    def __init__(self, translation_scale: float = 10.0):
        if not translation_scale >= 0:
            raise ValueError(f"translation_scale must be >= 0, got {translation_scale!r}")
        self.translation_scale = float(translation_scale)

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (2 + self.space_dim,)

    def _rot(self, cs: Tensor, v: Tensor) -> Tensor:
        if self.space_dim == 2:
            return rotate2d(cs, v)
        xy = rotate2d(cs, v[..., :2])
        return torch.cat((xy, v[..., 2:].expand(*xy.shape[:-1], v.shape[-1] - 2)), dim=-1)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        cs = identity_cs(batch, dtype, device)
        return torch.cat((cs, cs.new_zeros(*batch, self.space_dim)), dim=-1)

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        cs = complex_mul(a[..., :2], b[..., :2])
        t = self._rot(a[..., :2], b[..., 2:]) + a[..., 2:]
        return torch.cat((cs, t), dim=-1)

    def inverse(self, a: Tensor) -> Tensor:
        cs = complex_conj(a[..., :2])
        return torch.cat((cs, -self._rot(cs, a[..., 2:])), dim=-1)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        cs = angle_to_cs(uniform_angle(batch, generator, dtype, device))
        t = gaussian(batch, self.space_dim, self.translation_scale, generator, dtype, device)
        return torch.cat((cs, t), dim=-1)

    def exp(self, xi: Tensor) -> Tensor:
        """``xi = (theta, u)`` ``(*batch, 1 + space_dim)``; the translation is ``V(theta) u`` (left Jacobian)."""
        theta = xi[..., 0]
        u = xi[..., 1:]
        a, b = _jacobian_coeffs(theta)
        x, y = u[..., 0], u[..., 1]
        txy = torch.stack((a * x - b * y, b * x + a * y), dim=-1)
        t = txy if self.space_dim == 2 else torch.cat((txy, u[..., 2:]), dim=-1)
        return torch.cat((angle_to_cs(theta), t), dim=-1)

    def log(self, g: Tensor) -> Tensor:
        theta = torch.atan2(g[..., 1], g[..., 0])
        # Inverse of V(theta) = [[a, -b], [b, a]]: V^-1 = [[a, b], [-b, a]] / (a^2 + b^2).
        a, b = _jacobian_coeffs(theta)
        n = a * a + b * b
        x, y = g[..., 2], g[..., 3]
        uxy = torch.stack(((a * x + b * y) / n, (-b * x + a * y) / n), dim=-1)
        u = uxy if self.space_dim == 2 else torch.cat((uxy, g[..., 4:]), dim=-1)
        return torch.cat((theta.unsqueeze(-1), u), dim=-1)

    def matrix(self, g: Tensor) -> Tensor:
        """Homogeneous matrix ``(*batch, d+1, d+1)``."""
        d = self.space_dim
        m = torch.zeros(*g.shape[:-1], d + 1, d + 1, dtype=g.dtype, device=g.device)
        m[..., :d, :d] = self.rotation(g)
        m[..., :d, d] = g[..., 2:]
        m[..., d, d] = 1
        return m

    def special_elements(self, dtype=None, device=None) -> Tensor:
        cs = special_cs(dtype, device)
        t = torch.zeros(cs.shape[0], self.space_dim, dtype=cs.dtype, device=device)
        t[:, 0] = torch.linspace(-1, 1, cs.shape[0], dtype=cs.dtype, device=device) * self.translation_scale
        return torch.cat((cs, t), dim=-1)

    def rotation(self, g: Tensor) -> Tensor:
        r2 = rotmat2d(g[..., :2])
        if self.space_dim == 2:
            return r2
        r = torch.zeros(*g.shape[:-1], 3, 3, dtype=g.dtype, device=g.device)
        r[..., :2, :2] = r2
        r[..., 2, 2] = 1
        return r

    def translation(self, g: Tensor) -> Tensor:
        return g[..., 2:]

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return self._rot(g[..., :2], v)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return self._rot(g[..., :2], p) + g[..., 2:]

    def planar_rotation(self, g: Tensor) -> Tensor:
        return g[..., :2]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(translation_scale={self.translation_scale:g})"


def _jacobian_coeffs(theta: Tensor) -> tuple[Tensor, Tensor]:
    """``sin(t) / t`` and ``(1 - cos t) / t``, the latter as ``2 sin^2(t/2) / t`` (no cancellation in float32),
    with Taylor series at ``|t| < 1e-6``."""
    small = theta.abs() < 1e-6
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1 - theta**2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, theta / 2 - theta**3 / 24, 2 * torch.sin(safe / 2) ** 2 / safe)
    return a, b


class SE2(_PlanarRigid):
    """Rigid motions of the plane. Layout ``(*batch, 4) = (cos theta, sin theta, tx, ty)``."""

    space_dim = 2


class SE2xR(_PlanarRigid):
    """Rotations about z and 3-D translations. Layout ``(*batch, 5) = (cos theta, sin theta, tx, ty, tz)``.

    This is the symmetry of a quadrotor swarm under gravity (the paper's G-bar).
    """

    space_dim = 3


class _CyclicRotations:
    """Rotations restricted to multiples of ``2 pi / n`` (a mixin over :class:`_PlanarRigid`): sampling, membership,
    special elements; no exponential map (the group is not connected)."""

    n: int

    def _init_cyclic(self, n: int) -> None:
        if int(n) != n or n < 1:
            raise ValueError(f"{type(self).__name__}(n) needs a positive integer n, got {n!r}")
        self.n = int(n)

    def rotation_element(self, k: Tensor, dtype=None) -> Tensor:
        """The rotations by ``2 pi k / n`` (no translation), ``(*k.shape, *element_shape)``, for integer ``k``."""
        theta = (2 * math.pi / self.n) * k.to(torch.float64)
        cs = angle_to_cs(theta).to(dtype if dtype is not None else torch.get_default_dtype())
        return torch.cat((cs, cs.new_zeros(*cs.shape[:-1], self.space_dim)), -1)

    def membership_residual(self, g: Tensor) -> Tensor:
        """The rigid group's residual plus the distance of the rotation to the nearest multiple of ``2 pi / n``."""
        res = super().membership_residual(g)
        theta = torch.atan2(g[..., 1], g[..., 0])
        k = torch.round(theta * (self.n / (2 * math.pi)))
        nearest = angle_to_cs(k * (2 * math.pi / self.n))
        return res + (g[..., :2] - nearest).abs().amax(-1)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        k = torch.randint(0, self.n, batch, generator=generator, device=device)
        rot = self.rotation_element(k, dtype=dtype).to(device)
        t = gaussian(batch, self.space_dim, self.translation_scale, generator, rot.dtype, device)
        return torch.cat((rot[..., :2], t), dim=-1)

    def special_elements(self, dtype=None, device=None) -> Tensor:
        ks = torch.tensor(sorted({0, 1 % self.n, self.n // 2, self.n - 1}), device=device)
        rot = self.rotation_element(ks, dtype=dtype).to(device)
        rot[:, 2] = torch.linspace(-1, 1, len(ks), dtype=rot.dtype, device=device) * self.translation_scale
        return rot

    def exp(self, xi: Tensor) -> Tensor:
        raise NotImplementedError(f"{self!r} is not connected: it has no exponential map")

    def log(self, g: Tensor) -> Tensor:
        raise NotImplementedError(f"{self!r} is not connected: it has no logarithm")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.n}, translation_scale={self.translation_scale:g})"


class CyclicSE2(_CyclicRotations, SE2):
    """The subgroup of SE(2) of rotations by multiples of ``2 pi / n`` and all planar translations (``C_n`` x| R^2).
    Same layout and actions as :class:`SE2`, so every SE(2) feature applies.

    The symmetry of a planar robot whose actuator box or state limits are per axis (GCBF+'s point masses: ``n = 4``).
    No frame can be built continuously from a vector for it; :func:`groupcanon.frames.cyclic_frames` gives every
    node its ``n`` frames to average over instead.
    """

    def __init__(self, n: int, translation_scale: float = 10.0):
        self._init_cyclic(n)
        SE2.__init__(self, translation_scale)


class CyclicSE2xR(_CyclicRotations, SE2xR):
    """The subgroup of SE2xR of rotations about z by multiples of ``2 pi / n`` and all 3-D translations. Same
    layout and actions as :class:`SE2xR` (GCBF+'s linear drone, whose limits are per axis: ``n = 4``)."""

    def __init__(self, n: int, translation_scale: float = 10.0):
        self._init_cyclic(n)
        SE2xR.__init__(self, translation_scale)
