"""Many small dense QPs by the batched interior-point method (:mod:`egcbf.qp.ipm`), with active-set polishing.

    min 1/2 x'Px + q'x   s.t.  G x <= h,        P (n, n) or (M, n, n), q (M, n), G (M, m, n), h (M, m)

:class:`DenseKKT` is the dense Newton linear algebra (one ``n x n`` Cholesky of ``P + G' diag(z / s) G`` per QP and
iteration, vectorized over the batch); :func:`solve_dense_ipm` solves the batch and polishes the converged
solutions (:func:`polish_dense`). Used for the per-agent QPs of the
decentralized CBF-QP baseline (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .ipm import INF, IPMSettings, solve_ipm

__all__ = ["LOOSE_TOL", "DenseKKT", "dense_settings", "polish_dense", "solve_dense_ipm"]

LOOSE_TOL = 1e-7  # tolerance accepted when double precision breaks down before ``tol`` is reached


def _mv(a: Tensor, x: Tensor) -> Tensor:
    """Batched ``A @ x``: ``(M, r, c), (M, c) -> (M, r)``."""
    return (a @ x[..., None])[..., 0]


def _cols_mv(cols: tuple[Tensor, ...], x: Tensor, init: Tensor | None = None) -> Tensor:
    """``init + A @ x`` from the columns ``cols`` of ``A`` (``c`` tensors ``(M, r)``) and ``x`` ``(M, c)``: for
    small ``c`` a chain of ``c`` fused multiply-adds is faster than a batched matrix product."""
    xs = x.unbind(-1)
    out = cols[0] * xs[0][:, None] if init is None else torch.addcmul(init, cols[0], xs[0][:, None])
    for col, xj in zip(cols[1:], xs[1:]):
        out = torch.addcmul(out, col, xj[:, None])
    return out


class _DenseNewton(NamedTuple):
    g_cols: tuple[Tensor, ...]  # the n columns of G, (M, m) each
    gt: Tensor  # G' (M, n, m), contiguous
    chol: Tensor  # (M, n, n) Cholesky factor of P + G' W G + 1e-14 I
    w: Tensor  # z / s (M, m)
    neg_r_d: Tensor  # -r_d (M, n, 1)
    r_p: Tensor
    s: Tensor
    z: Tensor

    def direction(self, rc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        t = torch.addcdiv(self.r_p, rc, self.z)  # r_p + rc / z
        rhs = torch.baddbmm(self.neg_r_d, self.gt, (self.w * t)[..., None], alpha=-1.0)  # -r_d - G' W t
        dx = torch.cholesky_solve(rhs, self.chol)[..., 0]
        dz = self.w * _cols_mv(self.g_cols, dx, init=t)  # W (G dx + t)
        return dx, torch.addcmul(rc, self.s, dz, value=-1.0) / self.z, dz  # ds = (rc - s dz) / z


@dataclass
class DenseKKT:
    """Dense batch ``P`` ``(n, n)`` (shared) or ``(M, n, n)``, ``q`` ``(M, n)``, ``G`` ``(M, m, n)``, ``h``
    ``(M, m)`` as a :class:`egcbf.qp.ipm.KKTSystem`: ``dual_scale = 1 + |q|_inf``,
    ``primal_scale = 1 + |h|_inf`` over the finite entries of ``h`` (below ``INF / 2``). Also kept: ``G'``
    ``(M, n, m)`` contiguous, whose rows are the columns of ``G`` (faster products at small ``n``), and
    ``P + 1e-14 I`` (the Newton matrix's regularized Hessian)."""

    P: Tensor
    q: Tensor
    G: Tensor
    GT: Tensor
    h: Tensor
    dual_scale: Tensor
    primal_scale: Tensor
    p_reg: Tensor

    @classmethod
    def build(cls, P: Tensor, q: Tensor, G: Tensor, h: Tensor) -> DenseKKT:
        """From ``P`` ``(n, n)`` (shared) or ``(M, n, n)`` and ``q, G, h``."""
        m_, n = q.shape
        dual = 1.0 + q.abs().amax(-1) if n else q.new_ones(m_)
        hf = torch.where(h.abs() < INF / 2, h.abs(), torch.zeros_like(h))
        primal = 1.0 + (hf.amax(-1) if h.shape[-1] else h.new_zeros(m_))
        p_reg = P + 1e-14 * torch.eye(n, dtype=P.dtype, device=P.device)
        return cls(P, q, G, G.transpose(-1, -2).contiguous(), h, dual, primal, p_reg)

    def take(self, idx: Tensor) -> DenseKKT:
        P, p_reg = (self.P, self.p_reg) if self.P.dim() == 2 else (self.P[idx], self.p_reg[idx])
        q, G, GT, h, dual, primal = (
            t[idx] for t in (self.q, self.G, self.GT, self.h, self.dual_scale, self.primal_scale)
        )
        return DenseKKT(P, q, G, GT, h, dual, primal, p_reg)

    def p_mul(self, x: Tensor) -> Tensor:
        return x @ self.P.mT if self.P.dim() == 2 else _mv(self.P, x)

    def g_mul(self, x: Tensor) -> Tensor:
        return _cols_mv(self.GT.unbind(1), x)

    def gt_mul(self, z: Tensor) -> Tensor:
        return _mv(self.GT, z)

    def newton(self, s: Tensor, z: Tensor, r_d: Tensor, r_p: Tensor) -> tuple[_DenseNewton, Tensor]:
        w = z / s
        n = self.P.shape[-1]
        k = torch.baddbmm(self.p_reg.expand(s.shape[0], n, n), self.GT * w[:, None, :], self.G)
        chol, info = torch.linalg.cholesky_ex(k)
        # (a NaN pivot fails the factorization; other non-finite entries give a non-finite step: both stop the QP)
        return _DenseNewton(self.GT.unbind(1), self.GT, chol, w, -r_d[..., None], r_p, s, z), info == 0


def polish_dense(
    P: Tensor, q: Tensor, G: Tensor, h: Tensor, x: Tensor, s: Tensor, z: Tensor, tol: float = 1e-10
) -> tuple[Tensor, Tensor]:
    """Active-set polishing (as OSQP's) of interior-point iterates ``x`` ``(M, n)``, ``s, z`` ``(M, m)`` of the QPs
    ``P`` ``(n, n)`` or ``(M, n, n)``, ``q``, ``G``, ``h``: guess the active rows (``z > s``), solve the
    equality-constrained QP's KKT system ``[P A'; A -1e-12 I] [x; lam] = [-q; h_A]`` (LU), and keep the result where
    it is primal feasible and its multipliers are non-negative (``tol`` relative to ``1 + |h|_inf``): it then meets
    the KKT conditions, up to the regularization's shift of the active rows by ``1e-12 lam`` (so a row whose
    multiplier exceeds ``100 (1 + |h|_inf)`` fails the feasibility test). The active rows are gathered first
    (padded to the largest count in the batch by decoupled rows ``lam = 0``; the inactive rows' multipliers are 0).
    Returns ``(x, polished (M,))``."""
    mq, m, n = G.shape
    P = P.expand(mq, n, n)
    act = z > s
    na = int(act.sum(-1).amax()) if mq and m else 0
    order = torch.argsort((~act).to(torch.int8), dim=-1, stable=True)[:, :na]  # active rows first
    a_act = act.gather(-1, order)
    ga = G.gather(1, order[..., None].expand(mq, na, n)) * a_act[..., None]
    k = torch.zeros(mq, n + na, n + na, dtype=x.dtype, device=x.device)
    k[:, :n, :n] = P
    k[:, :n, n:] = ga.transpose(-1, -2)
    k[:, n:, :n] = ga
    k[:, n:, n:] = torch.diag_embed(torch.where(a_act, -1e-12, 1.0).to(x.dtype))
    rhs = torch.cat((-q, torch.where(a_act, h.gather(-1, order), 0.0)), -1)
    sol, info = torch.linalg.solve_ex(k, rhs[..., None])
    sol = sol[..., 0]
    xp, lam = sol[:, :n], sol[:, n:]
    hf = torch.where(h.abs() < INF / 2, h.abs(), torch.zeros_like(h))
    scale = 1.0 + (hf.amax(-1) if m else h.new_zeros(mq))
    viol = (_mv(G, xp) - h).amax(-1) if m else xp.new_full((mq,), -1.0)
    lam_min = lam.amin(-1) if na else xp.new_zeros(mq)  # (min(lam_A, 0) in effect: the test is against -tol)
    good = (info == 0) & torch.isfinite(sol).all(-1) & (viol <= tol * scale) & (lam_min >= -tol * scale)
    return torch.where(good[:, None], xp, x), good


def dense_settings(tol: float = 1e-12, feas_tol: float = 1e-9, max_iter: int = 60) -> IPMSettings:
    """The interior-point settings of :func:`solve_dense_ipm` (the decentralized CBF-QP's per-agent QPs)."""
    return IPMSettings(
        tol=tol,
        feas_tol=feas_tol,
        max_iter=max_iter,
        min_slack=1.0,
        dual_relative=True,
        primal_violation=True,
        gap_relative=True,
        safeguard=True,
        best_iterate=False,
        loose_tol=LOOSE_TOL,
    )


def solve_dense_ipm(
    P: Tensor,
    q: Tensor,
    G: Tensor,
    h: Tensor,
    x0: Tensor | None = None,
    tol: float = 1e-12,
    max_iter: int = 60,
    polish: bool = True,
    feas_tol: float = 1e-9,
) -> tuple[Tensor, Tensor, Tensor]:
    """Solve ``M`` small QPs ``min 1/2 x'Px + q'x s.t. G x <= h`` (``P`` ``(n, n)`` shared or ``(M, n, n)``,
    ``q`` ``(M, n)``, ``G`` ``(M, m, n)``, ``h`` ``(M, m)``; float64, on their device) together.

    Rows that are all zero with ``h > 0`` are inactive padding. ``x0`` (default 0) need not be feasible; the
    slacks start at ``max(h - G x0, 1)``, the multipliers at 1. A QP has converged when
    ``|P x + q + G'z|_inf <= feas_tol max(1 + |q|_inf, |P x|_inf, |G'z|_inf)`` (relative, as OSQP's),
    ``|max(G x - h, 0)|_inf <= feas_tol (1 + |h|_inf)`` and ``mean(s z) <= tol (1 + |q|_inf)`` (the dual residual
    cannot go much below 1e-9 relative in double precision once ``z / s`` is huge). A QP that breaks down (NaN)
    or reaches ``max_iter`` keeps its last iterate, accepted if it meets ``LOOSE_TOL`` in all three. With
    ``polish`` the accepted solutions are refined by :func:`polish_dense`.

    Returns ``x`` ``(M, n)``, ``ok`` ``(M,)`` bool (accepted and finite), ``iterations`` ``(M,)`` int64.
    """
    m_, m = h.shape
    x0 = torch.zeros_like(q) if x0 is None else x0.to(q)
    kkt = DenseKKT.build(P, q, G, h)
    settings = dense_settings(tol, feas_tol, max_iter)
    res = solve_ipm(kkt, x0, torch.ones(m_, m, dtype=q.dtype, device=q.device), settings)
    x = res.x
    if polish:  # the accepted QPs only (the others are not used); a polished solution replaces its iterate
        xp, good = polish_dense(kkt.P, q, G, h, x, res.s, res.z)
        x = torch.where((res.converged & good)[:, None], xp, x)
    ok = res.converged & torch.isfinite(x).all(-1)
    return x, ok, res.iterations
