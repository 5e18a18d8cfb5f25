"""C_n: the cyclic subgroup of SO(2) of rotations by multiples of 2 pi / n, element shape ``(2,)``."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..group import default_dtype
from ._util import angle_to_cs
from .so2 import SO2

__all__ = ["Cyclic"]


class Cyclic(SO2):
    """Rotations by ``2 pi k / n``. Same layout as :class:`SO2` (``(cos, sin)``), so every SO(2) feature applies.

    ``index(g)`` recovers ``k`` in ``{0, ..., n-1}``; ``element(k)`` builds elements from integers.
    """

    def __init__(self, n: int):
        if int(n) != n or n < 1:
            raise ValueError(f"Cyclic(n) needs a positive integer n, got {n!r}")
        self.n = int(n)

    def element(self, k: Tensor, dtype=None) -> Tensor:
        """Elements ``(*k.shape, 2)`` for integer exponents ``k``."""
        theta = (2 * math.pi / self.n) * k.to(torch.float64)
        return angle_to_cs(theta).to(default_dtype(dtype))

    def index(self, g: Tensor) -> Tensor:
        """The integer ``k`` in ``{0, ..., n-1}`` of each element (rounded), dtype long."""
        theta = torch.atan2(g[..., 1], g[..., 0])
        return torch.round(theta * (self.n / (2 * math.pi))).long().remainder(self.n)

    def membership_residual(self, g: Tensor) -> Tensor:
        """SO(2)'s residual (unit length) plus the distance of ``g`` to the nearest rotation by a multiple of
        ``2 pi / n`` (largest entry of the difference), ``(*batch,)``; NaN for non-finite elements."""
        res = super().membership_residual(g)
        nearest = self.element(self.index(g), dtype=g.dtype).to(g.device)
        return res + (g - nearest).abs().amax(-1)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        k = torch.randint(0, self.n, batch, generator=generator, device=device)
        return self.element(k, dtype=dtype)

    def special_elements(self, dtype=None, device=None) -> Tensor:
        ks = sorted({0, 1 % self.n, self.n // 2, self.n - 1})
        return self.element(torch.tensor(ks, device=device), dtype=dtype)

    def exp(self, xi: Tensor) -> Tensor:
        raise NotImplementedError("Cyclic(n) is a finite group: it has no exponential map")

    def log(self, g: Tensor) -> Tensor:
        raise NotImplementedError("Cyclic(n) is a finite group: it has no logarithm")

    def __repr__(self) -> str:
        return f"Cyclic({self.n})"
