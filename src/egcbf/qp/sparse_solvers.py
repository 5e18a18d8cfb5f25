"""Solving the centralized CBF-QP (:class:`~egcbf.qp.sparse_qp.SparseQP`) with any sparse QP solver, through
`qpsolvers <https://qpsolvers.github.io/qpsolvers/>`_.

``qpsolvers`` gives one calling convention, ``min 1/2 x'Px + q'x  s.t.  G x <= h, A x = b, lb <= x <= ub``, to some
twenty solvers and keeps up with their APIs. What it does not know, and this module adds in one place:

* the QP's two-sided rows ``l <= C z <= u`` become ``G = [C_u; -C_l]`` (only the finite sides), the variable bounds
  go to ``lb, ub`` (``+-inf`` where unbounded);
* the tolerance and iteration limit are mapped to each solver's own setting names (:data:`SETTINGS`); a solver not
  listed there runs with its defaults, so ``eps_abs`` and ``max_iter`` do not reach it;
* the outcome is a :class:`~egcbf.qp.sparse_qp.SolveResult`: a failed or crashed solve is ``ok=False`` with a status
  (never an exception for the caller), the iteration count where the solver reports one (else -1);
* names: ``solver`` is any of ``qpsolvers.available_solvers``; ``"proxsuite"`` is kept as an alias of
  qpsolvers' ``"proxqp"``; a known solver that is not installed is named with its pip package, an unknown name with
  the installed ones.

The active-set polish of a solution (:func:`~egcbf.qp.sparse_qp.polish_sparse`) stays on top of whatever solver
returned it. The decentralized QPs (the dCBF-QP, the run-time filters, the learned CBF's QP target) do not go
through here: they are one batched interior-point solve in torch (:mod:`egcbf.qp.dense_qp`,
:mod:`egcbf.qp.ipm`), which runs on a GPU and over thousands of small QPs at once, which no qpsolvers
backend does.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from .ipm import INF

#: a :class:`egcbf.qp.sparse_qp.SparseQP` (not imported here: qp imports this module)
SparseQP = Any

__all__ = [
    "ALIASES",
    "PIP_PACKAGES",
    "SETTINGS",
    "SolveResult",
    "available_solvers",
    "require_solver",
    "solve_with_qpsolvers",
]


@dataclass
class SolveResult:
    """A solve's ``x`` (NaN if it failed), whether the solver reports it solved (``ok``), its ``status``, its
    ``iterations`` (-1 if the solver does not report them) and its wall time (ms)."""

    x: np.ndarray
    ok: bool
    status: str
    iterations: int
    solve_ms: float


#: names egcbf accepted before it used qpsolvers -> qpsolvers' name
ALIASES = {"proxsuite": "proxqp"}

#: qpsolvers' solver names -> the pip package that provides each (for the error of a missing one)
PIP_PACKAGES = {
    "clarabel": "clarabel", "cvxopt": "cvxopt", "daqp": "daqp", "ecos": "ecos", "gurobi": "gurobipy",
    "highs": "highspy", "hpipm": "hpipm_python", "kvxopt": "kvxopt", "mosek": "mosek", "osqp": "osqp",
    "piqp": "piqp", "proxqp": "proxsuite", "qpalm": "qpalm", "qpoases": "qpoases", "qpswift": "qpswift",
    "quadprog": "quadprog", "scs": "scs", "sip": "sip-python",
}  # fmt: skip


def _settings_piqp(eps: float, it: int) -> dict:
    return {"eps_abs": eps, "eps_rel": 0.0, "max_iter": it}


def _settings_osqp(eps: float, it: int) -> dict:
    return {"eps_abs": eps, "eps_rel": 0.0, "max_iter": 20 * it, "polishing": True}


def _settings_clarabel(eps: float, it: int) -> dict:
    return {"tol_feas": eps, "tol_gap_abs": eps, "max_iter": it}


def _settings_scs(eps: float, it: int) -> dict:
    return {"eps_abs": eps, "eps_rel": 0.0, "max_iters": 100 * it}


def _settings_highs(eps: float, it: int) -> dict:
    return {"primal_feasibility_tolerance": eps, "dual_feasibility_tolerance": eps, "output_flag": False}


#: solver -> its settings for ``(eps_abs, max_iter)``: the same tolerance (absolute, no relative part) and iteration
#: budget as the adapters egcbf had before (first-order solvers get more iterations, as their iterations are cheaper)
SETTINGS = {
    "piqp": _settings_piqp,
    "proxqp": _settings_piqp,
    "qpalm": _settings_piqp,
    "osqp": _settings_osqp,
    "clarabel": _settings_clarabel,
    "scs": _settings_scs,
    "highs": _settings_highs,
}


def available_solvers() -> list[str]:
    """The solvers installed here, by qpsolvers' names, plus the aliases egcbf keeps (``"proxsuite"``)."""
    import qpsolvers

    names = list(qpsolvers.available_solvers)
    return names + [a for a, target in ALIASES.items() if target in names]


