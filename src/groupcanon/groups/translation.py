"""R^d under addition: pure translations. Element shape ``(d,)``."""

from __future__ import annotations

import torch
from torch import Tensor

from ..group import Group, default_dtype
from ._util import gaussian

__all__ = ["Translation"]


class Translation(Group):
    """Translations of R^d. Layout ``(*batch, d)``; acts on ``Point(d)`` by ``p -> p + t``, trivially on vectors."""

    has_translation = True

    def __init__(self, d: int, translation_scale: float = 10.0):
        if int(d) != d or d < 1:
            raise ValueError(f"Translation(d) needs a positive integer d, got {d!r}")
        self.space_dim = int(d)
        self.translation_scale = float(translation_scale)

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (self.space_dim,)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return torch.zeros(*batch, self.space_dim, dtype=default_dtype(dtype), device=device)

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        return a + b

    def inverse(self, a: Tensor) -> Tensor:
        return -a

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        return gaussian(batch, self.space_dim, self.translation_scale, generator, dtype, device)

    def exp(self, xi: Tensor) -> Tensor:
        return xi

    def log(self, g: Tensor) -> Tensor:
        return g

    def matrix(self, g: Tensor) -> Tensor:
        d = self.space_dim
        m = torch.eye(d + 1, dtype=g.dtype, device=g.device).expand(*g.shape[:-1], d + 1, d + 1).clone()
        m[..., :d, d] = g
        return m

    def rotation(self, g: Tensor) -> Tensor:
        d = self.space_dim
        return torch.eye(d, dtype=g.dtype, device=g.device).expand(*g.shape[:-1], d, d)

    def translation(self, g: Tensor) -> Tensor:
        return g

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return v.expand(*torch.broadcast_shapes(g.shape, v.shape))

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return p + g

    def __repr__(self) -> str:
        return f"Translation({self.space_dim}, translation_scale={self.translation_scale:g})"
