"""GCBF+'s Dubins car, SE(2)-equivariant. Our :mod:`egcbf.robots.unicycle` stays the control-affine
variant; this one follows the reference (docs/robots.md):

State ``x`` ``(*batch, 5)``, control ``u`` ``(*batch, 2)``::

    x = [p (2), h (2, unit heading), v (1, forward speed)]      (the reference's (x, y, theta, v), theta as h)
    u = [omega_cmd, a]  in [-3, 3] each
    p' = v h,   theta' = 20 omega_cmd,   v' = a;   one explicit Euler step per period, then v clipped to [-0.8, 0.8]

The heading turns by exactly ``20 omega_cmd dt`` per step (the Euler step of the angle), so ``h`` stays a unit
vector. An agent within ``0.5 r`` of its goal is frozen: parked, its position and heading kept and its speed set
to 0 (:attr:`goal_freeze_radius`, :meth:`parked`, applied by :meth:`egcbf.env.SwarmEnv.step`).

Nominal controller (the reference's ``u_ref``, from invariants of the body frame): ``omega_cmd = +-k_omega
arccos(h . e / (d + 1e-4))`` (the bearing of the goal offset ``e``, regularized as the reference does, turning the
short way; ``k_omega = 1``), ``a = -k_a v + k_v min(d, R)`` (``k_a = 2.5``, ``k_v = 2.3``, ``d`` the goal distance
soft-clipped to ``R = 0.5`` as the reference does), **not clipped** (the step clips it, as in the reference).

Departures, on purpose: the LiDAR rays turn with the heading (the reference fixes its 16 rays in the world, which
breaks the rotation symmetry), the QP's input matrix uses the dynamics' turn gain 20 (the reference's
``control_affine_dyn`` says 10), and a frozen agent's speed is 0 (the reference keeps the speed it arrived with in
the state of a car that no longer moves, and its neighbours read it as motion; the trajectories of the frozen
agents are the same either way, docs/robots.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from groupcanon import FieldType
from groupcanon.features import Point, Scalar, Vector
from groupcanon.groups import SE2

from .base import hold_at_limit, require_positive
from .integrators import PLANAR_DEFAULTS
from .planar import H, HeadingSpeedRobot, P, V, perp

__all__ = ["DubinsCar", "DubinsParams"]


@dataclass(frozen=True)
class DubinsParams:
    """The reference's Dubins car (SI units): ``radius`` (m; EnvConfig sets it), ``turn_gain`` (``theta' = turn_gain
    omega_cmd``), ``max_control`` (the box of both commands), ``max_speed`` (the speed clip), the nominal gains
    ``k_omega``, ``k_a``, ``k_v`` and ``max_position_error`` (the nominal controller's soft distance clip, m),
    ``brisk_speed`` (m/s, the cruise of :meth:`DubinsCar.brisk_control`)."""

    radius: float = 0.05
    turn_gain: float = 20.0
    max_control: float = 3.0
    max_speed: float = 0.8
    k_omega: float = 1.0
    k_a: float = 2.5
    k_v: float = 2.3
    max_position_error: float = 0.5
    brisk_speed: float = 0.6

    def __post_init__(self) -> None:
        gains = ("k_omega", "k_a", "k_v", "max_position_error", "brisk_speed")
        require_positive(self, ("radius", "turn_gain", "max_control", "max_speed", *gains))
        if self.brisk_speed > self.max_speed:
            raise ValueError(f"DubinsParams.brisk_speed ({self.brisk_speed}) exceeds max_speed ({self.max_speed})")


class DubinsCar(HeadingSpeedRobot):
    """GCBF+'s Dubins car (module doc)."""

    name = "dubins_car"
    control_dim = 2
    group_name = "se2"
    interfaces = ("control",)
    env_defaults: ClassVar[dict] = PLANAR_DEFAULTS  # the reference's planar environments (rectangles, r, R, dt)
    #: the reference's training labels (EnvConfig fields): unsafe = an agent within 2 r, an obstacle within 1.5 r, or
    #: an approach along the heading within 3 r / 2 r (its "unsafe direction"); not the default (docs/robots.md)
    reference_labels: ClassVar[dict] = {
        "unsafe_agent_distance": 2.0,
        "unsafe_obstacle_distance": 1.5,
        "unsafe_approach_agent_distance": 3.0,
        "unsafe_approach_obstacle_distance": 2.0,
    }

    def cbf_qps(self) -> dict[str, type]:
        from .point_mass_qp import POINT_MASS_CBF_QPS

        return dict(POINT_MASS_CBF_QPS)

    def __init__(self, params: DubinsParams | None = None):
        if params is not None and not isinstance(params, DubinsParams):
            raise TypeError(f"DubinsCar params must be a DubinsParams, got {type(params).__name__}")
        self.params = DubinsParams() if params is None else params
        self.group = SE2()
        self.state_type = FieldType(self.group, {"p": Point(2), "h": Vector(2), "v": Scalar(1)})
        self.control_type = FieldType(self.group, {"u": Scalar(2)})

    @property
    def goal_freeze_radius(self) -> float:
        """Agents closer than this to their goals are frozen (the reference's ``0.5 r``)."""
        return 0.5 * self.params.radius

    # ------------------------------------------------------------------------------------------- dynamics
    def f0(self, x: Tensor) -> Tensor:
        return torch.cat((x[..., V] * x[..., H], torch.zeros_like(x[..., 2:5])), -1)

    def f1(self, x: Tensor) -> Tensor:
        out = x.new_zeros(*x.shape[:-1], 5, 2)
        out[..., H, 0] = self.params.turn_gain * perp(x[..., H])
        out[..., 4, 1] = 1.0
        return out

    def step(self, x: Tensor, u: Tensor, dt: float, substeps: int = 1, integrator: str = "euler") -> Tensor:
        if integrator != "euler":
            raise ValueError(f"the Dubins car integrates as the reference does: 'euler', not {integrator!r}")
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        h = dt / int(substeps)
        for _ in range(int(substeps)):
            p, head, v = x[..., P], x[..., H], x[..., V]
            turn = self.params.turn_gain * u[..., 0:1] * h
            c, s = torch.cos(turn), torch.sin(turn)
            new_head = c * head + s * perp(head)  # the angle's Euler step, exactly on the unit circle
            speed = (v + h * u[..., 1:2]).clamp(-self.params.max_speed, self.params.max_speed)
            x = torch.cat((p + h * v * head, new_head, speed), -1)
        return x

    def control_bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        hi = torch.full((2,), self.params.max_control, dtype=like.dtype, device=like.device)
        return -hi, hi

    def effective_control_bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The box, less the acceleration the speed clip discards at ``+-max_speed``
        (:meth:`egcbf.robots.base.Robot.effective_control_bounds`)."""
        lo, hi = super().effective_control_bounds(x)
        v = x[..., V]
        lo_a, hi_a = hold_at_limit(lo[..., 1:], hi[..., 1:], v, self.params.max_speed, torch.zeros_like(v))
        return torch.cat((lo[..., :1], lo_a), -1), torch.cat((hi[..., :1], hi_a), -1)

    # ------------------------------------------------------------------------------------------- control
    def nominal_control(self, x: Tensor, goals: Tensor) -> Tensor:
        """The reference's heading / speed law (module doc), unclipped."""
        return self._goal_law(x, goals, self.params.k_v)

    def _goal_law(self, x: Tensor, goals: Tensor, k_v: float) -> Tensor:
        """The nominal law with speed gain ``k_v`` (it cruises at ``k_v R / k_a``)."""
        head = x[..., H]
        e = goals.to(x.dtype) - x[..., P]
        forward = (head * e).sum(-1, keepdim=True)
        left = head[..., 0:1] * e[..., 1:2] - head[..., 1:2] * e[..., 0:1]
        dist_raw = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
        between = torch.arccos((forward / (dist_raw + 1e-4)).clamp(-1.0, 1.0))  # the reference's regularized angle
        q = self.params
        omega = q.k_omega * torch.where(left >= 0, between, -between)  # turn the short way
        soft = torch.sqrt(e.square().sum(-1, keepdim=True) + 1e-6)
        r = q.max_position_error
        dist = torch.linalg.vector_norm(e, dim=-1, keepdim=True) * torch.where(
            soft > r, r / soft, torch.ones_like(soft)
        )
        a = -q.k_a * x[..., V] + k_v * dist
        return torch.cat((omega, a), -1)

    def brisk_control(self, x: Tensor, goals: Tensor) -> Tensor:
        """The nominal law with its speed gain raised so that it cruises at ``brisk_speed`` (``k_v = k_a
        brisk_speed / R``; the nominal cruises at ``k_v R / k_a`` = 0.46 m/s), the same turn law. 0.6 m/s, not the
        0.8 of the speed clip: an EGCBF+ trained around a law at 0.8 was 96.9 % safe at N = 16, l = 4 on validation,
        the one around the nominal 99.8 % (docs/gcbfplus.md, "Brisk base law")."""
        q = self.params
        return self._goal_law(x, goals, q.k_a * q.brisk_speed / q.max_position_error)

    def command_feature(self, interface: str):
        self.check_interface(interface)
        return Scalar(2)

    def __repr__(self) -> str:
        return f"DubinsCar({self.params})"
