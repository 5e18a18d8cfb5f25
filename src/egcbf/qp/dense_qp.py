"""The decentralized CBF-QP's per-agent QPs as one dense batch: assembly and the two batched solvers.

Agent ``i``'s QP, variables ``z = (a_i (3), s_i (1))``, one slack shared by its rows (``docs/baselines.md``)::

    min  1/2 ||a - a_nom||^2 + 1/2 w2 s^2 + w1 s
    s.t. n_k . a + s >= b_k      (its CBF rows: half of every pair row, whole obstacle rows)
         lo <= Cb a <= hi,  s >= 0

:func:`assemble_decentralized` scatters the agents' rows into padded blocks (:class:`DenseBatchQP`);
:func:`solve_dense_batch_ipm` solves them all at once with the batched interior-point method
(:func:`egcbf.qp.dense_ipm.solve_dense_ipm`, on any torch device), :func:`solve_dense_batch` with proxsuite's
``dense.BatchQP`` (one QP object per agent), the controller's ``dcbf_solver="proxsuite"``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .dense_ipm import solve_dense_ipm
from .ipm import INF
from .sparse_qp import SlackPenalty

__all__ = [
    "DenseBatchQP",
    "assemble_decentralized",
    "inequality_form",
    "solve_dense_batch",
    "solve_dense_batch_ipm",
    "verified",
]

_PENALTY = SlackPenalty()


@dataclass
class DenseBatchQP:
    """``M`` dense QPs in ``(a (3), s (1))``: ``min 1/2 ||a - a_nom||^2 + 1/2 w2 s^2 + w1 s`` s.t.
    ``C z >= l`` (CBF rows, padded with inactive rows), bounds ``lo <= Cb a <= hi`` and ``s >= 0``.

    Arrays: ``a_nom (M, 3)``, ``cbf_normal (M, K, 3)``, ``cbf_rhs (M, K)`` (padding rows: normal 0, rhs -INF),
    ``bound_C (M, Kb, 3)``, ``bound_lo, bound_hi (M, Kb)``.
    """

    a_nom: np.ndarray
    cbf_normal: np.ndarray
    cbf_rhs: np.ndarray
    bound_C: np.ndarray
    bound_lo: np.ndarray
    bound_hi: np.ndarray
    penalty: SlackPenalty

    def __len__(self) -> int:
        return self.a_nom.shape[0]

    def matrices(self) -> tuple[np.ndarray, ...]:
        """Stacked dense ``H (4,4), g (M,4), C (M,m,4), l (M,m), u (M,m)`` in proxsuite's form ``l <= C z <= u``."""
        m_ = len(self)
        k = self.cbf_normal.shape[1]
        kb = self.bound_C.shape[1]
        H = np.diag([1.0, 1.0, 1.0, self.penalty.w2])
        g = np.concatenate([-self.a_nom, np.full((m_, 1), self.penalty.w1)], axis=1)
        nrow = k + kb + 1
        C = np.zeros((m_, nrow, 4))
        C[:, :k, :3] = self.cbf_normal
        C[:, :k, 3] = 1.0
        C[:, k : k + kb, :3] = self.bound_C
        C[:, -1, 3] = 1.0
        lo = np.concatenate([self.cbf_rhs, self.bound_lo, np.zeros((m_, 1))], axis=1)
        hi = np.concatenate([np.full((m_, k), INF), self.bound_hi, np.full((m_, 1), INF)], axis=1)
        return H, g, C, lo, hi


def assemble_decentralized(
    a_nom: np.ndarray,
    owner: np.ndarray,
    normal: np.ndarray,
    rhs: np.ndarray,
    bound_C: np.ndarray,
    bound_lo: np.ndarray,
    bound_hi: np.ndarray,
    penalty: SlackPenalty = _PENALTY,
    min_rows: int = 1,
) -> DenseBatchQP:
    """Scatter the agents' rows (``owner`` ``(R,)``) into padded blocks ``(M, K, ...)``, ``K`` = max count."""
    m_ = a_nom.shape[0]
    counts = np.bincount(owner, minlength=m_) if owner.size else np.zeros(m_, dtype=np.int64)
    k = max(int(counts.max(initial=0)), min_rows)
    order = np.argsort(owner, kind="stable")
    o = owner[order]
    first = np.searchsorted(o, np.arange(m_), side="left")
    slot = np.arange(o.size) - first[o]
    nrm = np.zeros((m_, k, 3))
    b = np.full((m_, k), -INF)
    nrm[o, slot] = normal[order]
    b[o, slot] = rhs[order]
    return DenseBatchQP(a_nom, nrm, b, bound_C, bound_lo, bound_hi, penalty)


