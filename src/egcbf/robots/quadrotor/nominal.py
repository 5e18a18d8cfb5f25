"""The equivariant nominal controller: Lee-Leok-McClamroch geometric control on SE(3) for set-point regulation.

Lee, Leok, McClamroch, "Geometric tracking control of a quadrotor UAV on SE(3)", CDC 2010, written z-up::

    e_x = clip(p - p_goal),  e_v = v
    F / m = -k_x e_x - k_v e_v + g e3                  (desired specific force, then limited, see below)
    b3d = F / |F|,  b2d = b3d x b1c / |.|,  b1d = b2d x b3d,  R_d = [b1d b2d b3d]
    e_R = (R_d^T R - R^T R_d)^vee / 2,  e_w = w        (set point: w_d = 0, feed-forward terms vanish)
    tau = J (-k_R e_R - k_w e_w) + w x J w,  F3 = m F . R e3

Equivariance under SE(2) x R (docs/dynamics.md): every world-frame vector above (e_x, e_v, F, b1c, b2d, b3d, the
columns of R and R_d) rotates with ``Rz``; ``g e3`` is fixed by ``Rz``; so ``R_d -> Rz R_d`` and ``R_d^T R``,
``e_R``, ``tau`` and ``F3`` are invariant, as the body-frame control must be. Two choices are needed for that:

- the desired heading ``b1c`` is the current body x axis projected onto the horizontal plane (a fixed world axis
  would break the rotation symmetry); where the body x axis is (nearly) vertical, the body y axis projected and
  turned by -90 degrees is used instead (equal to the former for a level drone, and well defined exactly when the
  former is not), so the output is always finite;
- the gains of x and y must be equal (checked by :class:`NominalGains`).

Two limits keep far goals from asking for the impossible (both commute with the symmetry): the position error is
clipped to norm ``max_position_error`` (GCBF+ clips it to the communication radius), and the desired force is kept
above the horizon: ``F_z >= min_lift g`` (never ask to fly upside down to fall faster than gravity) and tilt
``<= max_tilt``. The output is clipped to the actuator box.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from groupcanon.features import Point
from groupcanon.field_type import FieldType

from .dynamics import (
    DEFAULT_PARAMS,
    GROUP,
    QuadrotorParams,
    _check_last,
    _compiling,
    clip_control,
    consts,
    unpack,
)
from .so3 import vee

__all__ = [
    "DEFAULT_GAINS",
    "DEFAULT_MAX_POSITION_ERROR",
    "GOAL_TYPE",
    "NominalGains",
    "desired_heading",
    "nominal_control",
    "reject_disturbance",
    "track_acceleration",
]

#: Position error clip (m): GCBF+ clips the nominal controller's position error to the CrazyFlie comm radius, 1 m.
DEFAULT_MAX_POSITION_ERROR = 1.0
#: How the symmetry acts on a goal position: a point (rotated and translated).
GOAL_TYPE = FieldType(GROUP, {"goal": Point(3)})

# |horizontal part of body x|^2 below which the fallback heading is used (body x within 0.06 deg of vertical)
_HEADING_EPS2 = 1e-6


@dataclass(frozen=True)
class NominalGains:
    """Gains of the geometric controller, normalized by mass and inertia: ``K_x = m diag(kx)``, ``K_v = m diag(kv)``,
    ``K_R = diag(kR) J``, ``K_w = diag(kw) J``.

    Defaults are the Crazyflie gains used publicly with this controller (K_x = m diag(6.5, 6.5, 15),
    K_v = m diag(4, 4, 9), K_R = 544 J, K_w = 46.64 J): a critically damped attitude loop with natural frequency
    sqrt(544) = 23.3 rad/s. ``kx[0] == kx[1]`` and ``kv[0] == kv[1]`` are required for rotation equivariance.
    ``min_lift`` (fraction of g) and ``max_tilt`` (rad) limit the desired force direction.
    """

    kx: tuple[float, float, float] = (6.5, 6.5, 15.0)
    kv: tuple[float, float, float] = (4.0, 4.0, 9.0)
    kR: tuple[float, float, float] = (544.0, 544.0, 544.0)
    kw: tuple[float, float, float] = (46.64, 46.64, 46.64)
    min_lift: float = 0.3
    max_tilt: float = math.pi / 4

    def __post_init__(self) -> None:
        for name in ("kx", "kv", "kR", "kw"):
            val = tuple(float(v) for v in getattr(self, name))
            if len(val) != 3 or not all(math.isfinite(v) and v >= 0 for v in val):
                raise ValueError(
                    f"NominalGains.{name} must be 3 finite non-negative numbers, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, val)
        for name in ("kx", "kv"):
            val = getattr(self, name)
            if val[0] != val[1]:
                raise ValueError(
                    f"NominalGains.{name} must have equal x and y gains for rotation equivariance, got {val!r}"
                )
        if not 0 < self.min_lift <= 1:
            raise ValueError(f"NominalGains.min_lift must be in (0, 1], got {self.min_lift!r}")
        if not 0 < self.max_tilt < math.pi / 2:
            raise ValueError(f"NominalGains.max_tilt must be in (0, pi/2), got {self.max_tilt!r}")


DEFAULT_GAINS = NominalGains()


class _Gains(NamedTuple):
    kx: Tensor
    kv: Tensor
    KR: Tensor
    Kw: Tensor


def _make_gain_tensors(gains: NominalGains, params: QuadrotorParams, dtype, device) -> _Gains:
    kw = {"dtype": dtype, "device": device}
    j = torch.tensor(params.inertia, **kw)
    return _Gains(
        kx=torch.tensor(gains.kx, **kw),
        kv=torch.tensor(gains.kv, **kw),
        KR=torch.tensor(gains.kR, **kw) * j,
        Kw=torch.tensor(gains.kw, **kw) * j,
    )


@functools.lru_cache(maxsize=128)
def _cached_gain_tensors(gains: NominalGains, params: QuadrotorParams, dtype, device) -> _Gains:
    with torch.inference_mode(False), torch.no_grad():
        return _make_gain_tensors(gains, params, dtype, device)


def _gain_tensors(gains: NominalGains, params: QuadrotorParams, dtype, device) -> _Gains:
    if _compiling():  # see dynamics.quadrotor.consts
        return _make_gain_tensors(gains, params, dtype, device)
    return _cached_gain_tensors(gains, params, dtype, device)


def desired_heading(R: Tensor) -> Tensor:
    """Unit horizontal heading ``(*batch, 3)``: the body x axis ``R e1`` projected on the horizontal plane.

    Equivariant: ``desired_heading(Rz R) = Rz desired_heading(R)``. Where ``R e1`` is within ~0.06 degrees of
    vertical, ``Rz(-90 deg)`` applied to the horizontal part of the body y axis ``R e2`` is used instead (this
    equals the former for a level drone and has unit length when ``R e1`` is vertical), so the result is finite.
    """
    ax, ay = R[..., 0, 0], R[..., 1, 0]
    use = ax * ax + ay * ay > _HEADING_EPS2
    hx = torch.where(use, ax, R[..., 1, 1])
    hy = torch.where(use, ay, -R[..., 0, 1])
    n = torch.sqrt(hx * hx + hy * hy).clamp_min(1e-12)
    return torch.stack((hx / n, hy / n, torch.zeros_like(hx)), dim=-1)


def nominal_acceleration(
    x: Tensor,
    goal: Tensor,
    gains: NominalGains = DEFAULT_GAINS,
    max_position_error: float = DEFAULT_MAX_POSITION_ERROR,
) -> Tensor:
    """Position loop: the desired acceleration ``a = -k_x clip(p - goal) - k_v v`` ``(*batch, 3)``, world frame.

    Gravity is not included (hover is ``a = 0``); the position error is clipped to norm ``max_position_error``.
    Equivariant: ``a`` rotates with the scene (a ``Vector(3)``).
    """
    p, _, v, _ = unpack(x)
    _check_last(goal, 3, "goal")
    if not (math.isfinite(max_position_error) and max_position_error > 0):
        raise ValueError(f"max_position_error must be finite and > 0, got {max_position_error!r}")
    k = _gain_tensors(gains, DEFAULT_PARAMS, x.dtype, x.device)
    ex = p - goal
    n = torch.linalg.vector_norm(ex, dim=-1, keepdim=True)
    ex = ex * (max_position_error / n.clamp_min(max_position_error))
    return -k.kx * ex - k.kv * v


def desired_attitude(force: Tensor, heading: Tensor) -> Tensor:
    """The attitude ``R_d = [b1d b2d b3d]`` ``(*batch, 3, 3)`` that points the rotor axis along the desired force
    ``force`` ``(*batch, 3)`` (world frame, non-zero) and keeps the body x axis as close as it can to the horizontal
    ``heading`` ``(*batch, 3)``: ``b3d = F / |F|``, ``b2d = b3d x heading`` normalized, ``b1d = b2d x b3d`` (Lee et
    al. 2010; the Crazyflie firmware's Mellinger controller builds the same frame)."""
    b3d = force / torch.linalg.vector_norm(force, dim=-1, keepdim=True).clamp_min(1e-12)
    b2d = torch.linalg.cross(b3d, heading.expand_as(b3d), dim=-1)
    b2d = b2d / torch.linalg.vector_norm(b2d, dim=-1, keepdim=True).clamp_min(1e-12)
    b1d = torch.linalg.cross(b2d, b3d, dim=-1)
    return torch.stack((b1d, b2d, b3d), dim=-1)


def track_acceleration(
    x: Tensor,
    accel: Tensor,
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: NominalGains = DEFAULT_GAINS,
    clip: bool = True,
) -> Tensor:
    """Attitude loop: body-frame ``u = (tau, F3)`` ``(*batch, 4)`` tracking the world acceleration ``accel``.

    Desired specific force ``F / m = accel + g e3``, limited to ``F_z >= min_lift g`` and tilt ``<= max_tilt``;
    ``b3d = F / |F|``, heading held (:func:`desired_heading`), ``tau = -K_R e_R - K_w w + w x J w``,
    ``F3 = m F . R e3`` (Lee et al. 2010, set-point form). Clipped to the actuators if ``clip``.
    """
    _, R, _, w = unpack(x)
    c = consts(params, x)
    k = _gain_tensors(gains, params, x.dtype, x.device)
    g = params.gravity
    fz = (accel[..., 2:] + g).clamp_min(gains.min_lift * g)
    fh = accel[..., :2]
    lim = fz * math.tan(gains.max_tilt)
    fh = fh * (lim / torch.linalg.vector_norm(fh, dim=-1, keepdim=True).clamp_min(lim))
    force = torch.cat((fh, fz), dim=-1)

    Rd = desired_attitude(force, desired_heading(R))

    # attitude loop
    rt_rd = R.transpose(-1, -2) @ Rd
    e_r = 0.5 * vee(rt_rd.transpose(-1, -2) - rt_rd)
    tau = -k.KR * e_r - k.Kw * w + torch.linalg.cross(w, c.J * w, dim=-1)
    thrust = params.mass * (force * R[..., :, 2]).sum(-1, keepdim=True)
    batch = torch.broadcast_shapes(tau.shape[:-1], thrust.shape[:-1])
    u = torch.cat((tau.expand(*batch, 3), thrust.expand(*batch, 1)), dim=-1)
    return clip_control(u, params) if clip else u


def nominal_control(
    x: Tensor,
    goal: Tensor,
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: NominalGains = DEFAULT_GAINS,
    max_position_error: float = DEFAULT_MAX_POSITION_ERROR,
    clip: bool = True,
) -> Tensor:
    """Body-frame control ``u = (tau, F3)`` ``(*batch, 4)`` regulating ``x`` ``(*batch, 18)`` to hover at ``goal``
    ``(*batch, 3)`` (batch dims broadcast): :func:`track_acceleration` of :func:`nominal_acceleration`.

    SE(2) x R equivariant: ``nominal_control(phi_g x, g . goal) == nominal_control(x, goal)`` (the output is
    invariant because it is expressed in the body frame). ``clip=False`` returns the unclipped command.
    """
    a = nominal_acceleration(x, goal, gains, max_position_error)
    return track_acceleration(x, a, params, gains, clip)


def reject_disturbance(
    x: Tensor,
    u: Tensor,
    accel: Tensor,
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: NominalGains = DEFAULT_GAINS,
    clip: bool = True,
) -> Tensor:
    """The command ``(*batch, 4)`` that, under a world-frame disturbance acceleration ``accel`` ``(*batch, 3)`` (wind
    force over mass, a thrust error), does what ``u = (tau, F3)`` does in calm air, to first order in ``accel``.

    The thrust vector ``F3 b3`` becomes ``F3 b3 - m accel``: the collective thrust takes its component along the
    body axis ``b3 = R e3``, ``F3 - m accel . b3``, and the torque gets the attitude loop's pull toward the new
    direction, ``J k_R R^T (b3 x f) / |f|`` with ``f = F3 b3 / m - accel`` (the term :func:`track_acceleration`
    adds when its target acceleration drops by ``accel``). For ``u = track_acceleration(x, a)`` at the attitude that
    command asks for, away from its ``min_lift`` and ``max_tilt`` limits and before clipping, the thrust is
    ``track_acceleration(x, a - accel)``'s exactly and the tilt torques up to ``O(|accel|^2)``; the yaw torque keeps
    the command's (the heading hold's first-order answer to the tilt is left out). So for a command from this
    attitude loop (the ``accel`` interface, the nominal controller, the QPs), the attitude settles in steady wind
    where the thrust cancels it. ``accel == 0`` returns ``u`` exactly.

    Equivariant under SE(2) x R: ``accel`` is a world vector, the output body-frame and invariant.
    """
    _check_last(u, 4, "u")
    _, R, _, _ = unpack(x)
    k = _gain_tensors(gains, params, x.dtype, x.device)
    b3 = R[..., :, 2]
    thrust = u[..., 3:]
    f = thrust / params.mass * b3 - accel
    # b3 x f = -(b3 x accel): written so that accel == 0 gives exactly zero (also at zero thrust, f = 0)
    size = torch.linalg.vector_norm(f, dim=-1, keepdim=True).clamp_min(1e-6)
    turn = -torch.linalg.cross(b3, accel.expand_as(b3), dim=-1) / size
    tau = u[..., :3] + k.KR * (R.transpose(-1, -2) @ turn.unsqueeze(-1)).squeeze(-1)
    lift = thrust - params.mass * (accel * b3).sum(-1, keepdim=True)
    out = torch.cat((tau, lift), dim=-1)
    return clip_control(out, params) if clip else out
