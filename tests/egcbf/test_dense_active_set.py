"""The batched dual active-set solver of the per-agent filter QPs (egcbf.qp.dense_active_set) and the filters'
``qp_solver`` setting: on random batches (hypothesis, float64: padded rows, duplicate and parallel rows, rows that
conflict without the slack, yaw boxes, no CBF rows) its solutions meet the KKT conditions to 1e-9 (multipliers by a
non-negative least squares on the active rows), agree with the exported runtime's single-agent Goldfarb-Idnani
(:func:`egcbf.deploy.runtime.solve_qp`) to 1e-10, and the interior-point method's objective is no better; the
``cbf`` and ``prior`` filters give the interior-point method's commands within 1e-7 m/s^2 (but where the IPM falls
short on a degenerate QP); the settings record the solver (and the ``dcbf`` filter's stay as they were); the
learner's target keeps the IPM."""

import dataclasses
import functools
import inspect

import numpy as np
import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from egcbf.algo.config import TrainConfig
from egcbf.algo.edge_qp import SOLVERS, edge_qp_commands
from egcbf.control.filters import QP_SOLVERS, FilterConfig, FilteredController
from egcbf.deploy.runtime import solve_qp
from egcbf.env import EnvConfig, SwarmState
from egcbf.nn import CBFNet, PolicyNet
from egcbf.qp.dense_active_set import solve_dense_batch_active_set
from egcbf.qp.dense_qp import DenseBatchQP, solve_dense_batch_ipm
from egcbf.qp.ipm import INF
from egcbf.qp.sparse_qp import SlackPenalty
from egcbf.reproduce.plan import filter_settings
from egcbf.robots.quadrotor.barriers import AccelBounds, bound_rows

BOX = AccelBounds(7.0, -4.9, 7.0, polygon=2)  # the quadrotor's acceleration interface's box


