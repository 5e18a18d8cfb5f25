"""Use an escnn ``Representation`` as a batched groupcanon feature type (optional extra ``escnn``).

    from escnn import group as eg
    from groupcanon.compat.escnn import from_escnn

    rep = eg.directsum([eg.so2_group().irrep(k) for k in (0, 1, 2)])
    ft = from_escnn(rep)                       # an EscnnFeature bound to groups.SO2()
    y = ft.act(g, x)                           # g (*batch, 2), x (*batch, 5): one batched torch call

escnn evaluates one ``GroupElement`` at a time in float64 numpy and has no gradient with respect to the element.
This adapter reads what it needs from escnn once, at construction, and then evaluates the representation in torch
only: batched over any leading dimensions, differentiable with respect to the group element, on the device and
dtype of the inputs. escnn is never called per element.

How: escnn writes every representation as ``rho(g) = Q (psi_1(g) + ... + psi_m(g)) Q^-1`` (irreps ``psi_i``,
change of basis ``Q``). ``act(g, x)`` applies ``Q^-1``, then each irrep block to its channels, then ``Q``; each
distinct irrep is evaluated once per element, whatever its multiplicity:

=================  =============  ===================================================================================
escnn group        binds to       one irrep block, evaluated in torch
=================  =============  ===================================================================================
``so2_group()``    ``SO2()``      ``cos(k theta) I + sin(k theta) J`` with ``J = psi(pi / 2k)`` read from escnn
``o2_group()``     ``O2()``       ``(cos(k theta) I + sin(k theta) J) F^f`` with ``F = psi(flip)``: escnn's
                                  ``(f, theta)`` is ``R(theta) M^f`` (reflect first, then rotate)
``cyclic_group``   ``Cyclic(n)``  a table of the ``n`` matrices ``psi(r^k)``, indexed by ``Cyclic.index(g)``
``so3_group()``    ``SO3()``      ``D^1 = B^T R B``, ``D^l = C_l^T (D^(l-1) (x) D^1) C_l``: polynomials in ``R``
=================  =============  ===================================================================================

The SO(3) intertwiners ``B`` and ``C_l`` (isometries, found once as the null space of the intertwining equations at
a few random rotations) put escnn's Wigner-D basis into the recursion, so ``D^l(R)`` is an exact polynomial of
degree ``l`` in the entries of ``R``: no logarithm, no ``matrix_exp``, smooth gradients everywhere (half turns
included). Every feature compares itself with escnn at construction (float64, 1e-9), so a convention mismatch
raises instead of silently giving a wrong action.

An SO(2) representation also binds to any group with an SO(2) part (``Cyclic``, ``SE2``, ``SE2xR``), an SO(3)
representation to any group with a 3-D rotation part (``SE3``, ``SE2xR``), and every one to ``Trivial()``.
"""

from __future__ import annotations

import importlib.util
import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..features import FeatureType
from ..group import Group
from ..groups import O2, SO2, SO3, Cyclic, Trivial

__all__ = ["EscnnFeature", "from_escnn", "to_escnn_element"]

INSTALL_HINT = (
    "install the optional extra: pip install 'egcbf[escnn]' (or 'groupcanon[escnn]' for groupcanon alone) && "
    "pip install --no-deps escnn==1.0.11 "
    "(escnn's py3nj dependency needs a Fortran compiler and is optional, hence --no-deps), "
    "or run `make setup-escnn` in the egcbf repository. escnn needs numpy<2."
)

#: Tolerance of the construction-time comparison with escnn (float64, scaled by the conditioning of ``Q``).
SELF_CHECK_ATOL = 1e-9

#: SO(3) irreps up to this degree use one GEMM per degree (fast for small l); higher ones a 3-step contraction.
_GEMM_MAX_L = 4


def _escnn_group_module():
    """``escnn.group``, imported lazily, with an actionable ImportError if escnn is missing or broken."""
    try:
        import escnn.group as eg
    except Exception as err:  # with numpy 2, lie_learn fails with ValueError/AttributeError as well
        if importlib.util.find_spec("escnn") is None:
            raise ImportError(f"groupcanon.compat.escnn needs escnn, which is not installed: {INSTALL_HINT}") from err
        raise ImportError(
            f"escnn is installed but cannot be imported ({type(err).__name__}: {err}); {INSTALL_HINT}"
        ) from err
    return eg


