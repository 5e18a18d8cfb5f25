"""Hand-crafted CBF-QP baselines: barrier rows, sparse assembly, solvers, controllers, safety, equivariance."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from egcbf.control.controllers import NominalController, make_controller
from egcbf.env import EnvConfig, Obstacles, SwarmEnv, SwarmState
from egcbf.qp.constraints import Constraints
from egcbf.qp.dense_qp import assemble_decentralized, solve_dense_batch, solve_dense_batch_ipm
from egcbf.qp.sparse_qp import (
    INF,
    SOLVERS,
    SlackPenalty,
    assemble_centralized,
    dense_reference,
    polish_sparse,
    solve_sparse,
)
from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.barriers import (
    AccelBounds,
    BarrierConfig,
    agent_pairs,
    bound_rows,
    build_constraints,
    prune_redundant,
    split_for_agents,
)
from egcbf.robots.quadrotor.cbf_qp import (
    CentralizedCBFQP,
    default_bounds,
    nominal_acceleration,
    track_acceleration,
)
from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from egcbf.robots.quadrotor.nominal import nominal_control
from egcbf.robots.quadrotor.so3 import so3_exp, yaw_rotation

F64 = torch.float64
BOUNDS = default_bounds()


# ------------------------------------------------------------------------------------------------- scenes
def random_scene(seed: int, n: int = 24, area: float = 1.5, speed: float = 0.8, num_obstacles: int = 2):
    """Agents at least 0.2 m apart with random velocities, tilts and yaws; random goals; a few spheres."""
    gen = torch.Generator().manual_seed(seed)
    pts = []
    while len(pts) < n:
        c = torch.rand(3, generator=gen, dtype=F64) * area
        if all(float((c - q).norm()) > 0.2 for q in pts):
            pts.append(c)
    p = torch.stack(pts)
    yaw = (torch.rand(n, generator=gen, dtype=F64) * 2 - 1) * math.pi
    tilt = torch.randn(n, 3, generator=gen, dtype=F64) * 0.2
    tilt[:, 2] = 0
    R = yaw_rotation(yaw) @ so3_exp(tilt)
    v = torch.randn(n, 3, generator=gen, dtype=F64) * speed
    w = torch.randn(n, 3, generator=gen, dtype=F64) * 0.5
    x = dyn.state_from_parts(p, R, v, w)[None]
    goals = torch.rand(1, n, 3, generator=gen, dtype=F64) * area * 1.5
    centers = torch.rand(1, num_obstacles, 3, generator=gen, dtype=F64) * area + area * 0.2
    radii = 0.05 + 0.1 * torch.rand(1, num_obstacles, generator=gen, dtype=F64)
    # keep obstacles clear of the agents (surface distance > 2 r)
    far = ((p[None, :, None] - centers[:, None]).norm(dim=-1) - radii[:, None] > 0.1).all(1)
    obs = Obstacles(centers[:, far[0]], radii[:, far[0]])
    return SwarmState(x, goals, obs, 0), EnvConfig(num_agents=n, area_size=area, num_obstacles=obs.num_obstacles)


def numpy_rows(seed: int, n: int = 20):
    state, cfg = random_scene(seed, n)
    ctrl = CentralizedCBFQP()
    prep = ctrl._prepare(state, cfg)
    cons = build_constraints(prep.p[0], prep.v[0], prep.barrier, prep.centers[0], prep.radii[0], bounds=prep.bounds)
    return prep, cons


def transform(state: SwarmState, yaw: float, t) -> SwarmState:
    """Act with (Rz(yaw), t): p -> Rz p + t, R -> Rz R, v -> Rz v, w unchanged; goals and obstacles too."""
    Rz = yaw_rotation(torch.tensor(yaw, dtype=F64))
    t = torch.as_tensor(t, dtype=F64)
    p, R, v, w = dyn.unpack(state.x)
    x = dyn.state_from_parts(p @ Rz.T + t, Rz @ R, v @ Rz.T, w)
    obs = Obstacles(state.obstacles.centers @ Rz.T + t, state.obstacles.radii.clone())
    return SwarmState(x, state.goals @ Rz.T + t, obs, state.t)


# ---------------------------------------------------------------------------------------------- barriers
def test_pair_rows_match_barrier_derivative():
    """Row n.(a_i - a_j) >= b is h' + gamma h^3 >= 0 (wang) / h0'' + (k1+k2) h0' + k1 k2 h0 >= 0 (hocbf):
    check the row against finite differences of the barrier along a double-integrator trajectory."""
    rng = np.random.default_rng(0)
    for kind in ("wang", "hocbf"):
        cfg = BarrierConfig(kind=kind, cull_radius=2.0)
        p = np.array([[0.0, 0.0, 0.0], [0.6, 0.1, -0.05]])
        v = rng.normal(size=(2, 3)) * 0.5
        a = rng.normal(size=(2, 3))
        pairs = np.array([[0], [1]])

        def h(p_, v_, cfg=cfg):
            c = build_constraints(p_, v_, cfg)
            return c.h[0]

        cons = build_constraints(p, v, cfg)
        dt = 1e-5

        def at(t, p=p, v=v, a=a):
            return p + v * t + 0.5 * a * t * t, v + a * t

        if kind == "wang":
            hdot = (h(*at(dt)) - h(*at(-dt))) / (2 * dt)
            lhs = hdot + cfg.gamma * cons.h[0] ** 3
        else:
            h0 = cons.h[0]
            h1 = (h(*at(dt)) - h(*at(-dt))) / (2 * dt)
            h2 = (h(*at(dt)) - 2 * h0 + h(*at(-dt))) / dt**2
            lhs = (h2 + (cfg.k1 + cfg.k2) * h1 + cfg.k1 * cfg.k2 * h0) / (2 * cons.dist[0])
        row = cons.residual(a)[0]  # n.(a_i - a_j) - b, the same quantity (normalized)
        assert lhs == pytest.approx(row, rel=1e-5, abs=1e-5), kind
        assert agent_pairs(p, cfg).tolist() == pairs.tolist()


def test_pairs_radius_knn_and_batches():
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 2, size=(60, 3))
    cfg = BarrierConfig(cull_radius=0.6)
    pairs = agent_pairs(pos, cfg)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    ref = np.argwhere(np.triu(d < 0.6, 1))
    assert sorted(map(tuple, pairs.T.tolist())) == sorted(map(tuple, ref.tolist()))
    knn = agent_pairs(pos, BarrierConfig(cull_radius=0.6, max_neighbors=2))
    assert knn.shape[1] <= pairs.shape[1] and (knn[0] < knn[1]).all()
    # two environments never share a pair
    batch = np.repeat([0, 1], 30)
    bp = agent_pairs(pos, cfg, batch)
    assert (batch[bp[0]] == batch[bp[1]]).all()
    assert bp.shape[1] == sum(batch[ref[:, 0]] == batch[ref[:, 1]])


def test_pruning_is_lossless():
    prep, _ = numpy_rows(3, n=30)
    full = build_constraints(prep.p[0], prep.v[0], prep.barrier, prep.centers[0], prep.radii[0])
    pruned = prune_redundant(full, BOUNDS)
    assert len(pruned) < len(full)
    dropped = np.setdiff1d(np.arange(len(full)), np.nonzero(np.isin(full.rhs, pruned.rhs))[0])
    # every dropped row holds at every vertex of the bound sets of its agents
    C, lo, hi = bound_rows(prep.rot[0], BOUNDS)
    rng = np.random.default_rng(0)
    for c in dropped:
        for _ in range(20):
            ai, aj = (_random_in_bounds(rng, C[k], lo[k], hi[k]) for k in (full.i[c], max(full.j[c], 0)))
            lhs = full.normal[c] @ ai - (full.normal[c] @ aj if full.j[c] >= 0 else 0.0)
            assert lhs >= full.rhs[c] - 1e-9


def _random_in_bounds(rng, C, lo, hi):
    while True:
        a = rng.uniform(-8, 8, 3)
        v = C @ a
        if np.all(v >= lo) and np.all(v <= hi):
            return a


def test_split_halves_add_up():
    _, cons = numpy_rows(4)
    owner, normal, rhs = split_for_agents(cons)
    pair = cons.j >= 0
    p = int(pair.sum())
    assert owner.shape[0] == len(cons) + p
    np.testing.assert_allclose(rhs[: len(cons)][pair] + rhs[len(cons) :], cons.rhs[pair])
    np.testing.assert_allclose(normal[len(cons) :], -cons.normal[pair])
    np.testing.assert_array_equal(rhs[: len(cons)][~pair], cons.rhs[~pair])


def test_config_validation():
    with pytest.raises(ValueError, match="kind"):
        BarrierConfig(kind="cubic")
    with pytest.raises(ValueError, match="margin"):
        BarrierConfig(margin=-1.0)
    with pytest.raises(ValueError, match="max_neighbors"):
        BarrierConfig(max_neighbors=0)
    with pytest.raises(ValueError, match="z_min < 0 < z_max"):
        AccelBounds(z_min=1.0)
    state, cfg = random_scene(0, n=4)
    with pytest.raises(ValueError, match="brake_accel"):
        CentralizedCBFQP(brake_accel=50.0)(state, cfg)
    with pytest.raises(ValueError, match="unknown controller"):
        make_controller("mpc")


# ---------------------------------------------------------------------------------------------- assembly
def dense_assembly_reference(a_nom, cons: Constraints, C_b, lo_b, hi_b, pen: SlackPenalty):
    """Row-by-row (loops) dense version of the centralized QP, written independently of the sparse one."""
    n, s = a_nom.shape[0], len(cons)
    nz = 3 * n + s
    H = np.zeros((nz, nz))
    g = np.zeros(nz)
    for i in range(n):
        for d in range(3):
            H[3 * i + d, 3 * i + d] = 1.0
            g[3 * i + d] = -a_nom[i, d]
    rows, lo, hi = [], [], []
    for c in range(s):
        H[3 * n + c, 3 * n + c] = pen.w2
        g[3 * n + c] = pen.w1
        r = np.zeros(nz)
        r[3 * cons.i[c] : 3 * cons.i[c] + 3] += cons.normal[c]
        if cons.j[c] >= 0:
            r[3 * cons.j[c] : 3 * cons.j[c] + 3] -= cons.normal[c]
        r[3 * n + c] = 1.0
        rows.append(r), lo.append(cons.rhs[c]), hi.append(INF)
    for c in range(s):
        r = np.zeros(nz)
        r[3 * n + c] = 1.0
        rows.append(r), lo.append(0.0), hi.append(INF)
    for i in range(n):
        for k in range(C_b.shape[1]):
            r = np.zeros(nz)
            r[3 * i : 3 * i + 3] = C_b[i, k]
            rows.append(r), lo.append(lo_b[i, k]), hi.append(hi_b[i, k])
    return H, g, np.array(rows), np.array(lo), np.array(hi)


def _canonical(C, lo, hi):
    """Rows sorted, so that two constraint sets can be compared as sets of (row, lo, hi)."""
    key = np.concatenate([C, lo[:, None], np.minimum(hi, INF)[:, None]], axis=1)
    return key[np.lexsort(key.T[::-1])]


def test_sparse_assembly_equals_dense_reference():
    prep, cons = numpy_rows(5, n=10)
    pen = SlackPenalty(w1=7.0, w2=3.0)
    qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0], pen)
    H, g, C, lo, hi = dense_reference(qp)
    Hr, gr, Cr, lor, hir = dense_assembly_reference(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0], pen)
    np.testing.assert_allclose(H, Hr)
    np.testing.assert_allclose(g, gr)
    np.testing.assert_allclose(_canonical(C, lo, hi), _canonical(Cr, lor, hir), atol=1e-15)
    assert qp.C.format == "csc" and qp.H.format == "csc"


# -------------------------------------------------------------------------------------------------- solvers
#: the pip package behind each solver name egcbf tests (the optional ones come with the `solvers` extra, in `dev`)
_MODULES = {"piqp": "piqp", "proxsuite": "proxsuite", "osqp": "osqp", "clarabel": "clarabel", "highs": "highspy",
            "qpalm": "qpalm"}  # fmt: skip


@pytest.mark.parametrize("solver", SOLVERS)
def test_solution_satisfies_constraints_up_to_slack(solver):
    pytest.importorskip(_MODULES[solver])
    prep, cons = numpy_rows(6, n=30)
    n = prep.p.shape[1]
    qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0])
    res = solve_sparse(qp, solver, eps_abs=1e-9)
    assert res.ok, res.status
    a, s = res.x[: 3 * n].reshape(n, 3), res.x[3 * n :]
    assert s.min() >= -1e-8
    assert (cons.residual(a) + s).min() >= -1e-7
    bv = np.einsum("nkd,nd->nk", prep.bC[0], a)
    assert (bv - prep.blo[0]).min() >= -1e-7 and (prep.bhi[0] - bv).min() >= -1e-7
    # optimal: matches another solver and cannot be improved along the feasible direction to a_nom
    other = solve_sparse(qp, "proxsuite" if solver == "piqp" else "piqp", eps_abs=1e-9)
    np.testing.assert_allclose(res.x, other.x, atol=1e-4)


@pytest.mark.parametrize("solver", SOLVERS)
def test_solutions_are_those_of_the_adapters_before_qpsolvers(solver):
    """Through qpsolvers every solver egcbf had before returns what its hand-written adapter returned
    (tests/egcbf/qp_reference.py, three scenes of 30-120 agents): the raw solution within 1e-6, and after the polish
    (the exact optimum) within 1e-9 of the adapters' polished one; the solvers added with qpsolvers reach the same
    polished optimum as piqp's adapter did."""
    import json

    from qp_reference import DATA, LEGACY_SOLVERS

    pytest.importorskip(_MODULES[solver])
    for entry in json.loads(DATA.read_text()):
        prep, cons = numpy_rows(entry["seed"], n=entry["n"])
        qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0])
        res = solve_sparse(qp, solver, eps_abs=1e-9)
        polished, _ = polish_sparse(qp, res.x)
        if solver in LEGACY_SOLVERS:
            np.testing.assert_allclose(res.x, entry["solutions"][solver], atol=1e-6, rtol=0)
            np.testing.assert_allclose(polished, entry["polished"][solver], atol=1e-9, rtol=0)
        else:
            np.testing.assert_allclose(polished, entry["polished"]["piqp"], atol=1e-8, rtol=0)


