"""A planar unicycle (Dubins car with speed as a state), SE(2)-equivariant.

State ``x`` ``(*batch, 5)`` and control ``u`` ``(*batch, 2)``::

    x = [p (2, world position), h (2, unit heading, world), v (1, signed forward speed)]
    u = [omega (turn rate, rad/s), a (forward acceleration, m/s^2)]

    p' = v h,    h' = omega J h   (J: rotation by +90 degrees),    v' = a

This is GCBF+'s Dubins car ``(x, y, theta, v)`` with the heading angle stored as the unit vector
``(cos theta, sin theta)``: the symmetry then acts linearly and no angle wraps. It is control affine,
``f0 = (v h, 0, 0)``, ``f1 = [[0, 0], [J h, 0], [0, 1]]``. The integrator is classical RK4 with the heading
renormalized after every sub-step (a projection that commutes with rotations).

Symmetry: SE(2) (``groupcanon.groups.SE2``) acts by ``p -> R p + t``, ``h -> R h``, ``v -> v``; the control is
invariant. The frames are ``(h, p)``, so an agent sees its neighbourhood as from its own seat.

Nominal controller (equivariant, from body-frame quantities only): with the goal offset ``e`` (clipped to norm
``max_position_error``) in the body frame, ``(e_f, e_l) = (h . e, h x e)``, it turns towards the goal,
``omega = k_omega atan2(e_l, e_f)`` (faded out within ``goal_fade`` of the goal, where the bearing is ill-defined),
and tracks the forward speed ``v_d = clip(k_p e_f, +-max_speed)`` with ``a = k_v (v_d - v)``; both clipped to
the actuator box. Invariant inputs give an invariant control: ``u(phi_g x, g goal) = u(x, goal)`` (tested).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from groupcanon import FieldType
from groupcanon.features import Point, Scalar, Vector
from groupcanon.groups import SE2

from .base import require_positive, rk4_step
from .planar import H, HeadingSpeedRobot, P, V

__all__ = ["Unicycle", "UnicycleParams"]


@dataclass(frozen=True)
class UnicycleParams:
    """Actuator limits and nominal gains (SI units).

    Attributes:
        radius: collision radius (m); :class:`egcbf.env.EnvConfig` sets it from ``agent_radius``.
        max_turn_rate: ``|omega| <= max_turn_rate`` (rad/s).
        max_accel: ``|a| <= max_accel`` (m/s^2).
        max_speed: the nominal controller's speed limit (m/s).
        k_omega, k_p, k_v: nominal gains (1/s): turn rate per rad of bearing, target speed per m, accel per m/s.
        max_position_error: the nominal controller clips the goal offset to this norm (m).
        goal_fade: within this distance of the goal (m) the turn command fades to 0.
    """

    radius: float = 0.05
    max_turn_rate: float = 5.0
    max_accel: float = 3.0
    max_speed: float = 0.5
    k_omega: float = 4.0
    k_p: float = 1.0
    k_v: float = 2.5
    max_position_error: float = 0.5
    goal_fade: float = 0.05

    def __post_init__(self) -> None:
        require_positive(
            self,
            (
                "radius",
                "max_turn_rate",
                "max_accel",
                "max_speed",
                "k_omega",
                "k_p",
                "k_v",
                "max_position_error",
                "goal_fade",
            ),
        )


def perp(h: Tensor) -> Tensor:
    """``J h``: ``h`` rotated by +90 degrees."""
    return torch.stack((-h[..., 1], h[..., 0]), -1)


class Unicycle(HeadingSpeedRobot):
    """The planar unicycle swarm robot (module doc)."""

    name = "unicycle"
    control_dim = 2
    group_name = "se2"
    interfaces = ("control",)
    # GCBF+'s planar conventions: r = 0.05, communication radius 0.5, dt = 0.03, 256-step episodes
    env_defaults: ClassVar[dict] = {
        "area_size": 1.5,
        "agent_radius": 0.05,
        "comm_radius": 0.5,
        "obstacle_radius_range": (0.05, 0.15),
        "n_rays": 32,
        "lidar_max_hits": 16,
        "dt": 0.03,
        "substeps": 1,
        "max_steps": 256,
    }

    def cbf_qps(self) -> dict[str, type]:
        from .point_mass_qp import POINT_MASS_CBF_QPS

        return dict(POINT_MASS_CBF_QPS)

    def __init__(self, params: UnicycleParams | None = None):
        if params is not None and not isinstance(params, UnicycleParams):
            raise TypeError(f"Unicycle params must be a UnicycleParams, got {type(params).__name__}")
        self.params = UnicycleParams() if params is None else params
        self._group = SE2()
        self._state_type = FieldType(self._group, {"p": Point(2), "h": Vector(2), "v": Scalar(1)})
        self._control_type = FieldType(self._group, {"u": Scalar(2)})

    @property
    def group(self) -> SE2:
        return self._group

    @property
    def state_type(self) -> FieldType:
        return self._state_type

    @property
    def control_type(self) -> FieldType:
        return self._control_type

    # ------------------------------------------------------------------------------------------- dynamics
    def f0(self, x: Tensor) -> Tensor:
        z = torch.zeros_like(x[..., :3])
        return torch.cat((x[..., V] * x[..., H], z), -1)

    def f1(self, x: Tensor) -> Tensor:
        batch = x.shape[:-1]
        out = x.new_zeros(*batch, 5, 2)
        out[..., H, 0] = perp(x[..., H])
        out[..., 4, 1] = 1.0
        return out

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        h = x[..., H]
        return torch.cat((x[..., V] * h, u[..., 0:1] * perp(h), u[..., 1:2]), -1)

    @staticmethod
    def _project(x: Tensor) -> Tensor:
        h = x[..., H]
        return torch.cat((x[..., P], h / torch.linalg.vector_norm(h, dim=-1, keepdim=True), x[..., V]), -1)

    def step(self, x: Tensor, u: Tensor, dt: float, substeps: int = 1, integrator: str = "rk4") -> Tensor:
        if integrator == "euler":
            if int(substeps) != substeps or substeps < 1:
                raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
            h = dt / int(substeps)
            for _ in range(int(substeps)):
                x = self._project(x + h * self.xdot(x, u))
            return x
        if integrator != "rk4":
            raise ValueError(f"unknown integrator {integrator!r}; choose 'rk4' or 'euler'")
        return rk4_step(self.xdot, x, u, dt, substeps, self._project)

    def control_bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        hi = torch.tensor((self.params.max_turn_rate, self.params.max_accel), dtype=like.dtype, device=like.device)
        return -hi, hi

    # ------------------------------------------------------------------------------------------- control
    def nominal_control(self, x: Tensor, goals: Tensor) -> Tensor:
        q = self.params
        h = x[..., H]
        e = goals.to(x.dtype) - x[..., P]
        dist = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
        e = e * (q.max_position_error / dist.clamp_min(q.max_position_error))
        e_f = (h * e).sum(-1, keepdim=True)
        e_l = (h[..., 0:1] * e[..., 1:2]) - (h[..., 1:2] * e[..., 0:1])
        fade = (dist / q.goal_fade).clamp(max=1.0)
        omega = q.k_omega * torch.atan2(e_l, e_f) * fade
        v_d = (q.k_p * e_f).clamp(-q.max_speed, q.max_speed)
        a = q.k_v * (v_d - x[..., V])
        return self.clip_control(torch.cat((omega, a), -1))

    def command_feature(self, interface: str):
        """The policy output's feature type for ``interface``: the normalized control, invariant."""
        self.check_interface(interface)
        return Scalar(2)

    def __repr__(self) -> str:
        return f"Unicycle({self.params})"
