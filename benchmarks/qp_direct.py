"""The hand-written solver adapters egcbf used before it solved the centralized CBF-QP through qpsolvers, kept here
only so that ``benchmarks/qp_scaling.py --direct`` can measure qpsolvers' overhead against them in the same run
(issue 29). The library never imports this module; ``egcbf.qp.sparse_solvers`` is what solves.

Each adapter takes the :class:`egcbf.qp.sparse_qp.SparseQP` (two-sided rows ``l <= C z <= u`` and variable bounds)
and calls one solver's native Python API with the same tolerance and iteration budget as
``egcbf.qp.sparse_solvers.SETTINGS``. Copied from egcbf at commit e5a0b87 (``control/qp.py``).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from egcbf.qp.ipm import INF
from egcbf.qp.sparse_qp import SparseQP, _with_box_rows

__all__ = ["DIRECT", "solve_direct"]


def _solve_piqp(qp: SparseQP, eps_abs, max_iter, x0=None):
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


def _solve_proxsuite(qp: SparseQP, eps_abs, max_iter, x0=None):
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


def _solve_osqp(qp: SparseQP, eps_abs, max_iter, x0=None):
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


def _solve_clarabel(qp: SparseQP, eps_abs, max_iter, x0=None):
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


DIRECT = {"piqp": _solve_piqp, "proxsuite": _solve_proxsuite, "osqp": _solve_osqp, "clarabel": _solve_clarabel}


def solve_direct(
    qp: SparseQP, solver: str, eps_abs: float = 1e-7, max_iter: int = 1000
) -> tuple[np.ndarray, bool, float]:
    """``(x, ok, ms)`` of the pre-qpsolvers adapter of ``solver`` (wall time of setup + solve)."""
    t0 = time.perf_counter()
    x, ok, _, _ = DIRECT[solver](qp, eps_abs, max_iter, None)
    return x, ok, 1e3 * (time.perf_counter() - t0)