def _kind(escnn_group: Any) -> str:
    eg = _escnn_group_module()
    if isinstance(escnn_group, eg.SO2):
        return "so2"
    if isinstance(escnn_group, eg.O2):
        return "o2"
    if isinstance(escnn_group, eg.CyclicGroup):
        return "cyclic"
    if isinstance(escnn_group, eg.SO3):
        return "so3"
    raise TypeError(
        "groupcanon.compat.escnn supports representations of escnn's SO(2), O(2), C_n (cyclic_group) and SO(3), "
        f"not of {escnn_group} ({type(escnn_group).__name__})"
    )


def _default_group(kind: str, escnn_group: Any) -> Group:
    if kind == "cyclic":
        return Cyclic(escnn_group.order())
    return {"so2": SO2, "o2": O2, "so3": SO3}[kind]()


def to_escnn_element(escnn_group: Any, g: Tensor):
    """The escnn ``GroupElement`` of one groupcanon element ``g`` (no batch dimensions).

    ``g`` has the layout of the default groupcanon group of ``escnn_group``: ``(cos, sin)`` for SO(2) and C_n
    (``Cyclic.index`` gives escnn's integer), a ``2 x 2`` orthogonal matrix ``R(theta) M^f`` for O(2) (escnn's
    ``(f, theta)``), a ``3 x 3`` rotation matrix for SO(3) (escnn's ``'MAT'`` parametrization).
    """
    kind = _kind(escnn_group)
    g64 = g.detach().to("cpu", torch.float64)
    a = g64.numpy()
    if kind == "so2":
        return escnn_group.element(math.atan2(a[1], a[0]), "radians")
    if kind == "cyclic":
        return escnn_group.element(int(Cyclic(escnn_group.order()).index(g64)), "int")
    if kind == "o2":
        flip = int(a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0] < 0)
        return escnn_group.element((flip, math.atan2(a[1, 0], a[0, 0])), "radians")
    return escnn_group.element(a, "MAT")


# ----------------------------------------------------------------------------------------- construction
def _matrix(rep, element) -> np.ndarray:
    return np.asarray(rep(element), dtype=np.float64)


class _Block:
    """One distinct irrep: how to evaluate it in torch, and where its copies sit in the irrep basis."""

    def __init__(self, kind: str, size: int, consts: dict[str, np.ndarray] | None = None, freq: int = 0):
        self.kind = kind  # 'const' (trivial), 'planar' (SO(2)), 'o2', 'table' (C_n), 'wigner' (SO(3), freq = l)
        self.size = size
        self.freq = freq
        self.consts = {k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in (consts or {}).items()}
        self.index = torch.zeros(0, size, dtype=torch.long)  # (copies, size): positions in the irrep basis


