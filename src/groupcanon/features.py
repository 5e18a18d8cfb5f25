"""Feature types (how a group element acts on a feature vector) and their direct sum, :class:`FieldType`.

A :class:`FeatureType` has an integer ``dim`` and ``act(g, x)`` for ``x`` of shape ``(*batch, dim)`` and ``g`` of
shape ``(*batch, *G.element_shape)`` (batch dimensions broadcast). A user-defined type subclasses it and defines
those two; it is then specific to the group it was written for.

Built-in types are generic: they are declared without a group (``Vector(3)``) and bound to one when placed in a
``FieldType(G, [...])`` (or with ``Vector(3, group=G)``). Binding checks that the group can act on the type and
raises a ``ValueError`` naming both if it cannot.

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
from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor

from .group import Group, check_element_shape, require_group

__all__ = [
    "FeatureType",
    "FieldType",
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


def _fuse(features: Sequence[FeatureType], slices: Sequence[slice]) -> list[tuple[FeatureType, slice]]:
    """The action plan of a direct sum: its non-invariant fields, with adjacent built-in ``Vector`` (or ``Point``)
    fields of the same dimension and group merged into one multi-copy field (one kernel instead of several)."""
    plan: list[tuple[FeatureType, slice]] = []
    for f, s in zip(features, slices):
        if f.invariant:
            continue
        if plan:
            prev, ps = plan[-1]
            if (
                type(prev) is type(f)
                and type(f) in (Vector, Point)
                and prev.d == f.d
                and prev.group == f.group
                and ps.stop == s.start
            ):
                plan[-1] = (type(f)(f.d, n=prev.n + f.n, group=f.group), slice(ps.start, s.stop))
                continue
        plan.append((f, s))
    return plan


def _rotates_first_two_axes(group: Group) -> bool:
    """Whether the group's linear part is the rotation of the first two coordinates by its planar rotation
    (``R(g) = [[c, -s, 0], [s, c, 0], [0, 0, I]]``): SO2, SE2, SE2xR and products with one planar factor."""
    d = group.space_dim
    if d is None or d < 2:
        return False
    try:
        g = group.sample(5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        cs, rot = group.planar_rotation(g), group.rotation(g)
    except (NotImplementedError, TypeError, ValueError):
        return False
    expected = torch.eye(d, dtype=torch.float64).repeat(5, 1, 1)
    expected[:, :2, :2] = torch.stack((torch.stack((cs[:, 0], -cs[:, 1]), -1), cs.flip(-1)), -2)
    return rot.shape == expected.shape and torch.allclose(rot, expected, rtol=0.0, atol=1e-12)


def _planar_basis(group: Group, features: Sequence[FeatureType], slices: Sequence[slice]) -> Tensor | None:
    """``(dim, 3 dim)`` matrices ``[A0 | A1 | A2]`` with ``rho(g) x = x A0 + c (x A1) + s (x A2)`` for a group that
    rotates the first two axes (``(c, s)`` its planar rotation), if every non-invariant field is a built-in
    ``Vector`` or ``Rotation`` (linear in ``R(g)``, so in ``(c, s)``); else ``None``.

    A vector's ``(x, y)`` channels map to ``(c x - s y, s x + c y)``, every other channel to itself. The product
    ``x [A0 | A1 | A2]`` only copies or negates channels (one non-zero per column), so the result is the same
    floating-point number as rotating the channels one by one. It does not depend on ``g``: canonicalization
    computes it once per node and gathers it to the edges (:meth:`FieldType.act_gathered`), one small matrix
    product and two fused multiply-adds whatever the number of fields."""
    if not _rotates_first_two_axes(group):
        return None
    pairs: list[tuple[int, int]] = []
    for f, s in zip(features, slices):
        if f.invariant:
            continue
        if type(f) is Vector:
            pairs += [(s.start + i * f.d, s.start + i * f.d + 1) for i in range(f.n)]
        elif type(f) is Rotation:  # X -> R X: rows 0 and 1 of X (row-major) rotate as the x and y of each column
            pairs += [(s.start + c, s.start + f.d + c) for c in range(f.d)]
        else:
            return None
    if not pairs:
        return None
    dim = sum(f.dim for f in features)
    a0, a1, a2 = torch.eye(dim), torch.zeros(dim, dim), torch.zeros(dim, dim)
    for ix, iy in pairs:  # column j of A holds output channel j
        a0[ix, ix] = a0[iy, iy] = 0.0
        a1[ix, ix] = a1[iy, iy] = 1.0
        a2[iy, ix], a2[ix, iy] = -1.0, 1.0
    return torch.cat((a0, a1, a2), dim=1)


class FieldType:
    """The direct sum of feature types under one group: a feature vector is their concatenation.

    Args:
        group: the group acting on the fields.
        features: a sequence of feature types, or a mapping ``name -> feature type`` (named fields can be
            read with :meth:`get` / :meth:`split` and located with :meth:`slice`).

    ``act(g, x)`` maps ``x`` ``(*batch, dim)`` with ``g`` ``(*batch, *G.element_shape)`` field by field.
    """

    def __init__(self, group: Group, features: Sequence[FeatureType] | Mapping[str, FeatureType]):
        require_group(group, "FieldType(group, features): group")
        if isinstance(features, Mapping):
            names = [str(k) for k in features.keys()]
            feats = list(features.values())
        elif isinstance(features, Iterable) and not isinstance(features, (str, FeatureType)):
            feats = list(features)
            names = [None] * len(feats)
        else:
            raise TypeError(
                "FieldType(group, features): features must be a list (or a dict name -> type) of FeatureTypes, "
                f"got {type(features).__name__}"
            )
        for i, f in enumerate(feats):
            if not isinstance(f, FeatureType):
                raise TypeError(
                    f"FieldType(group, features): features[{i if names[i] is None else repr(names[i])}] must be a "
                    f"FeatureType, got {type(f).__name__}"
                )
        self.group = group
        self.features = tuple(f.bind(group) for f in feats)
        self.names = tuple(names)
        offsets, o = [], 0
        for f in self.features:
            offsets.append(o)
            o += f.dim
        self.dim = o
        self._slices = tuple(slice(a, a + f.dim) for a, f in zip(offsets, self.features))
        self.invariant = all(f.invariant for f in self.features)
        self._plan = _fuse(self.features, self._slices)
        self._planar = _planar_basis(group, self.features, self._slices)
        self._planar_on: dict[tuple[torch.device, torch.dtype], Tensor] = {}

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.features)

    def __iter__(self):
        return iter(self.features)

    def _index(self, key: int | str) -> int:
        if isinstance(key, str):
            if key not in self.names:
                raise KeyError(f"no field named {key!r}; fields: {[n for n in self.names if n]}")
            return self.names.index(key)
        return int(key)

    def slice(self, key: int | str) -> slice:
        """The channel slice of field ``key`` (index or name)."""
        return self._slices[self._index(key)]

    def get(self, x: Tensor, key: int | str) -> Tensor:
        """The channels of field ``key`` in ``x`` ``(*batch, dim)``."""
        return x[..., self.slice(key)]

    def split(self, x: Tensor) -> dict[str | int, Tensor]:
        """All fields of ``x``, keyed by name (or index for unnamed fields)."""
        return {(n if n is not None else i): x[..., s] for i, (n, s) in enumerate(zip(self.names, self._slices))}

    def __add__(self, other: FieldType) -> FieldType:
        if not isinstance(other, FieldType):
            return NotImplemented
        if other.group != self.group:
            raise ValueError(f"cannot add FieldTypes of different groups: {self.group} and {other.group}")
        if any(self.names) or any(other.names):
            names = [n if n is not None else f"field{i}" for i, n in enumerate(self.names + other.names)]
            if len(set(names)) != len(names):
                raise ValueError(f"duplicate field names in sum: {names}")
            return FieldType(self.group, dict(zip(names, self.features + other.features)))
        return FieldType(self.group, list(self.features + other.features))

    # ------------------------------------------------------------------ action
    def check(self, x: Tensor, what: str = "features") -> None:
        """Raise a clear ``ValueError`` if ``x`` is not ``(*batch, dim)``."""
        if not isinstance(x, Tensor):
            raise TypeError(f"{what} must be a torch.Tensor, got {type(x).__name__}")
        if x.dim() == 0 or x.shape[-1] != self.dim:
            raise ValueError(f"{what} have shape {tuple(x.shape)}, expected (*batch, {self.dim}) for {self!r}")

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        """``rho(g) x``: ``x`` ``(*batch, dim)``, ``g`` ``(*batch, *G.element_shape)``; batch dims broadcast."""
        check_element_shape(self.group, g, "act() argument g")
        self.check(x, "act() argument x")
        gb, xb = self.group.batch_shape(g), x.shape[:-1]
        try:
            batch = torch.broadcast_shapes(gb, xb)
        except RuntimeError:
            raise ValueError(
                f"group elements with batch shape {tuple(gb)} do not broadcast against features "
                f"with batch shape {tuple(xb)}"
            ) from None
        if self.invariant:
            return x.expand(*batch, self.dim)
        if self._planar is not None:
            return self._planar_combine(g, self._planar_lift(x))
        if len(self._plan) == 1 and self._plan[0][1] == slice(0, self.dim):
            return self._plan[0][0].act(g, x)
        # invariant channels are copied once; only the transformed fields are computed and written over them
        out = x.expand(*batch, self.dim).clone()
        for f, s in self._plan:
            out[..., s] = f.act(g, x[..., s])
        return out

    def act_gathered(self, g: Tensor, x: Tensor, index: Tensor) -> Tensor:
        """``act(g, x[index])`` for ``x`` ``(N, dim)``, ``index`` ``(E,)`` and ``g`` ``(E, *element_shape)``.

        The same numbers as ``act(g, x[index])``, with less memory traffic: all channels are gathered once and only
        the transformed fields are gathered again and acted on (canonicalization gathers every node's features
        once per edge, and most channels are usually invariant).
        """
        check_element_shape(self.group, g, "act_gathered() argument g")
        self.check(x, "act_gathered() argument x")
        if self._planar is not None and not self.invariant:
            return self._planar_combine(g, self._planar_lift(x).index_select(0, index))
        out = x.index_select(0, index)
        if self.invariant:
            return out
        if len(self._plan) == 1 and self._plan[0][1] == slice(0, self.dim):
            return self._plan[0][0].act(g, out)
        for f, s in self._plan:
            out[:, s] = f.act(g, x[:, s].index_select(0, index))
        return out

    def _planar_lift(self, x: Tensor) -> Tensor:
        """``x [A0 | A1 | A2]`` ``(*batch, 3 dim)`` (see :func:`_planar_basis`)."""
        key = (x.device, x.dtype)
        basis = self._planar_on.get(key)
        if basis is None:
            basis = self._planar_on[key] = self._planar.to(device=x.device, dtype=x.dtype)
        return x @ basis

    def _planar_combine(self, g: Tensor, lifted: Tensor) -> Tensor:
        """``y0 + c y1 + s y2`` from lifted features ``(*batch, 3 dim)`` and elements ``g``."""
        cs = self.group.planar_rotation(g)
        d = self.dim
        out = torch.addcmul(lifted[..., :d], cs[..., :1], lifted[..., d : 2 * d])
        return out.addcmul_(cs[..., 1:], lifted[..., 2 * d :])

    def __repr__(self) -> str:
        items = [f"{n}={f!r}" if n else repr(f) for n, f in zip(self.names, self.features)]
        return f"FieldType({self.group}, [{', '.join(items)}])"

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, FieldType)
            and self.group == other.group
            and self.features == other.features
            and self.names == other.names
        )

    def __hash__(self) -> int:
        return hash(repr(self))
