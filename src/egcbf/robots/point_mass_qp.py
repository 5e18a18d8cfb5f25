"""The hand-crafted decentralized CBF-QP (dCBF-QP) for GCBF+'s point masses (the single and double integrators and
the linear drone) and its cars (the Dubins car, our unicycle).

Each agent solves one small QP over its own control ``u_i`` (world frame, in the box that acts at its state:
:meth:`Robot.effective_control_bounds`, the robot's box less the pushes that a speed clip discards), from what it
senses:

    min  1/2 ||u - u_nom||^2 + 1/2 w2 s^2 + w1 s     (u_nom projected into that box: what the robot would execute)
    s.t. n . u + s >= b        one row per neighbour within the communication radius and per obstacle it is near
         lo <= u <= hi,  s >= 0

on the barrier ``h = ||dp||^2 - D^2`` of each pair (``dp = p_i - p_j``, ``D = 2 r + margin``) or obstacle (``dp``
from the obstacle's nearest surface point, ``D = r + margin``):

* single integrator (relative degree 1): ``h' + alpha h >= 0`` with ``h' = 2 dp . (u_i - u_j)``;
* every other robot (relative degree 2): ``h'' + (k1 + k2) h' + k1 k2 h >= 0`` with ``h' = 2 dp . dv`` and
  ``h'' = 2 ||dv||^2 + 2 dp . (a_i - a_j)``, where the world acceleration is affine in the control,
  ``a = A(x) + B(x) u`` with ``A = (dv/dx) f0``, ``B = (dv/dx) f1`` from the robot's control-affine model
  (:func:`acceleration_affine`; the double integrator's ``u / m``, the drone's ``-D v + 10 u``, a car's
  ``a h + v omega perp(h)``: a car at rest cannot steer away, only brake or speed up along its heading).

A pair's condition is split in halves (each agent enforces its own, assuming the neighbour keeps the other: the
dCBF-QP of the quadrotor and of GCBF+'s reference do the same); an obstacle's is the agent's alone. The rows read
only relative positions and velocities and the box is per axis, so the controller commutes with the quarter turns
and translations of the point masses (and with every rotation for the cars, whose controls are invariant). All
agents' QPs are one batch of the dense interior-point solver (:func:`egcbf.qp.dense_ipm.solve_dense_ipm`); an
agent whose QP fails gets its box-clipped nominal control and is counted (``num_failed``). In the full box (before
session 38) a row at a speed limit was met on paper by pushing a little less hard into the limit, which the clip
turns into a full push: the double integrator's dCBF-QP went from 98.4 to 100 % safe on a validation episode (seed
777, N = 256, l = 16, 32 rectangles, 1024 steps) with the acting box.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry.neighbors import radius_neighbors
from ..qp.dense_ipm import solve_dense_ipm

__all__ = ["AFFINE_ROBOTS", "POINT_MASS_CBF_QPS", "BarrierRows", "PointMassCBFConfig", "PointMassCCBF", "PointMassDCBF",
           "acceleration_affine", "barrier_rows", "solve_own_qps"]  # fmt: skip

#: the robots this dCBF-QP drives
AFFINE_ROBOTS = ("single_integrator", "double_integrator", "linear_drone", "dubins_car", "unicycle")


def acceleration_affine(robot, x: Tensor) -> tuple[Tensor, Tensor]:
    """``A (M, d), B (M, d, nu)`` with the world acceleration ``dv/dt = A + B u`` of states ``x`` ``(M, S)``: the
    Jacobian of ``robot.velocities`` times the drift ``f0`` and the input matrix ``f1`` (exact for a velocity that
    is linear in the state, as for the point masses; for a car ``v h``, the product rule)."""
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        v = robot.velocities(xg)
        rows = [torch.autograd.grad(v[:, k].sum(), xg, retain_graph=k + 1 < v.shape[1])[0] for k in range(v.shape[1])]
    jac = torch.stack(rows, 1)  # (M, d, S)
    f0, f1 = robot.f0(x), robot.f1(x)
    return (jac @ f0[..., None])[..., 0], jac @ f1


@dataclass(frozen=True)
class PointMassCBFConfig:
    """Barrier gains: ``alpha`` (1/s, relative degree 1), ``k1``, ``k2`` (1/s, relative degree 2), ``margin`` (m),
    the slack penalty ``w1``, ``w2``. ``k1 = k2 = 30`` and the 1 cm margin were chosen on validation episodes (seed
    777, N = 64, l = 4: the double integrator 100 % safe with 97 % reach, against 68 % safe with 3 and 3)."""

    alpha: float = 5.0
    k1: float = 30.0
    k2: float = 30.0
    margin: float = 0.01
    w1: float = 1e3
    w2: float = 1e3

    @classmethod
    def for_robot(cls, name: str) -> PointMassCBFConfig:
        """The defaults of robot ``name``: the point masses' above; the cars' ``k1 = k2 = 20`` and a 5 cm margin
        (chosen on validation episodes, seed 777, N = 64, l = 4, 8 rectangles, 10 episodes: the Dubins car 99.5 %
        safe with 56 % success, against 81 % safe with the point masses' gains; the unicycle 100 % against 89 %)."""
        if name in ("dubins_car", "unicycle"):
            return cls(k1=20.0, k2=20.0, margin=0.05)
        return cls()


class PointMassDCBF:
    """The point masses' and cars' dCBF-QP (module doc): ``u, info = ctrl(state, env_config)``; ``config``
    ``None``: the robot's defaults (:meth:`PointMassCBFConfig.for_robot`)."""

    name = "dcbf"

    def __init__(self, config: PointMassCBFConfig | None = None):
        self.config = config  # None: the robot's defaults (PointMassCBFConfig.for_robot), chosen at the first call

    @torch.no_grad()
    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0 = time.perf_counter()
        scene = barrier_rows(state, env_config, self.config, pairs="halves")
        b, n = state.x.shape[:2]
        u, failed = self._solve(scene)
        info = {"qp_ms": 1e3 * (time.perf_counter() - t0), "num_slack": 0, "num_failed": int(failed.sum()),
                "u_ref": scene.u_nom.view(b, n, -1).to(state.x.dtype)}  # fmt: skip
        return u.view(b, n, -1).to(state.x.dtype), info

    def _solve(self, scene: BarrierRows) -> tuple[Tensor, Tensor]:
        cfg = scene.cfg
        return solve_own_qps(scene.target, scene.lo, scene.hi, scene.i, scene.coef_i, scene.bound, cfg.w1, cfg.w2)


def solve_own_qps(
    target: Tensor, lo: Tensor, hi: Tensor, i: Tensor, coef: Tensor, bound: Tensor, w1: float, w2: float
) -> tuple[Tensor, Tensor]:
    """Every agent's QP over its own control, as one batch of the dense interior-point solver::

        min  1/2 ||u - target_a||^2 + 1/2 w2 s^2 + w1 s   s.t.  coef[k] . u + s >= bound[k]  (rows k with i[k] = a),
             lo_a <= u <= hi_a,  s >= 0

    ``target``, ``lo``, ``hi`` ``(M, nu)`` float64 (``target`` within the box), rows ``i`` ``(R,)`` (the agent),
    ``coef`` ``(R, nu)``, ``bound`` ``(R,)``. Returns ``u`` ``(M, nu)`` (clamped into the box; an agent whose QP
    failed keeps its ``target``) and the failed mask ``(M,)``. Used by the dCBF-QP and the learner's per-edge target
    for control-interface robots (:mod:`egcbf.algo.edge_qp`)."""
    m, d = target.shape
    if not i.numel():
        return target, torch.zeros(m, dtype=torch.bool)
    order = torch.argsort(i, stable=True)
    i, nrm, bound = i[order], coef[order], bound[order]
    counts = torch.bincount(i, minlength=m)
    k = int(counts.max())
    slot = torch.arange(i.numel()) - (torch.cumsum(counts, 0) - counts)[i]
    G = torch.zeros(m, k + 2 * d + 1, d + 1, dtype=torch.float64)
    h = torch.ones(m, k + 2 * d + 1, dtype=torch.float64)  # all-zero rows with h > 0: padding
    G[i, slot, :d] = -nrm
    G[i, slot, d] = -1.0
    h[i, slot] = -bound
    eye = torch.eye(d, dtype=torch.float64)
    G[:, k : k + d, :d] = eye
    h[:, k : k + d] = hi
    G[:, k + d : k + 2 * d, :d] = -eye
    h[:, k + d : k + 2 * d] = -lo
    G[:, -1, d] = -1.0
    h[:, -1] = 0.0
    P = torch.diag(torch.cat((torch.ones(d, dtype=torch.float64), torch.tensor([w2], dtype=torch.float64))))
    q = torch.cat((-target, torch.full((m, 1), w1, dtype=torch.float64)), 1)
    x0 = torch.zeros(m, d + 1, dtype=torch.float64)
    x0[:, d] = bound.clamp_min(0).max() + 1.0 if bound.numel() else 1.0
    z, ok, _ = solve_dense_ipm(P, q, G, h, x0=x0)
    u = torch.where(ok[:, None], z[:, :d], target).clamp(lo, hi)
    return u, ~ok


class PointMassCCBF:
    """The centralized CBF-QP of the point masses and cars: one QP per environment over every agent's control,
    one whole row per pair (no split) and per obstacle, a slack per row (``w1 s + w2 s^2 / 2``), the box as bounds;
    solved through qpsolvers (``solver``, :mod:`egcbf.qp.sparse_solvers`). An environment whose QP fails keeps
    its agents' box-clipped nominal controls (counted in ``num_failed``); ``num_slack`` counts rows with slack."""

    name = "ccbf"

    def __init__(self, config: PointMassCBFConfig | None = None, solver: str = "piqp"):
        self.config, self.solver = config, solver

    @torch.no_grad()
    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        import numpy as np
        import scipy.sparse as sp

        from ..qp.ipm import INF
        from ..qp.sparse_qp import SparseQP
        from ..qp.sparse_solvers import solve_with_qpsolvers

        t0 = time.perf_counter()
        rows = barrier_rows(state, env_config, self.config, pairs="whole")
        robot, cfg = rows.robot, rows.cfg
        b, n = state.x.shape[:2]
        nu = robot.control_dim
        lo, hi = rows.lo.numpy(), rows.hi.numpy()
        u_nom = rows.target.numpy()
        u = u_nom.copy()
        failed = slack = 0
        env = (rows.i // n).numpy()
        for e in range(b):
            own = slice(e * n, (e + 1) * n)  # this environment's agents
            k = np.nonzero(env == e)[0]
            if k.size == 0:
                continue
            r = k.size
            li = rows.i.numpy()[k] - e * n
            lj = rows.j.numpy()[k] - e * n
            ci, cj = rows.coef_i.numpy()[k], rows.coef_j.numpy()[k]
            pair = rows.j.numpy()[k] >= 0
            cols = [(li[:, None] * nu + np.arange(nu)).ravel(), (lj[pair][:, None] * nu + np.arange(nu)).ravel(),
                    n * nu + np.arange(r)]  # fmt: skip
            vals = [ci.ravel(), cj[pair].ravel(), np.ones(r)]
            rws = [np.repeat(np.arange(r), nu), np.repeat(np.arange(r)[pair], nu), np.arange(r)]
            entries = (np.concatenate(vals), (np.concatenate(rws), np.concatenate(cols)))
            C = sp.csc_matrix(entries, shape=(r, n * nu + r))
            qp = SparseQP(
                H=sp.diags(np.r_[np.ones(n * nu), np.full(r, cfg.w2)]).tocsc(),
                g=np.r_[-u_nom[own].ravel(), np.full(r, cfg.w1)],
                C=C, l=rows.bound.numpy()[k], u=np.full(r, INF),
                x_l=np.r_[lo[own].ravel(), np.zeros(r)], x_u=np.r_[hi[own].ravel(), np.full(r, INF)],
                num_agents=n, num_slack=r,
            )  # fmt: skip
            res = solve_with_qpsolvers(qp, self.solver, eps_abs=1e-9, max_iter=500)
            if res.ok and np.isfinite(res.x).all():
                u[own] = np.clip(res.x[: n * nu].reshape(n, nu), lo[own], hi[own])
                slack += int((res.x[n * nu :] > 1e-6).sum())
            else:
                failed += n
        out = torch.as_tensor(u, dtype=state.x.dtype).view(b, n, nu)
        info = {"qp_ms": 1e3 * (time.perf_counter() - t0), "num_slack": slack, "num_failed": failed,
                "u_ref": rows.u_nom.view(b, n, -1).to(state.x.dtype)}  # fmt: skip
        return out, info


@dataclass
class BarrierRows:
    """The barrier rows of a scene (float64, flat agent rows ``b N + i``): row ``k`` reads
    ``coef_i[k] . u_{i[k]} + coef_j[k] . u_{j[k]} >= bound[k]`` (``j = -1``: an obstacle row, the agent's alone);
    with ``pairs="halves"`` every pair gives each agent its own half-row (``j = -1``, the dCBF-QP), with
    ``pairs="whole"`` one row per unordered pair (the cCBF-QP). ``u_nom`` ``(M, nu)``; ``lo``, ``hi`` ``(M, nu)``
    the box that acts at each agent's state (:meth:`Robot.effective_control_bounds`: at a speed limit the pushes
    that the clip discards are gone); ``cfg`` the gains used."""

    robot: object
    cfg: PointMassCBFConfig
    u_nom: Tensor
    lo: Tensor
    hi: Tensor
    i: Tensor
    j: Tensor
    coef_i: Tensor
    coef_j: Tensor
    bound: Tensor

    @property
    def target(self) -> Tensor:
        """The QPs' reference ``(M, nu)``: the nominal control projected into the acting box, what the robot would
        execute (measured from beyond it, braking at a speed limit looked dearer than it is)."""
        return torch.maximum(torch.minimum(self.u_nom, self.hi), self.lo)


def barrier_rows(state, env_config, config: PointMassCBFConfig | None, pairs: str) -> BarrierRows:
    """The rows of the module doc for ``state`` (:class:`BarrierRows`); ``config`` ``None``: the robot's defaults."""
    robot = env_config.make_robot()
    if robot.name not in AFFINE_ROBOTS:
        raise ValueError(f"these CBF-QPs drive {', '.join(AFFINE_ROBOTS)}, not a {robot.name}")
    cfg = config or PointMassCBFConfig.for_robot(robot.name)
    b, n, _ = state.x.shape
    x = state.x.reshape(b * n, -1).to(torch.float64)
    goals = state.goals.reshape(b * n, -1).to(torch.float64)
    u_nom = robot.nominal_control(x, goals)
    lo, hi = (t.to(x.dtype).expand_as(u_nom).contiguous() for t in robot.effective_control_bounds(x))
    p, v = robot.positions(x), robot.velocities(x)
    if robot.kinematic:  # relative degree 1: p' = u
        drift, gain = None, torch.eye(robot.dim, dtype=x.dtype).expand(x.shape[0], -1, -1)
    else:
        drift, gain = acceleration_affine(robot, x)
    r = float(env_config.agent_radius)
    batch = torch.arange(b).repeat_interleave(n)
    src, dst = radius_neighbors(p, float(env_config.comm_radius), batch, sort=True)  # dst: the agent i
    if pairs == "whole":
        once = dst < src
        src, dst = src[once], dst[once]
    elif pairs != "halves":
        raise ValueError(f"pairs must be 'halves' or 'whole', got {pairs!r}")
    parts = []

    def add(i: Tensor, j: Tensor | None, dp: Tensor, dv: Tensor, clearance: float, share: float) -> None:
        dist = dp.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        nrm = dp / dist
        h = dp.square().sum(-1) - clearance**2
        coef = (nrm[:, None, :] @ gain[i])[:, 0]  # n^T B_i (nu,)
        coef_j = torch.zeros_like(coef) if j is None else -(nrm[:, None, :] @ gain[j])[:, 0]
        if drift is None:  # 2 dp . (u_i - u_j) >= -alpha h (a share of it)
            bound = -share * cfg.alpha * h / (2 * dist[:, 0])
        else:  # 2 dp . (a_i - a_j) >= -(2 |dv|^2 + (k1 + k2) 2 dp . dv + k1 k2 h) (a share of it)
            hdot = 2 * (dp * dv).sum(-1)
            total = 2 * dv.square().sum(-1) + (cfg.k1 + cfg.k2) * hdot + cfg.k1 * cfg.k2 * h
            own = drift[i] if j is None else drift[i] - drift[j]
            bound = (-share * total / 2 - (dp * own).sum(-1)) / dist[:, 0]
        parts.append((i, torch.full_like(i, -1) if j is None else j, coef, coef_j, bound))

    if src.numel():
        if pairs == "halves":
            add(dst, None, p[dst] - p[src], v[dst] - v[src], 2 * r + cfg.margin, 0.5)
        else:
            add(dst, src, p[dst] - p[src], v[dst] - v[src], 2 * r + cfg.margin, 1.0)
    obs = state.obstacles
    if obs.num_obstacles:
        bi, ni, ki = obs.near_pairs(state.positions.detach().to(torch.float64), float(env_config.comm_radius))
        i = bi * n + ni
        pts = p[i]
        near = _nearest_surface_point(obs, pts, bi, ki)
        add(i, None, pts - near, v[i], r + cfg.margin, 1.0)
    nu = robot.control_dim
    if not parts:
        empty = torch.zeros(0, dtype=torch.long)
        return BarrierRows(robot, cfg, u_nom, lo, hi, empty, empty, x.new_zeros(0, nu), x.new_zeros(0, nu),
                           x.new_zeros(0))  # fmt: skip
    return BarrierRows(robot, cfg, u_nom, lo, hi, *(torch.cat(t) for t in zip(*parts)))


def _nearest_surface_point(obs, points: Tensor, env: Tensor, k: Tensor) -> Tensor:
    """The point of obstacle ``k`` of environment ``env`` nearest to each of ``points`` ``(P, d)`` (float64)."""
    c = obs.centers[env, k].to(points.dtype)
    if obs.boxes is None:  # a sphere or disc: along the ray from its centre
        d = points - c
        return c + d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12) * obs.radii[env, k].to(points.dtype)[:, None]
    from ..geometry.rectangles import nearest_point

    box = obs.boxes[env, k].to(points.dtype)
    return nearest_point(points, c, box[:, :2], box[:, 2:])


#: the CBF-QP baselines of every control-affine point-mass robot and car (``Robot.cbf_qps``)
POINT_MASS_CBF_QPS = {"ccbf": PointMassCCBF, "dcbf": PointMassDCBF}
