"""The standalone runtime of an exported filtered controller: one agent's learned policy behind the ``dcbf`` filter,
with numpy and onnxruntime alone (no torch, no egcbf).

``egcbf export --controller egcbf+:dcbf`` (:mod:`egcbf.deploy.controller_export`) writes a directory with the
policy as ONNX (``policy.onnx``), the filter's settings and the robot's constants (``controller.json``) and a copy
of this file (``egcbf_runtime.py``); on the robot::

    from egcbf_runtime import Controller

    ctrl = Controller.load("egcbf+-dcbf")
    u, info = ctrl.step(state, goal, neighbours, neighbour_mask, hits, hit_mask,
                        accelerations=acc, obstacles=(centers, radii))

This file is the numpy implementation of what :class:`egcbf.deploy.agent.AgentFilteredController` computes (the
decentralized CBF-QP of :meth:`egcbf.robots.quadrotor.dcbf_qp.DecentralizedCBFQP.filter` for one agent, and the
attitude loop :func:`egcbf.robots.quadrotor.nominal.track_acceleration`); ``tests/egcbf/test_export_controller.py``
checks it against the PyTorch one. One step:

1. **Policy** (``policy.onnx``, float32): the agent's command from its own state, goal, the neighbours within the
   communication radius (the nearest ``max_neighbours``) and its LiDAR hits within the LiDAR range (the nearest
   ``max_hits``), as :class:`egcbf.deploy.agent.AgentController` selects them.
2. **Filter** (numpy, float64): one QP in the agent's acceleration ``a`` (m/s^2, world frame) and one slack ``s``::

       min  1/2 ||a - a_pi||^2 + 1/2 w2 s^2 + w1 s
       s.t. n_k . a + s >= b_k     (half of each neighbour's pair row, each sphere obstacle's whole row)
            lo <= C a <= hi         (the acceleration box, turning with the agent's yaw),   s >= 0

   with ``a_pi = command_unit * command`` and the rows of Wang et al.'s braking-distance barrier read at the
   look-ahead state ``p + T v + T^2 a_real / 2``, ``v + T a_real`` of the agent and of each neighbour (``a_real``
   their realized accelerations of the last step). The QP is solved exactly by a dual active-set method
   (Goldfarb-Idnani, :func:`solve_qp`); a solution that fails the check (:func:`verified`) is replaced by braking.
3. **Attitude loop** (numpy, float64): the body torque and thrust that track the filtered acceleration
   (:func:`track_acceleration`), clipped to the actuators.

Frames and units: world frame, SI units; the state is ``[p (3), R (9, row-major, body to world), v (3), w (3,
body rates)]``; the control ``u = (tau (3, N m, body frame), F3 (N))``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = [
    "FORMAT",
    "POLICY_FILE",
    "RUNTIME_FILE",
    "SETTINGS_FILE",
    "Controller",
    "ExportError",
    "agent_rows",
    "bound_rows",
    "filter_command",
    "solve_qp",
    "track_acceleration",
    "verified",
]

#: the ``format`` entry of ``controller.json`` this runtime reads
FORMAT = "egcbf filtered controller 1"
SETTINGS_FILE = "controller.json"
POLICY_FILE = "policy.onnx"
RUNTIME_FILE = "egcbf_runtime.py"
#: the ONNX policy's inputs and outputs (:mod:`egcbf.deploy.export`)
INPUT_NAMES = ("state", "goal", "neighbours", "neighbour_valid", "hits", "hit_valid")
OUTPUT_NAMES = ("u", "command")
STATE_DIM, DIM, CONTROL_DIM = 18, 3, 4
_HEADING_EPS2 = 1e-6  # |horizontal part of body x|^2 below which the heading falls back on body y


class ExportError(ValueError):
    """A directory that is not an exported filtered controller this runtime can run (the message says why)."""


# ------------------------------------------------------------------------------------------------- the rows
def _barrier_rows(dp: np.ndarray, dv: np.ndarray, D: np.ndarray, gamma: float, brake_sum: float,
                  curvature: bool = True) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Wang et al.'s braking-distance rows ``n . a >= b`` for relative positions ``dp`` and velocities ``dv``
    ``(R, 3)`` and safety distances ``D`` ``(R,)``: ``h = sqrt(2 A (d - D)) + d'``, ``h' + gamma h^3 >= 0``, with
    ``brake_sum = A`` the deceleration the row may spend (m/s^2). Returns ``normal (R, 3)`` (unit, from the other
    point to the agent) and ``rhs (R,)`` (m/s^2). Coincident points push along ``dv``, else ``+z``."""
    d = np.sqrt((dp * dp).sum(-1))
    d_safe = np.maximum(d, 1e-9)
    n = dp / d_safe[:, None]
    dv2 = (dv * dv).sum(-1)
    coincident = d <= 1e-9
    if coincident.any():
        speed = np.sqrt(dv2)[:, None]
        push = np.where(speed > 1e-9, dv / np.maximum(speed, 1e-9), np.array([0.0, 0.0, 1.0]))
        n = np.where(coincident[:, None], push, n)
    ddot = (n * dv).sum(-1)
    gap = np.maximum(d - D, 1e-6)
    s = np.sqrt(2.0 * brake_sum * gap)
    h = s + ddot
    turning = (dv2 - ddot * ddot) / d_safe if curvature else 0.0
    rhs = -gamma * h**3 - turning - brake_sum * ddot / s
    return n, rhs


