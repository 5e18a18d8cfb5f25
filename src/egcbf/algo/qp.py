"""The QP target ``u_QP`` of GCBF+ / EGCBF+: the centralized CBF-QP with the learned CBF, batched over graphs.

For one environment of ``N`` agents, with the learned CBF ``h`` (the slowly updated target copy), the nominal
command ``c_nom`` and the commands ``c`` of a control interface (:mod:`egcbf.algo.interface`: normalized
accelerations in each agent's yaw frame, or normalized torque and thrust)::

    min_{c, s}  1/2 ||c - c_nom||^2 + sum_i ( 1/2 w2 s_i^2 + w1 s_i )
    s.t.        Lf h_i + sum_j Lg_j h_i . c_j + alpha h_i + s_i >= 0      for every agent i
                lo <= c <= hi,  s >= 0

``Lf h_i`` and ``Lg_j h_i`` (the derivative of ``h_i`` along agent ``j``'s command) come from the interface's model,
built on the Jacobian ``dh_i/dx_j``, which comes from autograd with the graph's topology, goals and LiDAR hits held
fixed (the states enter as in :func:`egcbf.env.graph.refresh_graph`, as GCBF+ does), in *one* backward pass: every
edge reads its own copy of its sender's state, so the gradient of ``sum_i h_i`` with respect to the copies
separates into every ``dh_i/dx_j`` (:func:`cbf_jacobian`). Entries for agents outside ``i``'s neighbourhood are
exactly zero. GCBF+'s constants: ``alpha`` = 0.1 times the loss's class-K slope, ``w1 = 1e3``, ``w2 = 10``.

The QP is always feasible (the slack absorbs conflicts; the box contains the clipped reference). It is solved by
the batched primal-dual interior-point method of :mod:`egcbf.qp.ipm` (Mehrotra predictor-corrector; the
environments of a chunk advance together), in float64, with the Newton linear algebra of :class:`CBFQPKKT`, which
uses the problem's structure (one ``kN x kN`` Cholesky per environment and iteration). It runs on the device of the
data (CPU or GPU); checked against proxsuite in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..env.graph import SwarmGraph, with_agent_states
from ..qp.ipm import IPMSettings, solve_ipm

__all__ = ["CBFQPKKT", "CBFQPResult", "cbf_jacobian", "solve_cbf_qp"]


# ------------------------------------------------------------------------------------------ the CBF Jacobian
def cbf_jacobian(cbf: nn.Module, graph: SwarmGraph, x: Tensor) -> tuple[Tensor, Tensor]:
    """``h`` ``(B, N)`` and its Jacobian ``dh_i/dx_j`` ``(B, N, N, 18)`` at the states ``x`` ``(B, N, 18)`` of
    ``graph``'s agents (topology, goals and LiDAR hits held fixed), with one forward and one backward pass.

    Entries for agents ``j`` outside ``i``'s neighbourhood are exactly zero. The network's parameters get no
    gradient.
    """
    b, n, _ = x.shape
    m = b * n
    src, dst = graph.edge_index
    agent = src < m
    xf = x.detach().reshape(m, -1)
    with torch.enable_grad():
        x_edge = xf[src[agent]].clone().requires_grad_(True)
        x_recv = xf.clone().requires_grad_(True)
        h = cbf(with_agent_states(graph, x_recv, x_edge))
        g_edge, g_recv = torch.autograd.grad(h.sum(), (x_edge, x_recv))
    jac = torch.zeros(m, n, xf.shape[-1], dtype=xf.dtype, device=xf.device)
    jac.index_put_((dst[agent], src[agent] % n), g_edge, accumulate=True)
    own = torch.arange(m, device=xf.device)
    jac.index_put_((own, own % n), g_recv, accumulate=True)
    return h.detach().view(b, n), jac.view(b, n, n, -1)


# ------------------------------------------------------------------------------------------ the learned CBF-QP
@dataclass
class CBFQPKKT:
    """The learned-CBF QPs of ``B`` environments as a :class:`egcbf.qp.ipm.KKTSystem`, variables
    ``x = (u (nu), s (n))``::

        min 1/2 ||u - u_ref||^2 + 1/2 w2 ||s||^2 + w1 1's   s.t.  a u + s >= -b,  s >= 0,  lo <= u <= hi

    with ``a`` ``(B, n, nu)``, ``b`` ``(B, n)``, ``u_ref`` ``(B, nu)``, ``lo, hi`` ``(nu,)`` or ``(B, nu)``; the
    rows of ``G x <= h`` are stacked as (CBF ``(n)``, ``s >= 0`` ``(n)``, ``u <= hi`` ``(nu)``, ``-u <= -lo``
    ``(nu)``). The Newton system is solved through its structure: the slack block is diagonal and is eliminated,
    leaving ``K_u = D_u + a' W a`` (``D_u`` diagonal: the Hessian and the box rows; ``W`` diagonal, written without
    forming the CBF rows' weights or their inverses alone, which span ~30 orders of magnitude near convergence),
    one ``nu x nu`` Cholesky per problem and iteration. ``dual_scale = 1 + max(|u_ref|_inf, w1, 1)``,
    ``primal_scale = 1 + |h|_inf``.
    """

    a: Tensor
    q: Tensor
    h: Tensor
    dual_scale: Tensor
    primal_scale: Tensor
    w2: float

    @classmethod
    def build(cls, a: Tensor, b: Tensor, u_ref: Tensor, lo: Tensor, hi: Tensor, w1: float, w2: float) -> CBFQPKKT:
        bsz, _, nu = a.shape
        hvec = torch.cat((b, torch.zeros_like(b), hi.expand(bsz, nu), -lo.expand(bsz, nu)), -1)
        q = torch.cat((-u_ref, torch.full_like(b, w1)), -1)
        qn = 1 + torch.maximum(u_ref.abs().amax(-1), torch.full_like(b[:, 0], max(w1, 1.0)))
        return cls(a, q, hvec, qn, 1 + hvec.abs().amax(-1), w2)

    def take(self, idx: Tensor) -> CBFQPKKT:
        a, q, h, dual, primal = (t[idx] for t in (self.a, self.q, self.h, self.dual_scale, self.primal_scale))
        return CBFQPKKT(a, q, h, dual, primal, self.w2)

    def _split(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return x.split((self.a.shape[-1], self.a.shape[-2]), -1)

    def p_mul(self, x: Tensor) -> Tensor:
        u, s = self._split(x)
        return torch.cat((u, self.w2 * s), -1)

    def g_mul(self, x: Tensor) -> Tensor:
        return _g_mul(self.a, *self._split(x))

    def gt_mul(self, z: Tensor) -> Tensor:
        n, nu = self.a.shape[-2:]
        return torch.cat(_gt_mul(self.a.transpose(-1, -2), z, n, nu), -1)

    def newton(self, t: Tensor, y: Tensor, r_d: Tensor, r_p: Tensor) -> tuple[_Newton, Tensor]:
        """Factor ``K_u`` at the slacks ``t`` and multipliers ``y`` ``(B, 2n + 2nu)``."""
        a = self.a
        n, nu = a.shape[-2:]
        at = a.transpose(-1, -2)
        w = y / t
        _, w2v, w3v, w4v = w.split((n, n, nu, nu), -1)
        w1_inv = t[:, :n] / y[:, :n]  # 1 / W1
        du_diag = 1 + w3v + w4v  # Hessian + box rows: diagonal in u
        ds_diag = self.w2 + w2v  # Hessian + (s >= 0) rows: diagonal in s
        # eliminate s (its block is diagonal): K_u = D_u + a' diag(W1 D_s / (D_s + W1)) a, written so that neither
        # W1 nor 1/W1 is ever formed alone (they span ~30 orders of magnitude near convergence)
        w_tilde = 1 / (w1_inv + 1 / ds_diag)
        frac = 1 / (1 + ds_diag * w1_inv)  # W1 / (D_s + W1)
        k_u = at @ (w_tilde[..., None] * a) + torch.diag_embed(du_diag)
        chol, info = torch.linalg.cholesky_ex(k_u)
        ok = (info == 0) & torch.isfinite(k_u).flatten(1).all(-1)
        chol = torch.where(ok[:, None, None], chol, torch.eye(nu, dtype=a.dtype, device=a.device))
        rdu, rds = self._split(r_d)
        return _Newton(a, at, chol, frac, w1_inv, rdu, rds, r_p, t, y), ok


class _Newton(NamedTuple):
    """The Newton system of one interior-point iteration (the active problems)."""

    a: Tensor
    at: Tensor
    chol: Tensor  # Cholesky factor of K_u
    frac: Tensor  # W1 / (D_s + W1)
    w1_inv: Tensor  # 1 / W1
    rdu: Tensor
    rds: Tensor
    rp: Tensor
    t: Tensor
    y: Tensor

    def ksolve(self, ru: Tensor, rs: Tensor) -> tuple[Tensor, Tensor]:
        rhs = ru - (self.at @ (self.frac * rs)[..., None])[..., 0]
        zu = torch.cholesky_solve(rhs[..., None], self.chol)[..., 0]
        zs = self.frac * (rs * self.w1_inv - (self.a @ zu[..., None])[..., 0])  # (rs - W1 a zu) / (D_s + W1)
        return zu, zs

    def direction(self, rc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The step ``((du, ds), dt, dy)`` for the complementarity target ``rc`` ``(B, m)`` (``ds``: the QP's
        slacks, ``dt``: the inequality slacks, ``dy``: the multipliers)."""
        n = self.rds.shape[-1]
        gu, gs = _gt_mul(self.at, (rc + self.y * self.rp) / self.t, n, self.at.shape[-2])
        du, ds = self.ksolve(-self.rdu - gu, -self.rds - gs)
        dt = -self.rp - _g_mul(self.a, du, ds)
        dy = (rc - self.y * dt) / self.t
        return torch.cat((du, ds), -1), dt, dy


