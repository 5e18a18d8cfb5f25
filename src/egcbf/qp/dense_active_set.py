"""The per-agent QPs of :class:`~egcbf.qp.dense_qp.DenseBatchQP` solved exactly, all at once, by the dual active-set
method of Goldfarb and Idnani (1983), vectorized over the agents (numpy, float64).

Agent ``i``'s QP in ``z = (a (3), s)`` (:mod:`egcbf.qp.dense_qp`)::

    min  1/2 ||a - a_nom||^2 + 1/2 w2 s^2 + w1 s
    s.t. n_k . a + s >= b_k      (its CBF rows; padding rows have b_k <= -INF / 2)
         lo <= Cb a <= hi,  s >= 0

With ``y = S z``, ``S = diag(1, 1, 1, sqrt(w2))``, the Hessian is the identity and the QP is the Euclidean projection
of ``y0 = (a_nom, -w1 / sqrt(w2))`` onto the polyhedron ``A y >= b`` (``A = M S^-1`` for the rows ``M z >= b``).
The dual method starts at a dual-feasible point (here ``(a_nom, 0)`` with the row ``s >= 0`` active, multiplier
``w1``), adds the most violated row (violation over the row's norm) at every step and drops the active rows whose
multiplier would turn negative, until no row is violated. The active rows stay linearly independent, so at most
four are active: each agent's active set is padded to four slots (the Gram matrix of the active rows gets the
identity on its empty slots). A row that depends on the active ones gets the dual-only step of GI (a blocking row is
dropped; none: the QP is infeasible). The answer is then recomputed from the final active set's KKT system (the
projection of ``y0`` onto its affine hull), which is exact up to rounding.

This is the batched form of the exported runtime's single-agent :func:`egcbf.deploy.runtime.solve_qp` (same
selection rule and tolerances). Used by the run-time filters ``cbf`` and ``prior``
(:func:`egcbf.algo.edge_qp.edge_qp_commands`, ``FilterConfig.qp_solver = "active_set"``).
"""

from __future__ import annotations

import math

import numpy as np

from .dense_qp import DenseBatchQP
from .ipm import INF

__all__ = ["solve_dense_batch_active_set"]

#: an active row blocks the step when its multiplier's rate exceeds this (as the runtime's ``solve_qp``)
_BLOCK_TOL = 1e-14
#: a row depends on the active rows when its step's squared length is below this times its own squared norm
_DEPENDENT_TOL = 1e-24


