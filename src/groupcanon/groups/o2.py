"""O(2): rotations and reflections of the plane, stored as ``2 x 2`` orthogonal matrices, element shape ``(2, 2)``.

Every element is ``g = R(theta) M^f`` with ``M = diag(1, -1)`` (the reflection across the x axis) and ``f`` in
``{0, 1}``: reflect first (if ``f = 1``), then rotate. This is escnn's ``O2`` convention for the element
``(f, theta)``. ``angle(g)`` and ``flip(g)`` recover ``theta`` (the angle of the first column) and ``f``
(``det g < 0``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..group import Group, default_dtype
from ._util import rotmat2d, special_angle_tensor, uniform_angle

__all__ = ["O2"]


def _reflect(m: Tensor, flip: Tensor) -> Tensor:
    """``m M^f``: negate the second column where ``flip`` is true."""
    sign = torch.where(flip, -torch.ones_like(m[..., 0, 0]), torch.ones_like(m[..., 0, 0]))
    return torch.stack((m[..., 0], m[..., 1] * sign[..., None]), dim=-1)


class O2(Group):
    """The orthogonal group of the plane. Layout ``(*batch, 2, 2)``: orthogonal matrices (det +1 or -1).

    ``element(theta, flip)`` builds ``R(theta) M^flip`` from angles and booleans. Acts on ``Vector(2)`` and
    ``Point(2)`` (about the origin) through the matrix itself. It has no SO(2) part in the sense of
    ``planar_rotation`` (reflections reverse the rotation sense), so ``SO2Irrep`` does not bind to it; O(2)
    irreps come from :mod:`groupcanon.compat.escnn` or a user type.
    """

    space_dim = 2
    orientation_preserving = False

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (2, 2)

    # ------------------------------------------------------------------ construction and parts
    def element(self, theta: Tensor, flip: Tensor | bool = False, dtype=None) -> Tensor:
        """Elements ``R(theta) M^flip`` of shape ``(*batch, 2, 2)`` (``theta`` and ``flip`` broadcast)."""
        theta = torch.as_tensor(theta)
        if not theta.is_floating_point():
            theta = theta.to(default_dtype(dtype))
        if dtype is not None:
            theta = theta.to(dtype)
        flip = torch.as_tensor(flip, device=theta.device).to(torch.bool)
        theta, flip = torch.broadcast_tensors(theta, flip)
        return _reflect(rotmat2d(torch.stack((torch.cos(theta), torch.sin(theta)), -1)), flip)

    def angle(self, g: Tensor) -> Tensor:
        """``theta`` in (-pi, pi] of ``g = R(theta) M^f``: the angle of the first column."""
        return torch.atan2(g[..., 1, 0], g[..., 0, 0])

    def flip(self, g: Tensor) -> Tensor:
        """``f`` of ``g = R(theta) M^f`` as a bool tensor: whether ``g`` is a reflection (``det g < 0``)."""
        return g[..., 0, 0] * g[..., 1, 1] - g[..., 0, 1] * g[..., 1, 0] < 0

    # ------------------------------------------------------------------ group
    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return torch.eye(2, dtype=default_dtype(dtype), device=device).expand(*batch, 2, 2).clone()

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        return a @ b

    def inverse(self, a: Tensor) -> Tensor:
        return a.transpose(-1, -2)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        theta = uniform_angle(batch, generator, dtype, device)
        flip = torch.rand(*batch, generator=generator, dtype=theta.dtype, device=device) < 0.5
        return self.element(theta, flip)

    def matrix(self, g: Tensor) -> Tensor:
        return g

    def special_elements(self, dtype=None, device=None) -> Tensor:
        theta = special_angle_tensor(torch.float64, device)
        flip = torch.tensor([False, True], device=device)
        return self.element(theta[None, :], flip[:, None]).reshape(-1, 2, 2).to(default_dtype(dtype))

    # ------------------------------------------------------------------ affine interface
    def rotation(self, g: Tensor) -> Tensor:
        return g

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return (g @ v.unsqueeze(-1)).squeeze(-1)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return self.rotate(g, p)
