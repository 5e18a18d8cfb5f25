"""The :class:`Group` base class: batched group elements as plain tensors.

A group element is a plain ``torch.Tensor`` of shape ``(*batch, *G.element_shape)``. Leading dimensions are
batch dimensions, so ``frames[edge_index[1]]``, ``torch.cat``, ``.to(device)`` and ``.double()`` work as they do
for any tensor. Every operation broadcasts over batch dimensions, is differentiable, and runs on any device and
floating dtype without data-dependent Python branches.

A subclass implements only :attr:`element_shape`, :meth:`identity`, :meth:`compose`, :meth:`inverse` and
:meth:`sample`. Every operation that takes group elements (``compose``, ``inverse``, ``log``, ``matrix`` and the
affine interface) checks their trailing shape first and raises a ``ValueError`` naming the operation and the
expected shape (a shape comparison, no device synchronization); subclasses get the check automatically.
Whether the *values* are group elements (unit planar rotations, orthonormal matrices) is checked only on request,
by :meth:`Group.check_member`.

Groups that act on a Euclidean space by rigid motions (rotations, translations) also implement the *affine
interface* (:attr:`space_dim`, :meth:`rotate`, :meth:`translation`, ...), which is what the built-in
feature types :class:`~groupcanon.features.Vector`, :class:`~groupcanon.features.Point` and
:class:`~groupcanon.features.Rotation` use.
"""

from __future__ import annotations

import abc
import functools
import math
from typing import ClassVar

import torch
from torch import Tensor

__all__ = ["Group", "check_element_shape", "default_dtype", "require_group"]


def default_dtype(dtype: torch.dtype | None) -> torch.dtype:
    return torch.get_default_dtype() if dtype is None else dtype


def require_group(value, what: str) -> Group:
    """Return ``value`` if it is a :class:`Group`, else raise a ``TypeError`` naming ``what`` (the argument) and the
    type given; for an object that has a group (a ``FieldType``) the message points to its ``.group``."""
    if isinstance(value, Group):
        return value
    inner = getattr(value, "group", None)
    hint = f" (pass its .group, {inner}, instead)" if isinstance(inner, Group) else ""
    raise TypeError(f"{what} must be a groupcanon Group, got {type(value).__name__}{hint}")


def check_element_shape(group: Group, g: Tensor, what: str = "group element") -> None:
    """Raise a ``ValueError`` naming the mismatch if ``g`` is not ``(*batch, *group.element_shape)``."""
    if not isinstance(g, Tensor):
        raise TypeError(f"{what} for {group} must be a torch.Tensor, got {type(g).__name__}")
    shape = tuple(group.element_shape)
    k = len(shape)
    if g.dim() < k or tuple(g.shape[g.dim() - k :]) != shape:
        raise ValueError(
            f"{what} has shape {tuple(g.shape)}, but {group} elements have shape (*batch, {', '.join(map(str, shape))})"
            + ("" if k else " (empty trailing shape)")
        )


# Operations whose leading positional arguments are group elements: name -> how many.
_ELEMENT_ARGS = {
    "compose": 2,
    "inverse": 1,
    "log": 1,
    "matrix": 1,
    "rotation": 1,
    "translation": 1,
    "rotate": 1,
    "transform": 1,
    "planar_rotation": 1,
}


def _with_shape_check(fn, name: str, count: int):
    """``fn`` with its first ``count`` positional arguments checked to be elements of ``self``."""
    if getattr(fn, "_checks_elements", False):
        return fn

    @functools.wraps(fn)
    def checked(self, *args, **kwargs):
        shape = self.element_shape
        for i in range(min(count, len(args))):
            g = args[i]
            if not isinstance(g, Tensor) or g.shape[g.dim() - len(shape) :] != shape or g.dim() < len(shape):
                check_element_shape(self, g, f"{name}() argument {i + 1}")  # raises, naming the expected shape
        return fn(self, *args, **kwargs)

    checked._checks_elements = True
    return checked