def _support(normal: np.ndarray, bounds: dict) -> np.ndarray:
    """Upper bound of ``max |n . a|`` over the acceleration box for unit normals ``(R, 3)``."""
    nxy = np.sqrt(normal[:, 0] ** 2 + normal[:, 1] ** 2)
    circ = bounds["horizontal"] / math.cos(math.pi / (2 * bounds["polygon"]))
    return nxy * circ + np.abs(normal[:, 2]) * max(-bounds["z_min"], bounds["z_max"])


def agent_rows(p: np.ndarray, v: np.ndarray, nbr_p: np.ndarray, nbr_v: np.ndarray, centers: np.ndarray,
               radii: np.ndarray, settings: dict) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The agent's CBF rows ``n . a >= b`` at (look-ahead) position ``p`` and velocity ``v`` ``(3,)``.

    Args:
        p, v: the agent's position (m) and velocity (m/s), world frame, ``(3,)``.
        nbr_p, nbr_v: its neighbours' ``(K, 3)``; those at ``cull_radius`` or farther get no row.
        centers, radii: sphere obstacles ``(O, 3)``, ``(O,)`` (m); those whose surface is ``obstacle_cull`` or
            farther from the agent's surface get no row.
        settings: ``controller.json``'s ``filter`` entry.

    Returns:
        ``normal (R, 3)`` and ``rhs (R,)``: half of each neighbour's pair row (the neighbour keeps the other half),
        each obstacle's whole row; rows that every acceleration in the box satisfies are left out.
    """
    bar, bounds = settings["barrier"], settings["bounds"]
    r, margin, gamma, brake = bar["agent_radius"], bar["margin"], bar["gamma"], bar["brake_accel"]
    normals, rhss = [], []
    if nbr_p.shape[0]:
        dp, dv = p - nbr_p, v - nbr_v
        near = np.sqrt((dp * dp).sum(-1)) <= np.nextafter(bar["cull_radius"], 0.0)
        if near.any():
            n, b = _barrier_rows(dp[near], dv[near], np.full(int(near.sum()), 2 * r + margin), gamma, 2.0 * brake)
            keep = b > -2.0 * _support(n, bounds)
            normals.append(n[keep])
            rhss.append(0.5 * b[keep])
    if centers.shape[0]:
        dp = p - centers
        surface = np.sqrt((dp * dp).sum(-1)) - radii - r
        cull = bar["obstacle_cull"] if bar["obstacle_cull"] is not None else bar["cull_radius"]
        near = surface < cull
        if near.any():
            n, b = _barrier_rows(dp[near], np.broadcast_to(v, dp[near].shape), radii[near] + r + margin, gamma, brake)
            keep = b > -_support(n, bounds)
            normals.append(n[keep])
            rhss.append(b[keep])
    if not normals:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(normals), np.concatenate(rhss)


def bound_rows(rot: np.ndarray, bounds: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The acceleration box ``lo <= C a <= hi`` of an agent with attitude ``rot`` (9, row-major): ``polygon``
    horizontal directions at the agent's yaw plus multiples of ``pi / polygon``, and the vertical axis. Returns
    ``C (polygon + 1, 3)``, ``lo``, ``hi`` ``(polygon + 1,)`` (m/s^2)."""
    r00, r10, r01, r11 = rot[0], rot[3], rot[1], rot[4]
    psi = math.atan2(r10, r00) if r00 * r00 + r10 * r10 > _HEADING_EPS2 else math.atan2(-r01, r11)
    k = bounds["polygon"]
    ang = psi + np.arange(k) * (np.pi / k)
    C = np.zeros((k + 1, 3))
    C[:-1, 0], C[:-1, 1], C[-1, 2] = np.cos(ang), np.sin(ang), 1.0
    lo = np.concatenate((np.full(k, -bounds["horizontal"]), [bounds["z_min"]]))
    hi = np.concatenate((np.full(k, bounds["horizontal"]), [bounds["z_max"]]))
    return C, lo, hi


