"""One batched primal-dual interior-point method (Mehrotra predictor-corrector) for convex QPs, in torch.

Each of the ``B`` problems of a batch is

    min 1/2 x'Px + q'x   s.t.  G x <= h              x (B, n), h (B, m)

solved in the form ``G x + s = h``, ``s >= 0``, with multipliers ``z >= 0``. The iteration (:func:`solve_ipm`) is
written once; a problem supplies its data and its Newton linear algebra through :class:`KKTSystem`:

* :class:`egcbf.qp.dense_ipm.DenseKKT`: explicit ``P`` and ``G``, one ``n x n`` Cholesky of
  ``P + G' diag(z / s) G`` per problem and iteration; the per-agent QPs of the decentralized CBF-QP baseline
  (:func:`egcbf.qp.dense_qp.solve_dense_batch_ipm`).
* :class:`egcbf.algo.qp.CBFQPKKT`: the learned-CBF QP target, whose slack block is eliminated (one ``kN x kN``
  Cholesky per environment and iteration).

All problems advance together, on the device of the data, in float64. The working set is compacted as problems
stop, so that a stopped problem no longer moves and costs nothing; which problems go on is the one host
synchronization per iteration (with ``safeguard``, a second one decides whether any problem needs the centred step,
which is then computed: the results do not depend on it).

A problem stops when it has converged (:class:`IPMSettings`), when its Newton system cannot be factored, when its
next iterate would not be finite (double precision breaks down once ``z / s`` spans ~30 orders of magnitude; it
keeps its current iterate), or after ``max_iter`` Newton steps. The two callers keep the behaviour each had as a
separate solver (``docs/baselines.md``, ``docs/learning.md``):

=====================  ==========================================  ============================================
setting                dense per-agent QPs                         learned-CBF QP
=====================  ==========================================  ============================================
start                  ``x0`` given, ``s = max(h - G x0, 1)``,     ``u`` near its reference, slack 0.1,
                       ``z = 1``                                   ``s = max(h - G x0, 0.1)``, ``z = 1`` (``w1``
                                                                   on the rows ``slack >= 0``)
dual residual          relative to ``max(dual_scale, |Px|,         relative to ``dual_scale``
                       |G'z|)`` (``dual_relative``, as OSQP)
primal residual        violation ``max(Gx - h, 0)``                ``|Gx + s - h|``
gap                    ``mean(s z) / dual_scale``                  ``mean(s z)``
tolerances             ``tol`` 1e-12 (gap), ``feas_tol`` 1e-9      ``tol`` = ``feas_tol`` = 1e-8
iterations             ``max_iter`` 60 steps                       ``max_iter - 1`` = 49 steps
centring               ``sigma`` unclamped, with a centred         ``sigma`` clamped to ``[0, 1]``, no safeguard
                       fallback step where Mehrotra's corrector
                       does not reduce ``mean(s z)`` (safeguard)
returned iterate       the last; a problem that stops without      the best by the merit ``max(dual, primal,
                       converging is accepted if it meets          gap)``; converged iff that merit <= ``tol``
                       ``loose_tol`` = 1e-7
afterwards             active-set polishing (``polish_dense``)     clipped into the box, slack >= 0
=====================  ==========================================  ============================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

__all__ = ["INF", "IPMResult", "IPMSettings", "KKTSystem", "NewtonSystem", "solve_ipm"]

INF = 1e20  # "no bound" (proxsuite's and OSQP's convention); DenseKKT leaves such entries of h out of its scale


@dataclass(frozen=True)
class IPMSettings:
    """Settings of :func:`solve_ipm` (see the module's table for the two callers' choices).

    A problem has converged when its dual residual ``|P x + q + G'z|_inf / D <= feas_tol``, its primal residual
    ``/ primal_scale <= feas_tol`` and its gap ``mean(s z) (/ dual_scale with gap_relative) <= tol``, where ``D`` is
    the problem's ``dual_scale``, or ``max(dual_scale, |Px|_inf, |G'z|_inf)`` with ``dual_relative``; the primal
    residual is ``|G x + s - h|_inf``, or the violation ``|max(G x - h, 0)|_inf`` with ``primal_violation``.

    Attributes:
        tol: gap tolerance. feas_tol: residual tolerance (``None``: ``tol``).
        max_iter: Newton steps per problem at most (the residuals are evaluated ``max_iter + 1`` times).
        min_slack: the start's slack ``s = max(h - G x0, min_slack)``.
        sigma_max: upper clamp of Mehrotra's centring parameter ``sigma = (mu_aff / mu)^3`` (``inf``: none).
        safeguard: where the corrected step reduces ``mean(s z)`` by less than ``1 - 0.1 alpha``, take a plain
            centred Newton step (``sigma >= 0.1``, no second-order term) instead (Mehrotra's corrector can cycle).
        best_iterate: return each problem's best iterate by the merit ``max(dual, primal, gap)`` (near
            convergence rounding can make the iteration drift); otherwise its last one.
        loose_tol: (last iterate only) a problem that stops without converging is accepted when its last iterate
            meets ``loose_tol`` for all three measures.
    """

    tol: float = 1e-8
    feas_tol: float | None = None
    max_iter: int = 50
    min_slack: float = 1.0
    dual_relative: bool = False
    primal_violation: bool = False
    gap_relative: bool = False
    sigma_max: float = math.inf
    safeguard: bool = False
    best_iterate: bool = True
    loose_tol: float | None = None

    def __post_init__(self) -> None:
        if self.max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {self.max_iter}")
        if self.best_iterate and self.loose_tol is not None:
            raise ValueError("loose_tol applies to the last iterate only (best_iterate=False)")


class NewtonSystem(Protocol):
    """The factored Newton system of one iteration, for the problems still iterating."""

    def direction(self, rc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(dx (B, n), ds (B, m), dz (B, m))`` solving ``P dx + G'dz = -r_d``, ``G dx + ds = -r_p``,
        ``z ds + s dz = rc`` (``rc`` ``(B, m)``: the complementarity target)."""
        ...


