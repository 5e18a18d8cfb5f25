"""Pure functions between ROS 2 messages (:mod:`egcbf.ros.messages`) and what one agent's controller reads and
writes (:mod:`egcbf.deploy.agent`), both ways, float64-exact.

Conventions (REP 103 and REP 105): SI units, right-handed frames, z up; the world frame is the simulator's (its
``frame_id`` is the caller's, ``"world"`` by default); the body frame is x forward, y left, z up (the rotor axis),
the frame :mod:`egcbf.robots.quadrotor.dynamics` writes ``w``, ``tau`` and the thrust in. A quaternion is
``geometry_msgs/Quaternion``'s ``(x, y, z, w)``, Hamilton, the body-to-world rotation ``R`` (``v_world = R
v_body``), returned with ``w >= 0``. Stamps are integer nanoseconds (``builtin_interfaces/Time``'s ``sec * 10^9 +
nanosec``: exact both ways).

====================================  ===============================================================================
message                               egcbf
====================================  ===============================================================================
``nav_msgs/msg/Odometry``             the quadrotor's own state ``[p, R row-major, v, w]`` ``(18,)``
                                      (:func:`state_to_odometry`, :func:`odometry_to_state`): ``pose`` in the
                                      world frame, ``twist`` in the body frame (``child_frame_id``, nav_msgs'
                                      convention), so ``twist.linear = R^T v`` and ``twist.angular = w`` (our ``w``
                                      is already the body rate)
``sensor_msgs/msg/PointCloud2``       LiDAR hits ``(H, 3)`` and their mask ``(H,)`` (:func:`hits_to_cloud`,
                                      :func:`cloud_to_hits`): the valid hits as points with ``x, y, z`` float64 (or
                                      float32) fields, world frame, or body frame turned into the world frame
``egcbf_msgs/msg/AgentState``         a neighbour's broadcast ``(id, stamp, state (S,))``
                                      (:func:`agent_state`, :func:`agent_state_to_state`)
``geometry_msgs/msg/PointStamped``    the goal position ``(3,)`` (:func:`goal_to_point`, :func:`point_to_goal`)
``egcbf_msgs/msg/BodyRateThrust``     the body control ``u = (tau, F3)`` as body rate and thrust
                                      (:func:`body_rate_thrust`, :func:`body_rate_thrust_to_control`)
``crazyflie_interfaces/FullState``    the ``accel`` interface's world acceleration as a full-state set point
                                      (:func:`full_state`, :func:`full_state_setpoint`)
====================================  ===============================================================================

Round trips are exact up to float64 rounding (``1e-12`` is tested) where the message can hold the value: a rotation
goes through a unit quaternion, so an ``R`` that is not orthonormal comes back as the rotation of its quaternion
(the encoder refuses one farther than ``1e-3`` from a rotation, the simulator's own tolerance); a float32 cloud
holds float32 values. Every decoder checks the message's type and layout and refuses NaN or inf with a
``ValueError`` naming the field (:func:`cloud_to_hits` of a cloud that declares itself not dense masks its
non-finite points instead: that is how a LiDAR writes a ray without a return).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..robots.quadrotor.dynamics import DEFAULT_PARAMS, ROT, STATE_DIM, QuadrotorParams, W
from ..robots.quadrotor.dynamics import P as POS
from ..robots.quadrotor.dynamics import V as VEL
from .messages import AGENT_STATE, BODY_RATE_THRUST, FULL_STATE, typestore

__all__ = [
    "WORLD_FRAME",
    "agent_state",
    "agent_state_to_state",
    "body_rate_thrust",
    "body_rate_thrust_to_control",
    "check_type",
    "cloud_field",
    "cloud_to_hits",
    "full_state",
    "full_state_setpoint",
    "goal_to_point",
    "hits_to_cloud",
    "odometry_to_state",
    "point_to_goal",
    "quaternion_to_rotation",
    "rotation_to_quaternion",
    "seconds_to_ns",
    "stamp_ns",
    "state_to_odometry",
    "time_msg",
    "yaw_of",
]

#: the default ``frame_id`` of the world frame
WORLD_FRAME = "world"
ODOMETRY = "nav_msgs/msg/Odometry"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
_NS = 10**9
#: sensor_msgs/PointField datatypes and their numpy types (little-endian; ``is_bigendian`` flips them)
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FLOAT32, _FLOAT64, _UINT32 = 7, 8, 6
#: how far from a rotation an encoded attitude may be (max |R^T R - I|; the simulator's check_state tolerance)
ROTATION_ATOL = 1e-3


# ------------------------------------------------------------------------------------------------- helpers
def _types():
    return typestore().types


def check_type(msg, typename: str) -> None:
    """Raise ``TypeError`` unless ``msg`` is a ``rosbags`` message of type ``typename`` (e.g.
    ``"nav_msgs/msg/Odometry"``)."""
    got = getattr(msg, "__msgtype__", None)
    if got != typename:
        raise TypeError(f"expected a {typename} message, got {got or type(msg).__name__}")


def _array(x, shape: tuple[int, ...], name: str, *, finite: bool = True) -> np.ndarray:
    """``x`` (array-like or tensor) as a float64 array of ``shape`` (``-1``: any size), checked."""
    if hasattr(x, "detach"):  # a torch tensor
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, a.shape, strict=True)):
        want = tuple("any" if s == -1 else s for s in shape)
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if finite and not np.isfinite(a).all():
        raise ValueError(f"{name} holds NaN or inf")
    return a


def _finite(values: Sequence[float], name: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if not np.isfinite(a).all():
        raise ValueError(f"{name} holds NaN or inf")
    return a


def time_msg(ns: int):
    """``builtin_interfaces/msg/Time`` of ``ns`` nanoseconds (``ns >= 0``, an integer)."""
    if isinstance(ns, bool) or not isinstance(ns, (int, np.integer)) or ns < 0:
        raise ValueError(f"a stamp must be an integer number of nanoseconds >= 0, got {ns!r}")
    sec, nanosec = divmod(int(ns), _NS)
    return _types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def stamp_ns(stamp) -> int:
    """The nanoseconds of a ``builtin_interfaces/msg/Time`` (or of a message's ``header.stamp`` when given the
    message or its header)."""
    stamp = getattr(stamp, "header", stamp)
    stamp = getattr(stamp, "stamp", stamp)
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def seconds_to_ns(t: float) -> int:
    """``t`` seconds as integer nanoseconds (rounded to the nearest)."""
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"a time must be finite and >= 0 s, got {t!r}")
    return round(t * _NS)


def _header(ns: int, frame_id: str):
    return _types()["std_msgs/msg/Header"](stamp=time_msg(ns), frame_id=str(frame_id))


def _vector3(v: np.ndarray):
    return _types()["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _xyz(msg, name: str) -> np.ndarray:
    return _finite((msg.x, msg.y, msg.z), name)


# ----------------------------------------------------------------------------------------------- rotations
def rotation_to_quaternion(R) -> np.ndarray:
    """The unit quaternion ``(x, y, z, w)`` (``w >= 0``) of a rotation matrix ``R`` ``(3, 3)``, or ``(n, 4)`` of
    ``(n, 3, 3)`` (Shepperd's method: the largest of the four candidates, so every rotation is exact to
    rounding)."""
    R = np.asarray(R.detach().cpu().numpy() if hasattr(R, "detach") else R, dtype=np.float64)
    one = R.ndim == 2
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise ValueError(f"R must have shape (3, 3) or (n, 3, 3), got {R.shape}")
    if not np.isfinite(R).all():
        raise ValueError("R holds NaN or inf")
    R = R.reshape(-1, 3, 3)
    r = {(i, j): R[:, i, j] for i in range(3) for j in range(3)}
    diag = np.stack((r[0, 0] + r[1, 1] + r[2, 2], r[0, 0], r[1, 1], r[2, 2]), -1)
    k = np.argmax(diag, -1)
    sign = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)[k]
    s = 2.0 * np.sqrt(np.maximum(1.0 + (sign * np.stack((r[0, 0], r[1, 1], r[2, 2]), -1)).sum(-1), 0.0))
    a21, a02, a10 = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]  # the antisymmetric parts
    b01, b02, b12 = r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1]  # the symmetric parts
    quarter = s * s / 4  # the largest component, times s
    candidates = ((a21, a02, a10, quarter), (quarter, b01, b02, a21), (b01, quarter, b12, a02),
                  (b02, b12, quarter, a10))  # fmt: skip
    q = np.select([k[:, None] == j for j in range(4)], [np.stack(c, -1) for c in candidates]) / s[:, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[:, 3:] < 0, -q, q)
    return q[0] if one else q


def quaternion_to_rotation(q, *, atol: float = 1e-6) -> np.ndarray:
    """The rotation matrix ``(3, 3)`` of the quaternion ``q = (x, y, z, w)``, normalized first; a quaternion whose
    norm is farther than ``atol`` from 1 raises ``ValueError`` (not an orientation)."""
    q = _array(q, (4,), "quaternion")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > atol:
        raise ValueError(f"the quaternion {q.tolist()} has norm {n:.6g}, not 1: not an orientation")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rotation_of_state(state: np.ndarray) -> np.ndarray:
    R = state[ROT].reshape(3, 3)
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ROTATION_ATOL or abs(float(np.linalg.det(R)) - 1.0) > ROTATION_ATOL:
        raise ValueError(f"state: R is not a rotation (orthonormality error {err:.2e} > {ROTATION_ATOL:g})")
    return R


def yaw_of(R) -> float:
    """The heading the attitude loop holds, as a yaw angle (rad, about world z from world x): the angle of
    :func:`egcbf.robots.quadrotor.nominal.desired_heading` (the body x axis projected on the horizontal plane;
    near vertical, the body y axis turned by -90 degrees)."""
    R = _array(R, (3, 3), "R")
    ax, ay = R[0, 0], R[1, 0]
    if ax * ax + ay * ay > 1e-6:  # nominal._HEADING_EPS2
        return math.atan2(ay, ax)
    return math.atan2(-R[0, 1], R[1, 1])


# ------------------------------------------------------------------------------------------------ odometry
def state_to_odometry(state, *, stamp: int, frame_id: str = WORLD_FRAME, child_frame_id: str = "base_link"):
    """``nav_msgs/msg/Odometry`` of a quadrotor state.

    Args:
        state: ``(18,)`` ``[p (world, m), R (body-to-world, row-major), v (world, m/s), w (body, rad/s)]``.
        stamp: when the state holds, integer nanoseconds.
        frame_id: the world frame (``header.frame_id``); child_frame_id: the body frame.

    Returns:
        The message: ``pose.pose`` the position and the attitude's quaternion in ``frame_id``, ``twist.twist`` in
        the body frame (``linear = R^T v``, ``angular = w``), covariances zero (unknown). ``ValueError`` if the
        state holds NaN or inf or its ``R`` is farther than ``1e-3`` from a rotation.
    """
    x = _array(state, (STATE_DIM,), "state")
    R = _rotation_of_state(x)
    q = rotation_to_quaternion(R)
    t = _types()
    v_body = R.T @ x[VEL]
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x[0]), y=float(x[1]), z=float(x[2])),
        orientation=t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
    )
    twist = t["geometry_msgs/msg/Twist"](linear=_vector3(v_body), angular=_vector3(x[W]))
    return t[ODOMETRY](
        header=_header(stamp, frame_id),
        child_frame_id=str(child_frame_id),
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def odometry_to_state(msg, *, frame_id: str | None = None, linear_frame: str = "body") -> np.ndarray:
    """The quadrotor state ``(18,)`` float64 of a ``nav_msgs/msg/Odometry`` (the inverse of
    :func:`state_to_odometry`).

    Args:
        msg: the odometry; ``frame_id``: if given, ``header.frame_id`` must be it (the world frame).
        linear_frame: ``"body"`` (nav_msgs' convention: the twist is in ``child_frame_id``, ``v = R
            twist.linear``) or ``"world"`` (for an estimator that publishes the world velocity there).

    Returns:
        ``[p, R row-major, v (world), w (body)]``. ``TypeError`` for another message type, ``ValueError`` for NaN
        or inf, a quaternion that is not of unit norm, or another ``frame_id``.
    """
    check_type(msg, ODOMETRY)
    if linear_frame not in ("body", "world"):
        raise ValueError(f"linear_frame must be 'body' or 'world', got {linear_frame!r}")
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise ValueError(f"odometry in frame {msg.header.frame_id!r}, expected {frame_id!r}")
    pose, twist = msg.pose.pose, msg.twist.twist
    p = _xyz(pose.position, "odometry pose.position")
    o = pose.orientation
    R = quaternion_to_rotation(_finite((o.x, o.y, o.z, o.w), "odometry pose.orientation"))
    v = _xyz(twist.linear, "odometry twist.linear")
    w = _xyz(twist.angular, "odometry twist.angular")
    out = np.empty(STATE_DIM)
    out[POS], out[ROT], out[VEL], out[W] = p, R.reshape(9), R @ v if linear_frame == "body" else v, w
    return out


# ------------------------------------------------------------------------------------------------- clouds
def hits_to_cloud(hits, mask=None, *, stamp: int, frame_id: str = WORLD_FRAME, dtype: str = "float64",
                  agent=None):  # fmt: skip
    """``sensor_msgs/msg/PointCloud2`` of LiDAR hits.

    Args:
        hits: ``(H, 3)`` hit points (m, in ``frame_id``); mask: ``(H,)`` bool, the rows that hold a hit (``None``:
            all). Only those become points, in row order.
        stamp: integer nanoseconds; dtype: ``"float64"`` (exact) or ``"float32"`` (the usual LiDAR driver's; the
            points are rounded to float32).
        agent: ``(H,)`` integers (optional): a ``uint32`` field ``agent`` naming each point's owner (a recording's
            cloud of all agents' hits).

    Returns:
        An unorganized (``height = 1``), dense, little-endian cloud with fields ``x, y, z`` (and ``agent``).
        ``ValueError`` if a valid hit holds NaN or inf or the shapes disagree.
    """
    pts = _array(hits, (-1, 3), "hits", finite=False)
    keep = np.ones(len(pts), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if keep.shape != (len(pts),):
        raise ValueError(f"mask must have shape ({len(pts)},), got {keep.shape}")
    pts = pts[keep]
    if not np.isfinite(pts).all():
        raise ValueError("hits: a valid hit holds NaN or inf")
    if dtype not in ("float64", "float32"):
        raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")
    size, code = (8, _FLOAT64) if dtype == "float64" else (4, _FLOAT32)
    t = _types()
    field = t["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=k * size, datatype=code, count=1) for k, n in enumerate("xyz")]
    names, formats, offsets = ["x", "y", "z"], ["<f8" if size == 8 else "<f4"] * 3, [0, size, 2 * size]
    step = 3 * size
    if agent is not None:
        owner = np.asarray(agent)
        if owner.shape != keep.shape:
            raise ValueError(f"agent must have shape ({len(keep)},), got {owner.shape}")
        fields.append(field(name="agent", offset=step, datatype=_UINT32, count=1))
        names, formats, offsets = [*names, "agent"], [*formats, "<u4"], [*offsets, step]
        step += 4
    rec = np.zeros(len(pts), dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets,
                                             "itemsize": step}))  # fmt: skip
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if agent is not None:
        rec["agent"] = owner[keep]
    return t[POINT_CLOUD](
        header=_header(stamp, frame_id), height=1, width=len(pts), fields=fields, is_bigendian=False,
        point_step=step, row_step=step * len(pts), data=rec.view(np.uint8).reshape(-1).copy(), is_dense=True,
    )  # fmt: skip


def _cloud_records(msg) -> tuple[np.ndarray, dict]:
    """The points of a cloud as a structured array ``(height * width,)`` and its fields ``name -> PointField``."""
    check_type(msg, POINT_CLOUD)
    fields = {f.name: f for f in msg.fields}
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in fields.values():
        if f.datatype not in _FIELD_TYPES or f.count != 1:
            continue
        names.append(f.name)
        formats.append(order + _FIELD_TYPES[f.datatype])
        offsets.append(int(f.offset))
    n, step = int(msg.height) * int(msg.width), int(msg.point_step)
    if any(o + np.dtype(t).itemsize > step for o, t in zip(offsets, formats, strict=True)):
        raise ValueError(f"PointCloud2: a field lies beyond point_step = {step}")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if n and (msg.row_step < msg.width * step or data.size < msg.height * msg.row_step):
        raise ValueError(f"PointCloud2: {data.size} data bytes do not hold {msg.height} rows of {msg.width} points "
                         f"of {step} bytes (row_step {msg.row_step})")  # fmt: skip
    rows = data[: msg.height * msg.row_step].reshape(msg.height, msg.row_step)[:, : msg.width * step]
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    return np.ascontiguousarray(rows).view(dt).reshape(n), fields


def cloud_to_hits(msg, *, size: int | None = None, frame_id: str | None = None,
                  body_pose: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """LiDAR hits ``(H, 3)`` float64 and their mask ``(H,)`` of a ``sensor_msgs/msg/PointCloud2`` (the inverse of
    :func:`hits_to_cloud`).

    Args:
        msg: a cloud with ``x, y, z`` fields of type float32 or float64 (other fields are ignored), any
            ``height``, ``point_step`` and ``row_step``, either byte order.
        size: ``None``: one row per point of the cloud, in its order (a non-finite point of a cloud that is not
            ``is_dense``, a ray without a return, is a zero row with mask ``False``); an integer: the valid points
            first, in the cloud's order, then zero rows up to ``size`` (``ValueError`` if there are more).
        frame_id: if given, ``header.frame_id`` must be it.
        body_pose: ``(p (3,), R (3, 3))``: the cloud is in the body frame of a robot at ``p`` with attitude ``R``,
            and the points are returned in the world frame, ``p + R x``.

    Returns:
        ``hits, mask``. ``TypeError`` for another message type, ``ValueError`` for a missing or non-float
        ``x, y, z`` field, a ``data`` too short for the layout, or NaN in a cloud that declares itself dense.
    """
    rec, fields = _cloud_records(msg)
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise ValueError(f"PointCloud2 in frame {msg.header.frame_id!r}, expected {frame_id!r}")
    for name in "xyz":
        if name not in fields or fields[name].datatype not in (_FLOAT32, _FLOAT64) or fields[name].count != 1:
            have = {f.name: f.datatype for f in msg.fields}
            raise ValueError(f"PointCloud2 needs float32 or float64 fields x, y, z (one each); it has {have}")
    pts = np.stack([rec[n].astype(np.float64) for n in "xyz"], axis=-1).reshape(-1, 3)
    valid = np.isfinite(pts).all(-1)
    if msg.is_dense and not valid.all():
        raise ValueError(f"PointCloud2 declares itself dense but {int((~valid).sum())} point(s) hold NaN or inf")
    pts[~valid] = 0.0
    if body_pose is not None:
        p, R = _array(body_pose[0], (3,), "body_pose p"), _array(body_pose[1], (3, 3), "body_pose R")
        pts = np.where(valid[:, None], p + pts @ R.T, 0.0)
    if size is None:
        return pts, valid
    if int(valid.sum()) > size:
        raise ValueError(f"PointCloud2 holds {int(valid.sum())} hits, more than size = {size}")
    out, mask = np.zeros((size, 3)), np.zeros(size, dtype=bool)
    out[: int(valid.sum())], mask[: int(valid.sum())] = pts[valid], True
    return out, mask


def cloud_field(msg, name: str) -> np.ndarray:
    """The values ``(height * width,)`` of the scalar field ``name`` of a cloud (e.g. a recording's ``agent``)."""
    rec, fields = _cloud_records(msg)
    if name not in fields or name not in rec.dtype.names:
        raise ValueError(f"PointCloud2 has no scalar field {name!r}; it has {sorted(fields)}")
    return rec[name].copy()


# --------------------------------------------------------------------------------------------- broadcasts
def agent_state(agent_id: int, state, *, stamp: int, frame_id: str = WORLD_FRAME):
    """``egcbf_msgs/msg/AgentState`` of agent ``agent_id`` (an integer in ``[0, 2^32)``) with ``state`` ``(S,)``
    (world frame, SI units; the robot's own layout) at ``stamp`` (integer nanoseconds). ``ValueError`` on NaN."""
    if isinstance(agent_id, bool) or not isinstance(agent_id, (int, np.integer)) or not 0 <= agent_id < 2**32:
        raise ValueError(f"agent_id must be an integer in [0, 2^32), got {agent_id!r}")
    x = _array(state, (-1,), "state")
    return _types()[AGENT_STATE](header=_header(stamp, frame_id), id=int(agent_id), state=x.copy())


def agent_state_to_state(msg, *, state_dim: int | None = STATE_DIM,
                         frame_id: str | None = None) -> tuple[int, int, np.ndarray]:  # fmt: skip
    """``(id, stamp (ns), state (S,) float64)`` of an ``egcbf_msgs/msg/AgentState``; ``state_dim``: the length the
    state must have (``None``: any); ``frame_id``: if given, the frame it must be in. ``TypeError`` for another
    message type, ``ValueError`` for NaN, inf, another length or another frame."""
    check_type(msg, AGENT_STATE)
    x = np.array(msg.state, dtype=np.float64)
    if state_dim is not None and x.shape != (state_dim,):
        raise ValueError(f"AgentState of agent {msg.id}: state has {x.size} numbers, expected {state_dim}")
    if not np.isfinite(x).all():
        raise ValueError(f"AgentState of agent {msg.id}: state holds NaN or inf")
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise ValueError(f"AgentState of agent {msg.id} in frame {msg.header.frame_id!r}, expected {frame_id!r}")
    return int(msg.id), stamp_ns(msg), x


def goal_to_point(goal, *, stamp: int, frame_id: str = WORLD_FRAME):
    """``geometry_msgs/msg/PointStamped`` of a goal position ``(3,)`` (world frame, m)."""
    g = _array(goal, (3,), "goal")
    t = _types()
    point = t["geometry_msgs/msg/Point"](x=float(g[0]), y=float(g[1]), z=float(g[2]))
    return t[POINT_STAMPED](header=_header(stamp, frame_id), point=point)


def point_to_goal(msg, *, frame_id: str | None = None) -> np.ndarray:
    """The goal ``(3,)`` float64 of a ``geometry_msgs/msg/PointStamped`` (``frame_id``: the frame it must be in)."""
    check_type(msg, POINT_STAMPED)
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise ValueError(f"goal in frame {msg.header.frame_id!r}, expected {frame_id!r}")
    return _xyz(msg.point, "goal point")


# ------------------------------------------------------------------------------------------------ commands
def body_rate_thrust(u, state, dt: float, params: QuadrotorParams = DEFAULT_PARAMS, *, stamp: int,
                     frame_id: str = "base_link"):  # fmt: skip
    """``egcbf_msgs/msg/BodyRateThrust`` of the body control ``u = (tau, F3)`` at ``state``.

    The plant is driven by torque, a rate controller takes rates: the body rate is the one the torque brings the
    body to at the end of the control period, Euler's equation over one zero-order-hold step ``dt`` from the
    state's rate, ``w_cmd = w + dt J^-1 (tau - w x J w)`` (explicit Euler: the simulator's rate after ``dt`` to
    first order in ``dt``); ``thrust = F3`` (N). A rate loop that reaches ``w_cmd`` within the period applies the
    torque's mean. :func:`body_rate_thrust_to_control` inverts it exactly (to rounding).

    Args:
        u: ``(4,)`` ``[tau (body, N m), F3 (N)]``; state: the quadrotor state ``(18,)`` the control was computed at.
        dt: the control period (s), ``EnvConfig.dt``; params: the quadrotor's inertia.
        stamp: integer nanoseconds; frame_id: the body frame.
    """
    u, x = _array(u, (4,), "u"), _array(state, (STATE_DIM,), "state")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0 s, got {dt!r}")
    J = np.asarray(params.inertia, dtype=np.float64)
    w = x[W]
    rate = w + dt * (u[:3] - np.cross(w, J * w)) / J
    return _types()[BODY_RATE_THRUST](header=_header(stamp, frame_id), body_rate=_vector3(rate), thrust=float(u[3]))


def body_rate_thrust_to_control(msg, state, dt: float, params: QuadrotorParams = DEFAULT_PARAMS) -> np.ndarray:
    """The body control ``u = (tau, F3)`` ``(4,)`` of a body-rate command at ``state`` (the inverse of
    :func:`body_rate_thrust`): ``tau = J (w_cmd - w) / dt + w x J w``."""
    check_type(msg, BODY_RATE_THRUST)
    x = _array(state, (STATE_DIM,), "state")
    rate = _xyz(msg.body_rate, "body_rate")
    thrust = float(_finite((msg.thrust,), "thrust")[0])
    J = np.asarray(params.inertia, dtype=np.float64)
    w = x[W]
    return np.concatenate((J * (rate - w) / dt + np.cross(w, J * w), [thrust]))


def full_state(state, accel, *, stamp: int, frame_id: str = WORLD_FRAME, horizon: float = 0.0):
    """``crazyflie_interfaces/msg/FullState``: the world acceleration command of the ``accel`` interface as a
    full-state set point for an onboard position controller (Crazyswarm2's ``cmd_full_state``).

    The set point is the double integrator the command defines, ``horizon`` seconds ahead of ``state``:
    position ``p + v h + a h^2 / 2``, velocity ``v + a h``, acceleration ``a``. With ``horizon = 0`` (default) the
    position and velocity errors of the onboard controller vanish and it tracks the feed-forward acceleration
    alone, which is what our attitude loop does (:func:`egcbf.robots.quadrotor.nominal.track_acceleration`).
    The orientation is the yaw the attitude loop holds (:func:`yaw_of`, as a quaternion about world z); the body
    rate (``twist.angular``) is zero, the set-point form of our loop (``w_d = 0``).

    Args:
        state: the quadrotor state ``(18,)``; accel: ``(3,)`` world acceleration (m/s^2, gravity excluded: hover is
            0), ``accel_unit * command`` of the ``accel`` interface.
        stamp: integer nanoseconds; frame_id: the world frame; horizon: seconds ``>= 0``.
    """
    x, a = _array(state, (STATE_DIM,), "state"), _array(accel, (3,), "accel")
    if not (math.isfinite(horizon) and horizon >= 0):
        raise ValueError(f"horizon must be finite and >= 0 s, got {horizon!r}")
    h = float(horizon)
    p, v = x[POS] + x[VEL] * h + a * (h * h / 2), x[VEL] + a * h
    yaw = yaw_of(x[ROT].reshape(3, 3))
    t = _types()
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )
    twist = t["geometry_msgs/msg/Twist"](linear=_vector3(v), angular=_vector3(np.zeros(3)))
    return t[FULL_STATE](header=_header(stamp, frame_id), pose=pose, twist=twist, acc=_vector3(a))


def full_state_setpoint(msg) -> dict[str, np.ndarray | float]:
    """``position``, ``velocity``, ``acceleration`` (world, ``(3,)`` each), ``yaw`` (rad) and ``body_rate``
    ``(3,)`` of a ``crazyflie_interfaces/msg/FullState`` (the inverse of :func:`full_state`)."""
    check_type(msg, FULL_STATE)
    o = msg.pose.orientation
    R = quaternion_to_rotation(_finite((o.x, o.y, o.z, o.w), "FullState pose.orientation"))
    return {
        "position": _xyz(msg.pose.position, "FullState pose.position"),
        "velocity": _xyz(msg.twist.linear, "FullState twist.linear"),
        "acceleration": _xyz(msg.acc, "FullState acc"),
        "yaw": math.atan2(R[1, 0], R[0, 0]),
        "body_rate": _xyz(msg.twist.angular, "FullState twist.angular"),
    }
