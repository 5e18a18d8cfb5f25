"""The batched interior-point core (egcbf.qp.ipm) and its two Newton backends: KKT conditions on random strictly
convex QPs, agreement with PIQP, agreement of the dense and the structured backend, float32, batch independence."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from egcbf.algo.qp import CBFQPKKT, solve_cbf_qp
from egcbf.qp.dense_ipm import DenseKKT, dense_settings, polish_dense, solve_dense_ipm
from egcbf.qp.ipm import IPMSettings, solve_ipm

F64 = torch.float64
DENSE = dense_settings()  # the settings solve_dense_ipm uses (the decentralized CBF-QP's)


def random_qps(seed: int, batch: int, n: int, m: int, dtype=F64):
    """``batch`` strictly convex QPs ``min 1/2 x'Px + q'x s.t. G x <= h`` with a strictly feasible point."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(batch, n, n, generator=g, dtype=F64)
    P = a @ a.mT / n + 0.1 * torch.eye(n, dtype=F64)
    q = 3 * torch.randn(batch, n, generator=g, dtype=F64)
    G = torch.randn(batch, m, n, generator=g, dtype=F64)
    x_in = 0.5 * torch.randn(batch, n, generator=g, dtype=F64)
    h = (G @ x_in[..., None])[..., 0] + 0.01 + torch.rand(batch, m, generator=g, dtype=F64)
    return tuple(t.to(dtype) for t in (P, q, G, h))


def piqp_solve(P, q, G, h) -> np.ndarray:
    """Reference solutions by PIQP (a core dependency; proxsuite 0.6 wrongly reports some of these QPs infeasible)."""
    import piqp

    out = []
    for k in range(q.shape[0]):
        solver = piqp.DenseSolver()
        solver.settings.eps_abs = 1e-11
        solver.settings.eps_rel = 0.0
        solver.setup(P[k].numpy(), q[k].numpy(), None, None, G[k].numpy(), None, h[k].numpy())
        assert solver.solve() == piqp.PIQP_SOLVED
        out.append(np.array(solver.result.x))
    return np.stack(out)


def kkt_residuals(P, q, G, h, x, s, z) -> dict[str, Tensor]:
    """Per problem: stationarity relative to ``max(1 + |q|, |Px|, |G'z|)`` (the solver's own scale), primal
    residual relative to ``1 + |h|``, sign violation, complementarity ``max(s z)`` relative to ``1 + |q|``."""
    px, gz = (P @ x[..., None])[..., 0], (G.mT @ z[..., None])[..., 0]
    dual = torch.maximum(1 + q.abs().amax(-1), torch.cat((px, gz), -1).abs().amax(-1))
    return {
        "stationarity": (px + q + gz).abs().amax(-1) / dual,
        "primal": ((G @ x[..., None])[..., 0] + s - h).abs().amax(-1) / (1 + h.abs().amax(-1)),
        "sign": torch.cat((s, z), -1).clamp(max=0).abs().amax(-1),
        "complementarity": (s * z).amax(-1) / (1 + q.abs().amax(-1)),
    }


# ---------------------------------------------------------------------------------------------- the core itself
@given(seed=st.integers(0, 2**20), batch=st.integers(1, 6), n=st.integers(1, 6), m=st.integers(1, 10))
@settings(max_examples=30, deadline=None)
def test_core_satisfies_kkt_and_matches_piqp(seed, batch, n, m):
    """Every converged QP satisfies the KKT conditions to the solver's tolerances (the last iterate, as the dense
    settings return it) and its solution is PIQP's. (A few of these random QPs do not converge in 60 steps, as with
    the numpy solver this core replaced; their rate is tested below.)"""
    P, q, G, h = random_qps(seed, batch, n, m)
    res = solve_ipm(DenseKKT.build(P, q, G, h), torch.zeros_like(q), torch.ones_like(h), DENSE)
    assert res.x.shape == (batch, n) and res.s.shape == res.z.shape == (batch, m)
    assert res.iterations.shape == (batch,) and (res.iterations <= DENSE.max_iter).all()
    ok = res.converged
    r = kkt_residuals(P, q, G, h, res.x, res.s, res.z)
    assert (r["stationarity"][ok] <= 1e-7).all() and (r["primal"][ok] <= 1e-7).all(), r
    assert (r["sign"] == 0).all() and (r["complementarity"][ok] <= 1e-7).all(), r
    ref = piqp_solve(P, q, G, h)
    np.testing.assert_allclose(res.x[ok].numpy(), ref[ok.numpy()], rtol=0, atol=1e-5)
    # with polishing (the public dense solver): exact to rounding where the active set is identified
    x, okp, it = solve_dense_ipm(P, q, G, h)
    assert torch.equal(okp, ok) and torch.equal(it, res.iterations)
    np.testing.assert_allclose(x[ok].numpy(), ref[ok.numpy()], rtol=0, atol=1e-5)