# ------------------------------------------------------------------------------------------------- the QP
def solve_qp(a_ref: np.ndarray, normal: np.ndarray, rhs: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             w1: float, w2: float, max_iter: int = 200) -> tuple[np.ndarray, bool]:  # fmt: skip
    """The filter's QP in ``z = (a (3), s)``, exactly, by the dual active-set method of Goldfarb and Idnani (1983)::

        min 1/2 ||a - a_ref||^2 + 1/2 w2 s^2 + w1 s   s.t.  normal a + s >= rhs,  lo <= C a <= hi,  s >= 0

    With ``y = H^(1/2) z`` (``H = diag(1, 1, 1, w2)``) it is the projection of the unconstrained minimizer onto a
    polyhedron: starting there, the most violated row enters the active set at each step (rows whose multiplier
    would turn negative leave), until no row is violated; the result is then recomputed from the final active
    set's KKT system. At most four rows are active.

    Args:
        a_ref: ``(3,)`` the reference acceleration (m/s^2).
        normal, rhs: ``(R, 3)``, ``(R,)`` the CBF rows. C, lo, hi: the box ``(Kb, 3)``, ``(Kb,)``.
        w1, w2: the slack's linear and quadratic cost.
        max_iter: active-set changes before giving up.

    Returns:
        ``z`` ``(4,)`` and whether it converged (the QP is always feasible: ``a = 0`` with a large ``s``).
    """
    kb = C.shape[0]
    M = np.zeros((normal.shape[0] + 2 * kb + 1, 4))  # rows M z >= b
    M[: normal.shape[0], :3], M[: normal.shape[0], 3] = normal, 1.0
    M[normal.shape[0] : normal.shape[0] + kb, :3] = C
    M[normal.shape[0] + kb : -1, :3] = -C
    M[-1, 3] = 1.0
    b = np.concatenate((rhs, lo, -hi, [0.0]))
    scale = np.array([1.0, 1.0, 1.0, math.sqrt(w2)])
    M = M / scale  # in y = scale * z
    y0 = np.concatenate((a_ref, [-w1 / w2])) * scale
    norms = np.sqrt((M * M).sum(1))
    tol = 1e-12 * (1.0 + np.abs(b))
    y = y0.copy()
    active: list[int] = []
    u = np.zeros(0)
    for _ in range(max_iter):
        viol = M @ y - b
        p = int(np.argmin(viol / norms))
        if viol[p] >= -tol[p]:
            break
        u_p = 0.0
        while True:  # add row p, dropping the rows that block it
            n = M[p]
            if active:
                na = M[active]
                r = np.linalg.solve(na @ na.T, na @ n)
                step = n - na.T @ r
            else:
                r, step = np.zeros(0), n
            blocking = np.nonzero(r > 1e-14)[0]
            t1, k = math.inf, -1
            if blocking.size:
                ratios = u[blocking] / r[blocking]
                k = int(blocking[np.argmin(ratios)])
                t1 = float(ratios.min())
            dependent = float(step @ step) <= 1e-24 * float(n @ n)
            if dependent:
                if k < 0:
                    return _unscale(y, scale), False  # infeasible: cannot happen for this QP
                u, u_p = u - t1 * r, u_p + t1
                del active[k]
                u = np.delete(u, k)
                continue
            t2 = -float(n @ y - b[p]) / float(step @ n)
            t = min(t1, t2)
            y = y + t * step
            u, u_p = u - t * r, u_p + t
            if t2 <= t1:
                active.append(p)
                u = np.append(u, u_p)
                break
            del active[k]
            u = np.delete(u, k)
    else:
        return _unscale(y, scale), False
    if active:  # the exact projection onto the final active set: y = y0 + na' lam, na y = b_a
        na = M[active]
        lam = np.linalg.solve(na @ na.T, b[active] - na @ y0)
        y = y0 + na.T @ lam
    return _unscale(y, scale), True


