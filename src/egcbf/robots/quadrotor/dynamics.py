"""Rigid-body quadrotor dynamics (the paper's model), its integrator, and how the symmetry group acts on it.

State ``x`` ``(*batch, 18)`` and control ``u`` ``(*batch, 4)``::

    x = [p (3, world), R (9, body-to-world rotation, row-major), v (3, world), w (3, body)]
    u = [tau (3, body-frame torque), F3 (1, collective thrust along the body z axis)]

Equations of motion (z up, gravity ``g = 9.81`` along ``-z``)::

    p' = v
    R' = R [w]x                      (w is the body-frame angular velocity)
    v' = -g e3 + (F3 / m) R e3
    w' = J^-1 (tau - w x J w)

They are control affine: ``x' = f0(x) + f1(x) u``. The symmetry is SE(2) x R (rotations about world z and all
translations), acting by ``p -> Rz p + t``, ``R -> Rz R``, ``v -> Rz v``, ``w -> w`` on the state and trivially on
the body-frame control; see ``docs/dynamics.md`` for the derivation and for how the defaults below were measured.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from groupcanon.features import Point, Rotation, Scalar, Vector
from groupcanon.field_type import FieldType
from groupcanon.groups import SE2xR

from .so3 import dexpinv, exp_apply, hat, orthonormality_error, orthonormalize, rmul_exp

__all__ = [
    "CONTROL_DIM",
    "CONTROL_TYPE",
    "DEFAULT_DT",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_METHOD",
    "DEFAULT_PARAMS",
    "DEFAULT_SUBSTEPS",
    "GROUP",
    "ROT",
    "STATE_DIM",
    "STATE_TANGENT_TYPE",
    "STATE_TYPE",
    "TAU",
    "THRUST",
    "P",
    "QuadrotorParams",
    "V",
    "W",
    "check_control",
    "check_state",
    "clip_control",
    "f0",
    "f1",
    "hover_control",
    "hover_state",
    "state_from_parts",
    "step",
    "unpack",
    "xdot",
]

STATE_DIM = 18
CONTROL_DIM = 4
P, ROT, V, W = slice(0, 3), slice(3, 12), slice(12, 15), slice(15, 18)
TAU, THRUST = slice(0, 3), slice(3, 4)

#: Control period (zero-order hold) in seconds, chosen by measurement (docs/dynamics.md, "Control rate").
DEFAULT_DT = 0.025
#: Integrator sub-steps per control period, chosen by measurement (docs/dynamics.md).
DEFAULT_SUBSTEPS = 2
#: Integrator: "rk4" (Runge-Kutta-Munthe-Kaas, order 4, on SO(3)) or "euler" (semi-implicit Lie-Euler, order 1).
DEFAULT_METHOD = "rk4"
#: Episode length in steps of DEFAULT_DT that lets the nominal controller reach any goal in [0, 4]^3 from rest
#: (measured time-to-reach distribution in docs/dynamics.md, "Episode length").
DEFAULT_MAX_STEPS = 256

# ----------------------------------------------------------------------------------------------------- symmetry
#: The symmetry group of the swarm under gravity (the paper's G-bar): element ``(cos, sin, tx, ty, tz)``.
GROUP = SE2xR()
#: How ``g = (Rz, t)`` acts on a state: ``p -> Rz p + t``, ``R -> Rz R``, ``v -> Rz v``, ``w -> w``.
STATE_TYPE = FieldType(GROUP, {"p": Point(3), "R": Rotation(), "v": Vector(3), "w": Scalar(3)})
#: How the differential ``dphi_g`` acts on a state derivative ``x'`` (or any tangent vector, e.g. a gradient
#: direction): the same as :data:`STATE_TYPE` without the translation (``p' -> Rz p'``).
STATE_TANGENT_TYPE = FieldType(GROUP, {"p": Vector(3), "R": Rotation(), "v": Vector(3), "w": Scalar(3)})
#: Body-frame torque and thrust are invariant (the paper's ``psi_g(u) = (g tau, F3)`` is the identity here).
CONTROL_TYPE = FieldType(GROUP, {"tau": Scalar(3), "thrust": Scalar(1)})


# --------------------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters of one quadrotor; defaults are a Crazyflie 2.x (SI units).

    Sources:
      - mass and inertia: GCBF+'s CrazyFlie environment (Zhang et al., T-RO 2025, MIT-REALM/gcbfplus),
        ``m = 0.0299 kg``, ``J = diag(1.395e-5, 1.395e-5, 2.173e-5) kg m^2``; within a few percent of
        J. Förster, "System identification of the Crazyflie 2.0 nano quadrocopter", BSc thesis, ETH Zurich 2015
        (``m = 0.027 - 0.030``, ``Ixx = Iyy = 1.4e-5``, ``Izz = 2.17e-5``).
      - ``max_thrust = 0.59 N``: about 60 g of total static thrust (Förster 2015; Bitcraze's "PWM to thrust"
        measurements), a thrust-to-weight ratio of about 2.
      - ``arm_length = 0.046 m`` (centre to motor, 92 mm motor-to-motor diagonal) and
        ``torque_coefficient = 0.006 m`` (yaw drag torque per newton of rotor thrust, Förster 2015: 0.005964).
      - ``max_torque``: a per-axis box derived from the above for the X configuration, with each rotor in
        ``[0, max_thrust / 4]``: roll/pitch ``2 (max_thrust/4) arm/sqrt 2 = 9.6e-3 N m``, yaw
        ``2 (max_thrust/4) torque_coefficient = 1.77e-3 N m``. The box ignores the coupling with thrust (full
        torque needs two rotors off), as is usual for control-level models.
      - ``radius = 0.05 m``: the collision radius of an agent (GCBF+ convention).
    """

    mass: float = 0.0299
    inertia: tuple[float, float, float] = (1.395e-5, 1.395e-5, 2.173e-5)
    gravity: float = 9.81
    max_thrust: float = 0.59
    max_torque: tuple[float, float, float] = (9.6e-3, 9.6e-3, 1.77e-3)
    arm_length: float = 0.046
    torque_coefficient: float = 0.006
    radius: float = 0.05

    def __post_init__(self) -> None:
        def positive(name, value, n=None):
            vals = (value,) if n is None else tuple(value)
            if n is not None and len(vals) != n:
                raise ValueError(f"QuadrotorParams.{name} must have {n} entries, got {value!r}")
            if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in vals):
                raise ValueError(f"QuadrotorParams.{name} must be finite and > 0, got {value!r}")

        positive("mass", self.mass)
        positive("inertia", self.inertia, 3)
        positive("gravity", self.gravity)
        positive("max_thrust", self.max_thrust)
        positive("max_torque", self.max_torque, 3)
        positive("arm_length", self.arm_length)
        positive("torque_coefficient", self.torque_coefficient)
        positive("radius", self.radius)
        object.__setattr__(self, "inertia", tuple(float(v) for v in self.inertia))
        object.__setattr__(self, "max_torque", tuple(float(v) for v in self.max_torque))

    @property
    def hover_thrust(self) -> float:
        """Thrust that balances gravity, ``m g`` (N)."""
        return self.mass * self.gravity