class KKTSystem(Protocol):
    """A batch of QPs ``min 1/2 x'Px + q'x s.t. G x <= h``: its data and its Newton linear algebra.

    Attributes: ``q`` ``(B, n)``, ``h`` ``(B, m)``, ``dual_scale`` and ``primal_scale`` ``(B,)`` (positive: the
    residuals are measured relative to them).
    """

    q: Tensor
    h: Tensor
    dual_scale: Tensor
    primal_scale: Tensor

    def take(self, idx: Tensor) -> KKTSystem:
        """The problems ``idx`` ``(B',)`` (long) of the batch."""
        ...

    def p_mul(self, x: Tensor) -> Tensor:
        """``P x``: ``(B, n) -> (B, n)``."""
        ...

    def g_mul(self, x: Tensor) -> Tensor:
        """``G x``: ``(B, n) -> (B, m)``."""
        ...

    def gt_mul(self, z: Tensor) -> Tensor:
        """``G'z``: ``(B, m) -> (B, n)``."""
        ...

    def newton(self, s: Tensor, z: Tensor, r_d: Tensor, r_p: Tensor) -> tuple[NewtonSystem, Tensor]:
        """Factor the Newton system at ``(s, z)`` with the residuals ``r_d = P x + q + G'z`` ``(B, n)`` and
        ``r_p = G x + s - h`` ``(B, m)``; returns it and ``ok`` ``(B,)`` (False: it could not be factored, that
        problem stops; its directions may then be anything)."""
        ...


@dataclass
class IPMResult:
    """Solution of a batch: ``x`` ``(B, n)``, ``s`` and ``z`` ``(B, m)`` (the returned iterate), ``converged``
    ``(B,)`` bool, ``iterations`` ``(B,)`` int64 (Newton steps attempted), ``passes``: residual evaluations of the
    slowest problem (a stopped problem counted up to the pass at which it stopped), a 0-d int64 tensor."""

    x: Tensor
    s: Tensor
    z: Tensor
    converged: Tensor
    iterations: Tensor
    passes: Tensor


def _max_step(neg_v: Tensor, dv: Tensor) -> Tensor:
    """Largest ``a`` in ``(0, 1]`` with ``v + a dv >= 0``, per row, from ``-v`` and ``dv`` ``(B, k)``: ``(B, 1)``."""
    ratio = torch.where(dv < 0, neg_v / dv, torch.inf)  # the other entries are never used
    return ratio.amin(-1, keepdim=True).clamp(max=1.0) if ratio.shape[-1] else torch.ones_like(dv[..., :1])


