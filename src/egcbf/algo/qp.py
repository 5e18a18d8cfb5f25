"""The QP target ``u_QP`` of GCBF+ / EGCBF+: the centralized CBF-QP with the learned CBF, batched over graphs.

For one environment of ``N`` agents, with the learned CBF ``h`` (the slowly updated target copy), the nominal
command ``c_nom`` and the commands ``c`` of a control interface (:mod:`egcbf.algo.interface`: normalized
accelerations in each agent's yaw frame, or normalized torque and thrust)::

    min_{c, s}  1/2 ||c - c_nom||^2 + sum_i ( 1/2 w2 s_i^2 + w1 s_i )
    s.t.        Lf h_i + sum_j Lg_j h_i . c_j + alpha h_i + s_i >= 0      for every agent i
                lo <= c <= hi,  s >= 0

``Lf h_i`` and ``Lg_j h_i`` (the derivative of ``h_i`` along agent ``j``'s command) come from the interface's model,
built on the Jacobian ``dh_i/dx_j``, which comes from autograd with the graph's topology, goals and LiDAR hits held
fixed (the states enter as in :func:`egcbf.graph.refresh_graph`, as GCBF+ does), in *one* backward pass: every
edge reads its own copy of its sender's state, so the gradient of ``sum_i h_i`` with respect to the copies
separates into every ``dh_i/dx_j`` (:func:`cbf_jacobian`). Entries for agents outside ``i``'s neighbourhood are
exactly zero. GCBF+'s constants: ``alpha`` = 0.1 times the loss's class-K slope, ``w1 = 1e3``, ``w2 = 10``.

The QP is always feasible (the slack absorbs conflicts; the box contains the clipped reference). It is solved by a
primal-dual interior-point method (Mehrotra predictor-corrector) batched over environments, in float64, that uses
the problem's structure (one ``kN x kN`` Cholesky per iteration; ``_solve_structured``). It runs on the device of
the data (CPU or GPU), with no host round trip; checked against proxsuite in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..graph import SwarmGraph, with_agent_states

__all__ = ["CBFQPResult", "cbf_jacobian", "solve_cbf_qp"]


def _max_step(v: Tensor, dv: Tensor) -> Tensor:
    """Largest ``a`` in ``(0, 1]`` with ``v + a dv >= 0`` per batch row."""
    ratio = torch.where(dv < 0, -v / torch.where(dv < 0, dv, -torch.ones_like(dv)), torch.full_like(v, torch.inf))
    return ratio.amin(-1).clamp(max=1.0)


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
def _solve_structured(
    a: Tensor, b: Tensor, u_ref: Tensor, lo: Tensor, hi: Tensor, w1: float, w2: float, tol: float, max_iter: int
) -> tuple[Tensor, Tensor, Tensor, int]:
    """Interior point for ``min 1/2 ||u - u_ref||^2 + 1/2 w2 ||s||^2 + w1 1's``
    s.t. ``a u + s >= -b``, ``s >= 0``, ``lo <= u <= hi``; ``a`` ``(B, n, nu)``, ``b`` ``(B, n)``.

    Primal-dual Mehrotra predictor-corrector, with the Newton system solved through its structure: the slack
    block is diagonal and is eliminated, leaving ``K_u = D_u + a' W a`` (``D_u`` diagonal: the Hessian and the box
    rows; ``W`` diagonal, written without forming the CBF rows' weights or their inverses alone, which span ~30
    orders of magnitude near convergence), one ``nu x nu`` Cholesky per problem and iteration. Each iteration works
    on the problems not yet converged only, and each problem returns its best iterate by the merit
    ``max(dual residual / (1 + max(|u_ref|, w1)), primal residual / (1 + |h|), mean complementarity)``; converged
    means merit ``<= tol``. Returns ``(u, s, converged, iterations)``.
    """
    bsz, n, nu = a.shape
    lo_b, hi_b = lo.expand(bsz, nu), hi.expand(bsz, nu)
    hvec = torch.cat((b, torch.zeros_like(b), hi_b, -lo_b), -1)
    m = hvec.shape[-1]
    # start near the reference control (inside the box), with a small slack priced at its multiplier w1
    mid = (lo_b + hi_b) / 2
    u = mid + 0.9 * (u_ref - mid)
    s = torch.full_like(b, 0.1)
    t = (hvec - _g_mul(a, u, s)).clamp_min(0.1)
    y = torch.ones_like(hvec)
    y[:, n : 2 * n] = w1
    qn = 1 + torch.maximum(u_ref.abs().amax(-1), torch.full_like(b[:, 0], max(w1, 1.0)))
    hn = 1 + hvec.abs().amax(-1)
    done = torch.zeros(bsz, dtype=torch.bool, device=a.device)
    failed = torch.zeros_like(done)
    best = torch.full_like(b[:, 0], torch.inf)
    best_u, best_s = u.clone(), s.clone()
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        idx = (~done & ~failed).nonzero()[:, 0]
        if idx.numel() == 0:
            break
        a_, ur_, hv_ = a[idx], u_ref[idx], hvec[idx]
        u_, s_, t_, y_ = u[idx], s[idx], t[idx], y[idx]
        at_ = a_.transpose(-1, -2)
        gu, gs = _gt_mul(at_, y_, n, nu)
        rdu = u_ - ur_ + gu
        rds = w2 * s_ + w1 + gs
        rp = _g_mul(a_, u_, s_) + t_ - hv_
        mu = (t_ * y_).sum(-1) / m
        rd_max = torch.maximum(rdu.abs().amax(-1), rds.abs().amax(-1))
        merit = torch.maximum(torch.maximum(rd_max / qn[idx], rp.abs().amax(-1) / hn[idx]), mu)
        ok = merit <= tol
        done[idx] = ok
        better = merit < best[idx]  # keep the best iterate: near convergence rounding can make the iteration drift
        best[idx] = torch.where(better, merit, best[idx])
        best_u[idx] = torch.where(better[:, None], u_, best_u[idx])
        best_s[idx] = torch.where(better[:, None], s_, best_s[idx])
        w = y_ / t_
        _, w2v, w3v, w4v = w.split((n, n, nu, nu), -1)
        w1_inv = t_[:, :n] / y_[:, :n]  # 1 / W1
        du_diag = 1 + w3v + w4v  # Hessian + box rows: diagonal in u
        ds_diag = w2 + w2v  # Hessian + (s >= 0) rows: diagonal in s
        # eliminate s (its block is diagonal): K_u = D_u + a' diag(W1 D_s / (D_s + W1)) a, written so that neither
        # W1 nor 1/W1 is ever formed alone (they span ~30 orders of magnitude near convergence)
        w_tilde = 1 / (w1_inv + 1 / ds_diag)
        frac = 1 / (1 + ds_diag * w1_inv)  # W1 / (D_s + W1)
        k_u = at_ @ (w_tilde[..., None] * a_) + torch.diag_embed(du_diag)
        chol, info = torch.linalg.cholesky_ex(k_u)
        bad = (info != 0) | ~torch.isfinite(k_u).flatten(1).all(-1)
        if bool(bad.any()):  # numerical breakdown: stop iterating these problems (their best iterate is kept)
            failed[idx[bad & ~ok]] = True
            chol = torch.where(bad[:, None, None], torch.eye(nu, dtype=a.dtype, device=a.device), chol)

        sys_ = _Newton(a_, at_, chol, frac, w1_inv, rdu, rds, rp, t_, y_)
        du, ds, dt_, dy = sys_.direction(-t_ * y_)  # affine (predictor) direction
        step = torch.minimum(_max_step(t_, dt_), _max_step(y_, dy))[:, None]
        mu_aff = ((t_ + step * dt_) * (y_ + step * dy)).sum(-1) / m
        sigma = (mu_aff / mu.clamp_min(1e-300)).clamp(0, 1) ** 3
        du, ds, dt_, dy = sys_.direction(sigma[:, None] * mu[:, None] - t_ * y_ - dt_ * dy)  # corrector
        step = (0.99 * torch.minimum(_max_step(t_, dt_), _max_step(y_, dy))).clamp(max=1.0)
        move = (~ok & ~failed[idx] & torch.isfinite(step))[:, None]
        step = torch.where(move, step[:, None], torch.zeros_like(step[:, None]))
        u[idx] = torch.where(move, u_ + step * du, u_)
        s[idx] = torch.where(move, s_ + step * ds, s_)
        t[idx] = torch.where(move, (t_ + step * dt_).clamp_min(1e-200), t_)
        y[idx] = torch.where(move, (y_ + step * dy).clamp_min(1e-200), y_)
    return best_u, best_s, best <= tol, it


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

    def direction(self, rc: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The step ``(du, ds, dt, dy)`` for the complementarity target ``rc``."""
        n = self.rds.shape[-1]
        gu, gs = _gt_mul(self.at, (rc + self.y * self.rp) / self.t, n, self.at.shape[-2])
        du, ds = self.ksolve(-self.rdu - gu, -self.rds - gs)
        dt = -self.rp - _g_mul(self.a, du, ds)
        dy = (rc - self.y * dt) / self.t
        return du, ds, dt, dy


