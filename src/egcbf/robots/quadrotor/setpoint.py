"""A firmware-like setpoint tracker: the Crazyflie's Mellinger controller flying a full-state setpoint.

On a Crazyflie, the acceleration command does not reach the rotors through our attitude loop
(:func:`~.nominal.track_acceleration`): it is sent as a full-state setpoint (position, velocity, acceleration, yaw;
Crazyswarm2's ``cmd_full_state``, see :mod:`egcbf.ros.codecs`) at the control rate, and the firmware's controller
re-evaluates, at its own inner rate, a position/velocity PD on the error to the held setpoint plus the acceleration
feed-forward, then a geometric attitude loop (Mellinger and Kumar, ICRA 2011, as the Crazyflie firmware's
``controller_mellinger.c`` implements it)::

    F_des = m (a_sp + g e3) + K_p (p_sp - p) + K_d (v_sp - v)          (world frame, N)
    z_d = F_des / |F_des|,  x_c = (cos yaw_sp, sin yaw_sp, 0),  y_d = z_d x x_c / |.|,  x_d = y_d x z_d
    e_R = (R_d^T R - R^T R_d)^vee,  R_d = [x_d y_d z_d]         (the firmware's: twice Lee et al.'s e_R)
    tau = clamp(-K_R e_R - K_w w, moment limits),  F3 = F_des . R e3     (tau = 0 where F3 <= 0)

then the actuator box (:func:`~.dynamics.clip_control`). Between two setpoints the rigid body is integrated with
:func:`~.dynamics.step` over inner steps, the control held over each. What the firmware does that is left out here
(the function is pure: no state is carried from one control period to the next): the integral terms of the position
and attitude loops (they compensate battery sag, mass and motor mismatch, none of which the simulator has), the
setpoint's body-rate feed-forward (Crazyswarm2's full-state setpoint carries one; the codec sends zero), and the
derivative of the rate error (``kd_omega_rp``: see :class:`MellingerGains`).

Equivariance under SE(2) x R: ``p_sp`` is a point, ``v_sp`` and ``a_sp`` vectors, ``yaw_sp`` an angle (``yaw +
theta`` under a rotation by ``theta``); ``F_des``, ``x_c`` and the columns of ``R_d`` then rotate with the scene, the
body-frame control is invariant, and the next state is equivariant, as :func:`~.dynamics.step`'s is. The x and y
gains are equal (the firmware's ``_xy`` gains), as the symmetry needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .dynamics import DEFAULT_DT, DEFAULT_METHOD, DEFAULT_PARAMS, QuadrotorParams, clip_control, step, unpack
from .nominal import desired_attitude
from .so3 import orthonormalize, vee

__all__ = [
    "DEFAULT_INNER_RATE",
    "DEFAULT_MELLINGER_GAINS",
    "FIRMWARE_DEFAULTS",
    "MellingerGains",
    "inner_steps",
    "setpoint_control",
    "track_setpoint",
]

#: the firmware's attitude-loop rate (Hz): the Mellinger controller runs at ``ATTITUDE_RATE``, 500 Hz
DEFAULT_INNER_RATE = 500.0

#: the Crazyflie firmware's Mellinger defaults in its own units (``controller_mellinger.c``): position gains in N/m
#: and N s/m, attitude gains in motor-command units per rad and per rad/s, the thrust conversion ``massThrust`` in
#: command units per N, and the moment clamp (command units)
FIRMWARE_DEFAULTS = {
    "kp_xy": 0.4,
    "kd_xy": 0.2,
    "kp_z": 1.25,
    "kd_z": 0.4,
    "kR_xy": 70000.0,
    "kw_xy": 20000.0,
    "kR_z": 60000.0,
    "kw_z": 12000.0,
    "kd_omega_rp": 200.0,
    "massThrust": 132000.0,
    "moment_clamp": 32000.0,
}


def _command_to_torque(params: QuadrotorParams) -> tuple[float, float]:
    """Body torque (N m) per firmware moment-command unit, roll/pitch and yaw, for ``params``' geometry.

    The firmware sends ``massThrust * F`` (N) to each of the four motors as a command, so one command unit is
    ``1 / (4 massThrust)`` N of rotor thrust (linearized about hover). Its legacy mixer adds ``+-roll/2`` (and
    ``+-pitch/2``) to the four motors of the X frame, each at ``arm / sqrt 2`` from the roll (pitch) axis, and
    ``+-yaw`` to each, whose drag torque is ``torque_coefficient`` N m per N of thrust.
    """
    per_unit = 1.0 / (4.0 * FIRMWARE_DEFAULTS["massThrust"])
    roll = 4.0 * 0.5 * per_unit * params.arm_length / math.sqrt(2.0)
    yaw = 4.0 * per_unit * params.torque_coefficient
    return roll, yaw


_FW = FIRMWARE_DEFAULTS
_ROLL, _YAW = _command_to_torque(DEFAULT_PARAMS)


@dataclass(frozen=True)
class MellingerGains:
    """Gains of the setpoint tracker in SI units (module doc); equal x and y gains (the symmetry).

    Attributes:
        kp_xy, kp_z: position gains (N/m), ``K_p = diag(kp_xy, kp_xy, kp_z)``.
        kd_xy, kd_z: velocity gains (N s/m).
        kR_xy, kR_z: attitude gains (N m / rad) of roll/pitch and yaw.
        kw_xy, kw_z: body-rate gains (N m s / rad).
        moment_xy, moment_z: the clamp of the roll/pitch and yaw torques (N m), the firmware's +-32000 commands.
        kd_omega_rp: gain (N m s^2 / rad) of the roll/pitch rate error's derivative, ``-kd (w_k - w_{k-1}) / h``
            over the inner steps of one control period (0 at the first). Default 0: with instantaneous rotor
            thrust (this simulator) its discrete loop multiplies the angular acceleration by ``-kd / J`` each
            inner step, and the firmware's value gives ``kd / J = 1.8 > 1``, a divergence; on the vehicle the
            motors' lag and the gyro's low-pass filter, which the simulator does not model, keep it stable.

    :meth:`from_firmware` converts the firmware's defaults (:data:`FIRMWARE_DEFAULTS`) for a vehicle's geometry;
    the defaults here are that conversion for :data:`~.dynamics.DEFAULT_PARAMS` (the Crazyflie 2.x): position
    gains as the firmware's (already N/m and N s/m), attitude gains ``kR_xy = 8.6e-3 N m/rad`` (``2 kR_xy / J =
    1236 s^-2`` on Lee et al.'s half-size error, where our attitude loop has 544), ``kw_xy = 2.46e-3 N m s/rad``
    (``kw_xy / J = 177 s^-1``, our loop's 46.6: an overdamped loop whose slow pole is near ``2 kR_xy / kw_xy = 7
    rad/s``, where ours is critically damped at 23 rad/s), yaw ``kR_z = 2.73e-3``, ``kw_z = 5.5e-4``. The
    conversion takes the firmware's own linear thrust model (``massThrust``); a rotor's thrust grows about as the
    square of its command, so the local torque per command unit near hover may be up to twice this.
    """

    kp_xy: float = _FW["kp_xy"]
    kd_xy: float = _FW["kd_xy"]
    kp_z: float = _FW["kp_z"]
    kd_z: float = _FW["kd_z"]
    kR_xy: float = _FW["kR_xy"] * _ROLL
    kw_xy: float = _FW["kw_xy"] * _ROLL
    kR_z: float = _FW["kR_z"] * _YAW
    kw_z: float = _FW["kw_z"] * _YAW
    moment_xy: float = _FW["moment_clamp"] * _ROLL
    moment_z: float = _FW["moment_clamp"] * _YAW
    kd_omega_rp: float = 0.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"MellingerGains.{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("moment_xy", "moment_z"):
            if getattr(self, name) <= 0:
                raise ValueError(f"MellingerGains.{name} must be > 0, got {getattr(self, name)!r}")

    @classmethod
    def from_firmware(cls, params: QuadrotorParams = DEFAULT_PARAMS, kd_omega_rp: bool = False) -> MellingerGains:
        """The firmware's defaults (:data:`FIRMWARE_DEFAULTS`) in SI units for a vehicle of ``params``' arm length
        and torque coefficient (:func:`_command_to_torque`); ``kd_omega_rp=True`` keeps the firmware's rate-error
        derivative gain (class doc: it diverges with instantaneous rotor thrust)."""
        f = FIRMWARE_DEFAULTS
        roll, yaw = _command_to_torque(params)
        return cls(
            kp_xy=f["kp_xy"], kd_xy=f["kd_xy"], kp_z=f["kp_z"], kd_z=f["kd_z"],
            kR_xy=f["kR_xy"] * roll, kw_xy=f["kw_xy"] * roll, kR_z=f["kR_z"] * yaw, kw_z=f["kw_z"] * yaw,
            moment_xy=f["moment_clamp"] * roll, moment_z=f["moment_clamp"] * yaw,
            kd_omega_rp=f["kd_omega_rp"] * roll if kd_omega_rp else 0.0,
        )  # fmt: skip

    def to_dict(self) -> dict:
        """The gains by name (SI units), as a run's metadata records them."""
        return dict(vars(self))


