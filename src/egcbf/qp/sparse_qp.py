"""The centralized CBF-QP (cCBF-QP baseline): sparse assembly, solving (any sparse solver, through qpsolvers:
:mod:`egcbf.qp.sparse_solvers`), active-set polishing.

Centralized QP of one environment (``N`` agents, ``S`` CBF rows), variables ``z = [a (3N), s (S)]``:

    min  1/2 sum_i ||a_i - a_nom,i||^2 + sum_c (1/2 w2 s_c^2 + w1 s_c)
    s.t. n_c . (a_{i_c} - a_{j_c}) + s_c >= b_c        (CBF rows, one slack each)
         s_c >= 0
         lo <= C_i a_i <= hi                             (acceleration bounds, hard)

It is always feasible (``s`` absorbs any CBF conflict, the bounds contain ``a = 0``). The L1 weight ``w1`` is an exact
penalty: when the CBF rows are jointly feasible and ``w1`` exceeds their multipliers, the slack is zero; ``w2`` keeps
the Hessian positive definite. All matrices are built at once from edge lists (COO -> CSC), no loop over agents.

The decentralized baseline's per-agent QPs (same cost, one slack per agent) are in :mod:`egcbf.qp.dense_qp`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .constraints import Constraints
from .ipm import INF
from .sparse_solvers import SolveResult, require_solver, solve_with_qpsolvers

__all__ = [
    "INF",
    "SOLVERS",
    "SlackPenalty",
    "SolveResult",
    "SparseQP",
    "assemble_centralized",
    "dense_reference",
    "polish_sparse",
    "require_solver",
    "solve_sparse",
]

#: the solvers egcbf tests and sets tolerances for (:data:`egcbf.qp.sparse_solvers.SETTINGS`; ``"proxsuite"`` is
#: qpsolvers' ``"proxqp"``): piqp and proxsuite are core dependencies, the others come with the ``solvers`` extra. Any
#: other solver qpsolvers lists works too, with its own default settings.
SOLVERS = ("piqp", "proxsuite", "osqp", "clarabel", "highs", "qpalm")


@dataclass(frozen=True)
class SlackPenalty:
    """Slack cost ``1/2 w2 s^2 + w1 s`` (s in m/s^2, the acceleration cost is ``1/2 ||a - a_nom||^2``)."""

    w1: float = 1e3
    w2: float = 1e2


@dataclass
class SparseQP:
    """``min 1/2 z'Hz + g'z  s.t.  l <= C z <= u, x_l <= z <= x_u`` with ``z = [a (3 N), s (S)]``; CSC matrices."""

    H: sp.csc_matrix
    g: np.ndarray
    C: sp.csc_matrix
    l: np.ndarray
    u: np.ndarray
    x_l: np.ndarray
    x_u: np.ndarray
    num_agents: int
    num_slack: int


def assemble_centralized(
    a_nom: np.ndarray,
    cons: Constraints,
    bound_C: np.ndarray,
    bound_lo: np.ndarray,
    bound_hi: np.ndarray,
    penalty: SlackPenalty = SlackPenalty(),
) -> SparseQP:
    """Sparse centralized QP for ``N`` agents (``a_nom`` ``(N, 3)``), rows ``cons``, bounds ``(N, K, 3)``.

    Bound rows that act on a single coordinate (the vertical bound ``lo <= a_z <= hi``) become variable bounds
    ``x_l <= z <= x_u``, as does ``s >= 0``; the others (the horizontal polygon) are rows of ``C``.
    """
    n = a_nom.shape[0]
    s = len(cons)
    na = 3 * n
    nz = na + s
    H = sp.diags(np.concatenate([np.ones(na), np.full(s, penalty.w2)]), format="csc")
    g = np.concatenate([-a_nom.reshape(-1), np.full(s, penalty.w1)])

    rows, cols, vals = [], [], []
    r = np.arange(s)
    # CBF rows: n . a_i (3 entries), -n . a_j (3 entries, pairs only), + s_c
    rows.append(np.repeat(r, 3))
    cols.append((3 * cons.i[:, None] + np.arange(3)).reshape(-1))
    vals.append(cons.normal.reshape(-1))
    pair = cons.j >= 0
    rows.append(np.repeat(r[pair], 3))
    cols.append((3 * cons.j[pair, None] + np.arange(3)).reshape(-1))
    vals.append(-cons.normal[pair].reshape(-1))
    rows.append(r)
    cols.append(na + r)
    vals.append(np.ones(s))

    # bounds: single-coordinate rows -> variable bounds; the rest -> rows with their non-zero coefficients
    x_l = np.concatenate([np.full(na, -INF), np.zeros(s)])
    x_u = np.full(nz, INF)
    nnz_per_row = (bound_C != 0.0).sum(-1)  # (N, K)
    single = (nnz_per_row == 1).all(0)  # same structure for every agent
    ks, km = np.nonzero(single)[0], np.nonzero(~single)[0]
    if ks.size:
        dim = np.argmax(bound_C[:, ks] != 0.0, axis=-1)  # (N, ks)
        coef = np.take_along_axis(bound_C[:, ks], dim[..., None], -1)[..., 0]
        if np.any(coef <= 0):
            raise ValueError("single-coordinate bound rows need a positive coefficient")
        var = 3 * np.arange(n)[:, None] + dim
        np.maximum.at(x_l, var.reshape(-1), (bound_lo[:, ks] / coef).reshape(-1))
        np.minimum.at(x_u, var.reshape(-1), (bound_hi[:, ks] / coef).reshape(-1))
    bc = bound_C[:, km]
    k = km.size
    br = s + np.arange(n * k).reshape(n, k)
    ag, kk, dd = np.nonzero(bc != 0.0)
    rows.append(br[ag, kk])
    cols.append(3 * ag + dd)
    vals.append(bc[ag, kk, dd])
    m = s + n * k
    C = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(m, nz),
    )
    lo = np.concatenate([cons.rhs, bound_lo[:, km].reshape(-1)])
    hi = np.concatenate([np.full(s, INF), bound_hi[:, km].reshape(-1)])
    return SparseQP(H, g, C, lo, hi, x_l, x_u, n, s)


def _with_box_rows(qp: SparseQP) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
    """``C, l, u`` with the finite variable bounds appended as identity rows (for solvers without box support)."""
    idx = np.nonzero((qp.x_l > -INF / 2) | (qp.x_u < INF / 2))[0]
    eye = sp.csc_matrix((np.ones(idx.size), (np.arange(idx.size), idx)), shape=(idx.size, qp.C.shape[1]))
    return (
        sp.vstack([qp.C, eye], format="csc"),
        np.concatenate([qp.l, qp.x_l[idx]]),
        np.concatenate([qp.u, qp.x_u[idx]]),
    )


def dense_reference(qp: SparseQP) -> tuple[np.ndarray, ...]:
    """Dense ``H, g, C, l, u`` (variable bounds as rows): for tests on small problems."""
    C, lo, hi = _with_box_rows(qp)
    return qp.H.toarray(), qp.g.copy(), C.toarray(), lo, hi


def solve_sparse(
    qp: SparseQP,
    solver: str = "piqp",
    eps_abs: float = 1e-6,
    max_iter: int = 1000,
    x0: np.ndarray | None = None,
) -> SolveResult:
    """Solve a :class:`SparseQP` with ``solver`` (any of ``qpsolvers.available_solvers``, or ``"proxsuite"``) through
    :mod:`egcbf.qp.sparse_solvers`; never raises on a solver failure (``ok=False`` instead). ``ImportError`` /
    ``ValueError`` for a solver that is not installed / not known (:func:`require_solver`)."""
    return solve_with_qpsolvers(qp, solver, eps_abs, max_iter, x0)


def polish_sparse(
    qp: SparseQP, x: np.ndarray, active_tols: tuple[float, ...] = (1e-7, 1e-5), tol: float = 1e-9
) -> tuple[np.ndarray, bool]:
    """Active-set polishing of an approximate solution ``x`` (as OSQP's): rows and variable bounds within
    ``active_tol`` (relative) of a bound are made equalities and the KKT system
    ``[H A'; A 0] [x; nu] = [-g; b]`` is solved (``H`` diagonal: through its Schur complement ``A H^-1 A'``,
    sparse LU of it + 1e-12 I, refined). The result is kept only
    if it is feasible (``tol``, relative) and every multiplier has the sign of its bound, i.e. it satisfies the KKT
    conditions of the QP: it is the exact optimum, to rounding. The guesses ``active_tols`` are tried in turn;
    if none passes, ``x`` is returned unchanged. Returns ``(x, polished)``.
    """
    C, lo, hi = _with_box_rows(qp)
    cx = C @ x
    sl, su = 1.0 + np.abs(lo), 1.0 + np.abs(np.minimum(hi, INF))
    scale = 1.0 + np.abs(qp.g).max(initial=0.0)
    hd = qp.H.diagonal()
    if qp.H.nnz != np.count_nonzero(hd) or np.any(hd <= 0):
        raise ValueError("polish_sparse needs a positive diagonal H")
    hinv = 1.0 / hd
    tried = set()
    for active_tol in active_tols:
        act_lo = (lo > -INF / 2) & (cx - lo <= active_tol * sl)
        act_hi = (hi < INF / 2) & (hi - cx <= active_tol * su) & ~act_lo
        act = np.nonzero(act_lo | act_hi)[0]
        key = (act.tobytes(), act_lo[act].tobytes())
        if key in tried:
            continue
        tried.add(key)
        # H is diagonal: eliminate x, (A H^-1 A') nu = -A H^-1 g - b, x = -H^-1 (g + A' nu); the factorization
        # is regularized (+1e-12 I, for dependent active rows) and refined against the exact system
        A = C[act].tocsc()
        b = np.where(act_lo[act], lo[act], hi[act])
        S0 = (A @ sp.diags(hinv) @ A.T).tocsc()
        rhs = -(A @ (hinv * qp.g)) - b
        nu = np.zeros(act.size)
        if act.size:
            try:
                lu = spla.splu((S0 + 1e-12 * sp.eye(act.size)).tocsc(), permc_spec="MMD_AT_PLUS_A")
            except (RuntimeError, ValueError):
                continue
            for _ in range(3):  # iterative refinement towards the unregularized system
                nu = nu + lu.solve(rhs - S0 @ nu)
        xp = -hinv * (qp.g + A.T @ nu)
        if not (np.all(np.isfinite(xp)) and np.all(np.isfinite(nu))):
            continue
        cp = C @ xp
        feasible = np.all(cp - lo >= -tol * sl) and np.all(hi - cp >= -tol * su)
        signs = np.all(nu[act_lo[act]] <= tol * scale) and np.all(nu[act_hi[act]] >= -tol * scale)
        if feasible and signs:
            return xp, True
    return x, False