def _g_mul(a: Tensor, u: Tensor, s: Tensor) -> Tensor:
    """``G z`` for the stacked inequality rows (CBF, ``s >= 0``, ``u <= hi``, ``-u <= -lo``)."""
    return torch.cat((-(a @ u[..., None])[..., 0] - s, -s, u, -u), -1)


def _gt_mul(at: Tensor, y: Tensor, n: int, nu: int) -> tuple[Tensor, Tensor]:
    """``G' y`` split into its ``u`` and ``s`` parts."""
    y1, y2, y3, y4 = y.split((n, n, nu, nu), -1)
    return -(at @ y1[..., None])[..., 0] + y3 - y4, -y1 - y2


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
        lo, hi: ``(k,)`` the box.
        alpha: slope of the linear class-K function in the constraint.
        slack_linear, slack_quadratic: ``w1`` and ``w2`` of the slack cost.
        chunk: environments per batched solve.
    """
    b, n = h.shape
    k = lg.shape[-1]
    f64 = torch.float64
    h, lf, lg, u_ref, lo, hi = (t.detach().to(f64) for t in (h, lf, lg, u_ref, lo, hi))
    lo_v, hi_v = lo.repeat(n), hi.repeat(n)
    a = lg.reshape(b, n, k * n)  # rows: agent i; columns: (agent j, channel)
    rhs = lf + alpha * h
    u_ref = torch.maximum(torch.minimum(u_ref, hi), lo).reshape(b, k * n)
    us, ss, conv, iters = [], [], [], 0
    for c in range(0, b, chunk):
        sl = slice(c, min(c + chunk, b))
        u, s, ok, it = _solve_structured(
            a[sl], rhs[sl], u_ref[sl], lo_v, hi_v, slack_linear, slack_quadratic, tol, max_iter
        )
        us.append(u.clamp(lo_v, hi_v))
        ss.append(s.clamp_min(0.0))
        conv.append(ok)
        iters = max(iters, it)
    u = torch.cat(us)
    slack = torch.cat(ss)
    residual = lf + (a @ u[..., None])[..., 0] + alpha * h
    return CBFQPResult(u.reshape(b, n, k), slack, residual, torch.cat(conv), iters)