def solve_dense_batch(
    qps: DenseBatchQP, eps_abs: float = 1e-8, max_iter: int = 1000, num_threads: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve every per-agent QP with proxsuite's ``dense.BatchQP`` + ``solve_in_parallel``.

    Returns ``z (M, 4)``, ``ok (M,)`` bool, ``iterations (M,)``; failed QPs have ``ok = False`` (never raises).
    """
    from proxsuite import proxqp

    m_ = len(qps)
    H, g, C, lo, hi = qps.matrices()
    nrow = C.shape[1]
    batch = proxqp.dense.BatchQP()
    for q in range(m_):
        qp = batch.init_qp_in_place(4, 0, nrow)
        st = qp.settings
        st.eps_abs = eps_abs
        st.eps_rel = 0.0
        st.max_iter = max_iter
        st.verbose = False
        qp.init(H, g[q], None, None, C[q], lo[q], hi[q])
    proxqp.dense.solve_in_parallel(batch, num_threads=num_threads or 1)
    z = np.empty((m_, 4))
    ok = np.empty(m_, dtype=bool)
    it = np.empty(m_, dtype=np.int64)
    solved = proxqp.QPSolverOutput.PROXQP_SOLVED
    for q in range(m_):
        res = batch.get(q).results
        z[q] = res.x
        ok[q] = res.info.status == solved
        it[q] = res.info.iter
    ok &= np.isfinite(z).all(1)
    return z, ok, it


def inequality_form(
    qps: DenseBatchQP, device: torch.device | str | None = None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The batch as one-sided rows ``G z <= h`` on ``device`` (float64): ``P`` ``(4, 4)``, ``q`` ``(M, 4)``,
    ``G`` ``(M, K + 2 Kb + 1, 4)``, ``h`` ``(M, K + 2 Kb + 1)`` (rows: ``-(n . a + s) <= -b`` (CBF; padding rows
    all zero with ``h = 1``), ``Cb a <= hi``, ``-Cb a <= -lo``, ``-s <= 0``) and ``pad`` ``(M, K)`` (padding)."""
    f64 = dict(dtype=torch.float64, device=device)
    nrm, rhs = torch.as_tensor(qps.cbf_normal, **f64), torch.as_tensor(qps.cbf_rhs, **f64)
    bc = torch.as_tensor(qps.bound_C, **f64)
    blo, bhi = torch.as_tensor(qps.bound_lo, **f64), torch.as_tensor(qps.bound_hi, **f64)
    m_, k = rhs.shape
    kb = bc.shape[1]
    pad = rhs <= -INF / 2
    G = torch.zeros(m_, k + 2 * kb + 1, 4, **f64)
    G[:, :k, :3] = torch.where(pad[..., None], 0.0, -nrm)
    G[:, :k, 3] = torch.where(pad, 0.0, -1.0)
    G[:, k : k + kb, :3] = bc
    G[:, k + kb : k + 2 * kb, :3] = -bc
    G[:, -1, 3] = -1.0
    h = torch.cat((torch.where(pad, 1.0, -rhs), bhi, -blo, torch.zeros(m_, 1, **f64)), 1)
    P = torch.diag(torch.tensor([1.0, 1.0, 1.0, qps.penalty.w2], **f64))
    a_nom = torch.as_tensor(qps.a_nom, **f64)
    q = torch.cat((-a_nom, torch.full((m_, 1), qps.penalty.w1, **f64)), 1)
    return P, q, G, h, pad


def solve_dense_batch_ipm(
    qps: DenseBatchQP, tol: float = 1e-12, max_iter: int = 60, device: torch.device | str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-agent QPs of :class:`DenseBatchQP` by :func:`egcbf.qp.dense_ipm.solve_dense_ipm` on ``device``
    (default: the CPU); same returns as :func:`solve_dense_batch` (numpy).

    Agents whose nominal ``(a_nom, s = 0)`` satisfies all their rows are solved exactly (it is the unconstrained
    minimizer); the others start from the strictly feasible ``a = 0`` (hover, inside the bounds) with
    ``s = max(0, max_k b_k) + 1``.
    """
    P, q, G, h, pad = inequality_form(qps, device)
    m_ = q.shape[0]
    z = torch.zeros_like(q)
    z[:, :3] = -q[:, :3]
    free = ((G @ z[..., None])[..., 0] <= h).all(1)
    hard = (~free).nonzero()[:, 0]
    rhs = torch.as_tensor(qps.cbf_rhs, dtype=q.dtype, device=q.device)[hard]
    x0 = torch.zeros(hard.numel(), 4, dtype=q.dtype, device=q.device)
    top = torch.where(pad[hard], 0.0, rhs).amax(1) if rhs.shape[1] else x0[:, 3]
    x0[:, 3] = top.clamp_min(0.0) + 1.0
    x, ok_h, it_h = solve_dense_ipm(P, q[hard], G[hard], h[hard], x0=x0, tol=tol, max_iter=max_iter)
    z[hard] = x
    ok = torch.ones(m_, dtype=torch.bool, device=q.device)
    ok[hard] = ok_h
    it = torch.zeros(m_, dtype=torch.int64, device=q.device)
    it[hard] = it_h
    return z.cpu().numpy(), ok.cpu().numpy(), it.cpu().numpy()


def verified(qps: DenseBatchQP, z: np.ndarray, ok: np.ndarray, tol: float) -> np.ndarray:
    """``(M,)`` bool: the solver reported success and ``z = (a, s)`` ``(M, 4)`` satisfies the QP's CBF rows up to
    its slack (relative to ``1 + |b|``: barrier rows reach ``|b| ~ 1e3`` next to the safety distance) and its
    bounds, within ``tol``, with ``s >= -tol``. Agents where this is false get a fallback from the caller."""
    a, s = np.nan_to_num(z[:, :3]), np.nan_to_num(z[:, 3])
    res_rows = np.einsum("mkd,md->mk", qps.cbf_normal, a) + s[:, None]
    viol = (np.maximum(qps.cbf_rhs - res_rows, 0.0) / (1.0 + np.abs(qps.cbf_rhs))).max(1, initial=0.0)
    bv = np.einsum("mkd,md->mk", qps.bound_C, a)
    viol = np.maximum(viol, np.maximum(qps.bound_lo - bv, bv - qps.bound_hi).max(1, initial=0.0))
    return ok & np.isfinite(z).all(1) & (viol <= tol) & (s >= -tol)
