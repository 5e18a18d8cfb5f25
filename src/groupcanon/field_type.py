"""The direct sum of feature types under one group, :class:`FieldType`: a feature vector is the concatenation of
its fields (:mod:`groupcanon.features`), and a group element acts on it field by field.

For a group that rotates the first two axes (SO2, SE2, SE2xR, products with one planar factor) and fields that are
all built-in vectors and rotations, the action is linear in the planar rotation's ``(c, s)``: :class:`FieldType`
then acts with one small matrix product and two fused multiply-adds (:func:`_planar_basis`), and
:meth:`FieldType.act_gathered` computes the product once per node and gathers it to the edges.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor

from .features import FeatureType, Point, Rotation, Vector
from .group import Group, check_element_shape, require_group

__all__ = ["FieldType"]


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