def test_a_missing_solver_is_named_with_its_install_command(monkeypatch):
    import qpsolvers

    from egcbf.qp.sparse_qp import require_solver
    from egcbf.robots.quadrotor.cbf_qp import CBFQPConfig

    monkeypatch.setattr(qpsolvers, "available_solvers", [s for s in qpsolvers.available_solvers if s != "osqp"])
    with pytest.raises(ImportError, match=r"pip install osqp \(or pip install -e '\.\[solvers\]'\)"):
        require_solver("osqp")
    with pytest.raises(ImportError, match="osqp"):
        CBFQPConfig(solver="osqp")  # refused when configured, not at the first QP
    with pytest.raises(ImportError, match="pip install gurobipy"):
        CBFQPConfig(fallback_solver="gurobi")  # a solver qpsolvers knows but that is not installed
    with pytest.raises(ValueError, match=r"unknown QP solver 'nosuch'; installed: \[.*'piqp'.*'proxsuite'\]"):
        CBFQPConfig(fallback_solver="nosuch")
    assert require_solver("proxsuite") == "proxqp" and require_solver("piqp") == "piqp"
    CBFQPConfig(solver="proxsuite", fallback_solver=None)


def test_a_solver_crash_is_a_failed_solve(monkeypatch):
    """An exception inside the solver becomes ok=False with its message as the status, and NaN x."""
    import qpsolvers

    prep, cons = numpy_rows(6, n=10)
    qp = assemble_centralized(prep.a_nom[0], cons, prep.bC[0], prep.blo[0], prep.bhi[0])

    def crash(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(qpsolvers, "solve_problem", crash)
    res = solve_sparse(qp, "piqp")
    assert not res.ok and res.status == "error: RuntimeError: boom" and np.isnan(res.x).all()


def test_batched_ipm_matches_proxsuite_and_is_feasible():
    prep, cons = numpy_rows(7, n=40)
    owner, normal, rhs = split_for_agents(cons)
    n = prep.p.shape[1]
    qps = assemble_decentralized(prep.a_nom[0], owner, normal, rhs, prep.bC[0], prep.blo[0], prep.bhi[0])
    z, ok, it = solve_dense_batch_ipm(qps)
    zp, okp, _ = solve_dense_batch(qps, eps_abs=1e-10)
    assert ok.all() and okp.all() and it.max() <= 40
    np.testing.assert_allclose(z, zp, atol=1e-6)
    res = np.einsum("mkd,md->mk", qps.cbf_normal, z[:, :3]) + z[:, 3:]
    assert (res - qps.cbf_rhs).min() >= -1e-9 and z[:, 3].min() >= -1e-12
    assert z.shape == (n, 4)


def test_no_neighbours_returns_nominal():
    # agents 3 m apart (beyond the 1 m cull radius), goals close: a_nom inside the bounds
    p = torch.tensor([[0.5, 0.5, 0.5], [3.5, 0.5, 0.5], [0.5, 3.5, 3.5]], dtype=F64)
    x = dyn.hover_state(p, torch.tensor([0.3, -1.0, 2.0], dtype=F64))[None]
    goals = p[None] + torch.tensor([0.2, -0.1, 0.15], dtype=F64)
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    state, cfg = SwarmState(x, goals, obs, 0), EnvConfig(num_agents=3, area_size=4.0, num_obstacles=0)
    a_nom = nominal_acceleration(x, goals).numpy()
    for ctrl in (CentralizedCBFQP(), DecentralizedCBFQP()):
        u, info = ctrl(state, cfg)
        assert info["num_constraints"] == 0 and info["num_slack"] == 0 and info["num_failed"] == 0
        np.testing.assert_allclose(info["a_safe"], a_nom, atol=1e-7)
        np.testing.assert_allclose(u, nominal_control(x, goals, cfg.params), atol=1e-7)


def test_attitude_loop_reproduces_nominal_controller():
    state, cfg = random_scene(8, n=16)
    a_nom = nominal_acceleration(state.x, state.goals)
    u = track_acceleration(state.x, a_nom, cfg.params)
    torch.testing.assert_close(u, nominal_control(state.x, state.goals, cfg.params), rtol=0, atol=1e-15)
    un, info = NominalController()(state, cfg)
    torch.testing.assert_close(un, u, rtol=0, atol=1e-15)
    assert info["num_slack"] == 0 and info["num_failed"] == 0


def test_default_bounds_are_realizable():
    """Every vertex of the bound set needs thrust <= max_thrust, >= min_lift m g, and tilt <= max_tilt, so the
    attitude loop tracks it without its own limits changing the command."""
    from egcbf.robots.quadrotor.nominal import DEFAULT_GAINS

    p = dyn.DEFAULT_PARAMS
    b = BOUNDS
    for k in range(2 * b.polygon):
        ang = (k + 0.5) * math.pi / b.polygon
        for z in (b.z_min, b.z_max):
            f = np.array([b.circumradius * math.cos(ang), b.circumradius * math.sin(ang), z + p.gravity])
            assert p.mass * np.linalg.norm(f) <= p.max_thrust
            assert f[2] >= DEFAULT_GAINS.min_lift * p.gravity
            assert math.atan2(np.hypot(f[0], f[1]), f[2]) <= DEFAULT_GAINS.max_tilt + 1e-9


# ---------------------------------------------------------------------------------------- closed-loop safety
def head_on(offset: float = 0.0):
    p0 = torch.tensor([[0.4, 1.0, 1.0], [2.0, 1.0 + offset, 1.0]], dtype=F64)
    x = dyn.hover_state(p0, torch.tensor([0.0, 2.5], dtype=F64))[None]
    goals = p0.flip(0)[None].clone()
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    cfg = EnvConfig(num_agents=2, area_size=2.4, num_obstacles=0, max_steps=120)
    return SwarmState(x, goals, obs, 0), cfg


@pytest.mark.parametrize("name", ["ccbf", "dcbf", "nominal"])
def test_head_on_keeps_distance(name):
    state, cfg = head_on(offset=0.01)
    env = SwarmEnv(cfg, dtype=F64)
    ctrl = make_controller(name)
    dmin = math.inf
    for _ in range(cfg.max_steps):
        u, info = ctrl(state, cfg)
        assert info["num_failed"] == 0
        state, _ = env.step(state, u)
        dmin = min(dmin, float((state.positions[0, 0] - state.positions[0, 1]).norm()))
    if name == "nominal":
        assert dmin < 2 * cfg.agent_radius  # the scenario is a real test: without the filter they collide
    else:
        # the attitude loop's lag eats part of the 5 cm margin (docs/baselines.md), never all of it
        assert dmin > 2 * cfg.agent_radius + 0.005, dmin


@pytest.mark.parametrize("cls", [CentralizedCBFQP, DecentralizedCBFQP])
def test_overlapping_agents_give_slack_not_exceptions(cls):
    p = torch.tensor([[1.0, 1.0, 1.0], [1.03, 1.0, 1.0], [1.0, 1.04, 1.0]], dtype=F64)
    x = dyn.hover_state(p)[None].clone()
    x[0, :, dyn.V] = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=F64)
    goals = p.flip(0)[None].clone()
    obs = Obstacles(torch.tensor([[[1.0, 1.0, 1.1]]], dtype=F64), torch.tensor([[0.05]], dtype=F64))
    state, cfg = SwarmState(x, goals, obs, 0), EnvConfig(num_agents=3, area_size=2.0, num_obstacles=1)
    u, info = cls()(state, cfg)
    assert torch.isfinite(u).all()
    assert info["num_slack"] >= 1 and info["max_slack"] > 0
    assert info["num_failed"] == 0
    # the returned controls respect the actuator box
    torch.testing.assert_close(u, dyn.clip_control(u, cfg.params))


