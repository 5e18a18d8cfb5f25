"""The trivial group {e}: everything is invariant. Element shape ``(0,)``.

Wrapping a model with ``Trivial()`` gives the non-equivariant baseline with the same code: it acts (as the identity)
on every feature type of any dimension, and :class:`~groupcanon.Canonicalize` takes positions as ``Point(d)`` of the
width ``d`` of the ``pos`` given, so no ``pos_type`` is needed.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..group import Group, default_dtype

__all__ = ["Trivial"]


class Trivial(Group):
    """The group with one element. Acts as the identity on every feature type, of any dimension."""

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (0,)

    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return torch.zeros(*batch, 0, dtype=default_dtype(dtype), device=device)

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        batch = torch.broadcast_shapes(a.shape[:-1], b.shape[:-1])
        return a.new_zeros(*batch, 0)

    def inverse(self, a: Tensor) -> Tensor:
        return a

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        return self.identity(*batch, dtype=dtype, device=device)

    def exp(self, xi: Tensor) -> Tensor:
        return xi.new_zeros(*xi.shape[:-1], 0)

    def log(self, g: Tensor) -> Tensor:
        return g

    def matrix(self, g: Tensor) -> Tensor:
        return torch.ones(*g.shape[:-1], 1, 1, dtype=g.dtype, device=g.device)

    def acts_on_space(self, d: int) -> bool:
        return True

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        return v

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return p

    def planar_rotation(self, g: Tensor) -> Tensor:
        out = g.new_zeros(*g.shape[:-1], 2)
        out[..., 0] = 1
        return out