def random_batch(seed: int, m: int, k: int, scale: float, penalty: SlackPenalty | None = None) -> DenseBatchQP:
    """``m`` agents with up to ``k`` CBF rows each: unit normals, right-hand sides of size ``scale`` (some agents'
    references feasible), about a quarter padding, exact duplicates, parallel rows with other right-hand sides,
    opposite pairs that only the slack reconciles, yaw boxes of random yaw, references inside and outside."""
    rng = np.random.default_rng(seed)
    nrm = rng.normal(size=(m, k, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    rhs = scale * rng.normal(size=(m, k))
    if k >= 2:
        dup = rng.random(m) < 0.5
        nrm[dup, 1], rhs[dup, 1] = nrm[dup, 0], rhs[dup, 0]  # exact duplicates
        par = rng.random(m) < 0.3
        nrm[par, 1], rhs[par, 1] = nrm[par, 0], rhs[par, 0] - rng.random(par.sum())  # parallel, less binding
    if k >= 4:
        opp = rng.random(m) < 0.3
        nrm[opp, 3] = -nrm[opp, 2]
        rhs[opp, 2], rhs[opp, 3] = 1.0 + rng.random(opp.sum()), 1.0 + rng.random(opp.sum())  # slack needed
    pad = rng.random((m, k)) < 0.25
    nrm[pad], rhs[pad] = 0.0, -INF
    psi = rng.uniform(-np.pi, np.pi, m)
    rot = np.zeros((m, 9))
    rot[:, 0], rot[:, 1], rot[:, 3], rot[:, 4], rot[:, 8] = np.cos(psi), -np.sin(psi), np.sin(psi), np.cos(psi), 1.0
    bC, blo, bhi = bound_rows(rot, BOX)
    a_nom = rng.normal(size=(m, 3)) * rng.choice([0.1, 2.0, 10.0], size=(m, 1))
    return DenseBatchQP(a_nom, nrm, rhs, bC, blo, bhi, penalty or SlackPenalty())


def rows(q: DenseBatchQP, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Agent ``i``'s rows ``M z >= b`` (padding left out), as ``(R, 4)``, ``(R,)``."""
    keep = q.cbf_rhs[i] > -INF / 2
    n, r = q.cbf_normal[i][keep], q.cbf_rhs[i][keep]
    C = q.bound_C[i]
    M = np.concatenate((np.c_[n, np.ones(len(n))], np.c_[C, np.zeros(len(C))], np.c_[-C, np.zeros(len(C))],
                        [[0.0, 0.0, 0.0, 1.0]]))  # fmt: skip
    return M, np.concatenate((r, q.bound_lo[i], -q.bound_hi[i], [0.0]))


def with_slack(q: DenseBatchQP, a: np.ndarray) -> np.ndarray:
    """``z = (a, s)`` ``(M, 4)`` with the optimal slack of the accelerations ``a``: ``max(0, rows' shortfall)``."""
    short = np.where(q.cbf_rhs <= -INF / 2, 0.0, q.cbf_rhs - np.einsum("mkd,md->mk", q.cbf_normal, a))
    return np.c_[a, np.maximum(short.max(1, initial=0.0), 0.0)]


def objective(q: DenseBatchQP, z: np.ndarray) -> np.ndarray:
    a, s = z[:, :3], z[:, 3]
    return 0.5 * ((a - q.a_nom) ** 2).sum(1) + 0.5 * q.penalty.w2 * s**2 + q.penalty.w1 * s


def kkt_violation(q: DenseBatchQP, i: int, z: np.ndarray) -> dict:
    """Agent ``i``'s KKT residuals at ``z`` ``(4,)``: primal (relative to ``1 + |b|``), and stationarity of the
    best non-negative multipliers ``lam`` on the rows active within 1e-9 (relative to ``1 + |gradient|``;
    complementarity and dual feasibility hold by construction), and those multipliers (0 on the other rows)."""
    M, b = rows(q, i)
    res = M @ z - b
    primal = float(np.maximum(-res / (1.0 + np.abs(b)), 0.0).max())
    grad = np.r_[z[:3] - q.a_nom[i], q.penalty.w2 * z[3] + q.penalty.w1]  # H z + g = M_A' lam
    act = res <= 1e-9 * (1.0 + np.abs(b))
    lam = np.zeros(len(b))
    if act.any():
        lam[act], _ = nnls(M[act].T, grad)
    stat = float(np.abs(M.T @ lam - grad).max())
    return {"primal": primal, "stationarity": stat / (1.0 + np.abs(grad).max()), "lam": lam}


@given(
    seed=st.integers(0, 2**31), m=st.integers(1, 12), k=st.integers(0, 10),
    scale=st.sampled_from([0.1, 1.0, 5.0, 100.0]), w1=st.sampled_from([0.0, 1.0, 1e3]),
    w2=st.sampled_from([0.1, 1.0, 1e2, 1e4]),
)  # fmt: skip
@settings(max_examples=150, deadline=None)
def test_active_set_solutions_meet_the_kkt_conditions(seed, m, k, scale, w1, w2):
    """Exact: primal feasibility, dual feasibility, complementarity and stationarity to 1e-9; the runtime's
    single-agent solver to 1e-10; the interior-point method's objective is no better (up to what its small
    infeasibility buys, by duality). (Its solutions are not compared directly: on degenerate QPs, e.g. duplicate
    rows or a reference on the box, it stops short of its tolerance, 1e-6 and more away from the optimum.)"""
    q = random_batch(seed, m, k, scale, SlackPenalty(w1, w2))
    z, ok, it = solve_dense_batch_active_set(q)
    assert z.shape == (m, 4) and ok.shape == it.shape == (m,) and z.dtype == np.float64
    assert ok.all()
    zi, oki, _ = solve_dense_batch_ipm(q)
    f_as, f_ipm = objective(q, z), objective(q, zi)
    for i in range(m):
        kkt = kkt_violation(q, i, z[i])
        assert kkt["primal"] <= 1e-9 and kkt["stationarity"] <= 1e-9, (i, kkt)
        keep = q.cbf_rhs[i] > -INF / 2
        zr, okr = solve_qp(q.a_nom[i], q.cbf_normal[i][keep], q.cbf_rhs[i][keep], q.bound_C[i], q.bound_lo[i],
                           q.bound_hi[i], w1, w2)  # fmt: skip
        if okr:
            assert np.abs(zr - z[i]).max() <= 1e-10 * (1.0 + np.abs(zr).max())
        if oki[i]:  # by duality f(z_as) - lam' (M z_as - b) <= f(z) - lam' (M z - b) for any z, the IPM's too
            M, b, lam = *rows(q, i), kkt["lam"]
            bound = f_ipm[i] + lam @ np.maximum(b - M @ zi[i], 0.0) + lam @ np.abs(M @ z[i] - b)
            # (rounding: in the scaled variables the objective is 1/2 |y - y0|^2 - w1^2 / (2 w2), |y - y0| large)
            assert f_as[i] <= bound + 1e-10 + 1e-14 * (abs(f_ipm[i]) + w1**2 / w2)


def test_agents_whose_reference_is_feasible_keep_it():
    q = random_batch(3, 40, 6, 1.0)
    q.a_nom[:] = 0.0  # inside the box
    q.cbf_rhs[:20] = np.where(q.cbf_rhs[:20] > -INF / 2, -1.0, -INF)  # met at a = 0, s = 0
    z, ok, it = solve_dense_batch_active_set(q)
    assert ok.all() and np.all(it[:20] == 0) and np.all(z[:20] == 0.0)
    _, _, iti = solve_dense_batch_ipm(q)
    assert np.array_equal(it == 0, iti == 0)  # the same agents skipped


def test_agents_without_cbf_rows_are_clipped_into_their_box():
    q = random_batch(5, 30, 0, 1.0)
    q.a_nom[:] = np.random.default_rng(0).normal(size=(30, 3)) * 20.0
    z, ok, _ = solve_dense_batch_active_set(q)
    assert ok.all() and np.abs(z[:, 3]).max() <= 1e-12
    ca = np.einsum("mkd,md->mk", q.bound_C, z[:, :3])
    assert np.all(ca >= q.bound_lo - 1e-12) and np.all(ca <= q.bound_hi + 1e-12)
    for i in range(30):
        assert kkt_violation(q, i, z[i])["stationarity"] <= 1e-12


def test_infeasible_and_unconverged_agents_are_flagged():
    q = random_batch(7, 6, 3, 1.0)
    q.a_nom[:] = 20.0  # outside every box: every agent is solved
    q.bound_lo[1, 0], q.bound_hi[1, 0] = 1.0, -1.0  # lo > hi
    q.bound_C[2, 1] = 0.0
    q.bound_lo[2, 1] = 0.5  # a zero row that must reach 0.5
    _, ok, _ = solve_dense_batch_active_set(q)
    assert not ok[1] and not ok[2] and ok[[0, 3, 4, 5]].all()
    _, ok1, it1 = solve_dense_batch_active_set(q, max_iter=1)
    assert not ok1.any() and np.all(it1 <= 1)


def test_degenerate_inputs():
    empty = random_batch(0, 0, 3, 1.0)
    z, ok, it = solve_dense_batch_active_set(empty)
    assert z.shape == (0, 4) and ok.shape == it.shape == (0,)
    with pytest.raises(ValueError, match="w2 > 0"):
        solve_dense_batch_active_set(random_batch(0, 2, 2, 1.0, SlackPenalty(1.0, 0.0)))
    q = random_batch(4, 5, 3, 1.0)
    q.a_nom[1, 0], q.cbf_rhs[2, 0], q.cbf_normal[3, 1, 2], q.cbf_rhs[3, 1] = np.nan, np.nan, np.inf, 0.5
    _, ok, _ = solve_dense_batch_active_set(q)
    assert ok.tolist() == [True, False, False, False, True]
    # w1 < 0: the slack pays to be used; solved from the unconstrained minimizer
    q = random_batch(9, 8, 4, 1.0, SlackPenalty(-1.0, 2.0))
    z, ok, _ = solve_dense_batch_active_set(q)
    assert ok.all() and all(kkt_violation(q, i, z[i])["stationarity"] <= 1e-9 for i in range(8))


# ------------------------------------------------------------------------------------- the filters' setting
@functools.cache
def _nets():
    """The cpu preset's networks (small), moved off their zero-initialized priors (as tests/egcbf/test_filters.py)."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(TrainConfig.preset("egcbf+", "cpu").model, hidden=16, head_hidden=16)
    cbf, pol = CBFNet(cfg).double(), PolicyNet(cfg).double()
    with torch.no_grad():
        for p in (*cbf.parameters(), *pol.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    return cbf.eval(), pol.eval(), cfg


def _scene(num_agents: int, seed: int, obstacles: int = 2) -> tuple[SwarmState, EnvConfig]:
    cfg = EnvConfig(num_agents=num_agents, num_envs=2, area_size=1.5, num_obstacles=obstacles, n_rays=8,
                    lidar_max_hits=4)  # fmt: skip
    state = moving_scene(cfg, seed)
    x = state.x.clone()
    x[..., 12:15] *= 0.5
    return SwarmState(x, state.goals, state.obstacles), cfg


@pytest.mark.parametrize("kind", ["cbf", "prior"])
@given(seed=st.integers(0, 2**20))
@settings(max_examples=8, deadline=None)
def test_the_filters_commands_do_not_depend_on_the_solver(kind, seed):
    """The ``cbf`` and ``prior`` filters with the active-set and the interior-point solver: the same commands
    within 1e-7 m/s^2 (float64) and the same counts, except for a few agents where the IPM's own tolerance allows
    more (its stationarity is relative to the slack's cost w1 = 1e3: seen 2e-7 m/s^2) or where it stops short of
    it (a degenerate QP, e.g. a reference on an edge of the box that the IPM's rounding finds a hair outside: seen
    5e-5 m/s^2): there the active set's command meets the KKT conditions to 1e-9 and is no worse than the IPM's."""
    cbf, pol, cfg = _nets()
    state, ecfg = _scene(8, seed)
    qps, solve, out = [], SOLVERS["active_set"], {}
    with pytest.MonkeyPatch.context() as mp:  # record the QPs
        mp.setitem(SOLVERS, "active_set", lambda q, **kw: qps.append(q) or solve(q, **kw))
        for solver in QP_SOLVERS:
            ctrl = FilteredController(
                pol, cfg, FilterConfig(kind=kind, qp_solver=solver), cbf if kind == "cbf" else None
            )
            out[solver] = ctrl(state, ecfg)[1]
    a, b = out["active_set"], out["ipm"]
    assert a["num_failed"] == b["num_failed"] == 0 and a["num_active"] > 0
    diff = (a["a_safe"] - b["a_safe"]).abs().amax(-1).reshape(-1).numpy()
    (q,) = qps
    za, zb = (with_slack(q, info["a_safe"].reshape(-1, 3).numpy()) for info in (a, b))
    f_a, f_b = objective(q, za), objective(q, zb)
    for i in np.nonzero(diff > 1e-7)[0]:  # the exact one, and no worse than the IPM's (module doc's duality bound)
        kkt = kkt_violation(q, i, za[i])
        assert kkt["primal"] <= 1e-9 and kkt["stationarity"] <= 1e-9
        M, rhs, lam = *rows(q, i), kkt["lam"]
        bound = f_b[i] + lam @ np.maximum(rhs - M @ zb[i], 0.0) + lam @ np.abs(M @ za[i] - rhs)
        assert f_a[i] <= bound + 1e-10 + 1e-14 * (abs(f_b[i]) + q.penalty.w1**2 / q.penalty.w2)
    assert (diff > 1e-7).mean() <= 0.1
    if diff.max() <= 1e-7:
        assert a["num_slack"] == b["num_slack"] and a["num_active"] == b["num_active"]


def test_settings_record_the_solver_and_dcbf_is_unchanged():
    assert FilterConfig.for_kind("dcbf").settings() == {"barrier": "wang", "gamma": 50.0, "margin": 0.02,
                                                        "brake_accel": 3.0}  # fmt: skip
    assert FilterConfig.for_kind("dcbf", obstacle_sensing="lidar", lidar_hits="point").settings() == {
        "barrier": "wang", "gamma": 50.0, "margin": 0.02, "brake_accel": 3.0, "obstacle_sensing": "lidar",
        "lidar_hits": "point",
    }  # fmt: skip
    assert filter_settings("egcbf+:dcbf") == {
        "filter": "dcbf", "filter_config": {"barrier": "wang", "gamma": 50.0, "margin": 0.02, "brake_accel": 3.0}
    }  # fmt: skip
    assert FilterConfig(kind="dcbf").qp_solver is None
    for kind in ("cbf", "prior"):
        assert FilterConfig.for_kind(kind).settings() == {"alpha": 1.0, "margin": 0.0, "qp_solver": "active_set"}
        assert FilterConfig(kind=kind).qp_solver == "active_set"
        assert FilterConfig.for_kind(kind, qp_solver="ipm").settings()["qp_solver"] == "ipm"
        assert filter_settings(f"egcbf+:{kind}")["filter_config"]["qp_solver"] == "active_set"


def test_the_setting_is_validated():
    with pytest.raises(ValueError, match="qp_solver must be one of"):
        FilterConfig(kind="cbf", qp_solver="osqp")
    with pytest.raises(ValueError, match="qp_solver must be one of"):
        FilterConfig.for_kind("prior", qp_solver="")
    with pytest.raises(ValueError, match="own solver"):
        FilterConfig(kind="dcbf", qp_solver="ipm")
    with pytest.raises(ValueError, match="own solver"):
        FilterConfig.for_kind("dcbf", qp_solver="active_set")
    with pytest.raises(ValueError, match="solver must be one of"):
        edge_qp_commands(None, torch.zeros(1, 1, 18), None, torch.zeros(1, 1, 3), alpha=1.0, margin=0.0, cbf=None,
                         distance=0.25, horizon=1.0, solver="proxsuite")  # fmt: skip


def test_the_learners_target_keeps_the_interior_point_method(monkeypatch):
    """``edge_qp_commands`` (the learner's per-edge target calls it without ``solver``) defaults to the IPM."""
    assert inspect.signature(edge_qp_commands).parameters["solver"].default == "ipm"
    assert set(SOLVERS) == set(QP_SOLVERS)
    calls = []
    monkeypatch.setitem(SOLVERS, "ipm", lambda q, **kw: calls.append(len(q)) or solve_dense_batch_ipm(q, **kw))
    from egcbf.algo import GraphCBFLearner

    cfg = TrainConfig.preset("egcbf+", "tiny", qp_constraints="edges", num_agents=3, area_size=1.0, dtype="float64")
    learner = GraphCBFLearner(cfg)
    data = learner.collect(1).flatten()
    learner.reference(data)
    assert calls