def test_failed_solves_are_counted_and_braked(monkeypatch):
    import egcbf.robots.quadrotor.cbf_qp as mod

    state, cfg = random_scene(9, n=12)

    def broken(qp, solver, *a, **k):
        from egcbf.qp.sparse_qp import SolveResult

        return SolveResult(np.full(qp.H.shape[0], np.nan), False, "broken", 0, 0.0)

    monkeypatch.setattr(mod, "solve_sparse", broken)
    u, info = CentralizedCBFQP()(state, cfg)
    assert info["num_failed"] == 1 and torch.isfinite(u).all()
    v = state.x[0, :, dyn.V].numpy()
    a = info["a_safe"][0]
    assert (np.einsum("nd,nd->n", a, v) <= 1e-12).all()  # braking: opposes the velocity


def test_batched_environments_match_single():
    s1, cfg = random_scene(10, n=10)
    s2, _ = random_scene(11, n=10)
    obs = Obstacles(
        torch.cat([s1.obstacles.centers[:, :1], s2.obstacles.centers[:, :1]]),
        torch.cat([s1.obstacles.radii[:, :1], s2.obstacles.radii[:, :1]]),
    )
    both = SwarmState(torch.cat([s1.x, s2.x]), torch.cat([s1.goals, s2.goals]), obs, 0)
    for cls in (CentralizedCBFQP, DecentralizedCBFQP):
        ub, _ = cls()(both, cfg)
        for k, s in enumerate((s1, s2)):
            single = SwarmState(s.x, s.goals, Obstacles(obs.centers[k : k + 1], obs.radii[k : k + 1]), 0)
            u1, _ = cls()(single, cfg)
            torch.testing.assert_close(ub[k : k + 1], u1, rtol=0, atol=1e-7)