class Group(abc.ABC):
    """A Lie group (or finite group) whose elements are batched tensors.

    Required (abstract):
        element_shape: trailing shape of one element, e.g. ``(2,)`` for SO(2) stored as ``(cos, sin)``.
        identity(*batch, dtype=None, device=None) -> Tensor ``(*batch, *element_shape)``
        compose(a, b) -> a . b, broadcasting the batch dimensions of ``a`` and ``b``.
        inverse(a) -> a^-1.
        sample(*batch, generator=None, dtype=None, device=None): random elements; compact parts Haar-uniform.

    Optional (raise ``NotImplementedError`` by default): ``exp``, ``log``, ``matrix`` and the affine interface.
    """

    #: Dimension of the Euclidean space the group acts on by rigid motions, or ``None`` if it has no such action.
    space_dim: int | None = None
    #: True if the affine action has a translation part (Point features are translated).
    has_translation: bool = False
    #: True if every rotation part has determinant +1 (False for groups with reflections, e.g. O(2)).
    orientation_preserving: bool = True

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        for name, count in _ELEMENT_ARGS.items():
            fn = cls.__dict__.get(name)
            if fn is not None and not getattr(fn, "__isabstractmethod__", False):
                setattr(cls, name, _with_shape_check(fn, name, count))

    # ----------------------------------------------------------------------------------------- required
    @property
    @abc.abstractmethod
    def element_shape(self) -> tuple[int, ...]:
        """Trailing shape of one group element."""

    @abc.abstractmethod
    def identity(self, *batch: int, dtype: torch.dtype | None = None, device=None) -> Tensor:
        """The identity element, repeated over ``batch``."""

    @abc.abstractmethod
    def compose(self, a: Tensor, b: Tensor) -> Tensor:
        """The product ``a . b`` (apply ``b`` first, then ``a``); batch dimensions broadcast."""

    @abc.abstractmethod
    def inverse(self, a: Tensor) -> Tensor:
        """The inverse ``a^-1``."""

    @abc.abstractmethod
    def sample(
        self,
        *batch: int,
        generator: torch.Generator | None = None,
        dtype: torch.dtype | None = None,
        device=None,
    ) -> Tensor:
        """Random elements of shape ``(*batch, *element_shape)``; compact parts are Haar-distributed."""

    # ----------------------------------------------------------------------------------------- optional
    def exp(self, xi: Tensor) -> Tensor:
        """Exponential map from Lie-algebra coordinates ``(*batch, dim)`` to elements."""
        raise NotImplementedError(f"{self} does not implement exp")

    def log(self, g: Tensor) -> Tensor:
        """Logarithm (principal branch): elements to Lie-algebra coordinates ``(*batch, dim)``."""
        raise NotImplementedError(f"{self} does not implement log")

    def matrix(self, g: Tensor) -> Tensor:
        """A faithful matrix representation ``(*batch, n, n)`` (homogeneous matrix for rigid motions)."""
        raise NotImplementedError(f"{self} does not implement matrix")

    def special_elements(self, dtype: torch.dtype | None = None, device=None) -> Tensor:
        """A batch ``(k, *element_shape)`` of elements where numerics are delicate (angles near 0, pi, 2 pi).

        The testing kit mixes them into random samples. The default is the identity only.
        """
        return self.identity(1, dtype=dtype, device=device)

    # ------------------------------------------------------------------------------ affine interface
    def rotation(self, g: Tensor) -> Tensor:
        """Linear (rotation) part ``(*batch, d, d)`` of the rigid motion, ``d = space_dim``."""
        raise NotImplementedError(f"{self} does not act on a Euclidean space by rigid motions")

    def translation(self, g: Tensor) -> Tensor:
        """Translation part ``(*batch, d)``; zeros for groups without translations."""
        if self.space_dim is None:
            raise NotImplementedError(f"{self} does not act on a Euclidean space by rigid motions")
        r = self.rotation(g)
        return r.new_zeros(r.shape[:-1])

    def rotate(self, g: Tensor, v: Tensor) -> Tensor:
        """Apply the linear part to vectors: ``v`` ``(*batch, d)`` -> ``R(g) v``. Subclasses override for speed."""
        return (self.rotation(g) @ v.unsqueeze(-1)).squeeze(-1)

    def transform(self, g: Tensor, p: Tensor) -> Tensor:
        """Apply the rigid motion to points: ``p`` ``(*batch, d)`` -> ``R(g) p + t(g)``."""
        return self.rotate(g, p) + self.translation(g)

    def planar_rotation(self, g: Tensor) -> Tensor:
        """``(cos theta, sin theta)`` ``(*batch, 2)`` of the group's SO(2) part, for SO(2) irreps."""
        raise NotImplementedError(f"{self} has no SO(2) part for SO(2) irreps")

    def acts_on_space(self, d: int) -> bool:
        """Whether the built-in Vector/Point/Rotation features of dimension ``d`` are defined for this group."""
        return self.space_dim == d

    # ----------------------------------------------------------------------------------------- helpers
    @property
    def element_numel(self) -> int:
        return math.prod(self.element_shape)

    def check(self, g: Tensor, what: str = "group element") -> None:
        """Raise a clear ``ValueError`` if ``g`` does not have this group's element shape."""
        check_element_shape(self, g, what)

    def membership_residual(self, g: Tensor) -> Tensor:
        """How far each element of ``g`` ``(*batch, *element_shape)`` is from the group, ``(*batch,)``: NaN for
        non-finite elements, else the largest entry of ``|R^T R - I|`` of the rotation part, plus
        ``|det R - 1|`` for orientation-preserving groups (0 for groups without a rotation part)."""
        self.check(g, "g")
        flat = g.reshape(*self.batch_shape(g), self.element_numel)  # not -1: ambiguous for an empty batch
        finite = torch.isfinite(flat).all(-1)  # all() of an empty row is True
        res = torch.zeros(finite.shape, dtype=g.dtype if g.is_floating_point() else torch.float64, device=g.device)
        if self.space_dim is not None:
            try:
                r = self.rotation(g)
            except NotImplementedError:
                r = None
            if r is not None and r.shape[-1] > 0:
                eye = torch.eye(r.shape[-1], dtype=r.dtype, device=r.device)
                res = (r.transpose(-1, -2) @ r - eye).abs().amax(dim=(-2, -1))
                if self.orientation_preserving:
                    res = res + (torch.linalg.det(r) - 1).abs()
        return torch.where(finite, res, torch.full_like(res, float("nan")))

    def check_member(self, g: Tensor, atol: float = 1e-4, what: str = "group element") -> None:
        """Raise a ``ValueError`` if any element of ``g`` is not in the group up to ``atol`` (see
        :meth:`membership_residual`): a non-unit planar rotation, a non-orthogonal or reflected matrix, NaN or inf.

        Opt-in (it synchronizes with the device): :class:`~groupcanon.Canonicalize` calls it on every frame when
        constructed with ``check_frames=True``.
        """
        self.check(g, what)
        res = self.membership_residual(g)
        bad = ~(res <= atol)  # NaN counts as bad
        if bool(bad.any()):
            idx = tuple(bad.nonzero()[0].tolist())
            worst = float(res[bad].nan_to_num(nan=float("inf")).max())
            raise ValueError(
                f"{what}: {int(bad.sum())} of {bad.numel()} are not elements of {self} (first at batch index {idx}, "
                f"residual {worst:.3g} > atol={atol:g}); build frames with groupcanon.frames or normalize them"
            )

    def batch_shape(self, g: Tensor) -> torch.Size:
        return g.shape[: g.dim() - len(self.element_shape)]

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    #: attributes that only tune :meth:`sample` (e.g. ``translation_scale``): not part of the group's identity, so
    #: ``SE2(1.0) == SE2()`` and a FieldType over one serves the other
    sampling_attributes: ClassVar[tuple[str, ...]] = ("translation_scale",)

    def _identity_items(self) -> tuple:
        return tuple(sorted((k, v) for k, v in self.__dict__.items() if k not in self.sampling_attributes))

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self._identity_items() == other._identity_items()

    def __hash__(self) -> int:
        return hash((type(self).__name__, repr(self._identity_items())))