def _unscale(y: np.ndarray, scale: np.ndarray) -> np.ndarray:
    return y / scale


def verified(z: np.ndarray, ok: bool, normal: np.ndarray, rhs: np.ndarray, C: np.ndarray, lo: np.ndarray,
             hi: np.ndarray, tol: float) -> bool:  # fmt: skip
    """Whether ``z = (a, s)`` solves the QP's rows up to its slack (relative to ``1 + |b|``) and its box within
    ``tol`` (m/s^2), with ``s >= -tol``, after the solver reported success (``ok``); otherwise the agent brakes."""
    if not (ok and np.isfinite(z).all()):
        return False
    a, s = z[:3], z[3]
    viol = float((np.maximum(rhs - (normal @ a + s), 0.0) / (1.0 + np.abs(rhs))).max(initial=0.0))
    bv = C @ a
    viol = max(viol, float(np.maximum(lo - bv, bv - hi).max(initial=0.0)))
    return viol <= tol and s >= -tol


def _brake(v: np.ndarray, bounds: dict, gain: float) -> np.ndarray:
    """The fallback of a failed QP: ``-gain v`` scaled into the ball inscribed in the box."""
    a = -gain * v
    inscribed = min(bounds["horizontal"], -bounds["z_min"], bounds["z_max"])
    return a * min(1.0, 0.99 * inscribed / max(float(np.linalg.norm(a)), 1e-12))


def filter_command(state: np.ndarray, a_ref: np.ndarray, nbr_states: np.ndarray, accelerations: np.ndarray | None,
                   centers: np.ndarray, radii: np.ndarray, settings: dict) -> tuple[np.ndarray, dict]:  # fmt: skip
    """The ``dcbf`` filter of one agent: the safe acceleration closest to ``a_ref``.

    Args:
        state: ``(18,)`` the agent's state (float64). a_ref: ``(3,)`` the policy's acceleration (m/s^2, world).
        nbr_states: ``(K, 18)`` its neighbours' broadcast states (finite).
        accelerations: ``(1 + K, 3)`` the agent's and its neighbours' realized accelerations of the last step
            (m/s^2), or ``None`` (zero).
        centers, radii: ``(O, 3)``, ``(O,)`` the sphere obstacles it senses.
        settings: ``controller.json``'s ``filter`` entry.

    Returns:
        ``a_safe`` ``(3,)`` (m/s^2) and ``{"failed", "slack", "num_rows"}``.
    """
    x = np.concatenate((state[None], nbr_states))
    p, v = x[:, 0:3], x[:, 12:15]
    t = settings["lookahead"]
    if t:
        acc = np.zeros_like(v) if accelerations is None else accelerations
        p = p + t * v + 0.5 * t**2 * acc
        v = v + t * acc
    normal, rhs = agent_rows(p[0], v[0], p[1:], v[1:], centers, radii, settings)
    bounds = settings["bounds"]
    C, lo, hi = bound_rows(state[3:12], bounds)
    pen = settings["penalty"]
    z, ok = solve_qp(a_ref, normal, rhs, C, lo, hi, pen["w1"], pen["w2"])
    if verified(z, ok, normal, rhs, C, lo, hi, settings["slack_tol"]):
        return z[:3], {"failed": False, "slack": float(z[3]), "num_rows": int(rhs.shape[0])}
    return _brake(v[0], bounds, settings["brake_gain"]), {"failed": True, "slack": 0.0, "num_rows": int(rhs.shape[0])}