def test_most_random_qps_converge_and_polish_exactly():
    P, q, G, h = random_qps(7, 400, 4, 8)
    res = solve_ipm(DenseKKT.build(P, q, G, h), torch.zeros_like(q), torch.ones_like(h), DENSE)
    _, polished = polish_dense(P, q, G, h, res.x, res.s, res.z)
    x, ok, _ = solve_dense_ipm(P, q, G, h)
    assert ok.float().mean() >= 0.97 and torch.equal(ok, res.converged)
    assert (polished & ok).float().mean() >= 0.9
    ref = piqp_solve(P, q, G, h)
    np.testing.assert_allclose(x[ok].numpy(), ref[ok.numpy()], rtol=0, atol=1e-6)
    # a polished solution satisfies the KKT conditions up to its regularization (active rows shifted by 1e-12 lam):
    # feasible to 1e-10 relative, and no worse than PIQP's
    sel = polished & ok
    xs, r = x[sel], torch.as_tensor(ref)[sel]
    Ps, qs, Gs, hs = P[sel], q[sel], G[sel], h[sel]
    assert ((Gs @ xs[..., None])[..., 0] - hs).amax(-1).le(1e-10 * (1 + hs.abs().amax(-1))).all()

    def objective(v):
        return 0.5 * (v[:, None, :] @ Ps @ v[..., None])[:, 0, 0] + (qs * v).sum(-1)

    assert (objective(xs) <= objective(r) + 1e-10 * (1 + objective(r).abs())).all()


@given(seed=st.integers(0, 2**20), n=st.integers(1, 5), m=st.integers(1, 8))
@settings(max_examples=15, deadline=None)
def test_a_batch_is_solved_as_its_problems_alone(seed, n, m):
    """Converged problems leave the working set: solving them together or one by one gives the same answers."""
    P, q, G, h = random_qps(seed, 5, n, m)
    x, ok, it = solve_dense_ipm(P, q, G, h, polish=False)
    for k in range(5):
        xk, okk, itk = solve_dense_ipm(P[k : k + 1], q[k : k + 1], G[k : k + 1], h[k : k + 1], polish=False)
        assert bool(okk[0]) == bool(ok[k]) and int(itk[0]) == int(it[k])
        torch.testing.assert_close(xk[0], x[k], rtol=0, atol=1e-9)


def test_iteration_cap_and_loose_acceptance():
    """max_iter bounds the Newton steps; a QP stopped early is accepted only if it meets loose_tol."""
    P, q, G, h = random_qps(3, 40, 4, 9)
    kkt = DenseKKT.build(P, q, G, h)
    full = solve_ipm(kkt, torch.zeros_like(q), torch.ones_like(h), DENSE)
    assert full.converged.all() and int(full.iterations.max()) > 4
    short = solve_ipm(kkt, torch.zeros_like(q), torch.ones_like(h), IPMSettings(**{**DENSE.__dict__, "max_iter": 4}))
    assert int(short.iterations.max()) == 4 and not short.converged.all()
    strict = IPMSettings(**{**DENSE.__dict__, "max_iter": 4, "loose_tol": None})
    assert not solve_ipm(kkt, torch.zeros_like(q), torch.ones_like(h), strict).converged.any()
    with pytest.raises(ValueError, match="loose_tol"):
        IPMSettings(best_iterate=True, loose_tol=1e-7)


def test_empty_batch():
    P, q, G, h = random_qps(0, 0, 3, 4)
    x, ok, it = solve_dense_ipm(P, q, G, h)
    assert x.shape == (0, 3) and ok.shape == it.shape == (0,)


def test_float32_is_refused():
    """float64 only: in float32 many problems stall far from any useful tolerance (measured: with tol = feas_tol =
    1e-5, 29 of 200 random QPs did not converge and the others were up to 9e-3 from the float64 solution)."""
    P, q, G, h = random_qps(0, 4, 3, 5, dtype=torch.float32)
    with pytest.raises(TypeError, match="float64"):
        solve_ipm(DenseKKT.build(P, q, G, h), torch.zeros_like(q), torch.ones_like(h), DENSE)
    with pytest.raises(TypeError, match="float64"):
        solve_dense_ipm(P, q, G, h)
    # the learned-CBF QP casts its inputs to float64 itself
    a, rhs, u_ref, lo, hi = (t.float() for t in learned_cbf_problem(0, 2, 3, 2))
    res = solve_cbf_qp(torch.zeros_like(rhs), rhs, a.view(2, 3, 3, 2), u_ref.view(2, 3, 2), lo[:2], hi[:2], alpha=0.1)
    assert res.u.dtype == F64 and res.converged.all()