def _make_block(kind: str, psi, escnn_group) -> _Block:
    size = psi.size
    if kind == "cyclic":
        table = np.stack([_matrix(psi, escnn_group.element(k, "int")) for k in range(escnn_group.order())])
        if size == 1 and np.all(table == 1):
            return _Block("const", 1)
        return _Block("table", size, {"table": table})
    if kind == "so3":
        return _Block("const", 1) if size == 1 else _Block("wigner", size, freq=(size - 1) // 2)

    # SO(2) and O(2): the rotation part of a 1-D irrep is trivial; a 2-D irrep rotates by k theta.
    def at(theta: float, flip: int = 0) -> np.ndarray:
        return _matrix(psi, escnn_group.element((flip, theta) if kind == "o2" else theta, "radians"))

    if size == 1:
        return _Block("const", 1) if kind == "so2" else _Block("o2", 1, {"flip": at(0.0, 1)})
    freq = int(psi.attributes["frequency"])
    J = at(math.pi / (2 * freq))  # psi at a quarter turn of its frequency: the unit rotation generator
    if kind == "so2":
        return _Block("planar", 2, {"J": J}, freq=freq)
    return _Block("o2", 2, {"J": J, "flip": at(0.0, 1)}, freq=freq)


def _intertwiner(pairs: list[tuple[np.ndarray, np.ndarray]], what: str) -> np.ndarray:
    """The isometry ``X`` ``(p, d)`` with ``M X = X psi`` for every ``(M, psi)`` in ``pairs`` (a 1-D solution space)."""
    p, d = pairs[0][0].shape[0], pairs[0][1].shape[0]
    # Row-major vec: vec(M X) = (M kron I) vec X and vec(X psi) = (I kron psi^T) vec X. The solution is the
    # eigenvector of the smallest eigenvalue (0) of the Gram matrix of these equations.
    gram = np.zeros((p * d, p * d))
    for m, psi in pairs:
        k = np.kron(m, np.eye(d)) - np.kron(np.eye(p), psi.T)
        gram += k.T @ k
    w, v = np.linalg.eigh(gram)
    if not (abs(w[0]) <= 1e-9 * w[-1] and w[1] > 1e-6 * w[-1]):
        raise RuntimeError(f"groupcanon.compat.escnn: no unique intertwiner for {what} (eigenvalues {w[:2]})")
    u, _, vt = np.linalg.svd(v[:, 0].reshape(p, d), full_matrices=False)
    return u @ vt  # the nearest isometry (orthogonal reps: X^T X = c I by Schur's lemma)


def _so3_chain(escnn_group, l_max: int) -> list[np.ndarray]:
    """``[B, C_2, ..., C_lmax]``: ``D^1 = B^T R B`` and ``D^l = C_l^T (D^(l-1) kron D^1) C_l`` in escnn's bases."""
    gen = torch.Generator().manual_seed(12345)
    rotations = SO3().sample(4, generator=gen, dtype=torch.float64).numpy()
    elements = [escnn_group.element(r, "MAT") for r in rotations]
    psi = {l: [_matrix(escnn_group.irrep(l), e) for e in elements] for l in range(1, l_max + 1)}
    chain = [_intertwiner(list(zip(rotations, psi[1])), "SO(3) irrep 1 and the rotation matrix")]
    for l in range(2, l_max + 1):
        pairs = [(np.kron(a, b), c) for a, b, c in zip(psi[l - 1], psi[1], psi[l])]
        chain.append(_intertwiner(pairs, f"SO(3) irrep {l} in irrep {l - 1} (x) irrep 1"))
    return chain


# ----------------------------------------------------------------------------------------- evaluation
def _rotation_block(theta: Tensor, freq: int, J: Tensor) -> Tensor:
    c, s = torch.cos(freq * theta), torch.sin(freq * theta)
    eye = torch.eye(2, dtype=J.dtype, device=J.device)
    return c[..., None, None] * eye + s[..., None, None] * J


def _wigner(R: Tensor, chain: list[Tensor], l_max: int) -> list[Tensor]:
    """``[D^1(R), ..., D^lmax(R)]`` for rotations ``R`` ``(*batch, 3, 3)``, in escnn's bases."""
    B = chain[0]
    d1 = B.transpose(0, 1) @ R @ B
    batch = R.shape[:-2]
    out = [d1]
    flat1 = d1.reshape(*batch, 1, 9)
    for l in range(2, l_max + 1):
        n, d = 2 * l - 1, 2 * l + 1
        prev, c = out[-1], chain[l - 1]
        if l <= _GEMM_MAX_L:  # c is W_l (9 n^2, d^2): one GEMM on the products D^(l-1)_ij D^1_ab
            prod = (prev.reshape(*batch, n * n, 1) * flat1).reshape(*batch, 9 * n * n)
            out.append((prod @ c).reshape(*batch, d, d))
        else:  # c is C_l (n, 3, d): D^l = C^T (D^(l-1) kron D^1) C in three contractions, O(l^3)
            t = torch.einsum("...ab,jbc->...jac", d1, c)
            u = torch.einsum("...ij,...jac->...iac", prev, t)
            out.append(torch.einsum("iae,...iac->...ec", c, u))
    return out


def _broadcast_last(ts: list[Tensor]) -> list[Tensor]:
    batch = torch.broadcast_shapes(*(t.shape[:-1] for t in ts))
    return [t.expand(*batch, t.shape[-1]) for t in ts]


class EscnnFeature(FeatureType):
    """A groupcanon feature type that evaluates an escnn ``Representation`` in batched torch.

    Args:
        representation: an escnn ``Representation`` of ``so2_group()``, ``o2_group()``, ``cyclic_group(n)`` or
            ``so3_group()`` (or an escnn ``nn.FieldType``, whose ``representation`` is used).
        group: the groupcanon group acting (default ``SO2()``, ``O2()``, ``Cyclic(n)`` or ``SO3()``).
        self_check: compare with escnn at a few random elements now (float64) and raise if they differ.

    ``act(g, x)`` maps ``x`` ``(*batch, dim)`` to ``rho(g) x``; ``matrix(g)`` is ``rho(g)`` ``(*batch, dim, dim)``.
    Both broadcast batch dimensions, follow the dtype and device of their input, and are differentiable with
    respect to ``g`` (except through discrete parts: C_n and the flip of O(2)).
    """

    def __init__(self, representation: Any, group: Group | None = None, *, self_check: bool = True):
        eg = _escnn_group_module()
        if not isinstance(representation, eg.Representation) and isinstance(
            getattr(representation, "representation", None), eg.Representation
        ):
            representation = representation.representation  # an escnn.nn.FieldType
        if not isinstance(representation, eg.Representation):
            raise TypeError(f"from_escnn needs an escnn Representation, got {type(representation).__name__}")
        self.representation = representation
        self.escnn_group = representation.group
        self.kind = _kind(self.escnn_group)
        self.dim = int(representation.size)
        self.group = _default_group(self.kind, self.escnn_group)
        self._cache: dict[tuple, dict] = {}
        self._build(representation)
        if self_check:
            self._self_check()
        if group is not None:
            self._check_group(group)
            self.group = group

    def _build(self, rep) -> None:
        blocks: dict[tuple, _Block] = {}
        where: dict[tuple, list[list[int]]] = {}
        offset = 0
        for irrep_id in rep.irreps:
            key = tuple(irrep_id)
            psi = self.escnn_group.irrep(*key)
            if key not in blocks:
                blocks[key] = _make_block(self.kind, psi, self.escnn_group)
                where[key] = []
            where[key].append(list(range(offset, offset + psi.size)))
            offset += psi.size
        if offset != self.dim:
            raise ValueError(f"{rep}: its irreps add up to {offset} dimensions, the representation has {self.dim}")
        perm = []
        for key, block in blocks.items():
            block.index = torch.tensor(where[key], dtype=torch.long)
            perm.extend(i for copy in where[key] for i in copy)
        self._blocks = list(blocks.values())
        self._inv_perm = None if perm == list(range(self.dim)) else torch.argsort(torch.tensor(perm))
        q = np.asarray(rep.change_of_basis, dtype=np.float64)
        self._has_basis = not np.array_equal(q, np.eye(self.dim))
        self._q = torch.as_tensor(q)
        self._q_inv = torch.as_tensor(np.asarray(rep.change_of_basis_inv, dtype=np.float64))
        self._l_max = max((b.freq for b in self._blocks if b.kind == "wigner"), default=0)
        chain = _so3_chain(self.escnn_group, self._l_max) if self._l_max else []
        for l in range(2, self._l_max + 1):  # precompute the GEMM form W_l of C_l for small l
            n, d = 2 * l - 1, 2 * l + 1
            c3 = chain[l - 1].reshape(n, 3, d)
            chain[l - 1] = np.einsum("iae,jbc->ijabec", c3, c3).reshape(9 * n * n, d * d) if l <= _GEMM_MAX_L else c3
        self._chain = [torch.as_tensor(np.ascontiguousarray(c)) for c in chain]
        self.invariant = all(b.kind == "const" for b in self._blocks)  # only trivial irreps

    def _self_check(self) -> None:
        # Haar-random elements only: escnn goes through Euler angles for SO(3) and loses up to 1e-7 near the
        # identity and half turns (gimbal lock), where this adapter stays exact.
        g = self.group.sample(4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        ours = self.matrix(g).numpy()
        worst = max(
            float(np.abs(m - _matrix(self.representation, to_escnn_element(self.escnn_group, gi))).max())
            for gi, m in zip(g, ours)
        )
        scale = self.dim * float(self._q.abs().max() * self._q_inv.abs().max())  # rounding grows with cond(Q)
        if not worst <= SELF_CHECK_ATOL * max(1.0, scale):
            raise RuntimeError(
                f"groupcanon.compat.escnn: {self.representation} evaluated in torch differs from escnn by "
                f"{worst:.2e}: this representation is not supported (please report it)"
            )

    # ------------------------------------------------------------------ groups
    def _check_group(self, group: Group) -> None:
        if not isinstance(group, Group):
            raise TypeError(f"{self!r} must be bound to a groupcanon Group, got {type(group).__name__}")
        if isinstance(group, Trivial):
            return
        if self.kind == "so2":
            try:
                group.planar_rotation(group.identity(1))
                ok = True
            except NotImplementedError:
                ok = False
        elif self.kind == "o2":
            ok = isinstance(group, O2)
        elif self.kind == "cyclic":
            ok = isinstance(group, Cyclic) and group.n == self.escnn_group.order()
        else:
            try:
                ok = group.space_dim == 3 and tuple(group.rotation(group.identity(1)).shape[-2:]) == (3, 3)
            except NotImplementedError:
                ok = False
        if not ok:
            need = {
                "so2": "a group with an SO(2) part (SO2, Cyclic, SE2, SE2xR)",
                "o2": "groups.O2()",
                "cyclic": f"groups.Cyclic({self.escnn_group.order()})",
                "so3": "a group with a 3-D rotation part (SO3, SE3, SE2xR)",
            }[self.kind]
            raise ValueError(f"{group} cannot act on {self!r}: it needs {need}")

    def bind(self, group: Group) -> FeatureType:
        """This feature acting through ``group`` (a copy if ``group`` differs); ``ValueError`` if it cannot."""
        if group == self.group:
            return self
        self._check_group(group)
        bound = object.__new__(type(self))
        bound.__dict__.update(self.__dict__)
        bound.group = group
        return bound

    # ------------------------------------------------------------------ evaluation
    def _constants(self, dtype: torch.dtype, device) -> dict:
        key = (dtype, str(device))
        found = self._cache.get(key)
        if found is None:
            found = {
                "q": self._q.to(device, dtype),
                "q_inv": self._q_inv.to(device, dtype),
                "blocks": [
                    {"index": b.index.to(device), **{k: v.to(device, dtype) for k, v in b.consts.items()}}
                    for b in self._blocks
                ],
                "chain": [c.to(device, dtype) for c in self._chain],
                "inv_perm": None if self._inv_perm is None else self._inv_perm.to(device),
            }
            self._cache[key] = found
        return found

    def _block_matrices(self, g: Tensor, consts: dict) -> list[Tensor]:
        group = self.group
        group.check(g)
        batch = group.batch_shape(g)
        if self.kind == "so2":
            cs = group.planar_rotation(g)
            theta = torch.atan2(cs[..., 1], cs[..., 0])
        elif self.kind == "o2":
            theta, flip = group.angle(g), group.flip(g)[..., None, None]
        elif self.kind == "cyclic":
            k = group.index(g)
        else:
            wigner = _wigner(group.rotation(g), consts["chain"], self._l_max) if self._l_max else []
        mats = []
        for block, c in zip(self._blocks, consts["blocks"]):
            if block.kind == "const":
                m = torch.ones(1, 1, dtype=g.dtype, device=g.device).expand(*batch, 1, 1)
            elif block.kind == "table":
                m = c["table"][k]
            elif block.kind == "planar":
                m = _rotation_block(theta, block.freq, c["J"])
            elif block.kind == "o2":
                f = c["flip"]
                if block.size == 1:
                    m = torch.where(flip, f, torch.ones_like(f))
                else:
                    reflect = torch.where(flip, f, torch.eye(2, dtype=f.dtype, device=f.device))
                    m = _rotation_block(theta, block.freq, c["J"]) @ reflect
            else:
                m = wigner[block.freq - 1]
            mats.append(m)
        return mats

    def act(self, g: Tensor, x: Tensor) -> Tensor:
        group = self.group
        if isinstance(group, Trivial):
            return x.expand(*torch.broadcast_shapes(group.batch_shape(g), x.shape[:-1]), self.dim)
        if x.shape[-1] != self.dim:
            raise ValueError(f"{self!r} acts on features of shape (*batch, {self.dim}), got {tuple(x.shape)}")
        consts = self._constants(x.dtype, x.device)
        mats = self._block_matrices(g.to(x.dtype), consts)
        y = x @ consts["q_inv"].transpose(0, 1) if self._has_basis else x
        outs = []
        for m, c in zip(mats, consts["blocks"]):
            yb = y[..., c["index"]]  # (*batch, copies, size)
            outs.append((m.unsqueeze(-3) @ yb.unsqueeze(-1)).squeeze(-1).flatten(-2))
        z = torch.cat(_broadcast_last(outs), dim=-1)
        if consts["inv_perm"] is not None:
            z = z[..., consts["inv_perm"]]
        return z @ consts["q"].transpose(0, 1) if self._has_basis else z

    def matrix(self, g: Tensor) -> Tensor:
        """``rho(g)`` ``(*batch, dim, dim)`` for ``g`` ``(*batch, *group.element_shape)``."""
        pos = g.dim() - len(self.group.element_shape)
        eye = torch.eye(self.dim, dtype=g.dtype, device=g.device)
        return self.act(g.unsqueeze(pos), eye).transpose(-1, -2)

    def __repr__(self) -> str:
        name = getattr(self.representation, "name", "?")
        return f"EscnnFeature({name!r} of {self.escnn_group}, dim={self.dim}, group={self.group})"


def from_escnn(representation: Any, group: Group | None = None) -> EscnnFeature:
    """The groupcanon feature type of an escnn ``Representation`` (see :class:`EscnnFeature`)."""
    return EscnnFeature(representation, group)
