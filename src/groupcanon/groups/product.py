"""Direct products G1 x G2 x ... of groups. Element shape ``(sum_i numel(G_i),)``: the flattened factors, concatenated.

On Euclidean spaces a product acts block-diagonally: factor ``i`` moves coordinates
``[sum_{j<i} d_j, sum_{j<=i} d_j)`` where ``d_j`` is the factor's ``space_dim`` (factors without an affine action
contribute no coordinates). For example ``Product(SE2(), Translation(1))`` acts on ``Point(3)`` exactly like
``SE2xR()``. To make a feature transform under one factor only, use ``features.OnFactor(i, feature)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..group import Group
from .trivial import Trivial

__all__ = ["Product"]


def _has_planar_rotation(G: Group) -> bool:
    """Whether ``G`` has an SO(2) part of its own (the trivial group's identity rotation does not count)."""
    if isinstance(G, Trivial):
        return False
    try:
        G.planar_rotation(G.identity(1))
    except NotImplementedError:
        return False
    return True


class Product(Group):
    """The direct product of ``groups`` (at least two). ``factor(g, i)`` extracts the i-th component."""

    def __init__(self, *groups: Group):
        if len(groups) < 2:
            raise ValueError("Product needs at least two groups")
        for G in groups:
            if not isinstance(G, Group):
                raise TypeError(f"Product factors must be groupcanon Groups, got {type(G).__name__}")
        self.groups = tuple(groups)
        self._numels = tuple(G.element_numel for G in groups)
        self._offsets = tuple(int(sum(self._numels[:i])) for i in range(len(groups)))
        dims = [G.space_dim for G in groups]
        self._space_dims = tuple(0 if d is None else d for d in dims)
        self.space_dim = None if all(d is None for d in dims) else int(sum(self._space_dims))
        self.has_translation = any(G.has_translation for G in groups)
        self._planar_owners = tuple(i for i, G in enumerate(groups) if _has_planar_rotation(G))

    @property
    def element_shape(self) -> tuple[int, ...]:
        return (int(sum(self._numels)),)

    # ------------------------------------------------------------------ packing
    def factor(self, g: Tensor, i: int) -> Tensor:
        """The i-th factor of ``g``, shape ``(*batch, *G_i.element_shape)``."""
        o, n = self._offsets[i], self._numels[i]
        return g[..., o : o + n].reshape(*g.shape[:-1], *self.groups[i].element_shape)

    def pack(self, parts) -> Tensor:
        """Inverse of :meth:`factor`: concatenate factor elements (their batch dims broadcast)."""
        flat = [p.reshape(*G.batch_shape(p), G.element_numel) for p, G in zip(parts, self.groups)]  # not -1: empty
        batch = torch.broadcast_shapes(*(f.shape[:-1] for f in flat))
        return torch.cat([f.expand(*batch, f.shape[-1]) for f in flat], dim=-1)

    def _map(self, fn, *elements: Tensor) -> Tensor:
        return self.pack([fn(G, *(self.factor(e, i) for e in elements)) for i, G in enumerate(self.groups)])

    def membership_residual(self, g: Tensor) -> Tensor:
        """The largest residual of the factors (:meth:`Group.membership_residual`)."""
        self.check(g, "g")
        parts = [G.membership_residual(self.factor(g, i)) for i, G in enumerate(self.groups)]
        return torch.stack(parts).amax(0) if parts[0].numel() else parts[0]

    # ------------------------------------------------------------------ group
    def identity(self, *batch, dtype=None, device=None) -> Tensor:
        return self.pack([G.identity(*batch, dtype=dtype, device=device) for G in self.groups])

    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        return self._map(lambda G, x, y: G.compose(x, y), a, b)

    def inverse(self, a: Tensor) -> Tensor:
        return self._map(lambda G, x: G.inverse(x), a)

    def sample(self, *batch, generator=None, dtype=None, device=None) -> Tensor:
        return self.pack([G.sample(*batch, generator=generator, dtype=dtype, device=device) for G in self.groups])

    def matrix(self, g: Tensor) -> Tensor:
        """Block-diagonal matrix of the factors' matrices."""
        mats = [G.matrix(self.factor(g, i)) for i, G in enumerate(self.groups)]
        n = sum(m.shape[-1] for m in mats)
        batch = torch.broadcast_shapes(*(m.shape[:-2] for m in mats))
        out = torch.zeros(*batch, n, n, dtype=g.dtype, device=g.device)
        o = 0
        for m in mats:
            k = m.shape[-1]
            out[..., o : o + k, o : o + k] = m
            o += k
        return out

    def special_elements(self, dtype=None, device=None) -> Tensor:
        """Each factor's special elements, cycled to equal length and paired row by row (row ``k``: every factor's
        ``k``-th special element)."""
        specials = [G.special_elements(dtype=dtype, device=device) for G in self.groups]
        k = max(s.shape[0] for s in specials)
        parts = [s.repeat(math.ceil(k / s.shape[0]), *([1] * (s.dim() - 1)))[:k] for s in specials]
        return self.pack(parts)

    # ------------------------------------------------------------------ affine
    def acts_on_space(self, d: int) -> bool:
        return self.space_dim == d

    def _split_space(self, v: Tensor):
        out, o = [], 0
        for d in self._space_dims:
            out.append(v[..., o : o + d])
            o += d
        return out

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        pieces = [
            G.rotate(self.factor(g, i), vi) if d else vi
            for i, (G, d, vi) in enumerate(zip(self.groups, self._space_dims, self._split_space(v)))
        ]
        batch = torch.broadcast_shapes(*(p.shape[:-1] for p in pieces))
        return torch.cat([p.expand(*batch, p.shape[-1]) for p in pieces], dim=-1)

    def translation(self, g: Tensor) -> Tensor:
        parts = []
        for i, (G, d) in enumerate(zip(self.groups, self._space_dims)):
            if not d:
                continue
            gi = self.factor(g, i)
            parts.append(G.translation(gi) if G.has_translation else gi.new_zeros(*G.batch_shape(gi), d))
        return torch.cat(parts, dim=-1)

    def rotation(self, g: Tensor) -> Tensor:
        d = self.space_dim
        if d is None:
            return super().rotation(g)
        out = torch.zeros(*g.shape[:-1], d, d, dtype=g.dtype, device=g.device)
        o = 0
        for i, (G, di) in enumerate(zip(self.groups, self._space_dims)):
            if di:
                out[..., o : o + di, o : o + di] = G.rotation(self.factor(g, i))
                o += di
        return out

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        return self.rotate(g, p) + self.translation(g)

    def planar_rotation(self, g: Tensor) -> Tensor:
        owners = self._planar_owners
        if len(owners) != 1:
            raise NotImplementedError(
                f"{self} has {len(owners)} SO(2) factors: use features.OnFactor(i, SO2Irrep(k)) to choose one"
            )
        i = owners[0]
        return self.groups[i].planar_rotation(self.factor(g, i))

    def __repr__(self) -> str:
        return "Product(" + ", ".join(map(repr, self.groups)) + ")"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Product) and self.groups == other.groups

    def __hash__(self) -> int:
        return hash(("Product", self.groups))
