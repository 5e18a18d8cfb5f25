"""QP plumbing for the CBF-QP baselines: sparse assembly of the centralized QP, batched dense per-agent QPs, solvers.

Centralized QP of one environment (``N`` agents, ``S`` CBF rows), variables ``z = [a (3N), s (S)]``:

    min  1/2 sum_i ||a_i - a_nom,i||^2 + sum_c (1/2 w2 s_c^2 + w1 s_c)
    s.t. n_c . (a_{i_c} - a_{j_c}) + s_c >= b_c        (CBF rows, one slack each)
         s_c >= 0
         lo <= C_i a_i <= hi                             (acceleration bounds, hard)

It is always feasible (``s`` absorbs any CBF conflict, the bounds contain ``a = 0``). The L1 weight ``w1`` is an exact
penalty: when the CBF rows are jointly feasible and ``w1`` exceeds their multipliers, the slack is zero; ``w2`` keeps
the Hessian positive definite. All matrices are built at once from edge lists (COO -> CSC), no loop over agents.

Per-agent (decentralized) QP, variables ``(a_i (3), s_i (1))``: same cost with one slack shared by agent ``i``'s rows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .barriers import Constraints

__all__ = [
    "SOLVERS",
    "DenseBatchQP",
    "SlackPenalty",
    "SolveResult",
    "SparseQP",
    "assemble_centralized",
    "assemble_decentralized",
    "dense_reference",
    "polish_sparse",
    "require_solver",
    "solve_batch_ipm",
    "solve_dense_batch",
    "solve_dense_batch_ipm",
    "solve_sparse",
]

INF = 1e20  # proxsuite's and OSQP's "no bound"
LOOSE_TOL = 1e-7  # batched IPM: tolerance accepted when double precision breaks down before ``tol`` is reached

SOLVERS = ("piqp", "proxsuite", "osqp", "clarabel")


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


@dataclass
class SolveResult:
    x: np.ndarray
    ok: bool
    status: str
    iterations: int
    solve_ms: float


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


#: the optional solvers and how to get them (piqp and proxsuite are core dependencies)
_EXTRA_SOLVERS = {"osqp": "osqp>=0.6", "clarabel": "clarabel>=0.7"}


def require_solver(name: str) -> None:
    """Raise ``ValueError`` for an unknown solver name and ``ImportError`` (saying how to install it) for a known
    solver whose package is missing: ``osqp`` and ``clarabel`` come with the ``solvers`` extra."""
    import importlib.util

    if name not in SOLVERS:
        raise ValueError(f"unknown QP solver {name!r}; choose one of {SOLVERS}")
    if importlib.util.find_spec(name) is None:
        hint = (
            f"pip install -e '.[solvers]' (or pip install '{_EXTRA_SOLVERS[name]}')"
            if name in _EXTRA_SOLVERS
            else (f"pip install {name}")
        )
        raise ImportError(f"QP solver {name!r} is not installed: {hint}")


def solve_sparse(
    qp: SparseQP,
    solver: str = "piqp",
    eps_abs: float = 1e-6,
    max_iter: int = 1000,
    x0: np.ndarray | None = None,
) -> SolveResult:
    """Solve a :class:`SparseQP`; never raises on a solver failure (``ok=False`` instead)."""
    require_solver(solver)
    t0 = time.perf_counter()
    try:
        x, ok, status, it = _SPARSE[solver](qp, eps_abs, max_iter, x0)
    except ImportError:
        raise
    except Exception as exc:  # a solver crash is a failed solve, never an exception for the caller
        x, ok, status, it = None, False, f"error: {type(exc).__name__}: {exc}", 0
    ms = 1e3 * (time.perf_counter() - t0)
    if x is None or x.shape != (qp.H.shape[0],) or not np.all(np.isfinite(x)):
        return SolveResult(np.full(qp.H.shape[0], np.nan), False, status, it, ms)
    return SolveResult(x, ok, status, it, ms)


def _solve_piqp(qp: SparseQP, eps_abs, max_iter, x0):
    import piqp

    solver = piqp.SparseSolver()
    st = solver.settings
    st.eps_abs = eps_abs
    st.eps_rel = 0.0
    st.max_iter = max_iter
    st.verbose = False
    inf = np.inf
    solver.setup(
        qp.H,
        qp.g,
        None,
        None,
        qp.C,
        np.where(qp.l <= -INF / 2, -inf, qp.l),
        np.where(qp.u >= INF / 2, inf, qp.u),
        np.where(qp.x_l <= -INF / 2, -inf, qp.x_l),
        np.where(qp.x_u >= INF / 2, inf, qp.x_u),
    )
    status = solver.solve()
    ok = status == piqp.PIQP_SOLVED
    return np.array(solver.result.x), ok, str(status).split(".")[-1], int(solver.result.info.iter)


def _solve_proxsuite(qp: SparseQP, eps_abs, max_iter, x0):
    from proxsuite import proxqp

    C, lo, hi = _with_box_rows(qp)
    n, m = qp.H.shape[0], C.shape[0]
    solver = proxqp.sparse.QP(n, 0, m)
    st = solver.settings
    st.eps_abs = eps_abs
    st.eps_rel = 0.0
    st.max_iter = max_iter
    st.verbose = False
    solver.init(qp.H, qp.g, None, None, C, lo, hi)
    if x0 is not None:
        st.initial_guess = proxqp.InitialGuess.WARM_START
        solver.solve(x0, None, None)
    else:
        solver.solve()
    res = solver.results
    status = res.info.status
    ok = status == proxqp.QPSolverOutput.PROXQP_SOLVED
    return np.array(res.x), ok, status.name, int(res.info.iter)


def _solve_osqp(qp: SparseQP, eps_abs, max_iter, x0):
    import osqp

    C, lo, hi = _with_box_rows(qp)
    big = osqp.constant("OSQP_INFTY")
    prob = osqp.OSQP()
    prob.setup(
        P=sp.triu(qp.H, format="csc"),
        q=qp.g,
        A=C,
        l=np.maximum(lo, -big),
        u=np.minimum(hi, big),
        eps_abs=eps_abs,
        eps_rel=0.0,
        max_iter=max_iter * 20,
        polishing=True,
        verbose=False,
    )
    if x0 is not None:
        prob.warm_start(x=x0)
    res = prob.solve()
    status = res.info.status
    return np.asarray(res.x, dtype=np.float64), status == "solved", status, int(res.info.iter)


def _solve_clarabel(qp: SparseQP, eps_abs, max_iter, x0):
    import clarabel

    C, lo, hi = _with_box_rows(qp)
    up = hi < INF / 2
    dn = lo > -INF / 2
    A = sp.vstack([C[up], -C[dn]], format="csc")
    b = np.concatenate([hi[up], -lo[dn]])
    st = clarabel.DefaultSettings()
    st.verbose = False
    st.tol_feas = eps_abs
    st.tol_gap_abs = eps_abs
    st.max_iter = max_iter
    sol = clarabel.DefaultSolver(sp.triu(qp.H, format="csc"), qp.g, A, b, [clarabel.NonnegativeConeT(b.size)], st)
    res = sol.solve()
    status = str(res.status)
    return np.asarray(res.x, dtype=np.float64), status == "Solved", status, int(res.iterations)


_SPARSE = {"piqp": _solve_piqp, "proxsuite": _solve_proxsuite, "osqp": _solve_osqp, "clarabel": _solve_clarabel}


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


# ---------------------------------------------------------------------------------------------------------------
# decentralized: one small dense QP per agent


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
    penalty: SlackPenalty = SlackPenalty(),
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


def _mv(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Batched ``A @ x``: ``(M, r, c) x (M, c) -> (M, r)``."""
    return (A @ x[..., None])[..., 0]