def _amax(t: Tensor) -> Tensor:
    """``max(t, -1)`` with 0 for an empty last axis: ``(B, k) -> (B,)``."""
    return t.amax(-1) if t.shape[-1] else t.new_zeros(t.shape[:-1])


def solve_ipm(kkt: KKTSystem, x0: Tensor, z0: Tensor, settings: IPMSettings = IPMSettings()) -> IPMResult:
    """Solve the batch ``kkt`` from ``x0`` ``(B, n)`` (any point: the method handles primal residuals) with the
    multipliers ``z0`` ``(B, m)`` (positive, or 0 on rows whose multiplier may start at 0) and the slacks
    ``max(h - G x0, min_slack)``; see the module doc. Works on the device of ``x0``, in float64 (``TypeError``
    otherwise).

    Mehrotra predictor-corrector: the affine direction ``rc = -s z`` gives the step ``alpha_aff`` and
    ``sigma = (mu_aff / mu)^3``; the corrected direction ``rc = sigma mu - s z - ds_aff dz_aff`` is taken with
    ``0.99`` of the largest step that keeps ``s, z >= 0`` (floored at ``1e-300``). A problem whose
    next iterate has a non-finite entry (seen through the sum of its entries) keeps its current one and stops.
    """
    if x0.dtype != torch.float64 or kkt.h.dtype != torch.float64:
        raise TypeError(
            f"solve_ipm needs float64 data, got {x0.dtype} / {kkt.h.dtype}: near convergence the Newton systems span "
            "~30 orders of magnitude, and in float32 many problems stall far from their tolerance (cast first)"
        )
    with torch.inference_mode():  # no autograd bookkeeping (cheaper small operations); returns normal tensors
        res = _solve(kkt, x0, z0, settings)
    return IPMResult(*(t.clone() for t in (res.x, res.s, res.z, res.converged, res.iterations, res.passes)))