# ------------------------------------------------------------------------------------------ the attitude loop
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array((a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]))


def track_acceleration(state: np.ndarray, accel: np.ndarray, robot: dict) -> np.ndarray:
    """The attitude loop (Lee et al. 2010, set-point form): body control ``u = (tau, F3)`` ``(4,)`` tracking the
    world acceleration ``accel`` ``(3,)`` (m/s^2, hover is 0) from ``state`` ``(18,)``, clipped to the actuators.

    Desired specific force ``accel + g e3`` with ``F_z >= min_lift g`` and tilt ``<= max_tilt``; desired attitude
    from it and the held heading; ``tau = -K_R e_R - K_w w + w x J w``, ``F3 = m F . R e3``. ``robot``:
    ``controller.json``'s ``robot`` entry (``params``, ``gains``)."""
    prm, gains = robot["params"], robot["gains"]
    R, w = state[3:12].reshape(3, 3), state[15:18]
    g = prm["gravity"]
    J = np.asarray(prm["inertia"], dtype=np.float64)
    fz = max(accel[2] + g, gains["min_lift"] * g)
    fh = accel[:2]
    lim = fz * math.tan(gains["max_tilt"])
    fh = fh * (lim / max(math.sqrt(fh[0] * fh[0] + fh[1] * fh[1]), lim))
    force = np.array((fh[0], fh[1], fz))
    b3d = force / math.sqrt(force @ force)
    ax, ay = R[0, 0], R[1, 0]
    hx, hy = (ax, ay) if ax * ax + ay * ay > _HEADING_EPS2 else (R[1, 1], -R[0, 1])
    hn = max(math.sqrt(hx * hx + hy * hy), 1e-12)
    b1c = np.array((hx / hn, hy / hn, 0.0))
    b2d = _cross(b3d, b1c)
    b2d = b2d / max(math.sqrt(b2d @ b2d), 1e-12)
    b1d = _cross(b2d, b3d)
    rt_rd = R.T @ np.stack((b1d, b2d, b3d), axis=-1)
    m = rt_rd.T - rt_rd
    e_r = 0.5 * np.array((m[2, 1], m[0, 2], m[1, 0]))
    KR, Kw = np.asarray(gains["kR"]) * J, np.asarray(gains["kw"]) * J
    tau = -KR * e_r - Kw * w + _cross(w, J * w)
    thrust = prm["mass"] * float(force @ R[:, 2])
    tmax = np.asarray(prm["max_torque"], dtype=np.float64)
    return np.concatenate((np.clip(tau, -tmax, tmax), [min(max(thrust, 0.0), prm["max_thrust"])]))