def _solve(gram: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``gram^-1 rhs`` for ``gram`` ``(W, 4, 4)``, ``rhs`` ``(W, 4)``, and ``(W,)`` bool: where it failed (a
    singular matrix: numpy refuses the whole batch, so those are then solved one by one) or is not finite."""
    try:
        x = np.linalg.solve(gram, rhs[..., None])[..., 0]
        bad = np.zeros(len(x), dtype=bool)
    except np.linalg.LinAlgError:
        x = np.zeros_like(rhs)
        bad = np.zeros(len(x), dtype=bool)
        for i in range(len(x)):
            try:
                x[i] = np.linalg.solve(gram[i], rhs[i])
            except np.linalg.LinAlgError:
                bad[i] = True
    bad |= ~np.isfinite(x).all(-1)
    return np.where(bad[:, None], 0.0, x), bad


def _gram(na: np.ndarray, act: np.ndarray) -> np.ndarray:
    """The active rows' Gram matrix ``(W, 4, 4)``, the identity on the empty slots (whose rows are zero)."""
    g = na @ na.transpose(0, 2, 1)
    d = np.arange(4)
    g[:, d, d] += ~act
    return g


def solve_dense_batch_active_set(
    qps: DenseBatchQP, tol: float = 1e-12, max_iter: int = 60, device=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every per-agent QP of ``qps`` (module doc) by the batched dual active-set method; the returns of
    :func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`.

    Args:
        qps: ``M`` QPs: ``a_nom (M, 3)``, ``cbf_normal (M, K, 3)``, ``cbf_rhs (M, K)`` (rows with
            ``rhs <= -INF / 2`` are padding and ignored; so is a bound whose ``lo <= -INF / 2`` or ``hi >= INF / 2``),
            ``bound_C (M, Kb, 3)``, ``bound_lo, bound_hi (M, Kb)``, ``penalty`` (``w2 > 0``; ``w1 >= 0`` starts at
            ``s = 0``, a negative ``w1`` at the unconstrained minimizer).
        tol: a row counts as violated below ``-tol (1 + |b|)``.
        max_iter: active-set changes (one row added or dropped) allowed per agent.
        device: ignored (numpy on the CPU); the IPM's signature.

    Returns:
        ``z`` ``(M, 4)`` float64 ``(a, s)``, ``ok`` ``(M,)`` bool, ``iterations`` ``(M,)`` int64 (active-set changes;
        0 for the agents whose ``(a_nom, 0)`` is feasible, which is then their exact optimum). Where ``ok`` the
        result is the exact optimum up to rounding (all rows hold within ``tol (1 + |b|)`` before the final
        recomputation, whose multipliers are the method's non-negative ones). ``ok`` is False for an agent that
        did not converge within ``max_iter``, whose rows are infeasible (a violated row that depends on the active
        rows with no row to drop: a zero row with ``b > 0``, a box with ``lo > hi``), whose active rows' Gram matrix
        is singular, or whose result is not finite (its ``z`` is then the last iterate), and one whose data (other
        than padding and absent bounds) is not finite (unsolved: ``z = (a_nom, 0)``); the caller falls back.
    """
    w1, w2 = float(qps.penalty.w1), float(qps.penalty.w2)
    if not (math.isfinite(w1) and math.isfinite(w2) and w2 > 0):
        raise ValueError(f"solve_dense_batch_active_set needs a finite w1 and w2 > 0, got w1={w1!r}, w2={w2!r}")
    a_nom = np.asarray(qps.a_nom, dtype=np.float64)
    nrm = np.asarray(qps.cbf_normal, dtype=np.float64)
    rhs = np.asarray(qps.cbf_rhs, dtype=np.float64)
    bc = np.asarray(qps.bound_C, dtype=np.float64)
    blo = np.asarray(qps.bound_lo, dtype=np.float64)
    bhi = np.asarray(qps.bound_hi, dtype=np.float64)
    m_, k = rhs.shape
    kb = bc.shape[1]
    z = np.zeros((m_, 4))
    z[:, :3] = a_nom
    ok = np.ones(m_, dtype=bool)
    iters = np.zeros(m_, dtype=np.int64)
    if m_ == 0:
        return z, ok, iters
    pad = rhs <= -INF / 2
    lo_off, hi_off = blo <= -INF / 2, bhi >= INF / 2
    # agents whose (a_nom, s = 0) is feasible: the unconstrained minimizer over s >= 0, exactly (w1 >= 0)
    na_ = (nrm @ a_nom[:, :, None])[..., 0]
    ba_ = (bc @ a_nom[:, :, None])[..., 0]
    free = (pad | (na_ >= rhs)).all(1) & (lo_off | (ba_ >= blo)).all(1) & (hi_off | (ba_ <= bhi)).all(1)
    if w1 < 0:
        free[:] = False
    finite = (np.isfinite(a_nom).all(1) & np.isfinite(nrm).all((1, 2)) & (pad | np.isfinite(rhs)).all(1)
              & np.isfinite(bc).all((1, 2)) & ~np.isnan(blo).any(1) & ~np.isnan(bhi).any(1))  # fmt: skip
    ok &= finite  # (such an agent keeps z = (a_nom, 0), unsolved)
    hard = np.nonzero(~free & finite)[0]
    nh = hard.size
    if nh == 0:
        return z, ok, iters

    # rows A y >= b of the hard agents: CBF (K), Cb a >= lo (Kb), -Cb a >= -hi (Kb), s >= 0; inactive: b = -inf
    sw = math.sqrt(w2)
    m = k + 2 * kb + 1
    box = np.concatenate((bc[hard], np.zeros((nh, kb, 1))), 2)
    A = np.concatenate(
        (np.concatenate((nrm[hard], np.full((nh, k, 1), 1.0 / sw)), 2), box, -box,
         np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0 / sw]), (nh, 1, 4))), 1,
    )  # fmt: skip
    b = np.concatenate(
        (np.where(pad[hard], -np.inf, rhs[hard]), np.where(lo_off[hard], -np.inf, blo[hard]),
         np.where(hi_off[hard], -np.inf, -bhi[hard]), np.zeros((nh, 1))), 1,
    )  # fmt: skip
    norms = np.sqrt(np.einsum("wrd,wrd->wr", A, A))
    inv_norm = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    neg_tol = -tol * (1.0 + np.abs(b))
    y0 = np.concatenate((a_nom[hard], np.full((nh, 1), -w1 / sw)), 1)

    # the working set (compacted as agents finish; A, b... are indexed by wid): iterate, padded active set
    wid = np.arange(nh)  # index into the hard agents
    y = y0.copy()
    na = np.zeros((nh, 4, 4))  # the active rows, zero on the empty slots
    aidx = np.full((nh, 4), m)  # their rows (m: empty slot)
    act = np.zeros((nh, 4), dtype=bool)
    u = np.zeros((nh, 4))  # their multipliers
    if w1 >= 0:  # start at (a_nom, 0) with s >= 0 active: y - y0 = A_s' u with u = w1
        y[:, 3] = 0.0
        na[:, 0] = A[:, -1]
        aidx[:, 0] = m - 1
        act[:, 0] = True
        u[:, 0] = w1
    p = np.full(nh, -1)  # the row being added (-1: choose one)
    up = np.zeros(nh)  # its multiplier so far
    nit = np.zeros(nh, dtype=np.int64)
    # results per hard agent: final iterate, active rows and their right-hand sides, converged
    y_out = y.copy()
    na_out, act_out = na.copy(), act.copy()
    ba_out = np.zeros((nh, 4))
    conv_out = np.zeros(nh, dtype=bool)

    def retire(mask: np.ndarray, converged: bool) -> None:
        nonlocal wid, y, na, aidx, act, u, p, up, nit
        w = wid[mask]
        y_out[w], na_out[w], act_out[w] = y[mask], na[mask], act[mask]
        ba_out[w] = np.where(act[mask], np.take_along_axis(b[w], np.minimum(aidx[mask], m - 1), 1), 0.0)
        conv_out[w] = converged
        iters[hard[w]] = nit[mask]
        keep = ~mask
        wid, y, na, aidx, act, u, p, up, nit = (t[keep] for t in (wid, y, na, aidx, act, u, p, up, nit))

    for step in range(max_iter + 1):
        choose = p < 0
        if choose.any():  # the most violated row (over its norm) of the agents between additions
            every = bool(choose.all())
            sel = slice(None) if every else np.nonzero(choose)[0]
            rows = wid if every else wid[sel]
            full_set = every and rows.size == nh
            ys = y[sel]
            viol = np.empty((ys.shape[0], m + 1))
            viol[:, :m] = ((A if full_set else A[rows]) @ ys[:, :, None])[..., 0] - b[rows]
            np.put_along_axis(viol, aidx[sel], np.inf, 1)  # not the active rows (column m: the empty slots)
            viol = viol[:, :m]
            score = np.where(viol < neg_tol[rows], viol * inv_norm[rows], np.inf)
            pick = np.argmin(score, 1)
            p[sel] = pick
            done = np.zeros(len(p), dtype=bool)
            done[sel] = score[np.arange(len(pick)), pick] == np.inf
            if done.any():
                retire(done, True)
        if len(wid) == 0 or step == max_iter:
            break
        # one step of every agent: add row p (full step) or drop a blocking row (partial or dual-only step)
        w = np.arange(len(wid))
        n = A[wid, p]
        r, bad = _solve(_gram(na, act), (na @ n[:, :, None])[..., 0])
        stp = n - (r[:, None, :] @ na)[:, 0]
        blocking = act & (r > _BLOCK_TOL)
        ratio = np.where(blocking, u / np.where(blocking, r, 1.0), np.inf)
        kk = np.argmin(ratio, 1)
        t1 = ratio[w, kk]
        # (four independent active rows span R^4: then n depends on them whatever the rounding of stp)
        dep = act.all(1) | (np.einsum("wd,wd->w", stp, stp) <= _DEPENDENT_TOL * np.einsum("wd,wd->w", n, n))
        sn = np.einsum("wd,wd->w", stp, n)
        gap = np.einsum("wd,wd->w", n, y) - b[wid, p]
        t2 = np.where(dep, np.inf, -gap / np.where(dep, 1.0, sn))
        add = ~dep & (t2 <= t1)
        fail = bad | (dep & (t1 == np.inf))
        t = np.where(fail, 0.0, np.minimum(t1, t2))
        y = y + np.where(dep | fail, 0.0, t)[:, None] * stp
        u = u - t[:, None] * r
        up = up + t
        nit += 1
        drop = ~add & ~fail
        if drop.any():
            d = np.nonzero(drop)[0]
            kd = kk[d]
            act[d, kd] = False
            na[d, kd] = 0.0
            u[d, kd] = 0.0
            aidx[d, kd] = m
        add &= ~fail
        if add.any():
            a_ = np.nonzero(add)[0]
            slot = np.argmin(act[a_], 1)  # the first empty slot
            act[a_, slot] = True
            na[a_, slot] = n[a_]
            aidx[a_, slot] = p[a_]
            u[a_, slot] = up[a_]
            p[a_] = -1
            up[a_] = 0.0
        if fail.any():
            retire(fail, False)
    if len(wid):
        retire(np.ones(len(wid), dtype=bool), False)  # out of iterations

    # the exact projection of y0 onto the final active set's affine hull: y = y0 + Na' lam, Na y = b_a
    c = np.nonzero(conv_out)[0]
    if c.size:
        nc, ac = na_out[c], act_out[c]
        lam, bad = _solve(_gram(nc, ac), np.where(ac, ba_out[c] - (nc @ y0[c][:, :, None])[..., 0], 0.0))
        y_out[c] = np.where(bad[:, None], y_out[c], y0[c] + (lam[:, None, :] @ nc)[:, 0])
        conv_out[c] &= ~bad
    zh = y_out / np.array([1.0, 1.0, 1.0, sw])
    z[hard] = zh
    ok[hard] = conv_out & np.isfinite(zh).all(1)
    return z, ok, iters
