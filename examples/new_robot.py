"""Add a robot of your own and train EGCBF+ on it: a differential-drive robot, SE(2)-equivariant.

A robot is a :class:`egcbf.robots.Robot`: control-affine dynamics, how the symmetry group acts on its state and
control (groupcanon FieldTypes), its frames, node features and an equivariant nominal controller. Register it, check
it, and the swarm, the graph, the learner and the evaluation take it as they take the quadrotor (docs/robots.md).

    python examples/new_robot.py          # checks the robot, trains EGCBF+ for a few updates, evaluates; prints OK
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from egcbf.algo import GraphCBFLearner
from egcbf.algo.config import TrainConfig
from egcbf.evaluate.episodes import evaluate
from egcbf.robots import Robot, register_robot, rk4_step
from egcbf.robots.checks import check_robot
from groupcanon import FieldType
from groupcanon.features import Point, Scalar, Vector
from groupcanon.frames import planar_frame
from groupcanon.groups import SE2


@dataclass(frozen=True)
class DiffDriveParams:
    radius: float = 0.05  # collision radius (m); EnvConfig sets it from agent_radius
    track: float = 0.1  # distance between the wheels (m)
    max_wheel_speed: float = 0.5  # m/s
    k_turn: float = 0.5  # nominal: wheel speed difference per rad of bearing
    k_speed: float = 1.0  # nominal: forward speed per m of goal distance


@register_robot
class DiffDrive(Robot):
    """State ``x = [p (2), h (2, unit heading)]``, control ``u = (v_left, v_right)`` wheel speeds:
    ``p' = (v_l + v_r) / 2 h``, ``h' = (v_r - v_l) / track J h``. Invariant controls; frames ``(h, p)``."""

    name = "diffdrive"
    dim, state_dim, control_dim = 2, 4, 2
    group_name = "se2"
    interfaces = ("control",)
    env_defaults: ClassVar[dict] = {
        "agent_radius": 0.05, "comm_radius": 0.5, "obstacle_radius_range": (0.05, 0.15), "dt": 0.03, "substeps": 1,
    }  # fmt: skip

    def __init__(self, params: DiffDriveParams | None = None):
        self.params = params or DiffDriveParams()
        self.group = SE2()
        self.state_type = FieldType(self.group, {"p": Point(2), "h": Vector(2)})
        self.control_type = FieldType(self.group, {"wheels": Scalar(2)})

    def f0(self, x):
        return torch.zeros_like(x)

    def f1(self, x):
        h, jh = x[..., 2:4], torch.stack((-x[..., 3], x[..., 2]), -1)
        forward = torch.cat((0.5 * h, torch.zeros_like(h)), -1)
        turn = torch.cat((torch.zeros_like(h), jh / self.params.track), -1)
        return torch.stack((forward - turn, forward + turn), -1)  # columns: v_left, v_right

    def step(self, x, u, dt, substeps=1, integrator="rk4"):
        def unit_heading(y):
            return torch.cat((y[..., :2], y[..., 2:4] / y[..., 2:4].norm(dim=-1, keepdim=True)), -1)

        return rk4_step(self.xdot, x, u, dt, substeps, unit_heading)

    def control_bounds(self, like):
        hi = torch.full((2,), self.params.max_wheel_speed, dtype=like.dtype, device=like.device)
        return -hi, hi

    def positions(self, x):
        return x[..., :2]

    def velocities(self, x):  # at rest between steps: the kinematic robot's velocity is its control
        return torch.zeros_like(x[..., :2])

    def heading(self, x):
        return planar_frame(x[..., 2:4])

    def frames(self, x):
        return torch.cat((planar_frame(x[..., 2:4]), x[..., :2]), -1)

    def rest_state(self, positions, yaw):
        return torch.cat((positions, torch.stack((yaw.cos(), yaw.sin()), -1).to(positions.dtype)), -1)

    @property
    def node_fields(self):
        return {"v": Vector(2), "h": Vector(2)}

    def agent_features(self, x):
        return torch.cat((self.velocities(x), x[..., 2:4]), -1)

    def nominal_control(self, x, goals):
        e = goals.to(x.dtype) - x[..., :2]
        h = x[..., 2:4]
        ahead = (h * e).sum(-1, keepdim=True)  # the goal in the body frame: invariant
        left = h[..., 0:1] * e[..., 1:2] - h[..., 1:2] * e[..., 0:1]
        forward = self.params.k_speed * ahead.clamp(-0.5, 0.5)
        turn = self.params.k_turn * torch.atan2(left, ahead)
        return self.clip_control(torch.cat((forward - turn, forward + turn), -1))

    def command_feature(self, interface):
        return Scalar(2)


def main() -> None:
    robot = DiffDrive()
    errors = check_robot(robot)  # raises if a claim fails
    print("robot checks (max relative error):", {k: f"{v:.1e}" for k, v in errors.items()})
    config = TrainConfig.preset("egcbf+", "tiny", robot="diffdrive", steps=3)
    learner = GraphCBFLearner(config)
    for _ in range(config.steps):
        info = learner.update()
    print(f"trained {config.steps} updates, last loss {info['loss/total']:.3f}")
    rows, _ = evaluate(lambda cfg: learner.controller(), [8], robot="diffdrive", area_size=2.0, episodes=2,
                       max_steps=40, show_progress=False)  # fmt: skip
    print(f"8 agents: safe {100 * rows[0]['safe_rate']:.0f} %, reach {100 * rows[0]['reach_rate']:.0f} %")
    print("OK")


if __name__ == "__main__":
    main()