# ------------------------------------------------------------------------------------------------ symmetry
@given(
    seed=st.integers(0, 2**31 - 1),
    yaw=st.floats(-math.pi, math.pi),
    t=st.tuples(*[st.floats(-5, 5)] * 3),
)
def test_equivariance_se2xr(seed, yaw, t):
    """Rotating the scene about z and translating it leaves the body-frame controls unchanged and rotates the
    safe accelerations."""
    state, cfg = random_scene(seed, n=14, area=1.2)
    moved = transform(state, yaw, t)
    Rz = yaw_rotation(torch.tensor(yaw, dtype=F64)).numpy()
    for cls in (CentralizedCBFQP, DecentralizedCBFQP):
        u, info = cls()(state, cfg)
        um, infom = cls()(moved, cfg)
        assert info["num_constraints"] == infom["num_constraints"]
        np.testing.assert_allclose(infom["a_safe"], info["a_safe"] @ Rz.T, atol=2e-5)
        torch.testing.assert_close(um, u, rtol=0, atol=1e-6)


def test_warm_start_and_constraint_generation_do_not_change_the_optimum():
    """The centralized QP solved by constraint generation (cold or warm-started from the previous step) equals the
    one-shot solve of the full QP."""
    cfg = EnvConfig(num_agents=40, area_size=1.6, num_obstacles=2, max_steps=20)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(3)
    ctrls = [CentralizedCBFQP(), CentralizedCBFQP(warm_start=False), CentralizedCBFQP(active_set=False)]
    worst = 0.0
    for _ in range(cfg.max_steps):
        outs = [c(state, cfg) for c in ctrls]
        for _, info in outs[1:]:
            worst = max(worst, float(np.abs(info["a_safe"] - outs[0][1]["a_safe"]).max()))
        state, _ = env.step(state, outs[0][0])
    assert worst < 1e-6, worst
