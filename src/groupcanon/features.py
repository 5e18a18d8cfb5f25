"""Feature types: how a group element acts on a feature vector (their direct sum is
:class:`groupcanon.field_type.FieldType`).

A :class:`FeatureType` has an integer ``dim`` and ``act(g, x)`` for ``x`` of shape ``(*batch, dim)`` and ``g`` of
shape ``(*batch, *G.element_shape)`` (batch dimensions broadcast). A user-defined type subclasses it and defines
those two; it is then specific to the group it was written for.

Built-in types are generic: they are declared without a group (``Vector(3)``) and bound to one when placed in a
``FieldType(G, [...])`` (:mod:`groupcanon.field_type`) or with ``Vector(3, group=G)``. Binding checks that the
group can act on the type and raises a ``ValueError`` naming both if it cannot.

======================  =====================================================  ==========================
type                    action                                                 needs
======================  =====================================================  ==========================
``Scalar(n)``           invariant                                              any group
``Vector(d, n=1)``      ``n`` vectors rotated: ``v -> R(g) v``                 ``group.space_dim == d``
``Point(d, n=1)``       ``n`` points moved: ``p -> R(g) p + t(g)``             ``group.space_dim == d``
``Rotation()``          flattened (row-major) ``d x d`` matrix: ``X -> R X``   ``group.space_dim``
``SO2Irrep(k)``         rotation by ``k theta`` (``dim`` 2; 1 for ``k = 0``)    an SO(2) part
``OnFactor(i, ft)``     ``ft`` acted on by factor ``i`` of a ``Product``        ``groups.Product``
======================  =====================================================  ==========================

The trivial group acts as the identity on every type, so the same declarations give a non-equivariant model.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from .group import Group, require_group

__all__ = [
    "FeatureType",
    "OnFactor",
    "Point",
    "Rotation",
    "SO2Irrep",
    "Scalar",
    "Vector",
]


def _unsqueeze_batch(group: Group, g: Tensor, times: int = 1) -> Tensor:
    """Insert ``times`` singleton batch dimensions just before the element dimensions of ``g``."""
    pos = g.dim() - len(group.element_shape)
    for _ in range(times):
        g = g.unsqueeze(pos)
    return g


class FeatureType:
    """Base class of feature types: subclasses set ``dim`` and implement ``act(g, x)``.

    ``act`` must be a group action: ``act(e, x) == x`` and ``act(a, act(b, x)) == act(compose(a, b), x)``
    (check with :func:`groupcanon.testing.check_action_laws`). It must broadcast batch dimensions of ``g`` and
    ``x`` and must not change the dtype or device.
    """

    dim: int
    #: True if ``act`` is the identity for every group element (lets FieldType skip work).
    invariant: bool = False

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        raise NotImplementedError(f"{type(self).__name__} must implement act(g, x)")

    def bind(self, group: Group) -> FeatureType:
        """Return this type bound to ``group``. User types are written for one group and are returned as is."""
        return self

    def __repr__(self) -> str:
        return f"{type(self).__name__}(dim={self.dim})"


class _BuiltinType(FeatureType):
    """A generic type: unbound until ``bind(group)`` (which validates) or ``group=`` at construction."""

    group: Group | None = None

    def _check(self, group: Group) -> None:  # raise ValueError if ``group`` cannot act on this type
        pass

    def bind(self, group: Group) -> FeatureType:
        require_group(group, f"{self!r}.bind(group): group")
        if self.group is not None:
            if self.group != group:
                raise ValueError(f"{self!r} is already bound to {self.group}, cannot bind it to {group}")
            return self
        self._check(group)
        bound = copy.copy(self)
        bound.group = group
        return bound

    def _bound_group(self) -> Group:
        if self.group is None:
            raise RuntimeError(
                f"{self!r} is not bound to a group: put it in a FieldType(G, [...]) or construct it with group=G"
            )
        return self.group

    def _init_group(self, group: Group | None) -> None:
        if group is not None:
            self._check(require_group(group, f"{type(self).__name__}(group=...)"))
            self.group = group

    def _require_space(self, group: Group, d: int) -> None:
        if not group.acts_on_space(d):
            where = (
                f"acts on {group.space_dim}-D space"
                if group.space_dim is not None
                else "has no action on a Euclidean space"
            )
            raise ValueError(f"{group} {where}: it cannot act on {self!r}")

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.__dict__ == other.__dict__

    def __hash__(self) -> int:
        return hash(repr(self))


class Scalar(_BuiltinType):
    """``n`` invariant channels."""

    invariant = True

    def __init__(self, n: int = 1, group: Group | None = None):
        if int(n) != n or n < 1:
            raise ValueError(f"Scalar(n) needs a positive integer n, got {n!r}")
        self.dim = int(n)
        self._init_group(group)

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        if self.group is None:
            return x
        batch = torch.broadcast_shapes(self.group.batch_shape(g), x.shape[:-1])
        return x.expand(*batch, self.dim)

    def __repr__(self) -> str:
        return f"Scalar({self.dim})"


class Vector(_BuiltinType):
    """``n`` vectors of ``R^d`` (``dim = n d``), rotated but not translated: ``v -> R(g) v``."""

    def __init__(self, d: int, n: int = 1, group: Group | None = None):
        if int(d) != d or d < 1 or int(n) != n or n < 1:
            raise ValueError(f"{type(self).__name__}(d, n) needs positive integers, got d={d!r}, n={n!r}")
        self.d, self.n = int(d), int(n)
        self.dim = self.d * self.n
        self._init_group(group)

    def _check(self, group: Group) -> None:
        self._require_space(group, self.d)

    def _apply(self, group: Group, g: Tensor, v: Tensor) -> Tensor:
        return group.rotate(g, v)

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        group = self._bound_group()
        if self.n == 1:
            return self._apply(group, g, x)
        v = x.reshape(*x.shape[:-1], self.n, self.d)
        out = self._apply(group, _unsqueeze_batch(group, g), v)
        return out.reshape(*out.shape[:-2], self.dim)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.d}" + (f", n={self.n})" if self.n != 1 else ")")


class Point(Vector):
    """``n`` points of ``R^d`` (``dim = n d``), rotated and translated: ``p -> R(g) p + t(g)``."""

    def _apply(self, group: Group, g: Tensor, v: Tensor) -> Tensor:
        return group.transform(g, v)


class Rotation(_BuiltinType):
    """A rotation matrix ``X`` ``d x d`` flattened row-major (``dim = d^2``), left-multiplied: ``X -> R(g) X``.

    ``d`` defaults to the group's ``space_dim`` when bound. Typical use: an agent's attitude ``R_i``
    (body-to-world), which a world-frame rotation ``R_g`` maps to ``R_g R_i``.
    """

    def __init__(self, d: int | None = None, group: Group | None = None):
        if d is not None and (int(d) != d or d < 1):
            raise ValueError(f"Rotation(d) needs a positive integer d, got {d!r}")
        self.d = None if d is None else int(d)
        self._init_group(group)

    @property
    def dim(self) -> int:
        if self.d is None:
            raise RuntimeError("Rotation() has no dimension until it is bound to a group (or given d)")
        return self.d * self.d

    def _check(self, group: Group) -> None:
        if self.d is None and group.space_dim is None:
            raise ValueError(
                f"{group} has no action on a Euclidean space of its own: it cannot act on Rotation(), whose "
                "dimension comes from the group's space_dim; give the dimension, Rotation(d)"
            )
        if self.d is not None:
            self._require_space(group, self.d)

    def bind(self, group: Group) -> FeatureType:
        bound = super().bind(group)
        if bound.d is None:
            bound.d = group.space_dim
        return bound

    def _init_group(self, group: Group | None) -> None:
        super()._init_group(group)
        if group is not None and self.d is None:
            self.d = group.space_dim

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        group = self._bound_group()
        d = self.d
        cols = x.reshape(*x.shape[:-1], d, d).transpose(-1, -2)  # rows of X^T are the columns of X
        out = group.rotate(_unsqueeze_batch(group, g), cols).transpose(-1, -2)
        return out.reshape(*out.shape[:-2], d * d)

    def __repr__(self) -> str:
        return "Rotation()" if self.d is None else f"Rotation({self.d})"


class SO2Irrep(_BuiltinType):
    """The real irreducible representation of SO(2) of frequency ``k``: rotation by ``k theta``.

    ``dim = 2`` for ``k != 0`` (a planar vector rotated ``k`` times as fast), ``dim = 1`` for ``k = 0`` (invariant).
    Any group with an SO(2) part (SO2, Cyclic, SE2, SE2xR) acts through that part.
    """

    def __init__(self, k: int, group: Group | None = None):
        if int(k) != k:
            raise ValueError(f"SO2Irrep(k) needs an integer frequency, got {k!r}")
        self.k = int(k)
        self.dim = 1 if self.k == 0 else 2
        self.invariant = self.k == 0
        self._init_group(group)

    def _check(self, group: Group) -> None:
        try:
            group.planar_rotation(group.identity(1))
        except NotImplementedError as err:
            raise ValueError(f"{group} has no SO(2) part: it cannot act on {self!r} ({err})") from None

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        group = self._bound_group()
        if self.k == 0:
            return x.expand(*torch.broadcast_shapes(group.batch_shape(g), x.shape[:-1]), 1)
        cs = group.planar_rotation(g)
        theta = torch.atan2(cs[..., 1], cs[..., 0]) * self.k
        c, s = torch.cos(theta), torch.sin(theta)
        return torch.stack((c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1]), dim=-1)

    def __repr__(self) -> str:
        return f"SO2Irrep({self.k})"


class OnFactor(_BuiltinType):
    """Feature ``feature`` transformed by factor ``index`` of a :class:`~groupcanon.groups.Product` only."""

    def __init__(self, index: int, feature: FeatureType, group: Group | None = None):
        if not isinstance(feature, FeatureType):
            raise TypeError(f"OnFactor needs a FeatureType, got {type(feature).__name__}")
        self.index = int(index)
        self.feature = feature
        if group is not None:
            self._check(require_group(group, "OnFactor(group=...)"))
            self.group = group
            self.feature = feature.bind(group.groups[self.index])

    @property
    def dim(self) -> int:  # read from the wrapped type: Rotation() only has a dimension once bound
        return self.feature.dim

    def _check(self, group: Group) -> None:
        factors = getattr(group, "groups", None)
        if factors is None:
            raise ValueError(f"OnFactor needs a groups.Product, got {group}")
        if not 0 <= self.index < len(factors):
            raise ValueError(f"{group} has {len(factors)} factors, OnFactor index {self.index} is out of range")
        self.feature.bind(factors[self.index])

    def bind(self, group: Group) -> FeatureType:
        self._check(group)
        bound = copy.copy(self)
        bound.group = group
        bound.feature = self.feature.bind(group.groups[self.index])
        return bound

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        group = self._bound_group()
        return self.feature.act(group.factor(g, self.index), x)

    def __repr__(self) -> str:
        return f"OnFactor({self.index}, {self.feature!r})"