# ---------------------------------------------------------------------------------------------- the controller
def _array(name: str, a, shape: tuple) -> np.ndarray:
    """``a`` as a float64 array of ``shape`` (``None`` entries: any size), or a ``ValueError`` naming it."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers, got {type(a).__name__}") from None
    if arr.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, arr.shape)):
        want = "(" + ", ".join("K" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _mask(name: str, mask, rows: int) -> np.ndarray:
    if mask is None:
        return np.ones(rows, dtype=bool)
    m = np.asarray(mask)
    if m.shape != (rows,) or m.dtype != bool:
        raise ValueError(f"{name} must be a bool array of shape ({rows},) (one entry per row), got {m.dtype} {m.shape}")
    return m


class Controller:
    """One agent's exported filtered controller (module doc): :meth:`load` it from its directory, call :meth:`step`
    once per control period.

    Attributes:
        settings: ``controller.json`` (the filter's settings, the robot's constants, the policy's layout).
        max_neighbours, max_hits: the policy's neighbour and LiDAR rows (the nearest are used beyond them).
        dtype: the dtype of the returned arrays (the filter and attitude loop compute in float64, the policy in
            float32).
    """

    def __init__(self, settings: dict, session, dtype=np.float64):
        self.settings, self.session = settings, session
        self.dtype = np.dtype(dtype)
        lay = settings["policy"]
        self.max_neighbours, self.max_hits = int(lay["max_neighbours"]), int(lay["max_hits"])
        self.comm_radius, self.lidar_range = float(lay["comm_radius"]), float(lay["lidar_range"])
        self.command_unit = float(lay["command_unit"])
        self._warned = False

    @classmethod
    def load(cls, directory, dtype=np.float64, threads: int = 1) -> Controller:
        """The controller exported to ``directory``.

        Args:
            directory: what ``egcbf export --controller`` wrote (``controller.json``, ``policy.onnx``).
            dtype: ``np.float64`` (default) or ``np.float32``, the dtype of :meth:`step`'s outputs.
            threads: onnxruntime's intra-op threads for the policy (1: one core).

        Raises:
            ExportError: ``directory`` is not such an export, or of a format this runtime does not read.
        """
        d = Path(directory)
        if not d.is_dir():
            raise ExportError(f"{d} is not a directory (an exported controller is a directory)")
        path = d / SETTINGS_FILE
        if not path.is_file() or not (d / POLICY_FILE).is_file():
            raise ExportError(f"{d} is not an exported controller: it lacks {SETTINGS_FILE} or {POLICY_FILE} "
                              "(write one with egcbf export --controller METHOD:dcbf)")  # fmt: skip
        try:
            settings = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ExportError(f"{path} cannot be read: {err}") from None
        if not isinstance(settings, dict) or settings.get("format") != FORMAT:
            got = settings.get("format") if isinstance(settings, dict) else None
            raise ExportError(f"{path}: format {got!r}, this runtime reads {FORMAT!r}")
        if np.dtype(dtype) not in (np.float64, np.float32):
            raise ValueError(f"dtype must be float64 or float32, got {dtype!r}")
        import onnxruntime

        opts = onnxruntime.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = int(threads)
        session = onnxruntime.InferenceSession(str(d / POLICY_FILE), opts, providers=["CPUExecutionProvider"])
        return cls(settings, session, dtype)

    # ------------------------------------------------------------------------------------------------ checks
    def _own(self, state, goal) -> tuple[np.ndarray, np.ndarray]:
        state, goal = _array("state", state, (STATE_DIM,)), _array("goal", goal, (DIM,))
        for name, a in (("state", state), ("goal", goal)):
            if not np.isfinite(a).all():
                raise ValueError(f"{name} holds NaN or inf")
        R = state[3:12].reshape(3, 3)
        err = max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
        if err > 1e-3:
            raise ValueError(f"state: R (state[3:12], row-major) is not a rotation (orthonormality error {err:.2e} > "
                             "0.001)")  # fmt: skip
        return state, goal

    def policy(self, state, goal, neighbours, neighbour_mask=None, hits=None, hit_mask=None) -> tuple[np.ndarray, dict]:
        """The policy's command alone (``policy.onnx``).

        Args:
            state: ``(18,)`` own state. goal: ``(3,)`` goal position (m).
            neighbours: ``(K, 18)`` neighbours' broadcast states, any ``K >= 0``, any order.
            neighbour_mask: ``(K,)`` bool, the rows that hold a neighbour (``None``: all).
            hits: ``(H, 3)`` LiDAR hit points (m, world), any ``H >= 0`` (``None``: none). hit_mask: as
                ``neighbour_mask``.

        Returns:
            ``command`` ``(3,)`` (float64, the acceleration in units of ``command_unit`` m/s^2, world frame) and the
            counts ``num_neighbours``, ``num_hits`` (rows used), ``dropped_neighbours``, ``dropped_hits`` (in range
            beyond the slots), ``rejected_neighbours``, ``rejected_hits`` (valid rows holding NaN or inf: dropped).
        """
        state, goal = self._own(state, goal)
        nbr, nmask = self._rows("neighbours", neighbours, neighbour_mask, STATE_DIM)
        pts, hmask = self._rows("hits", hits, hit_mask, DIM)
        return self._policy(state, goal, nbr, nmask, pts, hmask)

    def _rows(self, name: str, rows, mask, width: int) -> tuple[np.ndarray, np.ndarray]:
        rows = np.zeros((0, width)) if rows is None else _array(name, rows, (None, width))
        return rows, _mask(f"{name[:-1]}_mask", mask, rows.shape[0])

    def _policy(self, state, goal, nbr, nmask, pts, hmask) -> tuple[np.ndarray, dict]:
        p = state[0:3]
        finite_n, finite_h = np.isfinite(nbr).all(-1), np.isfinite(pts).all(-1)
        counts = {
            "rejected_neighbours": int((nmask & ~finite_n).sum()),
            "rejected_hits": int((hmask & ~finite_h).sum()),
        }
        nbr, pts = nbr[nmask & finite_n], pts[hmask & finite_h]
        d2 = ((nbr[:, 0:3] - p) ** 2).sum(-1)
        order = np.argsort(d2, kind="stable")
        heard = order[d2[order] < self.comm_radius**2]
        hd = np.sqrt(((pts - p) ** 2).sum(-1))
        horder = np.argsort(hd, kind="stable")
        seen = horder[hd[horder] <= self.lidar_range * (1 + 1e-6)]
        near, kept = nbr[heard[: self.max_neighbours]], pts[seen[: self.max_hits]]
        counts["dropped_neighbours"] = int(heard.shape[0] - near.shape[0])
        counts["dropped_hits"] = int(seen.shape[0] - kept.shape[0])
        if (counts["dropped_neighbours"] or counts["dropped_hits"]) and not self._warned:
            import warnings

            self._warned = True
            warnings.warn(f"Controller: {counts['dropped_neighbours']} neighbour(s) and {counts['dropped_hits']} "
                          f"hit(s) in range beyond the max_neighbours = {self.max_neighbours} / max_hits = "
                          f"{self.max_hits} slots were dropped (the nearest are kept; info counts them every call)",
                          stacklevel=3)  # fmt: skip
        k, h = self.max_neighbours, self.max_hits
        feeds = {
            "state": state.astype(np.float32),
            "goal": goal.astype(np.float32),
            "neighbours": np.zeros((k, STATE_DIM), dtype=np.float32),
            "neighbour_valid": np.arange(k) < near.shape[0],
            "hits": np.zeros((h, DIM), dtype=np.float32),
            "hit_valid": np.arange(h) < kept.shape[0],
        }
        feeds["neighbours"][: near.shape[0]] = near
        feeds["hits"][: kept.shape[0]] = kept
        command = self.session.run(["command"], feeds)[0].astype(np.float64)
        counts.update(num_neighbours=int(near.shape[0]), num_hits=int(kept.shape[0]))
        return command, counts

    def filter(self, state, command, neighbours, neighbour_mask=None, accelerations=None,
               obstacles=None) -> tuple[np.ndarray, dict]:  # fmt: skip
        """The ``dcbf`` filter and the attitude loop around a given policy ``command`` (``(3,)``, units of
        ``command_unit``): :meth:`step` without the policy. Arguments and returns as :meth:`step`'s."""
        state = self._own(state, np.zeros(DIM))[0]
        command = _array("command", command, (DIM,))
        if not np.isfinite(command).all():
            raise ValueError("command holds NaN or inf")
        nbr, nmask = self._rows("neighbours", neighbours, neighbour_mask, STATE_DIM)
        return self._filter(state, command, nbr, nmask, accelerations, obstacles)

    def _filter(self, state, command, nbr, nmask, accelerations, obstacles) -> tuple[np.ndarray, dict]:
        keep = nmask & np.isfinite(nbr).all(-1)
        acc = None
        if accelerations is not None:
            acc = _array("accelerations", accelerations, (1 + nbr.shape[0], DIM))
            if not np.isfinite(acc[0]).all():
                raise ValueError("accelerations[0] (the agent's own) holds NaN or inf")
            keep &= np.isfinite(acc[1:]).all(-1)
            acc = np.concatenate((acc[:1], acc[1:][keep]))
        if obstacles is None:
            centers, radii = np.zeros((0, DIM)), np.zeros(0)
        else:
            try:
                c, r = obstacles
            except (TypeError, ValueError):
                raise ValueError("obstacles must be a pair (centers (O, 3), radii (O,))") from None
            centers = _array("obstacles' centers", c, (None, DIM))
            radii = _array("obstacles' radii", r, (centers.shape[0],))
            if not (np.isfinite(centers).all() and np.isfinite(radii).all()):
                raise ValueError("obstacles hold NaN or inf")
        a_ref = self.command_unit * command
        a_safe, info = filter_command(state, a_ref, nbr[keep], acc, centers, radii, self.settings["filter"])
        u = track_acceleration(state, a_safe, self.settings["robot"])
        info.update(command=(a_safe / self.command_unit).astype(self.dtype), a_safe=a_safe.astype(self.dtype),
                    policy_command=command.astype(self.dtype), filter_neighbours=int(keep.sum()))  # fmt: skip
        return u.astype(self.dtype), info

    def step(self, state, goal, neighbours, neighbour_mask=None, hits=None, hit_mask=None, accelerations=None,
             obstacles=None) -> tuple[np.ndarray, dict]:  # fmt: skip
        """One control period: the policy's command, filtered, tracked by the attitude loop.

        Args:
            state: ``(18,)`` own state ``[p, R (row-major, body to world), v, w]`` (world frame, SI units).
            goal: ``(3,)`` its goal position (m).
            neighbours: ``(K, 18)`` the states its neighbours broadcast (any ``K >= 0``); pass every one heard: the
                policy reads those within ``comm_radius`` (the nearest ``max_neighbours``), the filter every one
                within its ``cull_radius`` at the look-ahead positions.
            neighbour_mask: ``(K,)`` bool, the rows that hold a neighbour (``None``: all).
            hits: ``(H, 3)`` its LiDAR hit points (m, world), read by the policy only (within ``lidar_range``, the
                nearest ``max_hits``). hit_mask: as ``neighbour_mask``.
            accelerations: ``(1 + K, 3)`` the agent's own and each neighbour row's realized acceleration of the last
                step, ``(v_t - v_{t-1}) / dt`` (m/s^2, world), or ``None`` (zero, as at an episode's first step).
            obstacles: ``(centers (O, 3), radii (O,))`` the sphere obstacles it senses (m), or ``None``.

        Returns:
            ``u`` ``(4,)``: body torque (N m, body frame) and thrust (N); and ``info``: ``command`` (the filtered
            acceleration in ``command_unit``), ``a_safe`` (m/s^2), ``policy_command``, ``failed`` (the QP failed and
            the agent brakes), ``slack`` (m/s^2), ``num_rows`` (the filter's CBF rows), ``filter_neighbours``, and
            :meth:`policy`'s counts. A valid neighbour or hit row holding NaN or inf is dropped and counted; a
            non-finite ``state``, ``goal`` or own acceleration raises ``ValueError``, as do wrong shapes.
        """
        state, goal = self._own(state, goal)
        nbr, nmask = self._rows("neighbours", neighbours, neighbour_mask, STATE_DIM)
        pts, hmask = self._rows("hits", hits, hit_mask, DIM)
        command, counts = self._policy(state, goal, nbr, nmask, pts, hmask)
        u, info = self._filter(state, command, nbr, nmask, accelerations, obstacles)
        info.update(counts)
        return u, info