DEFAULT_PARAMS = QuadrotorParams()


class Consts(NamedTuple):
    """Constant tensors of a :class:`QuadrotorParams` in one dtype and device."""

    J: Tensor  # diagonal inertia (3,)
    Jinv: Tensor  # its inverse (3,)
    gvec: Tensor  # gravity acceleration (0, 0, -g)
    tau_max: Tensor  # torque bounds (3,)
    e3: Tensor  # (0, 0, 1)


def _make_consts(params: QuadrotorParams, dtype: torch.dtype, device: torch.device) -> Consts:
    kw = {"dtype": dtype, "device": device}
    j = torch.tensor(params.inertia, **kw)
    return Consts(
        J=j,
        Jinv=1.0 / j,
        gvec=torch.tensor((0.0, 0.0, -params.gravity), **kw),
        tau_max=torch.tensor(params.max_torque, **kw),
        e3=torch.tensor((0.0, 0.0, 1.0), **kw),
    )


@functools.lru_cache(maxsize=128)
def _cached_consts(params: QuadrotorParams, dtype: torch.dtype, device: torch.device) -> Consts:
    with torch.inference_mode(False), torch.no_grad():  # usable later by autograd even if first seen in inference
        return _make_consts(params, dtype, device)


def _compiling() -> bool:
    fn = getattr(getattr(torch, "compiler", None), "is_compiling", None)
    return bool(fn()) if fn is not None else False