def _mtv(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Batched ``A' @ y``: ``(M, r, c) x (M, r) -> (M, c)``."""
    return (y[..., None, :] @ A)[..., 0, :]


def _cholesky(K: np.ndarray) -> np.ndarray:
    """Batched Cholesky factor of small SPD matrices ``(M, n, n)``; never raises: a non-positive pivot gives NaN
    in that QP only (it is then reported as not converged)."""
    n = K.shape[-1]
    L = np.zeros_like(K)
    for j in range(n):
        d = K[:, j, j] - (L[:, j, :j] ** 2).sum(1)
        ljj = np.sqrt(np.where(d > 0, d, np.nan))
        L[:, j, j] = ljj
        if j + 1 < n:
            L[:, j + 1 :, j] = (K[:, j + 1 :, j] - (L[:, j + 1 :, :j] * L[:, j, None, :j]).sum(-1)) / ljj[:, None]
    return L


def _chol_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``L L' x = b`` for a batch of small lower-triangular ``L`` ``(M, n, n)`` by substitution."""
    n = L.shape[-1]
    y = np.empty_like(b)
    for i in range(n):
        y[:, i] = (b[:, i] - (L[:, i, :i] * y[:, :i]).sum(1)) / L[:, i, i]
    x = np.empty_like(b)
    for i in range(n - 1, -1, -1):
        x[:, i] = (y[:, i] - (L[:, i + 1 :, i] * x[:, i + 1 :]).sum(1)) / L[:, i, i]
    return x


def _polish(P, q, G, h, x, s, z):
    """Active-set polishing (as OSQP's): guess the active rows (``z > s``), solve the equality-constrained QP's KKT
    system, and keep the result where it is primal feasible with non-negative multipliers (exact to rounding)."""
    mq, m, n = G.shape
    act = z > s
    Ga = G * act[..., None]
    K = np.zeros((mq, n + m, n + m))
    K[:, :n, :n] = P
    K[:, :n, n:] = np.swapaxes(Ga, -1, -2)
    K[:, n:, :n] = Ga
    diag = np.where(act, -1e-12, 1.0)
    K[:, np.arange(n, n + m), np.arange(n, n + m)] = diag
    rhs = np.concatenate([-q, np.where(act, h, 0.0)], axis=1)
    try:
        sol = np.linalg.solve(K, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return x, np.zeros(mq, dtype=bool)
    xp, lam = sol[:, :n], sol[:, n:]
    scale = 1.0 + np.where(np.abs(h) < INF / 2, np.abs(h), 0.0).max(1, initial=0.0)
    good = (
        np.isfinite(sol).all(1)
        & ((_mv(G, xp) - h).max(1, initial=-1.0) <= 1e-10 * scale)
        & (lam.min(1, initial=0.0) >= -1e-10 * scale)
    )
    return np.where(good[:, None], xp, x), good


def solve_batch_ipm(
    P: np.ndarray,
    q: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    x0: np.ndarray | None = None,
    tol: float = 1e-12,
    max_iter: int = 60,
    polish: bool = True,
    feas_tol: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectorized primal-dual interior-point method (Mehrotra predictor-corrector) for ``M`` small QPs

        min 1/2 x'Px + q'x   s.t.  G x <= h,       P (n, n) shared or (M, n, n), q (M, n), G (M, m, n), h (M, m)

    all advanced together (numpy, no loop over QPs). Rows that are all zero with ``h > 0`` are inactive padding.
    Converged QPs stop moving. ``x0`` should be strictly feasible (``G x0 < h``) where possible (an infeasible
    start also works: the method handles primal residuals).

    A QP has converged when ``||P x + q + G'z||_inf <= feas_tol max(1 + ||q||, ||P x||, ||G'z||)``,
    ``||max(G x - h, 0)||_inf <= feas_tol (1 + ||h||)`` and the mean complementarity ``s'z / m <= tol (1 + ||q||)``
    (infinity norms; the dual residual cannot go much below 1e-9 relative in double precision once ``z / s`` is
    huge). If rounding breaks the iteration down (NaN) or ``max_iter`` is reached, the last iterate is kept and
    accepted only if it meets ``LOOSE_TOL`` in all three. Returns ``x (M, n)``,
    ``converged (M,)``, ``iterations (M,)``. With ``polish`` the converged solutions are refined by one active-set
    KKT solve (kept only where it is feasible with non-negative multipliers), which makes them exact to rounding.
    """
    mq, n = q.shape
    m = G.shape[1]
    P = np.broadcast_to(P, (mq, n, n))
    x = np.zeros((mq, n)) if x0 is None else np.array(x0, dtype=np.float64)
    s = np.maximum(h - _mv(G, x), 1.0)  # positive start (infeasible-start IPM: r_p absorbs the shift)
    z = np.ones((mq, m))
    scale_d = 1.0 + np.abs(q).max(1, initial=0.0)
    scale_p = 1.0 + np.where(np.abs(h) < INF / 2, np.abs(h), 0.0).max(1, initial=0.0)
    done = np.zeros(mq, dtype=bool)
    iters = np.zeros(mq, dtype=np.int64)
    eye = np.eye(n)
    idx = np.arange(mq)  # the working set: QPs still iterating (compacted as they converge)
    Pw, qw, Gw, hw, sd, sp_ = P, q, G, h, scale_d, scale_p
    xw, sw, zw = x, s, z

    def converged(xw, sw, zw, Pw, qw, Gw, hw, sd, sp_, tol=tol, feas_tol=feas_tol):
        Gx = _mv(Gw, xw)
        Px, Gz = _mv(Pw, xw), _mtv(Gw, zw)
        r_d = Px + qw + Gz
        r_p = Gx + sw - hw
        mu = (sw * zw).sum(1) / m
        dual_scale = np.maximum(sd, np.maximum(np.abs(Px).max(1), np.abs(Gz).max(1)))  # relative, as OSQP's
        conv = (
            (np.abs(r_d).max(1) <= feas_tol * dual_scale)
            & (np.maximum(Gx - hw, 0.0).max(1) <= feas_tol * sp_)
            & (mu <= tol * sd)
        )
        return conv, r_d, r_p, mu

    def max_step(v, dv):
        neg = dv < 0
        ratio = np.divide(-v, dv, out=np.full_like(v, np.inf), where=neg)
        return np.minimum(1.0, ratio.min(1))

    for _ in range(max_iter + 1):
        conv, r_d, r_p, mu = converged(xw, sw, zw, Pw, qw, Gw, hw, sd, sp_)
        if conv.any():
            x[idx], s[idx], z[idx] = xw, sw, zw
            done[idx[conv]] = True
            keep = ~conv
            idx = idx[keep]
            if idx.size == 0:
                break
            Pw, qw, Gw, hw, sd, sp_ = Pw[keep], qw[keep], Gw[keep], hw[keep], sd[keep], sp_[keep]
            xw, sw, zw, r_d, r_p, mu = xw[keep], sw[keep], zw[keep], r_d[keep], r_p[keep], mu[keep]
        if _ == max_iter:
            break
        iters[idx] += 1
        w = zw / sw
        Kc = _cholesky(Pw + np.swapaxes(Gw, -1, -2) @ (w[..., None] * Gw) + 1e-14 * eye)

        def newton(rc, Gw=Gw, w=w, Kc=Kc, r_d=r_d, r_p=r_p, sw=sw, zw=zw):
            t = r_p + rc / zw
            dx = _chol_solve(Kc, -r_d - _mtv(Gw, w * t))
            dz = w * (_mv(Gw, dx) + t)
            return dx, (rc - sw * dz) / zw, dz

        # Mehrotra predictor-corrector
        dx, ds, dz = newton(-sw * zw)
        alpha = np.minimum(max_step(sw, ds), max_step(zw, dz))[:, None]
        mu_aff = ((sw + alpha * ds) * (zw + alpha * dz)).sum(1) / m
        sigma = (mu_aff / np.maximum(mu, 1e-300)) ** 3
        rc = -sw * zw - ds * dz + (sigma * mu)[:, None]
        dx, ds, dz = newton(rc)
        alpha = 0.99 * np.minimum(max_step(sw, ds), max_step(zw, dz))
        # safeguard (Mehrotra's corrector can cycle): where the corrected step does not reduce the complementarity
        # enough, take a plain centred Newton step (sigma >= 0.1, no second-order term) instead
        mu_new = ((sw + alpha[:, None] * ds) * (zw + alpha[:, None] * dz)).sum(1) / m
        weak = mu_new > (1.0 - 0.1 * alpha) * mu
        if weak.any():
            dx2, ds2, dz2 = newton(-sw * zw + (np.maximum(sigma, 0.1) * mu)[:, None])
            alpha2 = 0.99 * np.minimum(max_step(sw, ds2), max_step(zw, dz2))
            wk = weak[:, None]
            dx, ds, dz = np.where(wk, dx2, dx), np.where(wk, ds2, ds), np.where(wk, dz2, dz)
            alpha = np.where(weak, alpha2, alpha)
        alpha = alpha[:, None]
        xn = xw + alpha * dx
        sn = np.maximum(sw + alpha * ds, 1e-300)
        zn = np.maximum(zw + alpha * dz, 1e-300)
        # numerical breakdown (at the limit of double precision, w = z / s ~ 1e16): stop that QP at its last
        # iterate, accepted only if it meets a looser tolerance
        bad = ~(np.isfinite(xn).all(1) & np.isfinite(sn).all(1) & np.isfinite(zn).all(1))
        if bad.any():
            loose, *_ = converged(
                xw[bad], sw[bad], zw[bad], Pw[bad], qw[bad], Gw[bad], hw[bad], sd[bad], sp_[bad], LOOSE_TOL, LOOSE_TOL
            )
            bi = idx[bad]
            x[bi], s[bi], z[bi] = xw[bad], sw[bad], zw[bad]
            done[bi] = loose
            keep = ~bad
            idx = idx[keep]
            if idx.size == 0:
                break
            Pw, qw, Gw, hw, sd, sp_ = Pw[keep], qw[keep], Gw[keep], hw[keep], sd[keep], sp_[keep]
            xn, sn, zn = xn[keep], sn[keep], zn[keep]
        xw, sw, zw = xn, sn, zn
    if idx.size:  # out of iterations: accept what meets the loose tolerance
        x[idx], s[idx], z[idx] = xw, sw, zw
        done[idx], *_ = converged(xw, sw, zw, Pw, qw, Gw, hw, sd, sp_, LOOSE_TOL, LOOSE_TOL)
    if polish:
        sel = np.nonzero(done)[0]
        if sel.size:
            x[sel], _ = _polish(P[sel], q[sel], G[sel], h[sel], x[sel], s[sel], z[sel])
    ok = done & np.isfinite(x).all(1)
    return x, ok, iters


def solve_dense_batch_ipm(qps: DenseBatchQP, tol: float = 1e-12, max_iter: int = 60):
    """Per-agent QPs of :class:`DenseBatchQP` with :func:`solve_batch_ipm`; same returns as :func:`solve_dense_batch`.

    Agents whose nominal ``(a_nom, s = 0)`` satisfies all their rows are solved exactly (it is the unconstrained
    minimizer); the others start from the strictly feasible ``a = 0`` (hover, inside the bounds) with
    ``s = max(0, max_k b_k) + 1``.
    """
    m_ = len(qps)
    k = qps.cbf_normal.shape[1]
    w2, w1 = qps.penalty.w2, qps.penalty.w1
    # one-sided rows G z <= h: -(n.a + s) <= -b (CBF), +-Cb a <= hi / -lo (bounds), -s <= 0
    kb = qps.bound_C.shape[1]
    G = np.zeros((m_, k + 2 * kb + 1, 4))
    G[:, :k, :3] = -qps.cbf_normal
    G[:, :k, 3] = -1.0
    G[:, k : k + kb, :3] = qps.bound_C
    G[:, k + kb : k + 2 * kb, :3] = -qps.bound_C
    G[:, -1, 3] = -1.0
    pad = qps.cbf_rhs <= -INF / 2
    G[:, :k][pad] = 0.0
    h = np.concatenate([np.where(pad, 1.0, -qps.cbf_rhs), qps.bound_hi, -qps.bound_lo, np.zeros((m_, 1))], axis=1)
    P = np.diag([1.0, 1.0, 1.0, w2])
    q = np.concatenate([-qps.a_nom, np.full((m_, 1), w1)], axis=1)
    z = np.zeros((m_, 4))
    z[:, :3] = qps.a_nom
    free = (_mv(G, z) <= h).all(1)
    ok = np.ones(m_, dtype=bool)
    it = np.zeros(m_, dtype=np.int64)
    hard = np.nonzero(~free)[0]
    if hard.size:
        x0 = np.zeros((hard.size, 4))
        x0[:, 3] = np.maximum(0.0, np.where(pad[hard], 0.0, qps.cbf_rhs[hard]).max(1, initial=0.0)) + 1.0
        z[hard], ok[hard], it[hard] = solve_batch_ipm(P, q[hard], G[hard], h[hard], x0=x0, tol=tol, max_iter=max_iter)
    return z, ok, it
