"""GCBF+'s planar point-mass robots: the single integrator and the double integrator.

Both follow the GCBF+ reference's conventions exactly (docs/robots.md, "GCBF+'s single and double integrators"):

=================== ================== ============================== ================== ==========================
robot               state              control (box)                  dynamics           state clip (after a step)
=================== ================== ============================== ================== ==========================
single_integrator   ``p`` (2)          velocity, ``+-1`` per axis     ``p' = u``         none
double_integrator   ``(p, v)`` (4)     force, ``+-1`` per axis        ``p' = v``,        ``v`` to ``+-0.5`` per axis
                                                                      ``v' = u / m``
=================== ================== ============================== ================== ==========================

with ``m = 0.1`` kg, one explicit Euler step per control period ``dt = 0.03`` s (the reference's; ``integrator =
"rk4"`` is available), agent radius 0.05 m, communication and LiDAR range 0.5 m, 32 world-fixed LiDAR rays, 256
steps. The step clips the control to its box first (:meth:`Robot.clip_control`, by the caller) and the state after.

Nominal controller (the reference's ``u_ref``): a discrete-time LQR on the full error state ``e = goal_state - x``
(the goal's velocity is 0, so the velocity part is ``-v``), with ``e`` scaled to norm ``<= comm_radius`` (0.5) and
the result clipped to the box: ``u = clip(K e)``. ``K = (B^T X B + R)^-1 B^T X A`` from the discrete Riccati
equation of ``A = I``, ``B = dt I``, ``Q = 2 I``, ``R = I`` (single: ``K = 1.3845 I``) and of
``A = I + dt [[0, I], [0, 0]]``, ``B = dt [0; I / m]``, ``Q = 5 I``, ``R = I`` (double: ``1.585`` on the position
error, ``1.706`` on the velocity error, per axis).

Symmetry: the per-axis boxes and clips are invariant only under the rotations by multiples of 90 degrees and the
planar translations, ``C4 x| R^2`` (:class:`groupcanon.groups.CyclicSE2` ``(4)``; config name ``"se2c4"``), and a
point mass carries no heading from which to build a frame (a velocity vanishes at rest). So each agent gets the set of
its four frames, the rotations by ``k 90`` degrees at its position (:func:`groupcanon.frames.cyclic_frames`), and
the equivariant networks average over them (:meth:`egcbf.env.graph.SwarmGraph.expand_frames`): exact at every state,
zero velocity included, for four times the network's work. LiDAR rays are fixed in the world frame, as in the
reference (:meth:`heading` is the world x axis): with a number of rays divisible by 4 the ray set is invariant under
the group, so the hits move with the scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from groupcanon import FieldType
from groupcanon.features import Point, Vector
from groupcanon.frames import cyclic_frames
from groupcanon.groups import CyclicSE2, CyclicSE2xR

from .base import Robot, hold_at_limit, require_positive, rk4_step

__all__ = [
    "PLANAR_DEFAULTS",
    "DoubleIntegrator",
    "IntegratorParams",
    "LinearDrone",
    "SingleIntegrator",
    "discrete_lqr",
]

#: GCBF+'s planar environment defaults: rotated rectangles with sides in [0.1, 0.6] m (the double integrator's are
#: [0.1, 0.5]), 32 world-fixed rays, all kept
PLANAR_DEFAULTS: dict = {
    "area_size": 4.0,
    "agent_radius": 0.05,
    "comm_radius": 0.5,
    "obstacle_shape": "rectangle",
    "obstacle_side_range": (0.1, 0.6),
    "n_rays": 32,
    "lidar_max_hits": 32,
    "dt": 0.03,
    "substeps": 1,
    "integrator": "euler",
    "max_steps": 256,
}


@dataclass(frozen=True)
class IntegratorParams:
    """Point-mass parameters (SI units): ``radius`` (m; EnvConfig sets it), ``mass`` (kg, double integrator),
    ``max_control`` (the box, per axis), ``max_speed`` (the double integrator's velocity clip, per axis; m/s),
    ``max_position_error`` (the nominal controller scales the error state to this norm), ``dt`` (the period the LQR
    is designed for, s), the double integrator's brisk law's gains ``brisk_position_gain`` (1/s) and
    ``brisk_velocity_time`` (s) (:meth:`DoubleIntegrator.brisk_control`)."""

    radius: float = 0.05
    mass: float = 0.1
    max_control: float = 1.0
    max_speed: float = 0.5
    max_position_error: float = 0.5
    dt: float = 0.03
    brisk_position_gain: float = 4.0
    brisk_velocity_time: float = 0.06

    def __post_init__(self) -> None:
        positive = ("radius", "mass", "max_control", "max_speed", "max_position_error", "dt", "brisk_position_gain")
        require_positive(self, (*positive, "brisk_velocity_time"))


def discrete_lqr(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The gain ``K = (B^T X B + R)^-1 B^T X A`` of the discrete-time LQR (``u = -K x``), ``X`` the stabilizing
    solution of the discrete algebraic Riccati equation (float64)."""
    from scipy.linalg import solve_discrete_are

    x = solve_discrete_are(a, b, q, r)
    return np.linalg.solve(b.T @ x @ b + r, b.T @ x @ a)


class _PointMass(Robot):
    """What GCBF+'s point masses share: positions, world-fixed LiDAR, the four quarter-turn frames, the LQR law."""

    dim = 2
    control_dim = 2
    group_name = "se2c4"
    interfaces = ("control",)
    env_defaults: ClassVar[dict] = PLANAR_DEFAULTS
    #: the LiDAR rays are fixed in the world (``heading`` is no vector of the group): check_robot skips that claim
    world_fixed_lidar: ClassVar[bool] = True
    position_index = slice(0, 2)

    def cbf_qps(self) -> dict[str, type]:
        from .point_mass_qp import POINT_MASS_CBF_QPS

        return dict(POINT_MASS_CBF_QPS)

    def __init__(self, params: IntegratorParams | None = None):
        if params is not None and not isinstance(params, IntegratorParams):
            raise TypeError(f"{type(self).__name__} params must be an IntegratorParams, got {type(params).__name__}")
        self.params = IntegratorParams() if params is None else params
        self.group = CyclicSE2(4)
        self._gain = torch.as_tensor(self._lqr_gain(), dtype=torch.float64)  # (2, state_dim)

    def _lqr_gain(self) -> np.ndarray:
        raise NotImplementedError

    def control_bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        hi = torch.full((self.control_dim,), self.params.max_control, dtype=like.dtype, device=like.device)
        return -hi, hi

    def _clip_state(self, x: Tensor) -> Tensor:
        return x

    def effective_control_bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The box, less the pushes the velocity clip discards (:meth:`Robot.effective_control_bounds`): on an axis
        at ``+-max_speed`` the control beyond the one that holds the speed (``-f0_v / B``; 0 for the double
        integrator, ``D v / 10`` for the linear drone's damping)."""
        lo, hi = super().effective_control_bounds(x)
        if self.state_dim == self.dim:  # the single integrator: no velocity state, no clip
            return lo, hi
        v = self.velocities(x)
        gain = torch.diagonal(self.f1(x)[..., self.dim :, :], dim1=-2, dim2=-1)
        hold = -self.f0(x)[..., self.dim :] / gain
        return hold_at_limit(lo, hi, v, self.params.max_speed, hold)

    def step(self, x: Tensor, u: Tensor, dt: float, substeps: int = 1, integrator: str = "euler") -> Tensor:
        if int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        if integrator == "rk4":
            return self._clip_state(rk4_step(self.xdot, x, u, dt, substeps))
        if integrator != "euler":
            raise ValueError(f"unknown integrator {integrator!r}; choose 'euler' or 'rk4'")
        h = dt / int(substeps)
        for _ in range(int(substeps)):
            x = self._clip_state(x + h * self.xdot(x, u))
        return x

    def positions(self, x: Tensor) -> Tensor:
        return x[..., : self.dim]

    def heading(self, x: Tensor) -> Tensor:
        """The world x axis: the reference's LiDAR rays are fixed in the world."""
        out = torch.zeros(*x.shape[:-1], self.dim, dtype=x.dtype, device=x.device)
        out[..., 0] = 1.0
        return out

    def frames(self, x: Tensor) -> Tensor:
        """Each agent's four frames ``(*batch, 4, *element)`` (module doc): a frame set, averaged over."""
        return cyclic_frames(4, self.positions(x))

    @property
    def node_fields(self) -> dict:
        return {"v": Vector(self.dim)}

    def agent_features(self, x: Tensor) -> Tensor:
        return self.velocities(x)

    def nominal_control(self, x: Tensor, goals: Tensor) -> Tensor:
        goal_state = torch.cat((goals.to(x.dtype), torch.zeros_like(x[..., self.dim :])), -1)
        e = goal_state - x
        norm = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
        e = e * (self.params.max_position_error / norm.clamp_min(self.params.max_position_error))
        return self.clip_control(e @ self._gain.to(dtype=x.dtype, device=x.device).T)

    def command_feature(self, interface: str):
        self.check_interface(interface)
        return Vector(self.dim)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params})"