def _g_mul(a: Tensor, u: Tensor, s: Tensor) -> Tensor:
    """``G z`` for the stacked inequality rows (CBF, ``s >= 0``, ``u <= hi``, ``-u <= -lo``): ``u`` ``(B, nu)``,
    ``s`` ``(B, n)`` -> ``(B, 2n + 2nu)``."""
    return torch.cat((-(a @ u[..., None])[..., 0] - s, -s, u, -u), -1)


def _gt_mul(at: Tensor, y: Tensor, n: int, nu: int) -> tuple[Tensor, Tensor]:
    """``G' y`` split into its ``u`` and ``s`` parts: ``y`` ``(B, 2n + 2nu)`` -> ``(B, nu), (B, n)``."""
    y1, y2, y3, y4 = y.split((n, n, nu, nu), -1)
    return -(at @ y1[..., None])[..., 0] + y3 - y4, -y1 - y2


def _solve(
    a: Tensor, b: Tensor, u_ref: Tensor, lo: Tensor, hi: Tensor, w1: float, w2: float, tol: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, int]:
    """:func:`egcbf.qp.ipm.solve_ipm` on the QPs of :class:`CBFQPKKT`, from the reference control pulled
    towards the box's centre (``u = mid + 0.9 (u_ref - mid)``), a small slack ``0.1`` priced at its multiplier
    ``w1``, inequality slacks ``max(h - G x, 0.1)`` and multipliers 1. Returns ``u`` ``(B, nu)``, ``s`` ``(B, n)``,
    ``converged`` ``(B,)`` and the number of passes of the solver's loop plus one, capped at ``max_iter`` (what
    this solver has always reported as its iterations)."""
    bsz, n, nu = a.shape
    kkt = CBFQPKKT.build(a, b, u_ref, lo, hi, w1, w2)
    mid = (lo + hi).expand(bsz, nu) / 2
    x0 = torch.cat((mid + 0.9 * (u_ref - mid), torch.full_like(b, 0.1)), -1)
    y0 = torch.ones_like(kkt.h)
    y0[:, n : 2 * n] = w1
    settings = IPMSettings(tol=tol, max_iter=max_iter - 1, min_slack=0.1, sigma_max=1.0, best_iterate=True)
    res = solve_ipm(kkt, x0, y0, settings)
    u, s = res.x.split((nu, n), -1)
    return u, s, res.converged, min(max_iter, int(res.passes) + 1)