def require_solver(name: str) -> str:
    """qpsolvers' name of ``name`` if it is installed. ``ValueError`` listing the installed solvers for a name
    qpsolvers does not know; ``ImportError`` saying what to install for a known solver that is not installed."""
    import qpsolvers

    canonical = ALIASES.get(name, name)
    if canonical in qpsolvers.available_solvers:
        return canonical
    if canonical in PIP_PACKAGES:
        extra = " (or pip install -e '.[solvers]')" if canonical in ("osqp", "clarabel", "highs", "qpalm") else ""
        raise ImportError(f"QP solver {name!r} is not installed: pip install {PIP_PACKAGES[canonical]}{extra}")
    raise ValueError(f"unknown QP solver {name!r}; installed: {available_solvers()} (any qpsolvers solver works)")


def _one_sided(qp: SparseQP) -> tuple[sp.csc_matrix | None, np.ndarray | None]:
    """``G, h`` with ``G z <= h`` equivalent to the finite sides of ``l <= C z <= u``."""
    up, dn = qp.u < INF / 2, qp.l > -INF / 2
    if not (up.any() or dn.any()):
        return None, None
    G = sp.vstack([qp.C[up], -qp.C[dn]], format="csc")
    return G, np.concatenate([qp.u[up], -qp.l[dn]])


def _iterations(extras: dict) -> int:
    info = extras.get("info")
    for obj, key in ((info, "iter"), (info, "iterations"), (extras, "iter")):
        value = obj.get(key) if isinstance(obj, dict) else getattr(obj, key, None)
        if isinstance(value, (int, np.integer)):
            return int(value)
    return -1


def solve_with_qpsolvers(
    qp: SparseQP, solver: str, eps_abs: float, max_iter: int, x0: np.ndarray | None = None
) -> SolveResult:
    """Solve ``qp`` with ``solver`` (module doc); never raises on a solver failure (``ok=False``)."""
    import qpsolvers

    name = require_solver(solver)
    G, h = _one_sided(qp)
    lb = np.where(qp.x_l <= -INF / 2, -np.inf, qp.x_l)
    ub = np.where(qp.x_u >= INF / 2, np.inf, qp.x_u)
    problem = qpsolvers.Problem(qp.H, qp.g, G, h, None, None, lb, ub)
    kwargs = SETTINGS[name](eps_abs, max_iter) if name in SETTINGS else {}
    t0 = time.perf_counter()
    try:
        sol = qpsolvers.solve_problem(problem, solver=name, initvals=x0, verbose=False, **kwargs)
        x, ok, it = sol.x, bool(sol.found), _iterations(sol.extras or {})
        status = str((sol.extras or {}).get("status", "solved" if ok else "not solved"))
    except Exception as exc:  # a solver crash is a failed solve, never an exception for the caller
        x, ok, it, status = None, False, 0, f"error: {type(exc).__name__}: {exc}"
    ms = 1e3 * (time.perf_counter() - t0)
    n = qp.H.shape[0]
    if x is None or np.shape(x) != (n,) or not np.all(np.isfinite(x)):
        return SolveResult(np.full(n, np.nan), False, status, it, ms)
    return SolveResult(np.asarray(x, dtype=np.float64), ok, status, it, ms)
