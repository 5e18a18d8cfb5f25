"""The paper's quadrotor as a :class:`~egcbf.robots.base.Robot`: the rigid body of
:mod:`~egcbf.robots.quadrotor.dynamics` with the equivariant geometric controller of
:mod:`~egcbf.robots.quadrotor.nominal`, symmetric under SE(2) x R.

Everything here delegates to those modules (one implementation of each mechanism); this class only says how the
swarm, the graph and the learner read them. The node features are ``v`` (world velocity), ``R`` (attitude,
row-major) and ``w`` (body rates); frames are the yaw frames ``se2xr_frame(R e1, p)``.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from groupcanon import FeatureType, FieldType
from groupcanon.features import Rotation, Scalar, Vector
from groupcanon.frames import se2xr_frame
from groupcanon.groups import SE2xR

from ..base import Robot
from . import dynamics as dyn
from .nominal import desired_heading, nominal_control, reject_disturbance
from .setpoint import track_setpoint

__all__ = ["Quadrotor"]


class Quadrotor(Robot):
    """The quadrotor swarm robot (module doc); ``params`` are its physical parameters."""

    name = "quadrotor"
    dim = 3
    state_dim = dyn.STATE_DIM
    control_dim = dyn.CONTROL_DIM
    group_name = "se2xr"
    interfaces = ("accel", "torque")
    env_defaults: ClassVar[dict] = {}  # EnvConfig's own defaults are the quadrotor's
    position_index, velocity_index = dyn.P, dyn.V
    actuator_groups: ClassVar[dict[str, tuple[int, ...]]] = {"torque": (0, 1, 2), "thrust": (3,)}
    run_time_filters: ClassVar[bool] = True
    lidar_obstacle_rows: ClassVar[bool] = True
    flies_setpoints: ClassVar[bool] = True
    mirror_z: ClassVar[bool] = True
    training_recipe: ClassVar[str] = "paper"

    def __init__(self, params: dyn.QuadrotorParams | None = None):
        if params is not None and not isinstance(params, dyn.QuadrotorParams):
            raise TypeError(f"Quadrotor params must be a QuadrotorParams, got {type(params).__name__}")
        self.params = dyn.DEFAULT_PARAMS if params is None else params

    @property
    def group(self) -> SE2xR:
        return dyn.GROUP

    @property
    def state_type(self) -> FieldType:
        return dyn.STATE_TYPE

    @property
    def control_type(self) -> FieldType:
        return dyn.CONTROL_TYPE

    # ------------------------------------------------------------------------------------------- dynamics
    def f0(self, x: Tensor) -> Tensor:
        return dyn.f0(x, self.params)

    def f1(self, x: Tensor) -> Tensor:
        return dyn.f1(x, self.params)

    def xdot(self, x: Tensor, u: Tensor) -> Tensor:
        return dyn.xdot(x, u, self.params)

    def step(self, x: Tensor, u: Tensor, dt: float, substeps: int = 1, integrator: str = "rk4") -> Tensor:
        return dyn.step(x, u, dt, self.params, substeps, integrator)

    def fly_setpoint(
        self, x: Tensor, accel: Tensor, dt: float, integrator: str = "rk4", clip: bool = True
    ) -> tuple[Tensor, Tensor]:
        """The Crazyflie firmware's Mellinger controller at its inner rate (:func:`.setpoint.track_setpoint`, its
        default gains) holding position and velocity at their values now, the acceleration ``accel``, and the yaw
        the attitude loop holds (:func:`.nominal.desired_heading`), as the ROS bridge sends them
        (:mod:`egcbf.ros.codecs`)."""
        heading = desired_heading(x[..., dyn.ROT].reshape(*x.shape[:-1], 3, 3))
        yaw = torch.atan2(heading[..., 1], heading[..., 0])
        return track_setpoint(x, x[..., dyn.P], x[..., dyn.V], accel.to(x), yaw, dt, params=self.params,
                              method=integrator, clip=clip)  # fmt: skip

    def control_bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        c = dyn.consts(self.params, like)
        zero = torch.zeros(1, dtype=like.dtype, device=like.device)
        top = torch.full((1,), self.params.max_thrust, dtype=like.dtype, device=like.device)
        return torch.cat((-c.tau_max, zero)), torch.cat((c.tau_max, top))

    def clip_control(self, u: Tensor) -> Tensor:
        return dyn.clip_control(u, self.params)

    def check_state(self, x: Tensor, atol: float = 1e-3) -> None:
        dyn.check_state(x, atol)

    # ------------------------------------------------------------------------------------------- geometry
    def positions(self, x: Tensor) -> Tensor:
        return x[..., dyn.P]

    def velocities(self, x: Tensor) -> Tensor:
        return x[..., dyn.V]

    def heading(self, x: Tensor) -> Tensor:
        """The body x axis (the LiDAR pattern and the frames use its horizontal part)."""
        return x[..., dyn.ROT].reshape(*x.shape[:-1], 3, 3)[..., :, 0]

    def frames(self, x: Tensor) -> Tensor:
        return se2xr_frame(self.heading(x), x[..., dyn.P])

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        return dyn.hover_state(positions, yaw)

    # ------------------------------------------------------------------------------------------- features
    @property
    def node_fields(self) -> dict[str, FeatureType]:
        return {"v": Vector(3), "R": Rotation(3), "w": Scalar(3)}

    def agent_features(self, x: Tensor) -> Tensor:
        return torch.cat((x[..., dyn.V], x[..., dyn.ROT], x[..., dyn.W]), dim=-1)

    # ------------------------------------------------------------------------------------------- control
    def nominal_control(self, x: Tensor, goals: Tensor) -> Tensor:
        return nominal_control(x, goals, self.params)

    def attitudes(self, x: Tensor) -> Tensor:
        return x[..., dyn.ROT].reshape(*x.shape[:-1], 3, 3)

    def cbf_qps(self) -> dict[str, type]:
        from .cbf_qp import CentralizedCBFQP
        from .dcbf_qp import DecentralizedCBFQP

        return {"ccbf": CentralizedCBFQP, "dcbf": DecentralizedCBFQP}

    def reject_disturbance(self, x: Tensor, u: Tensor, accel: Tensor) -> Tensor:
        return reject_disturbance(x, u, accel, self.params)

    def command_feature(self, interface: str) -> FeatureType:
        if interface == "accel":
            return Vector(3)
        if interface == "torque":
            return Scalar(4)
        raise ValueError(f"the quadrotor has the command interfaces {self.interfaces}, not {interface!r}")

    def yaw_heading(self, x: Tensor) -> Tensor:
        """Unit horizontal heading ``(*batch, 3)`` (:func:`egcbf.robots.quadrotor.nominal.desired_heading`)."""
        return desired_heading(x[..., dyn.ROT].reshape(*x.shape[:-1], 3, 3))

    def __repr__(self) -> str:
        return "Quadrotor()" if self.params == dyn.DEFAULT_PARAMS else f"Quadrotor({self.params})"
