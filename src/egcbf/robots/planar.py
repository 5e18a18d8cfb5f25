"""What GCBF+'s Dubins car (:mod:`egcbf.robots.dubins`) and our planar unicycle (:mod:`egcbf.robots.unicycle`)
share: a planar state ``x = [p (2), h (2, unit heading), v (1, forward speed)]``, its geometry (positions, world
velocities, frames, the LiDAR heading), its graph features and how faults push it. Each robot adds its dynamics, its
actuator box and its nominal controller."""

from __future__ import annotations

import torch
from torch import Tensor

from groupcanon.features import Vector
from groupcanon.frames import planar_frame

from .base import Robot

__all__ = ["H", "HeadingSpeedRobot", "P", "V", "perp"]

P, H, V = slice(0, 2), slice(2, 4), slice(4, 5)


def perp(h: Tensor) -> Tensor:
    """``h`` turned a quarter turn counter-clockwise ``(*batch, 2)``."""
    return torch.stack((-h[..., 1], h[..., 0]), -1)


class HeadingSpeedRobot(Robot):
    """A planar robot whose state is ``[p, h, v]`` (module doc): ``dim = 2``, ``state_dim = 5``."""

    dim = 2
    state_dim = 5

    def check_state(self, x: Tensor, atol: float = 1e-3) -> None:
        super().check_state(x, atol)
        err = (torch.linalg.vector_norm(x[..., H], dim=-1) - 1).abs()
        if bool((err > atol).any()):
            bad = (err > atol).nonzero()[0].tolist()
            raise ValueError(f"{self.name} heading must be a unit vector (first bad at {tuple(bad)}: |h| - 1 = "
                             f"{err[tuple(bad)].item():.3g})")  # fmt: skip

    # ------------------------------------------------------------------------------------------- geometry
    def positions(self, x: Tensor) -> Tensor:
        return x[..., P]

    def velocities(self, x: Tensor) -> Tensor:
        return x[..., V] * x[..., H]

    def reject_disturbance(self, x: Tensor, u: Tensor, accel: Tensor) -> Tensor:
        """The forward acceleration ``u[..., 1]`` cancels the disturbance along the heading; the lateral part is
        beyond these robots' actuators (and their state: pushes drop it too, :meth:`perturbed`)."""
        a = u[..., 1:2] - (accel.to(u.dtype) * x[..., H]).sum(-1, keepdim=True)
        return self.clip_control(torch.cat((u[..., :1], a), -1))

    def perturbed(self, x: Tensor, dp: Tensor, dv: Tensor | None = None) -> Tensor:
        """Position moved by ``dp``; the speed changed by the component of ``dv`` along the heading (the state
        holds no lateral velocity)."""
        out = x.clone()
        out[..., P] += dp.to(x.dtype)
        if dv is not None:
            out[..., V] += (dv.to(x.dtype) * x[..., H]).sum(-1, keepdim=True)
        return out

    def heading(self, x: Tensor) -> Tensor:
        return planar_frame(x[..., H])

    def motion_direction(self, x: Tensor) -> Tensor:
        """The heading, whatever the speed (GCBF+'s Dubins car labels approaches along ``theta``)."""
        return self.heading(x)

    def frames(self, x: Tensor) -> Tensor:
        return torch.cat((planar_frame(x[..., H]), x[..., P]), -1)

    def parked(self, x: Tensor) -> Tensor:
        """``x`` with its speed zeroed (position and heading kept)."""
        return torch.cat((x[..., P], x[..., H], torch.zeros_like(x[..., V])), -1)

    def rest_state(self, positions: Tensor, yaw: Tensor) -> Tensor:
        h = torch.stack((torch.cos(yaw), torch.sin(yaw)), -1).to(positions.dtype)
        return torch.cat((positions, h, torch.zeros_like(positions[..., :1])), -1)

    # ------------------------------------------------------------------------------------------- features
    @property
    def node_fields(self) -> dict:
        return {"v": Vector(2), "h": Vector(2)}

    def agent_features(self, x: Tensor) -> Tensor:
        return torch.cat((self.velocities(x), x[..., H]), -1)
