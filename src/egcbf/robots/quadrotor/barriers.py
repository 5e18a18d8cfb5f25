"""Hand-crafted control barrier functions for the quadrotor swarm, through a thrust-vector (double-integrator) model.

Every agent's world-frame acceleration ``a_i = R_i F3_i e3 / m + g`` is treated as the virtual control of a double
integrator ``p_i'' = a_i`` (see ``docs/baselines.md`` for the derivation, the parameters and what is and is not
guaranteed). Each barrier yields constraints that are *linear* in the accelerations, in one common form

    n_c . a_{i_c} - n_c . a_{j_c} >= b_c          (j_c = -1: an obstacle, no second agent)

with ``n_c`` the unit vector from the other agent (or obstacle centre) to agent ``i_c``. Rows are normalized (divided
by ``2 ||dp||``) so that every constraint and every slack is in units of acceleration (m/s^2).

Coincident points (``||dp|| <= 1e-9``: two agents at exactly the same point, or an agent at an obstacle's centre)
have no direction from the geometry. Their row then pushes along the relative velocity ``dv`` if it is not zero,
else along world ``+z`` (agent ``i_c`` up, ``j_c`` down; the pair order ``i < j`` makes it deterministic), so the
constraint is never a zero row that constrains nothing.

Two barriers are available (``BarrierConfig.kind``):

* ``"wang"`` (default): the braking-distance barrier of Wang, Ames & Egerstedt (2017),
  ``h = sqrt(2 A_sum (d - D)) + d'`` with ``h' + gamma h^3 >= 0``, which accounts for bounded deceleration.
* ``"hocbf"``: second-order exponential CBF on ``h0 = ||dp||^2 - D^2``:
  ``h0'' + (k1 + k2) h0' + k1 k2 h0 >= 0`` (Nguyen & Sreenath 2016; Xiao & Belta 2019).

All quantities are relative positions and velocities, so the constraints are invariant under the symmetry of the
quadrotor (rotations about world z and translations): rotating the scene rotates every ``n_c`` and leaves ``b_c``
unchanged. The acceleration bounds are expressed in each agent's yaw frame (its heading), hence equivariant too.

Everything here is plain numpy (float64) on one batch of agents; the controllers convert from torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ...qp.constraints import Constraints

__all__ = [
    "LIDAR_HITS",
    "AccelBounds",
    "BarrierConfig",
    "agent_pairs",
    "bound_rows",
    "build_constraints",
    "hit_constraints",
    "obstacle_constraints",
    "pair_constraints",
    "perceived_constraints",
    "prune_redundant",
    "split_for_agents",
    "support_bound",
    "yaw_angle",
]

GRAVITY = 9.81
#: how the rows of :func:`hit_constraints` read one LiDAR return: ``"plane"`` (default) or ``"point"``
LIDAR_HITS = ("plane", "point")


@dataclass(frozen=True)
class BarrierConfig:
    """Parameters of the hand-crafted barriers (defaults chosen by measurement, see ``docs/baselines.md``).

    Attributes:
        kind: ``"wang"`` (braking distance, default: measured safer and cheaper) or ``"hocbf"`` (exponential
            second-order CBF on the squared distance).
        agent_radius: drone radius ``r`` (m); collisions are ``||p_i - p_j|| < 2 r``.
        margin: extra clearance (m): agent pairs keep ``D = 2 r + margin``, obstacles ``D = rho + r + margin``.
            It absorbs the attitude-loop lag (the real acceleration follows the commanded one after ~0.1 s).
        k1, k2: gains of the exponential CBF (1/s), ``kind="hocbf"``.
        gamma: class-K gain of ``h' >= -gamma h^3`` (``kind="wang"``), units (s/m)^2 / s.
        brake_accel: deceleration ``A`` (m/s^2) each agent is assumed able to spend on one pair (``kind="wang"``).
        cull_radius: agent pairs further apart (centre to centre, m) than this get no constraint; ``None``: the
            environment's communication radius (filled in by the controllers; required by the functions here).
        max_neighbors: keep only the ``k`` nearest agents of each agent (pairs in the union of both agents'
            lists); ``None`` keeps every agent within ``cull_radius``.
        obstacle_cull: obstacles whose surface is further than this (m) from the agent get no constraint
            (``None``: the same as ``cull_radius``).
        max_obstacles: keep only the ``k`` nearest obstacles per agent (``None``: all within ``obstacle_cull``).
    """

    kind: str = "wang"
    agent_radius: float = 0.05
    margin: float = 0.05
    k1: float = 3.0
    k2: float = 6.0
    gamma: float = 5.0
    brake_accel: float = 2.5
    cull_radius: float | None = None
    max_neighbors: int | None = None
    obstacle_cull: float | None = None
    max_obstacles: int | None = None

    def __post_init__(self):
        if self.kind not in ("hocbf", "wang"):
            raise ValueError(f"BarrierConfig.kind must be 'hocbf' or 'wang', got {self.kind!r}")
        for name in ("agent_radius", "k1", "k2", "gamma", "brake_accel", "cull_radius", "obstacle_cull"):
            v = getattr(self, name)
            if v is None and name in ("cull_radius", "obstacle_cull"):
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"BarrierConfig.{name} must be positive and finite, got {v!r}")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"BarrierConfig.margin must be >= 0, got {self.margin!r}")
        for name in ("max_neighbors", "max_obstacles"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or v < 1):
                raise ValueError(f"BarrierConfig.{name} must be None or a positive integer, got {v!r}")

    @property
    def safe_distance(self) -> float:
        """Agent–agent safety distance ``D_s = 2 r + margin``."""
        return 2 * self.agent_radius + self.margin


@dataclass(frozen=True)
class AccelBounds:
    """Rotation-equivariant bounds on the world acceleration ``a`` (gravity included: hover is ``a = 0``).

    Horizontal: ``|c_k . a| <= horizontal`` for the ``polygon`` directions ``c_k = (cos(psi + k pi / polygon),
    sin(psi + k pi / polygon), 0)``, ``psi`` the agent's yaw (heading of its body x axis): a regular
    ``2 polygon``-gon with in-radius ``horizontal`` that turns with the agent. Vertical: ``z_min <= a_z <= z_max``.
    """

    horizontal: float = 5.0
    z_min: float = -0.5 * GRAVITY
    z_max: float = 7.5
    polygon: int = 4

    def __post_init__(self):
        if not (self.horizontal > 0 and math.isfinite(self.horizontal)):
            raise ValueError(f"AccelBounds.horizontal must be positive, got {self.horizontal!r}")
        if not (self.z_min < 0 < self.z_max):
            raise ValueError(f"AccelBounds needs z_min < 0 < z_max (hover feasible), got {self.z_min}, {self.z_max}")
        if int(self.polygon) != self.polygon or self.polygon < 2:
            raise ValueError(f"AccelBounds.polygon must be an integer >= 2, got {self.polygon!r}")

    @property
    def circumradius(self) -> float:
        """Largest horizontal acceleration the polygon admits."""
        return self.horizontal / math.cos(math.pi / (2 * self.polygon))

    @property
    def inscribed(self) -> float:
        """Radius of the largest ball centred at 0 inside the bound set (acceleration available in any direction)."""
        return min(self.horizontal, -self.z_min, self.z_max)

    @classmethod
    def from_thrust(
        cls, max_thrust_accel: float, horizontal: float = 5.0, min_thrust_frac: float = 0.5, polygon: int = 4
    ) -> AccelBounds:
        """Bounds whose every corner needs a thrust ``F3 / m <= max_thrust_accel`` and ``>= min_thrust_frac g``.

        ``z_max`` is the largest vertical acceleration such that ``||a - g|| <= max_thrust_accel`` at the corners of
        the polygon (``sqrt(circumradius^2 + (z_max + g)^2) <= max_thrust_accel``); ``z_min = (min_thrust_frac - 1) g``.
        """
        circ = horizontal / math.cos(math.pi / (2 * polygon))
        room = max_thrust_accel**2 - circ**2
        if room <= (GRAVITY * 1.05) ** 2:
            raise ValueError(
                f"max thrust acceleration {max_thrust_accel:g} m/s^2 cannot hover while accelerating {horizontal:g}"
                " m/s^2 sideways; lower 'horizontal'"
            )
        return cls(horizontal, (min_thrust_frac - 1.0) * GRAVITY, math.sqrt(room) - GRAVITY, polygon)


def agent_pairs(pos: np.ndarray, cfg: BarrierConfig, batch: np.ndarray | None = None) -> np.ndarray:
    """Unordered agent pairs ``(2, P)`` with ``i < j``, same batch entry, closer than ``cfg.cull_radius``.

    With ``cfg.max_neighbors = k`` a pair is kept if either agent has the other among its ``k`` nearest (within the
    radius). A k-d tree (``scipy.spatial.cKDTree``, C code, O(M log M + P)) finds the pairs; environments of a batch
    are separated by shifting each one along x by more than the culling radius. Pairs are sorted (deterministic).
    """
    num = pos.shape[0]
    if num < 2:
        return np.zeros((2, 0), dtype=np.int64)
    pts = np.asarray(pos, dtype=np.float64)
    if batch is not None and num:
        span = float(np.ptp(pts[:, 0])) + 4.0 * cfg.cull_radius + 1.0
        pts = pts.copy()
        pts[:, 0] += np.asarray(batch, dtype=np.float64) * span
    tree = cKDTree(pts)
    if cfg.cull_radius is None:
        raise ValueError("BarrierConfig.cull_radius is None: set it (the controllers use the comm radius)")
    r = np.nextafter(cfg.cull_radius, 0.0)  # strict "<" like the rest of the project
    if cfg.max_neighbors is None:
        pr = tree.query_pairs(r, output_type="ndarray")
        if pr.size == 0:
            return np.zeros((2, 0), dtype=np.int64)
        key = np.sort(pr[:, 0].astype(np.int64) * num + pr[:, 1])  # query_pairs gives i < j
        return np.stack((key // num, key % num))
    k = int(cfg.max_neighbors)
    dist, idx = tree.query(pts, k=min(k + 1, num), distance_upper_bound=r)
    dist, idx = dist.reshape(num, -1), idx.reshape(num, -1)
    src = np.repeat(np.arange(num), idx.shape[1])
    dst = idx.reshape(-1)
    ok = (dst < num) & (dst != src)
    src, dst = src[ok], dst[ok]
    key = np.unique(np.minimum(src, dst).astype(np.int64) * num + np.maximum(src, dst))
    return np.stack((key // num, key % num))


def _rows_from_geometry(dp, dv, D, cfg: BarrierConfig, brake_sum: float, curvature: bool = True):
    """Normal, right-hand side and barrier value for rows with relative position ``dp``, velocity ``dv``.

    ``brake_sum`` is the total deceleration the pair can spend (``2 A`` for two agents, ``A`` for an obstacle).
    ``curvature = False`` drops the term ``(|dv|^2 - d'^2) / d`` of ``d''`` (the turning of ``n`` as the point
    moves past): the row of a plane through the point, normal to ``dp``, held fixed over the step.
    """
    d = np.sqrt((dp * dp).sum(-1))
    d_safe = np.maximum(d, 1e-9)
    n = dp / d_safe[:, None]
    dv2 = (dv * dv).sum(-1)
    coincident = d <= 1e-9
    if coincident.any():  # no direction from dp: push along dv, else +z (module doc)
        speed = np.sqrt(dv2)[:, None]
        push = np.where(speed > 1e-9, dv / np.maximum(speed, 1e-9), np.array([0.0, 0.0, 1.0]))
        n = np.where(coincident[:, None], push, n)
    ddot = (n * dv).sum(-1)  # d' (m/s)
    if cfg.kind == "hocbf":
        # h0 = d^2 - D^2, h0' = 2 dp.dv, h0'' = 2 |dv|^2 + 2 dp.(a_i - a_j); divide the row by 2 d.
        h0 = d * d - D * D
        rhs = -(dv2 + (cfg.k1 + cfg.k2) * d * ddot + 0.5 * cfg.k1 * cfg.k2 * h0) / d_safe
        return n, rhs, h0, d
    # Wang et al.: h = sqrt(2 A_sum (d - D)) + d';  h' = A_sum d' / sqrt(2 A_sum (d - D)) + d''
    # with d'' = n.(a_i - a_j) + (|dv|^2 - d'^2) / d.  Row: n.(a_i - a_j) >= -gamma h^3 - (|dv|^2 - d'^2)/d - A d'/s.
    gap = np.maximum(d - D, 1e-6)  # at or inside the safety distance: the barrier is singular; clamp (see docs)
    s = np.sqrt(2.0 * brake_sum * gap)
    h = s + ddot
    turning = (dv2 - ddot * ddot) / d_safe if curvature else 0.0
    rhs = -cfg.gamma * h**3 - turning - brake_sum * ddot / s
    return n, rhs, h, d


def pair_constraints(pos: np.ndarray, vel: np.ndarray, pairs: np.ndarray, cfg: BarrierConfig) -> Constraints:
    """Agent–agent rows for ``pairs`` ``(2, P)``: ``n . (a_i - a_j) >= b`` with ``n = (p_i - p_j) / d``."""
    if pairs.shape[1] == 0:
        return Constraints.empty()
    i, j = pairs[0], pairs[1]
    dp = pos[i] - pos[j]
    dv = vel[i] - vel[j]
    D = np.full(i.shape[0], cfg.safe_distance)
    n, rhs, h, d = _rows_from_geometry(dp, dv, D, cfg, 2.0 * cfg.brake_accel)
    return Constraints(i.astype(np.int64), j.astype(np.int64), n, rhs, h, d, D, int(i.shape[0]))


def obstacle_constraints(
    pos: np.ndarray, vel: np.ndarray, centers: np.ndarray, radii: np.ndarray, cfg: BarrierConfig
) -> Constraints:
    """Agent–sphere rows ``n . a_i >= b`` for spheres within ``cfg.obstacle_cull`` of the agent's surface distance.

    ``pos, vel`` ``(N, 3)``, ``centers`` ``(K, 3)``, ``radii`` ``(K,)``; dense in ``N x K`` (K is small).
    """
    if centers is None or len(centers) == 0 or pos.shape[0] == 0:
        return Constraints.empty()
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    dp_all = pos[:, None, :] - centers[None]  # (N, K, 3)
    dist = np.sqrt((dp_all**2).sum(-1))
    surface = dist - radii[None] - cfg.agent_radius
    cull = cfg.obstacle_cull if cfg.obstacle_cull is not None else cfg.cull_radius
    mask = surface < (np.inf if cull is None else cull)
    if cfg.max_obstacles is not None and centers.shape[0] > cfg.max_obstacles:
        rank = np.argsort(np.argsort(surface, axis=1, kind="stable"), axis=1, kind="stable")
        mask &= rank < cfg.max_obstacles
    i, k = np.nonzero(mask)
    if i.size == 0:
        return Constraints.empty()
    D = radii[k] + cfg.agent_radius + cfg.margin
    n, rhs, h, d = _rows_from_geometry(dp_all[i, k], vel[i], D, cfg, cfg.brake_accel)
    return Constraints(i.astype(np.int64), np.full(i.shape[0], -1, dtype=np.int64), n, rhs, h, d, D, 0)


def hit_constraints(pos: np.ndarray, vel: np.ndarray, points: np.ndarray, valid: np.ndarray,
                    cfg: BarrierConfig, model: str = "plane") -> Constraints:  # fmt: skip
    """Agent rows ``n . a_i >= b`` for every agent's own LiDAR hits, as the obstacle rows of
    :func:`obstacle_constraints` read spheres; the agent keeps ``D = r + margin`` from each hit.

    ``model`` (:data:`LIDAR_HITS`) is what one return stands for. ``"point"``: a point obstacle (radius 0). Its row
    credits the agent with the turning of the line of sight as it moves past the point, ``(|v|^2 - d'^2) / d`` in
    ``d''``, which a surface behind the point does not give: next to a sphere of radius ``rho`` the true term is
    ``(|v_t|^2) / (d + rho)``, so an agent sliding along a large obstacle is allowed to close on it (measured in
    docs/safety_filters.md). ``"plane"`` (default): the plane through the hit normal to the ray, fixed over the step
    (``d'' = n . a``, no turning term): for a convex obstacle seen along its normal the row is at least as
    demanding as the true surface's. Both read the same distance and closing speed; only ``d''`` differs.

    ``pos, vel`` ``(M, 3)``; ``points`` ``(M, H, 3)`` world-frame hits, ``valid`` ``(M, H)`` bool (the
    :class:`egcbf.env.lidar.LidarScan` of the agents, flattened). Each agent's rows read only its own scan."""
    if model not in LIDAR_HITS:
        raise ValueError(f"hit_constraints: model must be one of {LIDAR_HITS}, got {model!r}")
    i, k = np.nonzero(valid)
    if i.size == 0:
        return Constraints.empty()
    D = np.full(i.shape[0], cfg.agent_radius + cfg.margin)
    n, rhs, h, d = _rows_from_geometry(pos[i] - points[i, k], vel[i], D, cfg, cfg.brake_accel, model == "point")
    return Constraints(i.astype(np.int64), np.full(i.shape[0], -1, dtype=np.int64), n, rhs, h, d, D, 0)


def support_bound(normal: np.ndarray, bounds: AccelBounds) -> np.ndarray:
    """Upper bound of ``max |n . a|`` over the acceleration bounds, for unit ``n`` ``(R, 3)``.

    Uses the polygon's circumscribed circle: ``|n_xy| circumradius + |n_z| max(-z_min, z_max)``. Rotation invariant.
    """
    nxy = np.sqrt(normal[:, 0] ** 2 + normal[:, 1] ** 2)
    return nxy * bounds.circumradius + np.abs(normal[:, 2]) * max(-bounds.z_min, bounds.z_max)


def prune_redundant(cons: Constraints, bounds: AccelBounds) -> Constraints:
    """Drop rows that every pair of accelerations within ``bounds`` satisfies (lossless: the QP is unchanged).

    A row ``n . (a_i - a_j) >= b`` holds for all bounded accelerations when ``b <= -(S_i + S_j)``, ``S`` the
    :func:`support_bound` (one ``S`` for an obstacle row). The halves ``b / 2`` of the decentralized split are
    then redundant too (``S_i = S_j``: the bound sets have the same support in ``n`` and ``-n``).
    """
    if not len(cons):
        return cons
    s = support_bound(cons.normal, bounds) * np.where(cons.j >= 0, 2.0, 1.0)
    keep = cons.rhs > -s
    return cons if keep.all() else cons.subset(keep)


def build_constraints(
    pos: np.ndarray,
    vel: np.ndarray,
    cfg: BarrierConfig,
    centers: np.ndarray | None = None,
    radii: np.ndarray | None = None,
    batch: np.ndarray | None = None,
    bounds: AccelBounds | None = None,
) -> Constraints:
    """All rows (agent pairs first, then obstacles) for agents ``pos, vel`` ``(M, 3)``.

    ``batch`` ``(M,)`` separates environments (no pair across them); obstacles are then a per-environment list:
    ``centers`` a list of ``(K_b, 3)`` arrays and ``radii`` a list of ``(K_b,)`` arrays, one per environment.
    With ``bounds``, rows that cannot be violated by any bounded acceleration are dropped (:func:`prune_redundant`).
    """
    parts = [pair_constraints(pos, vel, agent_pairs(pos, cfg, batch), cfg)]
    parts += _obstacle_parts(pos, vel, cfg, centers, radii, batch)
    cons = Constraints.cat(parts)
    return cons if bounds is None else prune_redundant(cons, bounds)


def _obstacle_parts(pos, vel, cfg: BarrierConfig, centers, radii, batch) -> list[Constraints]:
    """The obstacle rows of :func:`build_constraints` (same arguments), one part per environment."""
    if centers is None:
        return []
    if batch is None:
        return [obstacle_constraints(pos, vel, centers, radii, cfg)]
    parts = []
    for b, (c, r) in enumerate(zip(centers, radii)):
        idx = np.nonzero(batch == b)[0]
        if idx.size == 0 or c is None or len(c) == 0:
            continue
        oc = obstacle_constraints(pos[idx], vel[idx], c, r, cfg)
        oc.i = idx[oc.i]
        parts.append(oc)
    return parts


def perceived_constraints(
    pos: np.ndarray,
    vel: np.ndarray,
    links: np.ndarray,
    sent_pos: np.ndarray,
    sent_vel: np.ndarray,
    cfg: BarrierConfig,
    centers: np.ndarray | None = None,
    radii: np.ndarray | None = None,
    batch: np.ndarray | None = None,
    bounds: AccelBounds | None = None,
) -> Constraints:
    """The rows of agents that know their neighbours only from the messages they received (:mod:`egcbf.faults`).

    ``pos, vel`` ``(M, 3)``: each agent's own estimate (world frame); ``links`` ``(2, L)``: the directed links
    ``(receiver r, sender s)`` whose messages arrived; ``sent_pos, sent_vel`` ``(L, 3)``: what each link's message
    tells its receiver of the sender (the messages of one sender may differ between links: held messages of
    different ages). Link ``l = (r, s)`` gives the pair row between agent ``r`` and a phantom agent ``M + l`` at
    ``sent_pos[l], sent_vel[l]`` (the sender as ``r`` perceives it), ``n . (a_r - a_{M+l}) >= b`` with
    ``n = (p_r - p_sent_l) / d``, so that ``split_for_agents(cons, num_agents=M)`` keeps exactly ``r``'s half
    ``n . a_r >= b / 2``: ``r``'s view of the pair need not be ``s``'s view of it. Obstacle rows, the pruning by
    ``bounds`` and the rest of the arguments as :func:`build_constraints`.
    """
    m = pos.shape[0]
    recv, send = np.asarray(links, dtype=np.int64).reshape(2, -1)
    sent_pos, sent_vel = np.asarray(sent_pos).reshape(-1, 3), np.asarray(sent_vel).reshape(-1, 3)
    if sent_pos.shape[0] != recv.shape[0] or sent_vel.shape[0] != recv.shape[0]:
        raise ValueError(f"perceived_constraints: {recv.shape[0]} links but {sent_pos.shape[0]} sent positions and "
                         f"{sent_vel.shape[0]} sent velocities (one per link)")  # fmt: skip
    both_pos = np.concatenate((pos, sent_pos))
    both_vel = np.concatenate((vel, sent_vel))
    pairs = pair_constraints(both_pos, both_vel, np.stack((recv, m + np.arange(recv.shape[0]))), cfg)
    if len(pairs):
        # coincident and at rest relative to each other (module doc): the phantom is always the row's j, which
        # would push every receiver up; +z for the lower agent index, -z for the higher, as build_constraints' halves
        dv = vel[recv] - sent_vel
        still = (pairs.dist <= 1e-9) & (np.sqrt((dv * dv).sum(-1)) <= 1e-9) & (recv > send)
        pairs.normal[still] *= -1.0
    parts = [pairs, *_obstacle_parts(pos, vel, cfg, centers, radii, batch)]
    cons = Constraints.cat(parts)
    return cons if bounds is None else prune_redundant(cons, bounds)


def split_for_agents(cons: Constraints, num_agents: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decentralized split: agent ``i`` enforces ``n . a_i >= b / 2`` and agent ``j`` ``-n . a_j >= b / 2`` for
    a pair (the two halves add up to the pair constraint); obstacle rows stay whole on their agent.

    ``num_agents = M``: the halves owned by rows ``>= M`` (the phantom senders of :func:`perceived_constraints`)
    belong to no agent and are left out.

    Returns ``owner (R,), normal (R, 3), rhs (R,)``.
    """
    pair = cons.j >= 0
    owner = np.concatenate([cons.i, cons.j[pair]])
    normal = np.concatenate([cons.normal, -cons.normal[pair]])
    rhs_i = np.where(pair, 0.5 * cons.rhs, cons.rhs)
    rhs = np.concatenate([rhs_i, 0.5 * cons.rhs[pair]])
    if num_agents is not None:
        real = owner < num_agents
        owner, normal, rhs = owner[real], normal[real], rhs[real]
    return owner, normal, rhs


def yaw_angle(rot_flat: np.ndarray) -> np.ndarray:
    """Yaw ``psi`` of the body x axis projected on the horizontal plane, from row-major ``R`` ``(M, 9)``.

    The same heading as :func:`egcbf.robots.quadrotor.nominal.desired_heading`: ``R e1 = (R00, R10, R20)``; where its
    horizontal part is shorter than 1e-3 (body x within 0.06 degrees of vertical) the body y axis turned by
    -90 degrees, ``(R11, -R01)``. Both rotate with the scene, so the bounds stay equivariant.
    """
    r00, r10, r01, r11 = rot_flat[:, 0], rot_flat[:, 3], rot_flat[:, 1], rot_flat[:, 4]
    use_x = r00 * r00 + r10 * r10 > 1e-6
    return np.where(use_x, np.arctan2(r10, r00), np.arctan2(-r01, r11))


def bound_rows(rot_flat: np.ndarray, bounds: AccelBounds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-agent bound rows: ``C (M, polygon + 1, 3)``, ``lo, hi (M, polygon + 1)``: ``lo <= C a <= hi``."""
    m = rot_flat.shape[0]
    psi = yaw_angle(rot_flat)
    ang = psi[:, None] + np.arange(bounds.polygon)[None] * (np.pi / bounds.polygon)
    C = np.zeros((m, bounds.polygon + 1, 3))
    C[:, :-1, 0] = np.cos(ang)
    C[:, :-1, 1] = np.sin(ang)
    C[:, -1, 2] = 1.0
    lo = np.empty((m, bounds.polygon + 1))
    hi = np.empty_like(lo)
    lo[:, :-1], hi[:, :-1] = -bounds.horizontal, bounds.horizontal
    lo[:, -1], hi[:, -1] = bounds.z_min, bounds.z_max
    return C, lo, hi
