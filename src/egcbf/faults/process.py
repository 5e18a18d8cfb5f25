"""The faults of one batch of episodes, step by step: what the controller sees, what the rotors do, what the wind
pushes (:class:`FaultProcess`).

The evaluation loop (:func:`egcbf.evaluate.episodes.run_episodes`) runs, each step::

    seen = faults.observe(state)            # the agents' estimates, with a Sensing for scans and messages
    u, info = controller(seen, env_config)  # the controller is unchanged
    u = faults.actuate(u, state)            # disturbance rejection, non-cooperative agents, actuation delay,
                                            # gain and bias errors
    state, info = env.step(state, u)        # the true dynamics and the true safety masks
    state = faults.push(state)              # wind and gusts (before the masks of the next step are read)

Every random number is a counter-based draw addressed by (episode seed, stream, step, agent, ...)
(:mod:`egcbf.faults.draws`), so results do not depend on batching. ``rotation`` (``(d, d)``) rotates every
world-frame draw and the wind: a scene rotated by ``R`` with ``rotation = R`` gets the rotated faults, which is how
the tests check that the closed loop under faults stays equivariant (isotropic noise has the same law rotated).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Sequence

import torch
from torch import Tensor

from ..env.config import EnvConfig
from ..env.swarm import SwarmState
from ..robots import Robot
from . import draws
from .onboard import Onboard, hover_commands
from .sensing import STREAMS, Sensing
from .spec import FaultConfig

__all__ = ["FaultProcess", "for_robot", "noncooperative_count", "noncooperative_mask", "unsupported_faults"]


def unsupported_faults(faults: FaultConfig, robot) -> dict[str, str]:
    """``{field: why}`` for every fault of ``faults`` that ``robot`` (a :class:`~egcbf.robots.base.Robot`) cannot
    take: a wind of another dimension, a velocity fault on a kinematic robot (its velocity is its command, so the
    fault would silently do nothing), an actuator group's gain or bias on a robot without that group. Empty: all of
    them act. :class:`FaultProcess` refuses any; ``egcbf eval --faults default`` leaves out those that came from
    ``default`` and says so (:func:`for_robot`)."""
    why = {}
    if faults.wind and len(faults.wind) != robot.dim:
        why["wind"] = f"wind needs {robot.dim} numbers for the {robot.name}, got {faults.wind}"
    if robot.kinematic:
        for name in ("vel_noise", "msg_predict", "gust") + (("wind",) if faults.wind else ()):
            if (getattr(faults, name) if name != "wind" else faults.wind) and name not in why:
                why[name] = (f"{name} acts on a velocity the {robot.name} does not have (its velocity is its "
                             "command, not its state): it would silently do nothing")  # fmt: skip
    groups = robot.actuator_groups
    for name, group in (("thrust_gain", "thrust"), ("torque_gain", "torque"), ("torque_bias", "torque")):
        if getattr(faults, name) > 0 and group not in groups:
            why[name] = (f"{name} needs the robot's {group!r} channels; the {robot.name} has "
                         f"{sorted(groups) or 'no named actuator groups'} (use gain= for every channel)")  # fmt: skip
    return why


def for_robot(faults: FaultConfig, robot, given: frozenset[str]) -> tuple[FaultConfig, dict[str, str]]:
    """``faults`` as ``robot`` can take them: the faults it cannot take (:func:`unsupported_faults`) that the spec
    did not set itself (``given``, :func:`egcbf.faults.spec.given_fields`: they came from ``default``) are reset to
    none; returns the faults and ``{left-out field: why}``. Raises ``ValueError`` for one the spec set itself."""
    why = unsupported_faults(faults, robot)
    own = [n for n in why if n in given]
    if own:
        raise ValueError(f"faults: {why[own[0]]}")
    if not why:
        return faults, {}
    zero = FaultConfig()
    return dataclasses.replace(faults, **{n: getattr(zero, n) for n in why}), why


def noncooperative_count(faults: FaultConfig, num_agents: int) -> int:
    """How many of ``num_agents`` agents ``faults.noncoop`` makes non-cooperative: ``noncoop * N`` rounded half up
    (a small fraction of a small swarm may round to none: ``egcbf eval`` refuses that for a fraction it was given,
    and says it for the default's). Raises ``ValueError`` when it leaves no cooperative agent (nothing to
    measure)."""
    k = math.floor(faults.noncoop * num_agents + 0.5)
    if num_agents > 0 and k >= num_agents:
        raise ValueError(f"faults: noncoop={faults.noncoop:g} of {num_agents} agents leaves no cooperative agent "
                         f"to measure; use a smaller fraction")  # fmt: skip
    return k


def noncooperative_mask(faults: FaultConfig, seeds: Tensor, num_agents: int) -> Tensor:
    """``(B, N)`` bool: the ``noncoop * N`` agents (rounded half up) of each episode that ignore their controller
    (the ones with the smallest draws of their episode; a pure function of the episode seed). Raises
    ``ValueError`` when that leaves no cooperative agent (there would be nothing to measure)."""
    b = seeds.shape[0]
    k = noncooperative_count(faults, num_agents)
    mask = torch.zeros(b, num_agents, dtype=torch.bool, device=seeds.device)
    if k > 0:
        u = draws.uniform(STREAMS["noncoop"], seeds.view(b, 1), torch.arange(num_agents, device=seeds.device))
        mask.scatter_(1, u.argsort(dim=1)[:, :k], True)
    return mask


class FaultProcess:
    """The faults of ``len(seeds)`` episodes simulated together (module doc).

    Args:
        faults: the fault levels.
        env_config: the environment (``dt``, ``num_agents``).
        robot: the agents' robot.
        seeds: the episode seed of each environment (:func:`egcbf.evaluate.episodes.episode_seed`).
        rotation: ``None``, or a ``(d, d)`` rotation applied to every world-frame draw and to the wind.
    """

    def __init__(
        self,
        faults: FaultConfig,
        env_config: EnvConfig,
        robot: Robot,
        seeds: Sequence[int],
        *,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        rotation: Tensor | None = None,
    ):
        why = unsupported_faults(faults, robot)
        if why:
            raise ValueError(f"faults: {next(iter(why.values()))}")
        self.faults, self.config, self.robot = faults, env_config, robot
        self.device, self.dtype = torch.device(device), dtype
        self.seeds = torch.as_tensor([int(s) for s in seeds], dtype=torch.int64, device=self.device)
        b, n, d = len(seeds), env_config.num_agents, robot.dim
        self.rotation = None if rotation is None else torch.as_tensor(rotation, dtype=torch.float64, device=device)
        self._agents = torch.arange(n, device=self.device).view(1, n, 1)
        self._axes = torch.arange(d, device=self.device).view(1, 1, d)
        self.noncoop = noncooperative_mask(faults, self.seeds, n)
        self.gains, self.bias = self._actuator_errors(b, n)
        self._seen: deque[Tensor] = deque(maxlen=faults.msg_delay + faults.msg_hold + 2)  # newest first
        self._errors: dict[str, tuple[int, Tensor]] = {}  # stream -> (step, estimation error): noise_tau only
        self._commands: deque[Tensor] = deque()
        self._starts: Tensor | None = None
        # the agents' own handling of their actuation delay and of disturbances (act_predict, dist_obs)
        self.onboard: Onboard | None = None
        if (faults.act_predict and faults.act_delay > 0) or faults.dist_obs:
            try:
                # an agent within 4 spreads of its estimate's distance error of parking may be parked
                rest = robot.goal_freeze_radius * 2.0 + 4.0 * math.sqrt(robot.dim) * faults.pos_noise
                self.onboard = Onboard(robot, env_config, act_delay=faults.act_delay,
                                       predict=bool(faults.act_predict), observe_disturbance=bool(faults.dist_obs),
                                       rest_radius=rest)  # fmt: skip
            except ValueError as err:
                raise ValueError(f"faults: dist_obs: {err}") from None
        self._gust = self._world(faults.gust * draws.normal(STREAMS["gust"], self.seeds.view(b, 1), -1,
                                                            self._axes[0]))  # fmt: skip
        wind = torch.zeros(d, dtype=torch.float64, device=self.device)
        if faults.wind:
            wind = self._world(torch.tensor(faults.wind, dtype=torch.float64, device=self.device))
        self._wind = wind

    # ---------------------------------------------------------------------------------------------- helpers
    def _world(self, v: Tensor) -> Tensor:
        """A world-frame draw, rotated by ``rotation`` when one is set."""
        return v if self.rotation is None else v @ self.rotation.T

    def _actuator_errors(self, b: int, n: int) -> tuple[Tensor, Tensor]:
        f, robot = self.faults, self.robot
        k = robot.control_dim
        half = torch.full((k,), f.gain, dtype=torch.float64)
        for name, group in (("thrust_gain", "thrust"), ("torque_gain", "torque")):
            if getattr(f, name) > 0:
                half[list(robot.actuator_groups[group])] = getattr(f, name)
        channels = torch.arange(k, device=self.device).view(1, 1, k)
        seeds = self.seeds.view(b, 1, 1)
        u = draws.uniform(STREAMS["gain"], seeds, self._agents, channels)
        gains = 1.0 + half.to(self.device) * (2.0 * u - 1.0)
        bias = torch.zeros(b, n, k, dtype=torch.float64, device=self.device)
        if f.torque_bias > 0:
            idx = list(robot.actuator_groups["torque"])
            v = draws.uniform(STREAMS["bias"], seeds, self._agents, channels)
            bias[..., idx] = (f.torque_bias * (2.0 * v - 1.0))[..., idx]
        return gains, bias

    def _noise(self, stream: str, std: float, t: int) -> Tensor:
        """The estimation error of step ``t`` ``(B, N, d)`` (world frame): ``std`` times the draws of the step, or
        with ``noise_tau`` the Gauss-Markov recursion over them (restarted from its stationary law when the steps
        are not consecutive, e.g. at an episode's first step)."""
        b = self.seeds.shape[0]
        z = self._world(std * draws.normal(STREAMS[stream], self.seeds.view(b, 1, 1), t, self._agents, self._axes))
        tau = self.faults.noise_tau
        if tau <= 0:
            return z
        last = self._errors.get(stream)
        if last is not None and last[0] == t - 1:
            rho = math.exp(-self.config.dt / tau)
            z = rho * last[1] + math.sqrt(1.0 - rho * rho) * z
        self._errors[stream] = (t, z)
        return z

    # -------------------------------------------------------------------------------------------------- steps
    def observe(self, state: SwarmState) -> SwarmState:
        """What the agents perceive of ``state``: their noisy estimates (broadcast to their neighbours as well),
        with a :class:`~egcbf.faults.sensing.Sensing` for LiDAR and messages when such faults are on or the agents'
        state is not the true one (position noise, prediction over an actuation delay: the LiDAR still measures
        from the true pose)."""
        f, robot = self.faults, self.robot
        if self._starts is None:
            self._starts = robot.positions(state.x).clone()
        estimate = state.x
        if f.pos_noise > 0 or f.vel_noise > 0:
            dp = self._noise("pos", f.pos_noise, state.t)
            dv = self._noise("vel", f.vel_noise, state.t) if f.vel_noise > 0 else None
            estimate = robot.perturbed(state.x, dp, dv)
        seen = estimate
        if self.onboard is not None:  # the agents' own prediction and disturbance estimate (also broadcast)
            seen = self.onboard.estimate(estimate, state.goals)
        self._seen.appendleft(seen)
        sensing = None
        # the LiDAR measures from the true pose whenever the agents' state differs from it (noise, prediction)
        if f.edge_faults or f.pos_noise > 0 or seen is not estimate:
            sent = self._seen[min(f.msg_delay, len(self._seen) - 1)]
            sensing = Sensing(f, robot, self.seeds, state.t, state.x, seen, sent, state.obstacles,
                              tuple(self._seen), self.config.dt, x_placed=estimate)  # fmt: skip
        return SwarmState(seen, state.goals, state.obstacles, state.t, state.robot, sensing)

    def actuate(self, u: Tensor, state: SwarmState) -> Tensor:
        """The command the actuators apply at ``state`` (true) for the controller's ``u`` ``(B, N, control_dim)``:
        the agents' disturbance rejection (``dist_obs``, for the state they commanded for), non-cooperative agents'
        own commands, then the actuation delay, then the gain and bias errors."""
        f, robot = self.faults, self.robot
        if self.onboard is not None:
            u = self.onboard.reject(u)
        if f.noncoop > 0 and bool(self.noncoop.any()):
            target = self._starts if f.noncoop_mode == "hover" else state.goals
            x = state.x  # a non-cooperative agent's autopilot knows its true state (and predicts like the others)
            if self.onboard is not None and self.onboard.predict and f.act_delay > 0:
                x = self.onboard.predicted(x, state.goals)
            own = robot.nominal_control(x, target.to(x.dtype)).to(u.dtype)
            u = torch.where(self.noncoop[..., None], own, u)
        if f.act_delay > 0 and not self._commands:  # the actuators' delay line starts from hover commands: the
            if self.onboard is not None:  # ones the agents take it to hold, else at the true states
                start = [c.to(u.dtype) for c in self.onboard.in_flight()]
            else:
                start = [c.to(u.dtype) for c in hover_commands(robot, state.x, f.act_delay)]
            self._commands.extend(start)
        if self.onboard is not None:
            self.onboard.record(u)  # what each agent sent (a non-cooperative one its own command)
        if f.act_delay > 0:
            self._commands.append(u)
            u = self._commands.popleft()
        if f.gain > 0 or f.thrust_gain > 0 or f.torque_gain > 0 or f.torque_bias > 0:
            u = u * self.gains.to(u.dtype) + self.bias.to(u.dtype)
        return u

    @property
    def disturbance(self) -> Tensor | None:
        """``dist_obs``: the agents' current estimate ``(B, N, dim)`` of the acceleration acting on them beyond their
        model (world frame, m/s^2); ``None`` before the first step or without the observer."""
        return None if self.onboard is None else self.onboard.disturbance

    @property
    def pushes(self) -> bool:
        """Whether wind or gusts push the agents (:meth:`push` then changes the state)."""
        return bool(self.faults.wind) or self.faults.gust > 0

    def push(self, state: SwarmState) -> SwarmState:
        """``state`` after the wind and gust acceleration of the step just taken (operator splitting: the
        velocity changes by ``a dt`` and the position by ``a dt^2 / 2``)."""
        f = self.faults
        if not self.pushes:
            return state
        dt = self.config.dt
        a = self._wind.view(1, 1, -1) + self._gust.view(self._gust.shape[0], 1, -1)
        x = self.robot.perturbed(state.x, 0.5 * a * dt * dt, a * dt)
        if f.gust > 0:  # Ornstein-Uhlenbeck, exact discretization
            rho = math.exp(-dt / f.gust_tau)
            z = draws.normal(STREAMS["gust"], self.seeds.view(-1, 1), state.t, self._axes[0])
            self._gust = rho * self._gust + f.gust * math.sqrt(1 - rho * rho) * self._world(z)
        return SwarmState(x, state.goals, state.obstacles, state.t, state.robot)
