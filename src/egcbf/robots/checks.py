"""Property checks for a :class:`~egcbf.robots.base.Robot`: run them on a robot of your own before training it.

``check_robot(robot)`` draws generic states (random positions and headings, then a few steps under random
controls within the actuator box) and random group elements, and measures every algebraic claim the swarm, the
graph and the learner rely on:

* the control-affine form: ``xdot(x, u) == f0(x) + f1(x) u``;
* equivariance of the dynamics: ``step(phi_g x, psi_g u) == phi_g step(x, u)``, of the actuator box and of the
  part of it that acts at a state (``effective_control_bounds``);
* the geometry: positions move as points, velocities and the heading as vectors, frames by ``g frames(x)``;
* the node features: ``agent_features(phi_g x) == rho_g agent_features(x)`` (``rho`` from ``node_fields``);
* the nominal controller: ``nominal_control(phi_g x, g goal) == psi_g nominal_control(x, goal)``, and the same for
  the brisk law (``brisk_control``);
* for a robot that freezes agents at their goals: ``parked(x)`` is at rest, in place, and equivariant.
* for a robot with a disturbance rejection (optional): none is the command, and it is equivariant.

It returns the largest error of each claim (max abs error over max(1, max abs value): the quadrotor's angular
accelerations reach 1e4 rad/s^2) and raises ``AssertionError`` naming every claim above ``atol``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from groupcanon import FieldType
from groupcanon.features import Vector

from .base import Robot

__all__ = ["check_robot", "generic_states"]


def generic_states(
    robot: Robot, batch: int, generator: torch.Generator, dtype: torch.dtype = torch.float64, steps: int = 3
) -> tuple[Tensor, Tensor]:
    """``(x (batch, S), goals (batch, d))``: agents at random positions in ``[0, 2]^d`` with random headings, moved
    ``steps`` control periods of 0.05 s under random controls within the box (so velocities and rates are not
    zero), and random goals."""
    d = robot.dim
    p = torch.rand(batch, d, generator=generator, dtype=dtype) * 2
    yaw = (torch.rand(batch, generator=generator, dtype=dtype) * 2 - 1) * math.pi
    x = robot.rest_state(p, yaw)
    lo, hi = robot.control_bounds(x)
    for _ in range(steps):
        u = lo + (hi - lo) * torch.rand(batch, robot.control_dim, generator=generator, dtype=dtype)
        x = robot.step(x, u, 0.05)
    goals = torch.rand(batch, d, generator=generator, dtype=dtype) * 2
    return x, goals


def _frames_error(robot: Robot, group, g: Tensor, x: Tensor, gx: Tensor, err) -> float:
    """``frames(phi_g x)`` against ``g frames(x)``; for frame sets ``(batch, F, *element)`` as sets: every frame of
    either side against the nearest frame of the other (so a set of copies of one frame fails too)."""
    fx, fgx = robot.frames(x), robot.frames(gx)
    if fx.dim() == x.dim() - 1 + 1 + len(group.element_shape):  # (batch, F, *element): a frame set
        f = fx.shape[1]
        moved = group.compose(g[:, None].expand(-1, f, *g.shape[1:]), fx)
        flat = (-1, f, max(1, fx[0, 0].numel()))
        dist = (fgx.reshape(flat)[:, :, None] - moved.reshape(flat)[:, None]).abs().amax(-1)  # (batch, F, F)
        if not dist.numel():
            return 0.0
        gap = torch.maximum(dist.amin(-1).amax(-1), dist.amin(-2).amax(-1))
        return float(gap.max() / moved.abs().max().clamp_min(1.0))
    return err(fgx, group.compose(g, fx))


def _clip_effective(robot: Robot, x: Tensor, u: Tensor) -> Tensor:
    """``u`` clamped into the part of the box that acts at ``x`` (:meth:`Robot.effective_control_bounds`)."""
    lo, hi = robot.effective_control_bounds(x)
    return torch.maximum(torch.minimum(u, hi), lo)


def check_robot(
    robot: Robot, *, batch: int = 64, seed: int = 0, dtype: torch.dtype = torch.float64, atol: float = 1e-9
) -> dict[str, float]:
    """Measure the robot's algebraic claims (module doc) on ``batch`` generic states; raise ``AssertionError``
    listing those whose error exceeds ``atol``. Returns ``{claim: max abs error / max(1, max abs value)}``."""
    gen = torch.Generator().manual_seed(seed)
    x, goals = generic_states(robot, batch, gen, dtype)
    group = robot.group
    g = group.sample(batch, generator=gen, dtype=dtype)
    lo, hi = robot.control_bounds(x)
    u = lo + (hi - lo) * (1.4 * torch.rand(batch, robot.control_dim, generator=gen, dtype=dtype) - 0.2)
    act_x, act_u = robot.state_type.act, robot.control_type.act
    vec = FieldType(group, [Vector(robot.dim)])
    feats = FieldType(group, dict(robot.node_fields))
    gx = act_x(g, x)

    def err(a: Tensor, b: Tensor) -> float:  # relative to the size of the reference, at least 1
        if a.shape != b.shape:
            return math.inf
        if b.numel() == 0:  # e.g. the trivial group's frames: nothing to compare
            return 0.0
        return float((a - b).abs().max() / b.abs().max().clamp_min(1.0))

    errors = {
        "xdot = f0 + f1 u": err(robot.xdot(x, u), robot.f0(x) + (robot.f1(x) @ u[..., None])[..., 0]),
        "step equivariant": err(robot.step(gx, act_u(g, u), 0.05, 2), act_x(g, robot.step(x, u, 0.05, 2))),
        "actuator box equivariant": err(robot.clip_control(act_u(g, u)), act_u(g, robot.clip_control(u))),
        "effective box equivariant": err(
            _clip_effective(robot, gx, act_u(g, u)), act_u(g, _clip_effective(robot, x, u))
        ),
        "positions are points": err(robot.positions(gx), group.transform(g, robot.positions(x))),
        "velocities are vectors": err(robot.velocities(gx), vec.act(g, robot.velocities(x))),
        "heading is a vector": 0.0 if robot.world_fixed_lidar else err(robot.heading(gx), vec.act(g, robot.heading(x))),
        "frames: g frames(x)": _frames_error(robot, group, g, x, gx, err),
        "node features equivariant": err(robot.agent_features(gx), feats.act(g, robot.agent_features(x))),
        "nominal control equivariant": err(
            robot.nominal_control(gx, group.transform(g, goals)), act_u(g, robot.nominal_control(x, goals))
        ),
        "brisk control equivariant": err(
            robot.brisk_control(gx, group.transform(g, goals)), act_u(g, robot.brisk_control(x, goals))
        ),
    }
    if robot.rejects_disturbances:  # optional: the disturbance observer's
        accel = torch.randn(batch, robot.dim, generator=gen, dtype=dtype)
        boxed = robot.clip_control(u)
        errors["disturbance rejection: none is the command"] = err(
            robot.reject_disturbance(x, boxed, torch.zeros_like(accel)), boxed
        )
        errors["disturbance rejection equivariant"] = err(
            robot.reject_disturbance(gx, act_u(g, boxed), vec.act(g, accel)),
            act_u(g, robot.reject_disturbance(x, boxed, accel)),
        )
    if robot.goal_freeze_radius > 0:  # the environment parks agents at their goals
        parked = robot.parked(x)
        errors["parked: at rest"] = err(robot.velocities(parked), torch.zeros_like(robot.velocities(x)))
        errors["parked: in place"] = err(robot.positions(parked), robot.positions(x))
        errors["parked equivariant"] = err(robot.parked(gx), act_x(g, parked))
    bad = {k: v for k, v in errors.items() if not v <= atol}
    if bad:
        raise AssertionError(f"{robot!r}: claims off by more than {atol:g}: {bad}")
    return errors