def consts(params: QuadrotorParams, ref: Tensor) -> Consts:
    """Constant tensors ``J, Jinv, gvec, tau_max, e3`` in ``ref``'s dtype and device.

    Cached per (params, dtype, device) in eager mode (no host-to-device copy per call); built inline while
    ``torch.compile`` traces (the cache would break the graph; the compiler folds the constants).
    """
    if _compiling():
        return _make_consts(params, ref.dtype, ref.device)
    return _cached_consts(params, ref.dtype, ref.device)


# ----------------------------------------------------------------------------------------------- input checks
def _check_last(t: Tensor, n: int, what: str) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{what} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() == 0 or t.shape[-1] != n:
        raise ValueError(f"{what} has shape {tuple(t.shape)}, expected (*batch, {n})")
    if not t.is_floating_point():
        raise TypeError(f"{what} must be a floating-point tensor, got {t.dtype}")


def check_control(u: Tensor) -> None:
    """Raise a clear error if ``u`` is not a floating tensor ``(*batch, 4)`` (shape only: no host sync)."""
    _check_last(u, CONTROL_DIM, "control u")


def check_state(x: Tensor, atol: float = 1e-3) -> None:
    """Raise ``ValueError`` naming the first agent whose state is non-finite or whose R is not a rotation.

    ``x`` is ``(*batch, 18)``, e.g. ``(num_envs, num_agents, 18)``; the message gives the agent's batch index
    (``(env, agent)`` for that layout) and how many agents are bad. ``R`` must satisfy
    ``max |R^T R - I| <= atol`` and ``|det R - 1| <= atol``. This check reads one boolean back to the host (a
    synchronization): call it at episode boundaries or every few steps, not inside differentiated code.
    """
    _check_last(x, STATE_DIM, "state x")
    finite = torch.isfinite(x).all(-1)
    r = x[..., ROT].reshape(*x.shape[:-1], 3, 3)
    orth = orthonormality_error(torch.where(finite[..., None, None], r, torch.eye(3, dtype=x.dtype, device=x.device)))
    bad = ~finite | (orth > atol)
    if not bool(bad.any()):
        return
    idx = tuple(int(i) for i in torch.nonzero(bad)[0].tolist())
    n_bad = int(bad.sum())
    row = x[idx] if idx else x
    if not bool(finite[idx]):
        fields = [
            name for name, s in (("p", P), ("R", ROT), ("v", V), ("w", W)) if not bool(torch.isfinite(row[s]).all())
        ]
        why = f"non-finite values in {', '.join(fields)}"
    else:
        why = f"R is not a rotation (orthonormality error {float(orth[idx]):.2e} > {atol:g})"
    raise ValueError(
        f"invalid quadrotor state for agent at batch index {idx} of batch shape {tuple(x.shape[:-1])}: {why}"
        f" ({n_bad} invalid agent{'s' if n_bad != 1 else ''} in total)"
    )


