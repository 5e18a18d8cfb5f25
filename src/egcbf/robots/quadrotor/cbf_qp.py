"""Hand-crafted CBF-QP baselines (Wang, Ames & Egerstedt 2017; GCBF+'s cCBF-QP / dCBF-QP) for the quadrotor swarm.

Hierarchical "thrust-vector" design (derivation and guarantees in ``docs/baselines.md``):

1. **Position loop -> nominal acceleration.** ``a_nom = -k_x clip(p - goal) - k_v v`` (world frame, gravity
   included in ``a = p''``): the position loop of the geometric nominal controller
   (:mod:`egcbf.robots.quadrotor.nominal`), with its gains and position-error clip.
2. **Safety filter on the acceleration.** Each agent is a double integrator ``p'' = a``; barriers on agent pairs
   and sphere obstacles (:mod:`egcbf.robots.quadrotor.barriers`) give constraints linear in the accelerations;
   acceleration bounds turn with the agent's heading. The centralized QP (:class:`CentralizedCBFQP`) solves one
   sparse QP over all agents of an environment; the decentralized one
   (:class:`egcbf.robots.quadrotor.dcbf_qp.DecentralizedCBFQP`) one small QP per agent, each agent enforcing half
   of every pair constraint.
3. **Attitude loop.** The safe acceleration is tracked by the geometric controller's attitude loop: desired force
   ``m (a_safe - g)``, thrust ``F3 = m (a_safe - g) . R e3``, torque from the attitude error
   (:func:`track_acceleration`, identical to :func:`egcbf.robots.quadrotor.nominal.nominal_control` for ``a = a_nom``).

Under message faults (``state.sensing`` of :mod:`egcbf.faults` with ``msg_loss`` or ``msg_delay``) the dCBF-QP's
agents know their neighbours only from the messages they received (:meth:`egcbf.faults.Sensing.received`, the
messages the learned policies' graphs receive too): agent ``i``'s half of a pair row reads its own estimate and the
neighbour's broadcast estimate, and a lost message removes the pair from ``i``'s QP only (so the two halves no
longer guarantee the pair: :mod:`~.dcbf_qp`). The centralized QP has no messages and refuses these faults.

Every step of the pipeline commutes with the symmetry (rotations about world z, translations), so the
body-frame controls are invariant: the baselines are SE(2) x R equivariant (tested).

Solver failures never raise: a QP whose solver reports failure, or whose solution violates a bound or a CBF row
by more than its slack (checked after every solve), is retried with a second solver, then replaced by a braking
fallback; both are counted in the controller's ``info``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from ...qp.constraints import Constraints
from ...qp.sparse_qp import SlackPenalty, assemble_centralized, polish_sparse, require_solver, solve_sparse
from .barriers import (
    LIDAR_HITS,
    AccelBounds,
    BarrierConfig,
    bound_rows,
    build_constraints,
)
from .dynamics import DEFAULT_PARAMS, QuadrotorParams
from .nominal import (
    DEFAULT_GAINS,
    DEFAULT_MAX_POSITION_ERROR,
    NominalGains,
    nominal_acceleration,
    track_acceleration,
)

__all__ = [
    "LIDAR_HITS",
    "OBSTACLE_SENSING",
    "CBFQPConfig",
    "CentralizedCBFQP",
    "brake_acceleration",
    "default_bounds",
    "nominal_acceleration",
    "track_acceleration",
]


# ------------------------------------------------------------------------------------------- the two loops
def default_bounds(
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: NominalGains = DEFAULT_GAINS,
    lift_fraction: float = 0.5,
    thrust_reserve: float = 0.9,
    polygon: int = 4,
) -> AccelBounds:
    """Acceleration bounds every point of which the attitude loop can realize without hitting its own limits.

    ``z_min = -(1 - lift_fraction) g`` (thrust never below ``lift_fraction m g``); the horizontal polygon's
    circumradius is ``tan(max_tilt) lift_fraction g`` (tilt <= ``max_tilt`` even at the lowest thrust); ``z_max``
    so that the thrust at every corner is at most ``thrust_reserve * max_thrust`` (the rest is margin for the
    projection ``F . R e3`` and the attitude loop).
    """
    g = params.gravity
    if not gains.min_lift <= lift_fraction < 1:
        raise ValueError(f"lift_fraction must be in [min_lift = {gains.min_lift}, 1), got {lift_fraction}")
    circ = math.tan(gains.max_tilt) * lift_fraction * g
    horizontal = circ * math.cos(math.pi / (2 * polygon))
    amax = thrust_reserve * params.max_thrust / params.mass
    room = amax**2 - circ**2
    if room <= (1.05 * g) ** 2:
        raise ValueError("the quadrotor's thrust cannot hover while accelerating sideways at the tilt limit")
    return AccelBounds(horizontal, -(1 - lift_fraction) * g, math.sqrt(room) - g, polygon)


def brake_acceleration(v: np.ndarray, bounds: AccelBounds, gain: float) -> np.ndarray:
    """Fallback acceleration of an agent whose QP failed: ``-gain v`` ``(..., 3)`` scaled into the ball inscribed
    in the bounds (a direction every agent can realize, whatever its heading)."""
    a = -gain * v
    nrm = np.linalg.norm(a, axis=-1, keepdims=True)
    return a * np.minimum(1.0, 0.99 * bounds.inscribed / np.maximum(nrm, 1e-12))


# ------------------------------------------------------------------------------------------------ config
#: where the hand-crafted QPs read obstacles from (``CBFQPConfig.obstacle_sensing``)
OBSTACLE_SENSING = ("map", "lidar")


def check_lidar_hits(owner: str, obstacle_sensing: str, lidar_hits: str) -> None:
    """Raise ``ValueError`` (naming ``owner``'s fields) unless ``lidar_hits`` is one of :data:`LIDAR_HITS`, and
    ``"point"`` only with ``obstacle_sensing = "lidar"`` (the map's rows read spheres, not hits)."""
    if lidar_hits not in LIDAR_HITS:
        raise ValueError(f"{owner}.lidar_hits must be one of {LIDAR_HITS}, got {lidar_hits!r}")
    if lidar_hits != "plane" and obstacle_sensing != "lidar":
        raise ValueError(f"{owner}.lidar_hits = {lidar_hits!r} needs obstacle_sensing = 'lidar' (with the map the "
                         "obstacle rows read spheres, not LiDAR hits)")  # fmt: skip


@dataclass(frozen=True)
class CBFQPConfig:
    """Configuration shared by the centralized and decentralized CBF-QP baselines.

    Attributes:
        barrier: the barrier (its ``agent_radius`` is replaced by the environment's at call time).
        bounds: acceleration bounds; ``None``: :func:`default_bounds` of the environment's quadrotor.
        penalty: slack cost ``1/2 w2 s^2 + w1 s`` (s in m/s^2).
        solver: centralized sparse solver, any of ``qpsolvers.available_solvers`` (through qpsolvers,
            :mod:`egcbf.qp.sparse_solvers`): ``"piqp"`` (default, fastest measured), ``"proxsuite"`` (qpsolvers'
            ``"proxqp"``), ``"osqp"``, ``"clarabel"``, ``"highs"``, ``"qpalm"``, ... ``fallback_solver`` is tried
            when it fails.
        dcbf_solver: per-agent QPs: ``"ipm"`` (batched interior point + polishing, on the state's device; default,
            fastest measured at N = 512) or ``"proxsuite"`` (``dense.BatchQP`` + ``solve_in_parallel``).
        eps_abs: absolute primal/dual tolerance (m/s^2). ``max_iter``: iteration cap per solve.
        slack_tol: a QP "needs slack" when some slack exceeds this (m/s^2); also the feasibility check tolerance.
        gains, max_position_error: the nominal controller's (position loop and attitude loop).
        brake_gain: fallback when a solve fails: ``a = -brake_gain v`` scaled into the bounds.
        active_set: centralized QP by constraint generation (exact; a few small QPs instead of one large one), with
            rows entering when their relative residual is below ``active_margin`` (0.5: measured fastest at N = 512);
            after ``max_rounds`` rounds the full QP is solved.
        warm_start: start the constraint generation from the rows (nearly) active at the previous call's solution
            (per environment; cleared at ``state.t == 0``). Only the work changes, not the optimum.
        obstacle_sensing: where the obstacle rows come from: ``"map"`` (the spheres of the obstacle map within range,
            default) or ``"lidar"`` (each agent's own LiDAR hits,
            :func:`~egcbf.robots.quadrotor.barriers.hit_constraints`; the decentralized QP only).
        lidar_hits: with ``obstacle_sensing = "lidar"``, what one hit stands for (:data:`LIDAR_HITS`): ``"plane"``
            (default: the plane through the hit normal to the ray) or ``"point"`` (a point obstacle, which lets an
            agent sliding along a large obstacle close on it); must stay ``"plane"`` with the map.
        polish: refine each centralized solution by an active-set KKT solve (:func:`egcbf.qp.sparse_qp.polish_sparse`),
            kept only when it is provably the exact optimum; makes the result independent of the solver's tolerance.
    """

    barrier: BarrierConfig = field(default_factory=BarrierConfig)
    bounds: AccelBounds | None = None
    penalty: SlackPenalty = field(default_factory=SlackPenalty)
    solver: str = "piqp"
    fallback_solver: str | None = "proxsuite"
    dcbf_solver: str = "ipm"
    eps_abs: float = 1e-9
    max_iter: int = 200
    slack_tol: float = 1e-4
    gains: NominalGains = DEFAULT_GAINS
    max_position_error: float = DEFAULT_MAX_POSITION_ERROR
    brake_gain: float = 4.0
    active_set: bool = True
    active_margin: float = 0.5
    max_rounds: int = 6
    polish: bool = True
    warm_start: bool = True
    obstacle_sensing: str = "map"
    lidar_hits: str = "plane"

    def __post_init__(self) -> None:
        if self.obstacle_sensing not in OBSTACLE_SENSING:
            raise ValueError(f"CBFQPConfig.obstacle_sensing must be one of {OBSTACLE_SENSING}, got "
                             f"{self.obstacle_sensing!r}")  # fmt: skip
        check_lidar_hits("CBFQPConfig", self.obstacle_sensing, self.lidar_hits)
        # an unknown or missing solver fails here, with how to install it, not at the first QP of an episode
        for name in (self.solver, self.fallback_solver):
            if name is not None:
                require_solver(name)


@dataclass
class _Prepared:
    x: Tensor
    p: np.ndarray  # (B, N, 3)
    v: np.ndarray
    rot: np.ndarray  # (B, N, 9)
    a_nom: np.ndarray  # (B, N, 3)
    centers: list  # per env (K, 3)
    radii: list
    barrier: BarrierConfig
    bounds: AccelBounds
    params: QuadrotorParams
    bC: np.ndarray = field(default=None)  # (B, N, K, 3)
    blo: np.ndarray = field(default=None)
    bhi: np.ndarray = field(default=None)


class _CBFQPBase:
    name = "cbf-qp"

    def __init__(self, config: CBFQPConfig | None = None, **overrides):
        self._warm: dict[int, np.ndarray] = {}  # per environment: the last safe accelerations (warm start only)
        cfg = config or CBFQPConfig()
        if overrides:
            bkeys = {k: overrides.pop(k) for k in list(overrides) if k in BarrierConfig.__dataclass_fields__}
            if bkeys:
                cfg = replace(cfg, barrier=replace(cfg.barrier, **bkeys))
            cfg = replace(cfg, **overrides)
        self.config = cfg

    def resolved(self, env_config) -> tuple[BarrierConfig, AccelBounds]:
        """The barrier and the acceleration bounds the QPs run with in ``env_config``'s environment: the barrier
        with the environment's agent radius and, where its ``cull_radius`` is ``None``, the communication radius;
        the configured bounds or :func:`default_bounds` of the environment's quadrotor."""
        cfg = self.config
        barrier = replace(cfg.barrier, agent_radius=float(env_config.agent_radius))
        if barrier.cull_radius is None:
            barrier = replace(barrier, cull_radius=float(env_config.comm_radius))
        return barrier, cfg.bounds or default_bounds(env_config.params, cfg.gains)

    def _prepare(self, state, env_config, a_ref: np.ndarray | None = None) -> _Prepared:
        """The QPs' data; ``a_ref`` ``(B, N, 3)`` replaces the nominal acceleration as the reference (which is then
        not computed)."""
        if env_config.robot != "quadrotor":  # the barriers and bounds are the quadrotor's acceleration command's
            raise ValueError(f"the hand-crafted CBF-QPs are written for the quadrotor, not a {env_config.robot}")
        if state.t == 0:  # a state entering the QP (a reset or a hand-built one): finite, rotations, radii > 0
            state.validate()
        cfg = self.config
        params = env_config.params
        barrier, bounds = self.resolved(env_config)
        if barrier.kind == "wang" and barrier.brake_accel > bounds.inscribed:
            raise ValueError(
                f"brake_accel = {barrier.brake_accel:g} m/s^2 exceeds the deceleration the bounds allow in every "
                f"direction ({bounds.inscribed:g} m/s^2): Wang et al.'s barrier would not be valid"
            )
        x = state.x.detach().to(torch.float64)
        goals = state.goals.detach().to(torch.float64)
        if a_ref is None:
            a_nom = nominal_acceleration(x, goals, cfg.gains, cfg.max_position_error).cpu().numpy()
        else:
            a_nom = np.asarray(a_ref, dtype=np.float64)
            if a_nom.shape != (*x.shape[:2], 3):
                raise ValueError(f"a_ref must have shape {(*x.shape[:2], 3)} (B, N, 3), got {a_nom.shape}")
        xn = x.cpu().numpy()
        obs = state.obstacles
        if obs.num_obstacles > 0:
            cen = obs.centers.detach().to(torch.float64).cpu().numpy()
            rad = obs.radii.detach().to(torch.float64).cpu().numpy()
            centers, radii = list(cen), list(rad)
        else:
            centers = radii = [None] * xn.shape[0]
        prep = _Prepared(x, xn[..., 0:3], xn[..., 12:15], xn[..., 3:12], a_nom, centers, radii, barrier, bounds, params)
        b, n = xn.shape[:2]
        C, lo, hi = bound_rows(prep.rot.reshape(b * n, 9), bounds)
        prep.bC, prep.blo, prep.bhi = C.reshape(b, n, *C.shape[1:]), lo.reshape(b, n, -1), hi.reshape(b, n, -1)
        return prep

    def _brake(self, v: np.ndarray, bounds: AccelBounds) -> np.ndarray:
        return brake_acceleration(v, bounds, self.config.brake_gain)

    def _finish(self, prep: _Prepared, a_safe: np.ndarray) -> Tensor:
        acc = torch.from_numpy(a_safe).to(prep.x)
        return track_acceleration(prep.x, acc, prep.params, self.config.gains)

    def _check(self, a, cons: Constraints, slack_rows, C, lo, hi) -> tuple[bool, float]:
        """Feasibility of a solution up to its slack: ``(ok, worst violation)``."""
        tol = self.config.slack_tol
        worst = 0.0
        if len(cons):  # relative to the row's size: Wang's rows reach |b| ~ 1e3 next to the safety distance
            worst = max(worst, float((-(cons.residual(a) + slack_rows) / (1.0 + np.abs(cons.rhs))).max()))
            worst = max(worst, float(-slack_rows.min()))
        bv = np.einsum("nkd,nd->nk", C, a)
        worst = max(worst, float((lo - bv).max(initial=0.0)), float((bv - hi).max(initial=0.0)))
        return worst <= tol, worst


# ---------------------------------------------------------------------------------------------- centralized
class CentralizedCBFQP(_CBFQPBase):
    """cCBF-QP: one sparse QP over all agents of each environment (loop over the ``B`` environments).

    ``u, info = ctrl(state, env_config)``: ``u`` ``(B, N, 4)`` body-frame controls (clipped to the actuators) in
    ``state.x``'s dtype and device; ``info`` holds ``qp_ms`` (wall time of building and solving all QPs of the
    step; ``qp_cpu_ms`` its CPU time, less sensitive to other processes), ``num_slack`` (QPs whose slack exceeds
    ``slack_tol``), ``num_failed`` (QPs replaced by the braking fallback), ``num_retried`` (solved by the fallback
    solver), ``num_rounds`` (constraint-generation rounds), ``num_constraints``, ``max_slack``, ``status``,
    ``a_safe`` and ``a_nom`` (``(B, N, 3)`` numpy arrays).
    """

    name = "ccbf"

    def __init__(self, config: CBFQPConfig | None = None, **overrides):
        super().__init__(config, **overrides)
        if self.config.obstacle_sensing != "map":
            raise ValueError("the centralized CBF-QP reads the obstacle map (obstacle_sensing = 'map'); LiDAR-only "
                             "sensing is the decentralized QP's (dcbf)")  # fmt: skip

    def _solve_full(self, prep: _Prepared, e: int, cons: Constraints):
        """Solve the QP with rows ``cons``: ``(a, s, status, retried, qp, x)``; ``a`` is None if every solver failed
        or no solution passed :meth:`_check`."""
        cfg = self.config
        n = prep.p.shape[1]
        qp = assemble_centralized(prep.a_nom[e], cons, prep.bC[e], prep.blo[e], prep.bhi[e], cfg.penalty)
        solvers = [cfg.solver] + ([cfg.fallback_solver] if cfg.fallback_solver else [])
        status = "not run"
        for k, name in enumerate(solvers):
            res = solve_sparse(qp, name, cfg.eps_abs, cfg.max_iter)
            status = f"{name}: {res.status}"
            if not res.ok:
                continue
            a, s = res.x[: 3 * n].reshape(n, 3), res.x[3 * n :]
            ok, _ = self._check(a, cons, s, prep.bC[e], prep.blo[e], prep.bhi[e])
            if ok:
                return a, s, status, k, qp, res.x
        return None, None, status, len(solvers), qp, None

    def _polished(self, prep: _Prepared, e: int, cons: Constraints, work: np.ndarray, qp, x, a, s):
        """Polish the final QP's solution (:func:`polish_sparse`) and keep it if it passes :meth:`_check` on all
        rows; returns ``(a, s (all rows), polished)``."""
        n = prep.p.shape[1]
        xp, ok = polish_sparse(qp, x)
        if not ok:
            return a, s, False
        ap = xp[: 3 * n].reshape(n, 3)
        sp_ = np.zeros(len(cons))
        sp_[work] = xp[3 * n :]
        good, _ = self._check(ap, cons, sp_, prep.bC[e], prep.blo[e], prep.bhi[e])
        return (ap, sp_, True) if good else (a, s, False)

    def _solve_env(self, prep: _Prepared, e: int, cons: Constraints):
        """Exact solve by constraint generation: ``(a, s (all rows), status, retried, rounds, polished)``.

        Start from the rows that the nominal accelerations violate or nearly satisfy (residual below
        ``active_margin``), solve, add every row the solution violates (or nearly), repeat. A row left out is
        satisfied by the final solution with zero slack, so the final solution is feasible for the full QP and
        optimal for a relaxation of it: it is the full QP's (unique) optimum. After ``max_rounds`` the full QP
        is solved directly. The final solution is polished once.
        """
        cfg = self.config
        if not cfg.active_set or len(cons) == 0:
            work = np.ones(len(cons), dtype=bool)
            a, s, st, k, qp, x = self._solve_full(prep, e, cons)
            rounds = 1
        else:
            scale = 1.0 + np.abs(cons.rhs)
            work = cons.residual(prep.a_nom[e]) < cfg.active_margin * scale
            guess = self._warm.get(e) if cfg.warm_start else None
            if guess is not None and guess.shape == prep.a_nom[e].shape:
                # warm start: the rows (nearly) active at the previous step's solution; the nominal's otherwise
                work = cons.residual(guess) < cfg.active_margin * scale
            k = 0
            for rounds in range(1, cfg.max_rounds + 2):
                if rounds == cfg.max_rounds + 1:  # give up generating: the full QP
                    work = np.ones(len(cons), dtype=bool)
                a, s_sub, st, kk, qp, x = self._solve_full(prep, e, cons.subset(work))
                k += kk
                if a is None:
                    break
                s = np.zeros(len(cons))
                s[work] = s_sub
                r = (cons.residual(a) + s) / scale
                if not (~work & (r < -0.1 * cfg.slack_tol)).any():
                    break
                work |= r < cfg.active_margin
        if a is None:
            self._warm.pop(e, None)
            return None, None, st, k, rounds, False
        self._warm[e] = a
        polished = False
        if cfg.polish:
            a, s, polished = self._polished(prep, e, cons, work, qp, x, a, s)
        return a, s, st, k, rounds, polished

    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        t0, c0 = time.perf_counter(), time.process_time()
        cfg = self.config
        if state.t == 0:
            self._warm.clear()
        prep = self._prepare(state, env_config)
        b = prep.p.shape[0]
        a_safe = np.empty_like(prep.a_nom)
        num_slack = num_failed = num_cons = num_retry = num_rounds = num_polished = 0
        max_slack = 0.0
        status = []
        for e in range(b):
            cons = build_constraints(
                prep.p[e], prep.v[e], prep.barrier, prep.centers[e], prep.radii[e], bounds=prep.bounds
            )
            num_cons += len(cons)
            a, s, st, retried, rounds, polished = self._solve_env(prep, e, cons)
            status.append(st)
            num_retry += retried
            num_rounds += rounds
            num_polished += polished
            if a is None:
                num_failed += 1
                a = self._brake(prep.v[e], prep.bounds)
                s = np.zeros(len(cons))
            a_safe[e] = a
            ms = float(s.max(initial=0.0))
            max_slack = max(max_slack, ms)
            num_slack += int(ms > cfg.slack_tol)
        qp_ms = 1e3 * (time.perf_counter() - t0)
        cpu_ms = 1e3 * (time.process_time() - c0)
        u = self._finish(prep, a_safe).to(state.x.dtype)
        info = {
            "qp_ms": qp_ms,
            "qp_cpu_ms": cpu_ms,
            "num_slack": num_slack,
            "num_failed": num_failed,
            "num_qps": b,
            "num_retried": num_retry,
            "num_rounds": num_rounds,
            "num_polished": num_polished,
            "num_constraints": num_cons,
            "max_slack": max_slack,
            "status": status,
            "a_safe": a_safe,
            "a_nom": prep.a_nom,
        }
        return u, info