@dataclass
class CBFQPResult:
    """Solution of a batch of learned-CBF QPs.

    Attributes:
        u: ``(B, N, k)`` the QP's commands (in the coordinates of the box).
        slack: ``(B, N)`` the CBF slacks ``s_i >= 0``.
        residual: ``(B, N)`` the CBF constraint value ``Lf h + Lg h u + alpha h`` at the solution (``>= -slack``).
        converged: ``(B,)`` the interior-point method met its tolerance.
        iterations: iterations of the slowest chunk.
    """

    u: Tensor
    slack: Tensor
    residual: Tensor
    converged: Tensor
    iterations: int

    def stats(self, slack_tol: float = 1e-6) -> dict[str, float]:
        """``num_slack`` (constraints with slack ``> slack_tol``), ``max_slack``, ``num_failed`` (not converged),
        ``num_constraints``."""
        return {
            "num_slack": int((self.slack > slack_tol).sum()),
            "max_slack": float(self.slack.max()) if self.slack.numel() else 0.0,
            "num_failed": int((~self.converged).sum()),
            "num_constraints": int(self.slack.numel()),
        }


def solve_cbf_qp(
    h: Tensor,
    lf: Tensor,
    lg: Tensor,
    u_ref: Tensor,
    lo: Tensor,
    hi: Tensor,
    *,
    alpha: float,
    slack_linear: float = 1e3,
    slack_quadratic: float = 10.0,
    tol: float = 1e-8,
    max_iter: int = 50,
    chunk: int = 1024,
) -> CBFQPResult:
    """Solve the centralized learned-CBF QP of every environment (module doc), in float64.

    The variables are the agents' commands in the coordinates where their bounds are the box ``[lo, hi]``
    (:meth:`egcbf.algo.interface.CommandInterface.to_local`; normalized torque and thrust, or accelerations in each
    agent's yaw frame).

    Args:
        h, lf: ``(B, N)``; lg: ``(B, N, N, k)`` ``[b, i, j]`` = the derivative of ``h_i`` along agent ``j``'s command.
        u_ref: ``(B, N, k)`` the reference command (clipped into the box here).
        lo, hi: ``(k,)`` the box, or ``(B, N, k)`` one box per agent.
        alpha: slope of the linear class-K function in the constraint.
        slack_linear, slack_quadratic: ``w1`` and ``w2`` of the slack cost.
        tol: an environment's QP has converged when its merit ``max(dual residual / (1 + max(|u_ref|, w1, 1)),
            primal residual / (1 + |rhs, bounds|), mean complementarity) <= tol``; its best iterate by that merit
            is returned.
        max_iter: residual evaluations per environment (``max_iter - 1`` Newton steps), at least 1.
        chunk: environments per batched solve.
    """
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    b, n = h.shape
    k = lg.shape[-1]
    f64 = torch.float64
    h, lf, lg, u_ref, lo, hi = (t.detach().to(f64) for t in (h, lf, lg, u_ref, lo, hi))
    lo_v, hi_v = (t.expand(b, n, k).reshape(b, n * k) for t in (lo, hi))  # one box per agent
    a = lg.reshape(b, n, k * n)  # rows: agent i; columns: (agent j, channel)
    rhs = lf + alpha * h
    u_ref = u_ref.reshape(b, k * n).clamp(lo_v, hi_v)
    us, ss, conv, iters = [], [], [], 0
    for c in range(0, b, chunk):
        sl = slice(c, min(c + chunk, b))
        lo_c, hi_c = lo_v[sl], hi_v[sl]
        u, s, ok, it = _solve(a[sl], rhs[sl], u_ref[sl], lo_c, hi_c, slack_linear, slack_quadratic, tol, max_iter)
        us.append(u.clamp(lo_c, hi_c))
        ss.append(s.clamp_min(0.0))
        conv.append(ok)
        iters = max(iters, it)
    u = torch.cat(us)
    slack = torch.cat(ss)
    residual = lf + (a @ u[..., None])[..., 0] + alpha * h
    return CBFQPResult(u.reshape(b, n, k), slack, residual, torch.cat(conv), iters)