# ------------------------------------------------------------------------------------------------ state parts
def unpack(x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(p, R, v, w)`` with ``R`` ``(*batch, 3, 3)`` (views into ``x``)."""
    _check_last(x, STATE_DIM, "state x")
    return x[..., P], x[..., ROT].reshape(*x.shape[:-1], 3, 3), x[..., V], x[..., W]


def state_from_parts(p: Tensor, R: Tensor, v: Tensor, w: Tensor) -> Tensor:
    """Inverse of :func:`unpack`; ``R`` may be ``(*batch, 3, 3)`` or flattened ``(*batch, 9)``. Batch dims broadcast."""
    r = R.reshape(*R.shape[:-2], 9) if R.dim() >= 2 and R.shape[-2:] == (3, 3) else R
    _check_last(p, 3, "position p")
    _check_last(r, 9, "rotation R (flattened)")
    _check_last(v, 3, "velocity v")
    _check_last(w, 3, "angular velocity w")
    batch = torch.broadcast_shapes(p.shape[:-1], r.shape[:-1], v.shape[:-1], w.shape[:-1])
    return torch.cat([t.expand(*batch, t.shape[-1]) for t in (p, r, v, w)], dim=-1)


def hover_state(p: Tensor, yaw: Tensor | None = None) -> Tensor:
    """A drone at rest at ``p`` ``(*batch, 3)``, level, with heading ``yaw`` ``(*batch,)`` (default 0)."""
    from .so3 import yaw_rotation

    if yaw is None:
        yaw = torch.zeros(p.shape[:-1], dtype=p.dtype, device=p.device)
    z = torch.zeros_like(p)
    return state_from_parts(p, yaw_rotation(yaw), z, z)


def hover_control(
    params: QuadrotorParams = DEFAULT_PARAMS, *batch: int, dtype: torch.dtype | None = None, device=None
) -> Tensor:
    """The control that keeps a level drone at rest: ``tau = 0``, ``F3 = m g``; shape ``(*batch, 4)``."""
    u = torch.zeros(*batch, CONTROL_DIM, dtype=dtype, device=device)
    u[..., 3] = params.hover_thrust
    return u


def clip_control(u: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """Enforce the actuator box: ``F3`` in ``[0, max_thrust]``, ``|tau_k| <= max_torque_k`` (body frame)."""
    check_control(u)
    tmax = consts(params, u).tau_max
    tau = torch.maximum(torch.minimum(u[..., TAU], tmax), -tmax)
    f = u[..., THRUST].clamp(0.0, params.max_thrust)
    return torch.cat((tau, f), dim=-1)


# ------------------------------------------------------------------------------------------------- vector field
def f0(x: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """Drift ``(*batch, 18)``: ``(v, R [w]x, -g e3, -J^-1 (w x J w))``."""
    _, r, v, w = unpack(x)
    c = consts(params, x)
    rdot = (r @ hat(w)).reshape(*x.shape[:-1], 9)
    vdot = c.gvec.expand_as(v)
    wdot = -c.Jinv * torch.linalg.cross(w, c.J * w, dim=-1)
    return torch.cat((v, rdot, vdot, wdot), dim=-1)


def f1(x: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """Input matrix ``(*batch, 18, 4)``: torque enters ``w'`` through ``J^-1``, thrust ``v'`` along ``R e3 / m``."""
    _check_last(x, STATE_DIM, "state x")
    c = consts(params, x)
    batch = x.shape[:-1]
    zeros = x.new_zeros(*batch, 12, 4)
    b3 = x[..., ROT].reshape(*batch, 3, 3)[..., :, 2:3] / params.mass  # (*batch, 3, 1)
    v_rows = torch.cat((x.new_zeros(*batch, 3, 3), b3), dim=-1)
    w_rows = torch.cat((torch.diag(c.Jinv).expand(*batch, 3, 3), x.new_zeros(*batch, 3, 1)), dim=-1)
    return torch.cat((zeros, v_rows, w_rows), dim=-2)


def _wdot(w: Tensor, tau: Tensor, c: Consts) -> Tensor:
    return c.Jinv * (tau - torch.linalg.cross(w, c.J * w, dim=-1))


def xdot(x: Tensor, u: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """The vector field ``f(x, u) = f0(x) + f1(x) u`` ``(*batch, 18)`` (computed directly; batch dims broadcast)."""
    _, r, v, w = unpack(x)
    check_control(u)
    c = consts(params, x)
    batch = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    rdot = (r @ hat(w)).reshape(*x.shape[:-1], 9)
    vdot = c.gvec + r[..., :, 2] * (u[..., THRUST] / params.mass)
    wdot = _wdot(w, u[..., TAU], c)
    return torch.cat([t.expand(*batch, t.shape[-1]) for t in (v, rdot, vdot, wdot)], dim=-1)


# --------------------------------------------------------------------------------------------------- integrator
def _substep_rk4(p, r, v, w, jtau, fm, h, c):
    """One Runge-Kutta-Munthe-Kaas 4 step: classical RK4 on (p, v, phi, w) with R = R0 exp([phi]x), phi(0) = 0.

    Only the body z axis of the stage attitudes is needed (for the thrust direction), so the stages apply
    ``exp`` to ``e3`` instead of forming matrices; ``R`` itself is updated once, at the end. ``(v, phi, w)`` are
    packed in one tensor so each Runge-Kutta combination is one operation.
    """
    e3 = c.e3.expand_as(v)

    def wdot(ww):
        return jtau - c.Jinv * torch.linalg.cross(ww, c.J * ww, dim=-1)

    def deriv(z):  # z = (v, phi, w) -> (v', phi', w')
        phi, ww = z[..., 3:6], z[..., 6:9]
        b3 = (r * exp_apply(phi, e3).unsqueeze(-2)).sum(-1)  # R0 exp([phi]x) e3
        return torch.cat((c.gvec + b3 * fm, dexpinv(phi, ww), wdot(ww)), dim=-1)

    hh = 0.5 * h
    z0 = torch.cat((v, torch.zeros_like(w), w), dim=-1)
    k1 = torch.cat((c.gvec + r[..., :, 2] * fm, w, wdot(w)), dim=-1)  # at phi = 0: R = R0, dexpinv(0, w) = w
    z2 = z0 + hh * k1
    k2 = deriv(z2)
    z3 = z0 + hh * k2
    k3 = deriv(z3)
    z4 = z0 + h * k3
    k4 = deriv(z4)
    s = h / 6
    z1 = z0 + s * (k1 + 2 * (k2 + k3) + k4)
    p1 = p + s * (v + 2 * (z2[..., 0:3] + z3[..., 0:3]) + z4[..., 0:3])
    return p1, rmul_exp(r, z1[..., 3:6]), z1[..., 0:3], z1[..., 6:9]


def _substep_euler(p, r, v, w, jtau, fm, h, c):
    """Semi-implicit Lie-Euler: w first, then R by the exponential map, then v with the new R, then p with the new v."""
    w1 = w + h * (jtau - c.Jinv * torch.linalg.cross(w, c.J * w, dim=-1))
    r1 = rmul_exp(r, h * w1)
    v1 = v + h * (c.gvec + r1[..., :, 2] * fm)
    return p + h * v1, r1, v1, w1


_METHODS = {"rk4": _substep_rk4, "euler": _substep_euler}


def step(
    x: Tensor,
    u: Tensor,
    dt: float = DEFAULT_DT,
    params: QuadrotorParams = DEFAULT_PARAMS,
    substeps: int = DEFAULT_SUBSTEPS,
    method: str = DEFAULT_METHOD,
    project: bool = True,
) -> Tensor:
    """Advance ``x`` by ``dt`` holding ``u`` constant (zero-order hold), with ``substeps`` integrator steps.

    ``R`` stays on SO(3): it is only ever updated by right-multiplication with ``so3_exp`` (exactly orthonormal up
    to rounding), and with ``project=True`` one Newton polar step at the end of ``dt`` removes accumulated
    rounding (float32 stays orthonormal to ~1e-7 indefinitely). Both are left-equivariant, so
    ``step(phi_g x, u) == phi_g step(x, u)`` exactly (up to rounding). Differentiable with torch autograd.

    ``u`` is applied as given (no clipping): call :func:`clip_control` first to respect actuator limits.
    Batch dims of ``x`` and ``u`` broadcast.
    """
    p, r, v, w = unpack(x)
    check_control(u)
    if method not in _METHODS:
        raise ValueError(f"unknown integrator {method!r}; choose one of {sorted(_METHODS)}")
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    if not isinstance(dt, Tensor) and not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt!r}")
    batch = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    p, v, w = (t.expand(*batch, 3) for t in (p, v, w))
    r = r.expand(*batch, 3, 3)
    c = consts(params, x)
    jtau = c.Jinv * u[..., TAU]  # J^-1 tau: constant over the step
    fm = u[..., THRUST] / params.mass
    h = dt / int(substeps)
    sub = _METHODS[method]
    for _ in range(int(substeps)):
        p, r, v, w = sub(p, r, v, w, jtau, fm, h, c)
    if project:
        r = orthonormalize(r)
    return state_from_parts(p, r, v, w)
