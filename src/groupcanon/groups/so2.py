"""SO(2): planar rotations, stored as unit complex numbers ``(cos theta, sin theta)``, element shape ``(2,)``."""

from __future__ import annotations

import torch
from torch import Tensor

from ..group import Group
from ._util import (
    angle_to_cs,
    complex_conj,
    complex_mul,
    identity_cs,
    rotate2d,
    rotmat2d,
    special_cs,
    uniform_angle,
)

__all__ = ["SO2"]


class SO2(Group):
    """Rotations of the plane. Element layout: ``(*batch, 2) = (cos theta, sin theta)``.

    The unit-complex layout composes without angle wrapping; ``log`` returns theta in (-pi, pi].
    Acts on ``Vector(2)``, ``Point(2)`` (rotation about the origin), ``Rotation()`` and ``SO2Irrep(k)``.
    """

    space_dim = 2

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (2,)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return identity_cs(batch, dtype, device)

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        return complex_mul(a, b)

    def inverse(self, a: Tensor) -> Tensor:
        return complex_conj(a)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        return angle_to_cs(uniform_angle(batch, generator, dtype, device))

    def exp(self, xi: Tensor) -> Tensor:
        """``xi`` ``(*batch, 1)``: the angle."""
        return angle_to_cs(xi[..., 0])

    def log(self, g: Tensor) -> Tensor:
        return torch.atan2(g[..., 1], g[..., 0]).unsqueeze(-1)

    def matrix(self, g: Tensor) -> Tensor:
        return rotmat2d(g)

    def special_elements(self, dtype=None, device=None) -> Tensor:
        return special_cs(dtype, device)

    def rotation(self, g: Tensor) -> Tensor:
        return rotmat2d(g)

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return rotate2d(g, v)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return rotate2d(g, p)

    def planar_rotation(self, g: Tensor) -> Tensor:
        return g