# ------------------------------------------------------------------------------------------ the two backends
def learned_cbf_problem(seed: int, b: int, n: int, k: int):
    """A random learned-CBF QP batch: ``a`` ``(b, n, k n)``, ``rhs`` ``(b, n)``, ``u_ref`` ``(b, k n)``, box."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(b, n, k * n, generator=g, dtype=F64)
    rhs = 2 * torch.randn(b, n, generator=g, dtype=F64)
    lo, hi = -torch.ones(k * n, dtype=F64), torch.ones(k * n, dtype=F64)
    u_ref = (1.5 * torch.randn(b, k * n, generator=g, dtype=F64)).clamp(-1, 1)
    return a, rhs, u_ref, lo, hi


def as_dense(kkt: CBFQPKKT):
    """The same QPs with explicit ``P``, ``G`` (the rows of :class:`CBFQPKKT`)."""
    b, n, nu = kkt.a.shape
    P = torch.diag(torch.cat((torch.ones(nu, dtype=F64), torch.full((n,), kkt.w2, dtype=F64))))
    eye_u, eye_s = torch.eye(nu, dtype=F64).expand(b, nu, nu), torch.eye(n, dtype=F64).expand(b, n, n)
    zs, zu = torch.zeros(b, nu, n, dtype=F64), torch.zeros(b, n, nu, dtype=F64)
    G = torch.cat(
        (
            torch.cat((-kkt.a, -eye_s), -1),  # -(a u + s) <= b
            torch.cat((zu, -eye_s), -1),  # -s <= 0
            torch.cat((eye_u, zs), -1),  # u <= hi
            torch.cat((-eye_u, zs), -1),  # -u <= -lo
        ),
        -2,
    )
    return P, kkt.q, G, kkt.h


@given(seed=st.integers(0, 2**20), b=st.integers(1, 4), n=st.integers(1, 5), k=st.integers(1, 3))
@settings(max_examples=20, deadline=None)
def test_dense_and_structured_backends_agree(seed, b, n, k):
    a, rhs, u_ref, lo, hi = learned_cbf_problem(seed, b, n, k)
    structured = CBFQPKKT.build(a, rhs, u_ref, lo, hi, w1=50.0, w2=10.0)
    dense = DenseKKT.build(*as_dense(structured))
    # the same products
    xr = torch.randn(b, k * n + n, dtype=F64)
    zr = torch.rand(b, 2 * n + 2 * k * n, dtype=F64)
    for f in ("p_mul", "g_mul", "gt_mul"):
        arg = zr if f == "gt_mul" else xr
        torch.testing.assert_close(getattr(structured, f)(arg), getattr(dense, f)(arg), rtol=1e-13, atol=1e-13)
    # the same Newton directions
    s_, z_ = torch.rand_like(zr) + 0.1, torch.rand_like(zr) + 0.1
    r_d, r_p, rc = torch.randn_like(xr), torch.randn_like(zr), torch.randn_like(zr)
    (ns, oks), (nd, okd) = structured.newton(s_, z_, r_d, r_p), dense.newton(s_, z_, r_d, r_p)
    assert oks.all() and okd.all()
    for u, v in zip(ns.direction(rc), nd.direction(rc)):
        torch.testing.assert_close(u, v, rtol=1e-9, atol=1e-9)
    # the same solutions, with either caller's settings
    x0 = torch.cat((u_ref, torch.full_like(rhs, 0.1)), -1)
    for cfg in (IPMSettings(tol=1e-8, max_iter=49, min_slack=0.1, sigma_max=1.0), DENSE):
        rs = solve_ipm(structured, x0, torch.ones_like(structured.h), cfg)
        rd = solve_ipm(dense, x0, torch.ones_like(dense.h), cfg)
        assert torch.equal(rs.converged, rd.converged) and torch.equal(rs.iterations, rd.iterations)
        torch.testing.assert_close(rs.x[rs.converged], rd.x[rd.converged], rtol=0, atol=1e-7)
    # and the learned-CBF QP's solver agrees with the polished dense solution to its tolerance (merit 1e-8: the gap,
    # which bounds the distance to the optimum by ~1e-4 where a constraint is weakly active)
    res = solve_cbf_qp(torch.zeros_like(rhs), rhs, a.view(b, n, n, k), u_ref.view(b, n, k), lo[:k], hi[:k],
                       alpha=0.3, slack_linear=50.0)  # fmt: skip
    xd, okd, _ = solve_dense_ipm(*as_dense(CBFQPKKT.build(a, rhs, u_ref, lo, hi, w1=50.0, w2=10.0)))
    assert res.converged.all() and okd.all()
    torch.testing.assert_close(res.u.reshape(b, -1), xd[:, : k * n], rtol=0, atol=1e-3)
    torch.testing.assert_close(res.slack, xd[:, k * n :].clamp_min(0), rtol=0, atol=1e-3)
