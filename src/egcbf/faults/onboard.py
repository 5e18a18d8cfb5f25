"""What an agent's flight stack does around its controller with what it knows of itself (:class:`Onboard`): command
for the state its command will act on (a Smith predictor over its actuation delay) and cancel the acceleration it
measures beyond its model (a disturbance observer). Neither changes the controller: the same learned policy or QP
runs inside::

    onboard = Onboard(robot, env_config, act_delay=2, predict=True, observe_disturbance=True)
    # each control period:
    x_for = onboard.estimate(x_est, goal)   # the state to command for (and, predicting, to broadcast)
    u, _ = controller(x_for, ...)           # unchanged
    u = onboard.command(u)                  # what to send to the actuators

The simulator's fault process (:mod:`egcbf.faults`, the ``act_predict`` and ``dist_obs`` handling) runs one for
the whole swarm; a robot runs one for itself around :class:`egcbf.deploy.agent.AgentController` (docs/deploy.md).
Shapes: any batch of agents ``(*batch,)``; states ``(*batch, S)``, commands ``(*batch, k)``, goals and the disturbance
``(*batch, d)`` (world frame; the disturbance in m/s^2).

The prediction rolls the estimate through :func:`egcbf.env.swarm.advance` (the simulator's own period: clip,
integrator, parking) with the commands in flight; the observer compares the velocity estimate with that model's
prediction from the previous estimate under the command that acted, and low-passes the difference
(``d <- d + beta (a - d)``, ``beta = 1 - exp(-dt / tau)``); the rejection is
:meth:`egcbf.robots.Robot.reject_disturbance`. Neither knows gain errors or wind: the observer measures them, and
with it the prediction adds the measured disturbance back to each period its commands (which cancel it) are rolled
over.
"""

from __future__ import annotations

import math
from collections import deque

import torch
from torch import Tensor

from ..env.config import EnvConfig
from ..env.swarm import advance
from ..robots import Robot

__all__ = ["DIST_OBS_TAU", "Onboard", "hover_commands"]

#: time constant (s) of the disturbance estimate: short enough to follow a gust (the faults' ``gust_tau``, 1 s),
#: long enough to average the velocity-estimate noise it differentiates (its error is about ``vel_noise / tau``:
#: 0.08 m/s^2 at 2 cm/s)
DIST_OBS_TAU = 0.25