DEFAULT_MELLINGER_GAINS = MellingerGains()


def inner_steps(dt: float = DEFAULT_DT, inner_rate: float = DEFAULT_INNER_RATE) -> int:
    """How many inner steps one control period ``dt`` (s) takes at ``inner_rate`` (Hz): ``ceil(dt * inner_rate)``
    (up to 1e-9), so the inner steps are equal and no longer than ``1 / inner_rate``. At the defaults, 25 ms at
    500 Hz is 12.5 periods: 13 inner steps of 1.92 ms (520 Hz); the firmware instead alternates 12 and 13 ticks
    between setpoints arriving at 40 Hz."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt!r}")
    if not (math.isfinite(inner_rate) and inner_rate > 0):
        raise ValueError(f"inner_rate must be finite and > 0 (Hz), got {inner_rate!r}")
    return max(1, math.ceil(dt * inner_rate - 1e-9))


def _gain_vectors(gains: MellingerGains, ref: Tensor) -> tuple[Tensor, ...]:
    kw = {"dtype": ref.dtype, "device": ref.device}
    g = gains
    return (
        torch.tensor((g.kp_xy, g.kp_xy, g.kp_z), **kw),
        torch.tensor((g.kd_xy, g.kd_xy, g.kd_z), **kw),
        torch.tensor((g.kR_xy, g.kR_xy, g.kR_z), **kw),
        torch.tensor((g.kw_xy, g.kw_xy, g.kw_z), **kw),
        torch.tensor((g.moment_xy, g.moment_xy, g.moment_z), **kw),
        torch.tensor((g.kd_omega_rp, g.kd_omega_rp, 0.0), **kw),
    )


def setpoint_control(
    x: Tensor,
    p_sp: Tensor,
    v_sp: Tensor,
    a_sp: Tensor,
    yaw_sp: Tensor,
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: MellingerGains = DEFAULT_MELLINGER_GAINS,
    w_prev: Tensor | None = None,
    h: float | None = None,
    clip: bool = True,
) -> Tensor:
    """One evaluation of the tracker (module doc): the body-frame control ``u = (tau, F3)`` ``(*batch, 4)`` (N m,
    N) at the states ``x`` ``(*batch, 18)`` for the setpoint ``p_sp`` (m), ``v_sp`` (m/s), ``a_sp`` (m/s^2), all
    ``(*batch, 3)`` world frame, and ``yaw_sp`` ``(*batch,)`` (rad, about world z from world x). ``w_prev``: the
    body rates one inner step ``h`` (s) earlier, for the ``kd_omega_rp`` term (``None``: that term is 0). Batch
    dims broadcast; clipped to the actuator box if ``clip``."""
    _, R, v, w = unpack(x)
    p = x[..., 0:3]
    kp, kd, kR, kw, mlim, kdd = _gain_vectors(gains, x)
    force = params.mass * a_sp + kp * (p_sp - p) + kd * (v_sp - v)
    force = torch.cat((force[..., :2], force[..., 2:] + params.mass * params.gravity), dim=-1)
    xc = torch.stack((torch.cos(yaw_sp), torch.sin(yaw_sp), torch.zeros_like(yaw_sp)), dim=-1)
    Rd = desired_attitude(force, xc)
    rt_rd = R.transpose(-1, -2) @ Rd
    e_r = vee(rt_rd.transpose(-1, -2) - rt_rd)  # no 1/2: the firmware's attitude error
    tau = -kR * e_r - kw * w
    if w_prev is not None and gains.kd_omega_rp > 0:
        tau = tau - kdd * (w - w_prev) / h
    tau = torch.maximum(torch.minimum(tau, mlim), -mlim)
    thrust = (force * R[..., :, 2]).sum(-1, keepdim=True)
    tau = torch.where(thrust > 0, tau, torch.zeros_like(tau))
    batch = torch.broadcast_shapes(tau.shape[:-1], thrust.shape[:-1])
    u = torch.cat((tau.expand(*batch, 3), thrust.expand(*batch, 1)), dim=-1)
    return clip_control(u, params) if clip else u


def track_setpoint(
    x: Tensor,
    p_sp: Tensor,
    v_sp: Tensor,
    a_sp: Tensor,
    yaw_sp: Tensor,
    dt: float = DEFAULT_DT,
    inner_rate: float = DEFAULT_INNER_RATE,
    params: QuadrotorParams = DEFAULT_PARAMS,
    gains: MellingerGains = DEFAULT_MELLINGER_GAINS,
    method: str = DEFAULT_METHOD,
    clip: bool = True,
) -> tuple[Tensor, Tensor]:
    """One control period ``dt`` (s) of the rigid body under the tracker holding the setpoint ``(p_sp, v_sp, a_sp,
    yaw_sp)`` (:func:`setpoint_control`'s arguments): :func:`inner_steps` inner steps of ``h = dt / n``, each
    re-evaluating the tracker at the current state and integrating :func:`~.dynamics.step` (one ``method`` step of
    ``h``, the control held) from it; the attitude is re-orthonormalized once, at the end.

    Returns the next states ``(*batch, 18)`` and the mean control over the period ``(*batch, 4)`` (N m, N: what the
    rotors delivered on average, for the metrics that read a control). Pure, batched, on the device and in the
    dtype of ``x``; SE(2) x R equivariant (module doc).
    """
    n = inner_steps(dt, inner_rate)
    h = dt / n
    w_prev = None
    u_sum = None
    for _ in range(n):
        u = setpoint_control(x, p_sp, v_sp, a_sp, yaw_sp, params, gains, w_prev, h, clip)
        w_prev = x[..., 15:18]
        x = step(x, u, h, params, substeps=1, method=method, project=False)
        u_sum = u if u_sum is None else u_sum + u
    p, R, v, w = unpack(x)
    x = torch.cat((p, orthonormalize(R).reshape(*R.shape[:-2], 9), v, w), dim=-1)
    return x, u_sum / n