class SingleIntegrator(_PointMass):
    """GCBF+'s single integrator (module doc): state ``p`` (2), control the velocity."""

    name = "single_integrator"
    state_dim = 2
    kinematic = True

    def __init__(self, params: IntegratorParams | None = None):
        super().__init__(params)
        self.state_type = FieldType(self.group, {"p": Point(2)})
        self.control_type = FieldType(self.group, {"u": Vector(2)})

    def _lqr_gain(self) -> np.ndarray:
        eye = np.eye(2)
        return discrete_lqr(eye, self.params.dt * eye, 2 * eye, eye)

    def f0(self, x: Tensor) -> Tensor:
        return torch.zeros_like(x)

    def f1(self, x: Tensor) -> Tensor:
        return torch.eye(2, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], 2, 2)

    def velocities(self, x: Tensor) -> Tensor:  # kinematic: the velocity is the control, not part of the state
        return torch.zeros_like(x)

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        return positions.clone()


class DoubleIntegrator(_PointMass):
    """GCBF+'s double integrator (module doc): state ``(p, v)`` (4), control the force; ``v`` clipped per axis."""

    name = "double_integrator"
    state_dim = 4
    velocity_index = slice(2, 4)
    env_defaults: ClassVar[dict] = {**PLANAR_DEFAULTS, "obstacle_side_range": (0.1, 0.5)}
    #: the reference's training labels (EnvConfig fields): unsafe = a collision (2 r, r) or an approach within 3 r /
    #: 2 r (its "unsafe direction", :func:`egcbf.env.swarm.approach_unsafe`); not the default, which kept our
    #: recipe safer at scale (docs/robots.md)
    reference_labels: ClassVar[dict] = {
        "unsafe_agent_distance": 2.0,
        "unsafe_obstacle_distance": 1.0,
        "unsafe_approach_agent_distance": 3.0,
        "unsafe_approach_obstacle_distance": 2.0,
    }

    def __init__(self, params: IntegratorParams | None = None):
        super().__init__(params)
        self.state_type = FieldType(self.group, {"p": Point(2), "v": Vector(2)})
        self.control_type = FieldType(self.group, {"u": Vector(2)})

    def _lqr_gain(self) -> np.ndarray:
        q = self.params
        a = np.eye(4)
        a[0, 2] = a[1, 3] = q.dt
        b = np.zeros((4, 2))
        b[2, 0] = b[3, 1] = q.dt / q.mass
        return discrete_lqr(a, b, 5 * np.eye(4), np.eye(2))

    def brisk_control(self, x: Tensor, goals: Tensor) -> Tensor:
        """A cascade: the velocity target ``g e`` points straight at the goal (``e = goal - p``) with ``g =
        min(k_p, max_speed / max_k |e_k|)``: the larger axis at the speed limit, as the nominal law cruises, until
        ``max_speed / k_p`` (12.5 cm) from the goal, where the nominal LQR, tuned gently, starts to slow about half a
        metre out; tracked with time constant ``tau``: ``u = clip(m (v_target - v) / tau)``. Quarter-turn
        equivariant (the max over axes is invariant). Straight, not per-axis saturated: a target of the box's corner
        leaves an agent behind an obstacle with nothing to slide along (docs/robots.md, "The brisk base law")."""
        q = self.params
        e = goals.to(x.dtype) - x[..., :2]
        # straight at the goal, the larger axis at the speed limit (as the nominal cruises), braking near the goal
        gain = (q.max_speed / e.abs().amax(-1, keepdim=True).clamp_min(1e-12)).clamp_max(q.brisk_position_gain)
        v_target = gain * e
        return self.clip_control(q.mass * (v_target - x[..., 2:4]) / q.brisk_velocity_time)

    def f0(self, x: Tensor) -> Tensor:
        return torch.cat((x[..., 2:4], torch.zeros_like(x[..., 2:4])), -1)

    def f1(self, x: Tensor) -> Tensor:
        out = x.new_zeros(*x.shape[:-1], 4, 2)
        out[..., 2, 0] = out[..., 3, 1] = 1.0 / self.params.mass
        return out

    def _clip_state(self, x: Tensor) -> Tensor:
        s = self.params.max_speed
        return torch.cat((x[..., :2], x[..., 2:4].clamp(-s, s)), -1)

    def velocities(self, x: Tensor) -> Tensor:
        return x[..., 2:4]

    def reject_disturbance(self, x: Tensor, u: Tensor, accel: Tensor) -> Tensor:
        """The force less ``m accel`` (a point mass cancels any acceleration within its box)."""
        return self.clip_control(u - self.params.mass * accel.to(u.dtype))

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        return torch.cat((positions, torch.zeros_like(positions)), -1)