class Onboard:
    """One agent's (or a batch of agents') handling of its actuation delay and of disturbances (module doc).

    Args:
        robot: the agents' robot (``observe_disturbance`` needs its ``reject_disturbance``).
        config: the environment of the model (``dt``, the actuator clip, the integrator).
        act_delay: control periods between a command and its actuation (0: none).
        predict: command for the estimate rolled ``act_delay`` periods ahead with the commands in flight.
        observe_disturbance: estimate the disturbance acceleration and cancel it in every command.
        tau: the disturbance estimate's time constant (s).
        rest_radius: for a robot the environment parks at its goal (``robot.goal_freeze_radius > 0``): within this
            distance of its goal (m, estimated) the disturbance estimate rests, since the environment parks on the
            true position and the model on the estimate (the mismatch is no disturbance, and a parked agent needs no
            rejection). Default ``2 goal_freeze_radius``; under position noise, add a few times its spread.
    """

    def __init__(
        self,
        robot: Robot,
        config: EnvConfig,
        *,
        act_delay: int = 0,
        predict: bool = False,
        observe_disturbance: bool = False,
        tau: float = DIST_OBS_TAU,
        rest_radius: float | None = None,
    ):
        if not isinstance(act_delay, int) or isinstance(act_delay, bool) or act_delay < 0:
            raise ValueError(f"Onboard: act_delay must be a whole number of control periods >= 0, got {act_delay!r}")
        if not (isinstance(tau, (int, float)) and math.isfinite(tau) and tau > 0):
            raise ValueError(f"Onboard: tau must be a finite number of seconds > 0, got {tau!r}")
        if observe_disturbance and not robot.rejects_disturbances:
            raise ValueError(f"the disturbance observer needs the robot's disturbance rejection "
                             f"(Robot.reject_disturbance); the {robot.name} has none")  # fmt: skip
        self.robot, self.config = robot, config
        self.act_delay, self.predict, self.observe_disturbance = act_delay, bool(predict), bool(observe_disturbance)
        self.beta = 1.0 - math.exp(-config.dt / tau)
        self.rest_radius = 2.0 * robot.goal_freeze_radius if rest_radius is None else float(rest_radius)
        self._sent: deque[Tensor] = deque()  # the commands in flight, oldest first
        self._estimate: Tensor | None = None  # the last estimate (before the prediction)
        self._goals: Tensor | None = None
        self._applied: Tensor | None = None  # the command that acted over the last period
        self._for: Tensor | None = None  # the state the coming command is for
        self._disturbance: Tensor | None = None

    @property
    def disturbance(self) -> Tensor | None:
        """The current disturbance estimate ``(*batch, d)`` (m/s^2, world frame); ``None`` before the first
        estimate or without the observer."""
        return self._disturbance

    def estimate(self, x: Tensor, goals: Tensor) -> Tensor:
        """Take this period's state estimate ``x`` ``(*batch, S)`` (goals ``(*batch, d)``, for the model's parking);
        return the state to command for: ``x`` itself, or rolled over the commands in flight when predicting."""
        robot = self.robot
        if x.shape[-1:] != (robot.state_dim,) or goals.shape != (*x.shape[:-1], robot.dim):
            raise ValueError(f"Onboard.estimate: the {robot.name} needs x (*batch, {robot.state_dim}) and goals "
                             f"(*batch, {robot.dim}), got {tuple(x.shape)} and {tuple(goals.shape)}")  # fmt: skip
        if self._estimate is not None and x.shape != self._estimate.shape:
            raise ValueError(f"Onboard.estimate: x changed shape from {tuple(self._estimate.shape)} to "
                             f"{tuple(x.shape)}; one Onboard serves one agent (or one batch) throughout")  # fmt: skip
        if self.observe_disturbance:
            self._observe(x, goals)
        self._estimate, self._goals = x, goals
        if self.predict and self.act_delay > 0:
            x = self.predicted(x, goals)
        self._for = x
        return x

    def predicted(self, x: Tensor, goals: Tensor) -> Tensor:
        """``x`` ``(*batch, S)`` rolled over the commands in flight (oldest first) through the robot's dynamics,
        each period with the estimated disturbance acting as the simulator applies wind (velocity ``+ d dt``,
        position ``+ d dt^2 / 2``): the commands already cancel it, so the model must add it back."""
        dt = self.config.dt
        d = None if self._disturbance is None else self._disturbance.to(x.dtype)
        for u in self._in_flight(x):
            x, _ = advance(self.robot, self.config, x, u.to(x.dtype), goals)
            if d is not None:
                x = self.robot.perturbed(x, 0.5 * d * dt * dt, d * dt)
        return x

    def reject(self, u: Tensor) -> Tensor:
        """``u`` ``(*batch, k)`` with the estimated disturbance cancelled (as is without the observer)."""
        if self._disturbance is None:
            return u
        return self.robot.reject_disturbance(self._for.to(u.dtype), u, self._disturbance.to(u.dtype))

    def record(self, u: Tensor) -> None:
        """Note ``u`` ``(*batch, k)`` as this period's sent command (what the actuators will apply after the
        delay; the command leaving the delay now is the one that acts over this period)."""
        if self._estimate is None:
            raise RuntimeError("Onboard.record before Onboard.estimate: take the period's estimate first")
        applied = u
        if self.act_delay > 0:
            self._in_flight(self._estimate)
            self._sent.append(u)
            applied = self._sent.popleft()
        if self.observe_disturbance:
            self._applied = applied

    def command(self, u: Tensor) -> Tensor:
        """The command to send for the controller's ``u`` (:meth:`reject`, then :meth:`record`)."""
        u = self.reject(u)
        self.record(u)
        return u

    def in_flight(self) -> list[Tensor]:
        """The ``act_delay`` commands sent but not yet applied, oldest first; before the first command, the hover
        commands at the first estimate (what the agent takes its actuators to start with: the simulator's fault
        process seeds its actuators with these)."""
        if self._estimate is None:
            raise RuntimeError("Onboard.in_flight before Onboard.estimate: take the period's estimate first")
        return self._in_flight(self._estimate)

    def _observe(self, x: Tensor, goals: Tensor) -> None:
        robot = self.robot
        if self._disturbance is None:
            self._disturbance = x.new_zeros(*x.shape[:-1], robot.dim)
        elif self._applied is not None:
            model, _ = advance(robot, self.config, self._estimate, self._applied.to(x.dtype), self._goals)
            a = (robot.velocities(x) - robot.velocities(model)) / self.config.dt
            step = self.beta * (a - self._disturbance)
            if robot.goal_freeze_radius > 0:  # near its goal the agent may be parked (rest_radius)
                gap = torch.linalg.vector_norm(robot.positions(self._estimate) - self._goals.to(x.dtype), dim=-1)
                step = torch.where((gap < self.rest_radius)[..., None], 0.0, step)
            self._disturbance = self._disturbance + step
        self._applied = None  # used once: a period without a recorded command skips the next update

    def _in_flight(self, x: Tensor) -> list[Tensor]:
        if not self._sent:
            self._sent.extend(hover_commands(self.robot, x, self.act_delay))
        return list(self._sent)


def hover_commands(robot: Robot, x: Tensor, n: int) -> list[Tensor]:
    """The ``n`` commands an agent's actuators start with before its first command (the delay line's contents):
    the nominal control holding its position ``x`` ``(*batch, S)``, each ``(*batch, k)``."""
    return [robot.nominal_control(x, robot.positions(x))] * n
