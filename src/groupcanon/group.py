"""The :class:`Group` base class: batched group elements as plain tensors.

A group element is a plain ``torch.Tensor`` of shape ``(*batch, *G.element_shape)``. Leading dimensions are
batch dimensions, so ``frames[edge_index[1]]``, ``torch.cat``, ``.to(device)`` and ``.double()`` work as they do
for any tensor. Every operation broadcasts over batch dimensions, is differentiable, and runs on any device and
floating dtype without data-dependent Python branches.

A subclass implements only :attr:`element_shape`, :meth:`identity`, :meth:`compose`, :meth:`inverse` and
:meth:`sample`. Groups that act on a Euclidean space by rigid motions (rotations, translations) also implement the
*affine interface* (:attr:`space_dim`, :meth:`rotate`, :meth:`translation`, ...), which is what the built-in
feature types :class:`~groupcanon.features.Vector`, :class:`~groupcanon.features.Point` and
:class:`~groupcanon.features.Rotation` use.
"""

from __future__ import annotations

import abc
import math

import torch
from torch import Tensor

__all__ = ["Group", "check_element_shape", "default_dtype"]


def default_dtype(dtype: torch.dtype | None) -> torch.dtype:
    return torch.get_default_dtype() if dtype is None else dtype


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

    def batch_shape(self, g: Tensor) -> torch.Size:
        return g.shape[: g.dim() - len(self.element_shape)]

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and self.__dict__ == other.__dict__

    def __hash__(self) -> int:
        return hash((type(self).__name__, repr(self)))