#: GCBF+'s linear drone's environment defaults: spheres of radius 0.075-0.15 m, 3-D LiDAR, 16 hits kept
_DRONE_DEFAULTS: dict = {
    **PLANAR_DEFAULTS,
    "area_size": 4.0,
    "obstacle_shape": "round",
    "obstacle_radius_range": (0.075, 0.15),
    "lidar_max_hits": 16,
}


class LinearDrone(_PointMass):
    """GCBF+'s linear drone: state ``(p, v)`` (6), control an acceleration command ``c`` in ``[-1, 1]^3``,
    ``v' = -D v + 10 c`` with damping ``D = diag(1.1, 1.1, 6)``, ``v`` clipped to ``+-0.5`` per axis after each
    Euler step. Nominal controller: the reference's LQR on the error state (``A = expm(A_c dt)``, ``B = B_c`` not
    times ``dt``, as its code does; ``Q = diag(50, 50, 50, 1, 1, 1)``, ``R = I``). Symmetry: quarter turns about z
    and 3-D translations (:class:`groupcanon.groups.CyclicSE2xR` ``(4)``, config name ``"se2xrc4"``), four frames
    per agent averaged over, as for the planar point masses."""

    name = "linear_drone"
    dim = 3
    state_dim = 6
    position_index, velocity_index = slice(0, 3), slice(3, 6)
    control_dim = 3
    group_name = "se2xrc4"
    env_defaults: ClassVar[dict] = _DRONE_DEFAULTS
    damping = (1.1, 1.1, 6.0)
    gain = 10.0

    def __init__(self, params: IntegratorParams | None = None):
        super().__init__(params)
        self.group = CyclicSE2xR(4)
        self.state_type = FieldType(self.group, {"p": Point(3), "v": Vector(3)})
        self.control_type = FieldType(self.group, {"u": Vector(3)})

    def _continuous(self) -> tuple[np.ndarray, np.ndarray]:
        a = np.zeros((6, 6))
        a[0, 3] = a[1, 4] = a[2, 5] = 1.0
        a[3, 3], a[4, 4], a[5, 5] = (-d for d in self.damping)
        b = np.zeros((6, 3))
        b[3, 0] = b[4, 1] = b[5, 2] = self.gain
        return a, b

    def _lqr_gain(self) -> np.ndarray:
        from scipy.linalg import expm

        a, b = self._continuous()
        q = np.diag([50.0, 50.0, 50.0, 1.0, 1.0, 1.0])
        return discrete_lqr(expm(a * self.params.dt), b, q, np.eye(3))

    def f0(self, x: Tensor) -> Tensor:
        damping = torch.tensor(self.damping, dtype=x.dtype, device=x.device)
        return torch.cat((x[..., 3:6], -damping * x[..., 3:6]), -1)

    def f1(self, x: Tensor) -> Tensor:
        out = x.new_zeros(*x.shape[:-1], 6, 3)
        out[..., 3, 0] = out[..., 4, 1] = out[..., 5, 2] = self.gain
        return out

    def _clip_state(self, x: Tensor) -> Tensor:
        s = self.params.max_speed
        return torch.cat((x[..., :3], x[..., 3:6].clamp(-s, s)), -1)

    def velocities(self, x: Tensor) -> Tensor:
        return x[..., 3:6]

    def reject_disturbance(self, x: Tensor, u: Tensor, accel: Tensor) -> Tensor:
        """The command less ``accel / gain`` (its acceleration channel is ``gain c``)."""
        return self.clip_control(u - accel.to(u.dtype) / self.gain)

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        return torch.cat((positions, torch.zeros_like(positions)), -1)