def _solve(kkt: KKTSystem, x0: Tensor, z0: Tensor, settings: IPMSettings) -> IPMResult:
    """:func:`solve_ipm` (in inference mode)."""
    st = settings
    feas_tol = st.tol if st.feas_tol is None else st.feas_tol
    dtype, dev = x0.dtype, x0.device
    floor = 1e-300
    b, m = kkt.h.shape
    n, mm = x0.shape[-1], max(m, 1)  # (mm: the mean complementarity of a problem without rows is 0)
    s0 = (kkt.h - kkt.g_mul(x0)).clamp_min(st.min_slack)
    # the iterate (x, s, z) as one tensor (B, n + 2m): fewer operations per iteration on small problems
    v = torch.cat((x0, s0, z0), -1)
    # per problem: the returned iterate, converged, Newton steps attempted, passes that count (written at its stop)
    out = v.clone()
    converged = torch.zeros(b, dtype=torch.bool, device=dev)
    iters = torch.zeros(b, dtype=torch.int64, device=dev)
    counted = torch.zeros(b, dtype=torch.int64, device=dev)
    tols = torch.tensor([feas_tol, feas_tol, st.tol], dtype=dtype, device=dev)
    # the working set: a problem that stops is frozen (it no longer moves; what it returns is recorded), and the
    # frozen problems are dropped once they are a quarter of the set (fewer gathers than dropping them at once)
    idx = torch.arange(b, device=dev)
    w = kkt
    best = torch.full((b,), torch.inf, dtype=dtype, device=dev)
    bv = v
    broken = torch.zeros(b, dtype=torch.bool, device=dev)
    frozen = torch.zeros(b, dtype=torch.bool, device=dev)
    conv_w, iters_w, counted_w = converged, iters, counted
    for k in range(st.max_iter + 1 if b else 0):
        x, s, z = v.split((n, m, m), -1)
        gx, px, gz = w.g_mul(x), w.p_mul(x), w.gt_mul(z)
        r_d = px + w.q + gz
        r_p = gx + s - w.h
        sz = s * z
        mu = sz.sum(-1, keepdim=True) / mm
        dual_scale = w.dual_scale
        if st.dual_relative:
            dual_scale = torch.maximum(dual_scale, _amax(torch.cat((px, gz), -1).abs()))
        e_p = (gx - w.h).clamp_min(0.0) if st.primal_violation else r_p.abs()
        num = torch.stack((_amax(r_d.abs()), _amax(e_p), mu[:, 0]), -1)
        den = torch.stack(
            (dual_scale, w.primal_scale, w.dual_scale if st.gap_relative else torch.ones_like(mu[:, 0])), -1
        )
        err = num / den  # (B, 3): dual, primal, gap
        done = (err <= tols).all(-1) & ~broken
        ok = done
        if st.best_iterate:
            merit = err.amax(-1)
            better = (merit < best) & ~broken
            best = torch.where(better, merit, best)
            bv = torch.where(better[:, None], v, bv)
        else:
            bv = v
            if st.loose_tol is not None:  # decides only for the problems that stop now without converging
                ok = done | (err <= st.loose_tol).all(-1)
        # a problem stops when it has converged, after a breakdown (flagged at the previous pass and not moved
        # since: it counts up to that pass), or after max_iter steps; it has then attempted k steps
        stop = done | broken | frozen if k < st.max_iter else torch.ones_like(done)
        new = stop & ~frozen
        conv_w = torch.where(new, ok, conv_w)
        iters_w = torch.where(new, k, iters_w)
        counted_w = torch.where(new, k + 1 - broken.long(), counted_w)
        frozen = stop
        num_frozen = int(frozen.sum())  # (the one synchronization per iteration)
        if 4 * num_frozen >= idx.numel():  # record and drop the frozen problems
            gone = frozen.nonzero()[:, 0]
            sel = idx[gone]
            out[sel], converged[sel], iters[sel], counted[sel] = bv[gone], conv_w[gone], iters_w[gone], counted_w[gone]
            if num_frozen == idx.numel():
                break
            keep = (~frozen).nonzero()[:, 0]
            idx, w = idx[keep], w.take(keep)
            v, bv, best, sz, r_d, r_p, mu = v[keep], bv[keep], best[keep], sz[keep], r_d[keep], r_p[keep], mu[keep]
            conv_w, iters_w, counted_w, frozen = conv_w[keep], iters_w[keep], counted_w[keep], frozen[keep]
            x, s, z = v.split((n, m, m), -1)

        sys_, factored = w.newton(s, z, r_d, r_p)
        neg_sz = -v[:, n:]  # -(s, z)
        # predictor (affine scaling)
        _, ds, dz = sys_.direction(-sz)
        alpha = _max_step(neg_sz, torch.cat((ds, dz), -1))
        mu_aff = ((s + alpha * ds) * (z + alpha * dz)).sum(-1, keepdim=True) / mm
        sigma = (mu_aff / mu.clamp_min(floor)).clamp(0.0, st.sigma_max) ** 3
        # corrector
        d = torch.cat(sys_.direction(sigma * mu - sz - ds * dz), -1)
        alpha = 0.99 * _max_step(neg_sz, d[:, n:])
        vn = v + alpha * d
        vn[:, n:].clamp_min_(floor)  # (a step keeps 1% of each positive entry: this only lifts exact zeros)
        if st.safeguard:  # a centred step where the corrected one reduces mean(s z) too little (z0 > 0 here)
            mu_new = (vn[:, n : n + m] * vn[:, n + m :]).sum(-1, keepdim=True) / mm
            weak = (mu_new > (1.0 - 0.1 * alpha) * mu) & ~frozen[:, None]
            if bool(weak.any()):  # (only then: the work is skipped, the results are the same)
                c = torch.cat(sys_.direction(sigma.clamp(min=0.1) * mu - sz), -1)
                vc = v + 0.99 * _max_step(neg_sz, c[:, n:]) * c
                vc[:, n:].clamp_min_(floor)
                vn = torch.where(weak, vc, vn)
        broken = ~(factored & torch.isfinite(vn.sum(-1)))  # (a non-finite entry makes the sum non-finite)
        v = torch.where((broken | frozen)[:, None], v, vn)
    x, s, z = out.split((n, m, m), -1)
    return IPMResult(x, s, z, converged, iters, counted.amax() if b else counted.new_zeros(()))
