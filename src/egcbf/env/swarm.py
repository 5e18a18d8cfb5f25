"""The swarm environment: configuration, batched state, reset (sampling), step, safety masks.

The robot is a plug-in (``EnvConfig.robot``, :mod:`egcbf.robots`): the paper's quadrotor (default, 3-D) or the
planar unicycle (2-D: positions, goals, obstacles and LiDAR live in the plane). ``d`` below is ``robot.dim``.

Everything is batched over ``B = num_envs`` environments of ``N = num_agents`` agents and vectorized: no Python
loop over agents or environments. Agent–agent proximity always goes through the sparse cell-list search
(:func:`egcbf.geometry.neighbors.radius_neighbors`), never a dense ``N x N`` matrix.

Conventions (GCBF+, see ``docs/metrics.md``), with ``r`` the agent radius:

* collision (evaluation): agent–agent distance ``< 2 r``, or inside an obstacle inflated by ``r``;
* unsafe (training labels): agent–agent distance ``< 2.5 r``, or inside an obstacle inflated by ``1.5 r``
  (``EnvConfig.unsafe_*_distance``), or, when ``EnvConfig.unsafe_approach_*`` ask for it (the GCBF+ reference's
  labels of its double integrator and Dubins car, ``Robot.reference_labels``), moving toward a near agent or
  LiDAR hit within its collision cone (:func:`approach_unsafe`);
* reached: distance to the own goal ``< 2 r``.

Reset: obstacles (spheres in 3-D, discs in 2-D, centre uniform in ``[0, l]^d``, radius uniform in
``obstacle_radius_range``), then
starts and goals uniform in ``[0, l]^d`` with pairwise distance ``> 4 r`` within each set and outside every
obstacle inflated by ``4 r``. Agents start at rest and level; with ``random_yaw=True`` (default) each gets a
uniformly random yaw, so that training data covers the whole orbit of the rotation part of the symmetry group
(with a fixed yaw every episode would start at the same heading, an arbitrary world direction that the
non-equivariant baselines could overfit to).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ..geometry.neighbors import radius_neighbors
from ..robots import DEFAULT_ROBOT, Robot, make_robot
from .config import EnvConfig, _is_int
from .lidar import LidarScan, RayFaults
from .obstacles import Obstacles, sample_obstacles, sample_rectangle_obstacles
from .sampling import sample_separated_points
from .scenes import cos_sin_degrees, rotate_about_center, scene_boxes, wrap_angle

__all__ = [
    "NonFiniteInputError",
    "NonFiniteStateError",
    "StepInfo",
    "SwarmEnv",
    "SwarmState",
    "advance",
    "approach_unsafe",
    "cast_lidar",
    "safety_masks",
]


class NonFiniteStateError(FloatingPointError):
    """Raised when a step produces NaN or inf (the simulation never continues silently)."""


class NonFiniteInputError(NonFiniteStateError, ValueError):
    """A NaN or inf in what a user passes to the simulator (a state entering it, or a control): both a bad input
    (``ValueError``) and a non-finite simulation (:class:`NonFiniteStateError`)."""


@dataclass
class SwarmState:
    """State of ``B`` environments of ``N`` agents.

    Attributes:
        x: ``(B, N, S)`` agent states of ``robot`` (quadrotor: ``S = 18``, ``[p, R (row-major), v, w]``, see
            ``egcbf.robots.quadrotor.dynamics``; unicycle: ``S = 5``, ``[p, h, v]``).
        goals: ``(B, N, d)`` goal positions (``d = robot.dim``).
        obstacles: spheres (discs in 2-D), ``centers`` ``(B, K, d)``, ``radii`` ``(B, K)``.
        t: steps taken since reset (all environments step together).
        robot: the robot the states belong to (``None``: the quadrotor).
        sensing: ``None`` (a perfect world), or how the agents perceive it under faults
            (:class:`egcbf.faults.Sensing`: ``x`` is then what the agents estimate, and
            :func:`egcbf.env.graph.build_graph`
            takes its LiDAR scan and its messages from it). Only :mod:`egcbf.faults` sets it.
    """

    x: Tensor
    goals: Tensor
    obstacles: Obstacles
    t: int = 0
    robot: Robot | None = None
    sensing: Any = None

    def __post_init__(self) -> None:
        if self.robot is None:
            self.robot = make_robot(DEFAULT_ROBOT)
        s, d = self.robot.state_dim, self.robot.dim
        if self.x.dim() != 3 or self.x.shape[-1] != s:
            raise ValueError(f"{self.robot.name} state x must be (B, N, {s}), got {tuple(self.x.shape)}")
        if self.goals.shape != (*self.x.shape[:2], d):
            raise ValueError(f"goals must be (B, N, {d}) = {(*self.x.shape[:2], d)}, got {tuple(self.goals.shape)}")
        if self.obstacles.num_envs != self.x.shape[0]:
            raise ValueError(f"obstacles are for {self.obstacles.num_envs} environments, x for {self.x.shape[0]}")

    def validate(self, atol: float = 1e-3) -> None:
        """Raise ``ValueError`` naming the first bad entry if an agent state is non-finite or its attitude is not a
        rotation (:func:`egcbf.dynamics.check_state`, tolerance ``atol``), a goal is not finite, an obstacle centre
        is not finite or a radius is not ``> 0``. One synchronization: :meth:`SwarmEnv.step` calls it on states
        that enter the simulator (``t == 0``: a reset or a hand-built state), not on every step."""
        if not bool(torch.isfinite(self.x).all()):
            try:
                self.robot.check_state(self.x, atol)
            except ValueError as err:  # names the first non-finite agent and field
                raise NonFiniteInputError(str(err)) from None
        self.robot.check_state(self.x, atol)
        if not bool(torch.isfinite(self.goals).all()):
            b, i = (~torch.isfinite(self.goals)).any(-1).nonzero()[0].tolist()
            raise ValueError(f"goals hold NaN or inf (first: environment {b}, agent {i})")
        self.obstacles.validate()

    @property
    def num_envs(self) -> int:
        return self.x.shape[0]

    @property
    def num_agents(self) -> int:
        return self.x.shape[1]

    @property
    def positions(self) -> Tensor:
        """``(B, N, d)`` agent positions (a view)."""
        return self.robot.positions(self.x)

    @property
    def attitudes(self) -> Tensor:
        """``(B, N, 3, 3)`` body-to-world rotations (a view; quadrotor only)."""
        return self.robot.attitudes(self.x)

    def to(self, *args, **kwargs) -> SwarmState:
        return SwarmState(
            self.x.to(*args, **kwargs), self.goals.to(*args, **kwargs), self.obstacles.to(*args, **kwargs), self.t,
            self.robot, self.sensing,
        )  # fmt: skip

    def detach(self) -> SwarmState:
        return SwarmState(
            self.x.detach(), self.goals.detach(), self.obstacles.detach(), self.t, self.robot, self.sensing
        )

    def transform(self, g: Tensor) -> SwarmState:
        """The scene moved by ``g`` ``(B, *element)``, one element of the robot's group per environment (SE2xR
        ``(B, 5)`` for the quadrotor, SE2 ``(B, 4)`` for the unicycle): agent states act with ``robot.state_type``,
        goals and obstacle centres move as points, radii are unchanged.

        ``g`` may also be a single element applied to every environment. This is the global transform under
        which graph features in agent frames, the CBF and invariant controls are invariant.
        """
        group = self.robot.group
        group.check(g, "g")
        if g.dim() == 1:
            g = g.expand(self.num_envs, g.shape[-1])
        if g.shape[0] != self.num_envs:
            raise ValueError(f"g has {g.shape[0]} elements for {self.num_envs} environments")
        ge = g[:, None].to(self.x.dtype)
        turn = group.planar_rotation(ge) if self.obstacles.is_rectangles else None
        obs = self.obstacles.moved(group.transform(ge, self.obstacles.centers), turn)
        x = self.robot.state_type.act(ge, self.x)
        return SwarmState(x, group.transform(ge, self.goals), obs, self.t, self.robot)


@dataclass
class StepInfo:
    """Per-step masks of the state reached by a step (all ``(B, N)`` bool unless noted).

    Attributes:
        collision: agent–agent distance ``< 2 r`` or inside an obstacle inflated by ``r``.
        unsafe: agent–agent distance ``< 2.5 r`` or inside an obstacle inflated by ``1.5 r`` (training labels).
        reached: distance to goal ``< 2 r``.
        agent_collision, obstacle_collision: the two parts of ``collision``.
        done: ``(B,)`` the episode has reached ``max_steps``.
        t: the step index of the state (1 after the first step).
        u: ``(B, N, control_dim)`` the control actually applied (after clipping), or ``None`` for masks of a reset
            state.
    """

    collision: Tensor
    unsafe: Tensor
    reached: Tensor
    agent_collision: Tensor
    obstacle_collision: Tensor
    done: Tensor
    t: int
    u: Tensor | None = None


def safety_masks(
    positions: Tensor,
    goals: Tensor,
    obstacles: Obstacles,
    agent_radius: float,
    unsafe_agent: float = 2.5,
    unsafe_obstacle: float = 1.5,
    agent_pairs: tuple[Tensor, Tensor] | None = None,
) -> dict[str, Tensor]:
    """Collision / unsafe / reached masks ``(B, N)`` (module doc conventions); sparse agent–agent search.
    ``unsafe_agent``, ``unsafe_obstacle``: the unsafe distances in agent radii (``EnvConfig.unsafe_*_distance``).
    ``agent_pairs``: two ``(E,)`` index tensors of flattened agents (agent ``i`` of environment ``e`` is ``e * N +
    i``), pairs of one environment among which is every pair closer than the unsafe distance (once or both ways;
    say those a neighbour search of a larger radius found): only they are tested, with the search's own test,
    instead of a search (the same masks).

    Returns a dict with keys ``collision``, ``unsafe``, ``reached``, ``agent_collision``, ``obstacle_collision``,
    ``agent_unsafe``, ``obstacle_unsafe``.
    """
    b, n, d = positions.shape
    r = float(agent_radius)
    p = positions.detach().reshape(b * n, d)
    if agent_pairs is None:  # every pair closer than the unsafe distance, both ways
        batch = torch.arange(b, device=p.device).repeat_interleave(n)
        src, dst = radius_neighbors(p, unsafe_agent * r, batch, sort=False)
    else:
        src, dst = _pairs_closer(p, agent_pairs, unsafe_agent * r)
    close = (p.index_select(0, src) - p.index_select(0, dst)).norm(dim=-1) < 2 * r
    agent_unsafe = torch.zeros(b * n, dtype=torch.bool, device=p.device)
    agent_unsafe[dst] = True
    agent_coll = torch.zeros_like(agent_unsafe)
    agent_coll[dst[close]] = True
    agent_unsafe, agent_coll = agent_unsafe.view(b, n), agent_coll.view(b, n)
    obs_coll = torch.zeros(b * n, dtype=torch.bool, device=p.device)
    obs_unsafe = torch.zeros_like(obs_coll)
    if obstacles.num_obstacles > 0:  # sparse agent-obstacle pairs within 1.5 r of a surface
        bi, ni, ki = obstacles.near_pairs(positions.detach(), unsafe_obstacle * r)
        sd = obstacles.pair_distance(positions.detach()[bi, ni], bi, ki)
        flat = bi * n + ni
        obs_unsafe[flat] = True
        obs_coll[flat[sd < r]] = True
    obs_coll, obs_unsafe = obs_coll.view(b, n), obs_unsafe.view(b, n)
    reached = (positions.detach() - goals.detach().to(p.dtype)).norm(dim=-1) < 2 * r
    return {
        "collision": agent_coll | obs_coll,
        "unsafe": agent_unsafe | obs_unsafe,
        "reached": reached,
        "agent_collision": agent_coll,
        "obstacle_collision": obs_coll,
        "agent_unsafe": agent_unsafe,
        "obstacle_unsafe": obs_unsafe,
    }


def _pairs_closer(p: Tensor, pairs: tuple[Tensor, Tensor], radius: float) -> tuple[Tensor, Tensor]:
    """``src, dst``: both ways, the pairs among ``pairs`` (``(a, b)`` indices into ``p`` ``(M, d)``) closer than
    ``radius``, tested as :func:`~egcbf.geometry.neighbors.radius_neighbors` tests its candidates."""
    a, b = pairs
    keep = ((p.index_select(0, b) - p.index_select(0, a)).square().sum(-1) < float(radius) ** 2).nonzero().squeeze(1)
    a, b = a.index_select(0, keep), b.index_select(0, keep)
    return torch.cat((a, b)), torch.cat((b, a))


def approach_unsafe(
    positions: Tensor,
    direction: Tensor,
    agent_radius: float,
    agent_distance: float,
    scan: LidarScan | None = None,
    obstacle_distance: float = 0.0,
) -> Tensor:
    """GCBF+'s "unsafe direction" labels ``(B, N)`` bool (its double integrator's and Dubins car's unsafe mask).

    Agent ``i`` is unsafe when it moves toward a near obstacle to collision: another agent ``j`` at distance
    ``d < agent_distance * r`` with the angle between ``direction_i`` and ``p_j - p_i`` below ``asin(2 r / d)``
    (the cone of directions in which the two discs would touch), or a kept LiDAR hit of ``scan`` at ``d <
    obstacle_distance * r`` with the angle below ``asin(r / d)``. A distance of 0 turns that part off. Pairs closer
    than ``2 r`` (hits closer than ``r``) count as in the cone; they are collisions anyway.

    Args:
        positions: ``(B, N, d)``; direction: ``(B, N, d)`` (:meth:`Robot.motion_direction`: about unit, or about
            zero for an agent at rest, which is then never in a cone).
        scan: the LiDAR of the same state (needed when ``obstacle_distance > 0``).
    """
    b, n, d = positions.shape
    r = float(agent_radius)
    p = positions.detach()
    heading = direction.detach().to(p.dtype)
    out = torch.zeros(b * n, dtype=torch.bool, device=p.device)
    if agent_distance > 0 and n > 1:
        flat = p.reshape(b * n, d)
        batch = torch.arange(b, device=p.device).repeat_interleave(n)
        src, dst = radius_neighbors(flat, agent_distance * r, batch, sort=False)
        offset = flat.index_select(0, src) - flat.index_select(0, dst)
        out[dst[_in_cone(offset, heading.reshape(b * n, d).index_select(0, dst), 2 * r)]] = True
    out = out.view(b, n)
    if obstacle_distance > 0 and scan is not None:
        offset = scan.points.to(p.dtype) - p[..., None, :]  # (B, N, H, d)
        near = scan.valid & (scan.distance < obstacle_distance * r)
        out = out | (near & _in_cone(offset, heading[..., None, :].expand_as(offset), r)).any(-1)
    return out


def _in_cone(offset: Tensor, direction: Tensor, reach: float) -> Tensor:
    """Whether ``direction`` points within ``asin(reach / |offset|)`` of ``offset`` (GCBF+'s test, with its
    ``1e-4`` in the normalization): ``cos(angle) > sqrt(1 - (reach / |offset|)^2)``. ``(...,)`` bool."""
    dist = torch.linalg.vector_norm(offset, dim=-1)
    cos_angle = (offset * direction).sum(-1) / (dist + 1e-4)
    ratio = (reach / dist.clamp_min(1e-12)).clamp(max=1.0)
    return (dist <= reach) | (cos_angle > torch.sqrt(1 - ratio**2))


def advance(
    robot: Robot, config: EnvConfig, x: Tensor, u: Tensor, goals: Tensor, setpoint: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """One control period of the dynamics, as :meth:`SwarmEnv.step` integrates it: ``u`` ``(B, N, k)`` clipped to
    the actuator box (``config.clip_control``) and held, the robot's integrator, agents at their goals parked
    (``robot.goal_freeze_radius``). Returns the next states ``(B, N, S)`` and the control applied. No checks (the
    environment's step makes them); also what :mod:`egcbf.faults` predicts an agent's state with.

    ``setpoint`` (a robot that :attr:`~egcbf.robots.base.Robot.flies_setpoints`, the quadrotor): a world
    acceleration command ``(B, N, d)`` (m/s^2) flown as a full-state setpoint instead of ``u`` by the robot's
    firmware-like tracker (:meth:`~egcbf.robots.base.Robot.fly_setpoint`; the quadrotor's:
    :func:`egcbf.robots.quadrotor.setpoint.track_setpoint`); ``u`` is then ignored and the control returned is the
    tracker's mean over the period.
    """
    if setpoint is not None:
        x_next, u = robot.fly_setpoint(x, setpoint, config.dt, config.integrator, config.clip_control)
    else:
        if config.clip_control:
            u = robot.clip_control(u)
        x_next = robot.step(x, u, config.dt, config.substeps, config.integrator)
    if robot.goal_freeze_radius > 0:  # agents at their goals park (GCBF+'s Dubins car; Robot.parked)
        gap = torch.linalg.vector_norm(robot.positions(x) - goals.to(x_next.dtype), dim=-1)
        x_next = torch.where((gap < robot.goal_freeze_radius)[..., None], robot.parked(x), x_next)
    return x_next, u


def cast_lidar(
    config: EnvConfig, positions: Tensor, heading: Tensor, obstacles: Obstacles, ray_faults: RayFaults | None = None
) -> LidarScan:
    """:meth:`EnvConfig.scan <egcbf.env.config.EnvConfig.scan>` of ``config``: the LiDAR scan of the agents at
    ``positions`` with headings ``heading`` (``Robot.heading``: the body x axes of quadrotors, whose horizontal part
    turns the pattern; the unit headings of planar robots), both ``(B, N, d)``, among ``obstacles`` (``B``
    environments); ``ray_faults``: the sensor's faults on single rays (:func:`~egcbf.env.lidar.lidar_scan`).
    """
    return config.scan(positions, heading, obstacles, ray_faults)


class SwarmEnv:
    """Batched swarm environment of the robot ``config.make_robot()``.

    ``env = SwarmEnv(EnvConfig(num_agents=8), device="cpu", dtype=torch.float32)``;
    ``state = env.reset(seed)``; ``state, info = env.step(state, u)`` with ``u`` ``(B, N, control_dim)``
    (quadrotor: 4, body torque and thrust).
    """

    def __init__(self, config: EnvConfig, device: torch.device | str | None = None, dtype: torch.dtype | None = None):
        if not isinstance(config, EnvConfig):
            raise TypeError(f"SwarmEnv needs an EnvConfig, got {type(config).__name__}")
        self.config = config
        self.robot = config.make_robot()
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype or torch.get_default_dtype()
        if not self.dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating dtype, got {self.dtype}")

    def __repr__(self) -> str:
        c = self.config
        return (
            f"SwarmEnv(num_envs={c.num_envs}, num_agents={c.num_agents}, area_size={c.area_size:g}, "
            f"num_obstacles={c.num_obstacles}, device={self.device}, dtype={self.dtype})"
        )

    # ---------------------------------------------------------------------------------------------- reset
    def reset(self, seed: int) -> SwarmState:
        """Sample ``B`` new episodes reproducibly from ``seed`` (the same seed gives the same state on any device)."""
        if not _is_int(seed):
            raise TypeError(f"seed must be an int, got {type(seed).__name__}")
        c = self.config
        gen = torch.Generator().manual_seed(seed)
        f64 = torch.float64
        d = self.robot.dim
        if c.obstacle_shape == "rectangle":
            obstacles = sample_rectangle_obstacles(
                c.num_envs, c.num_obstacles, c.area_size, c.obstacle_side_range, generator=gen, dtype=f64
            )
        else:
            obstacles = sample_obstacles(
                c.num_envs, c.num_obstacles, c.area_size, c.obstacle_radius_range, generator=gen, dtype=f64, dim=d
            )
        boxes = scene_boxes(c.scene, c.area_size, d)
        sampling = dict(generator=gen, dtype=f64, max_rounds=c.max_sampling_rounds, dim=d)
        args = (c.area_size, c.start_separation * c.agent_radius, obstacles, c.obstacle_clearance * c.agent_radius)
        if c.max_travel is not None:  # starts first, then each goal within max_travel of its own start
            starts = sample_separated_points(c.num_envs, 1, c.num_agents, *args, **sampling)
            goals = sample_separated_points(c.num_envs, 1, c.num_agents, *args, anchors=starts,
                                            max_offset=c.max_travel, **sampling)  # fmt: skip
            pts = torch.cat((starts, goals), 1)
        elif boxes is None:  # starts and goals drawn together (the generator stream of every earlier release)
            pts = sample_separated_points(c.num_envs, 2, c.num_agents, *args, **sampling)
        else:
            sets = [sample_separated_points(c.num_envs, 1, c.num_agents, *args, box=b, **sampling) for b in boxes]
            pts = torch.cat(sets, 1)
        if c.random_yaw:
            yaw = (torch.rand(c.num_envs, c.num_agents, generator=gen, dtype=f64) * 2 - 1) * math.pi
        else:
            yaw = torch.zeros(c.num_envs, c.num_agents, dtype=f64)
        if c.scene_yaw != 0:
            pts = rotate_about_center(pts, c.scene_yaw, c.area_size)
            turn = torch.tensor(cos_sin_degrees(c.scene_yaw), dtype=f64).expand(c.num_envs, 1, 2)
            obstacles = obstacles.moved(rotate_about_center(obstacles.centers, c.scene_yaw, c.area_size), turn)
            yaw = wrap_angle(yaw + math.radians(c.scene_yaw))
        x = self.robot.rest_state(pts[:, 0], yaw)
        state = SwarmState(x, pts[:, 1], obstacles, 0, self.robot)
        return state.to(device=self.device, dtype=self.dtype)

    # ----------------------------------------------------------------------------------------------- step
    def step(self, state: SwarmState, u: Tensor, setpoint: Tensor | None = None) -> tuple[SwarmState, StepInfo]:
        """:meth:`transition`, then the masks of the state it reaches (:meth:`info`, with the control applied)."""
        new, u = self.transition(state, u, setpoint)
        return new, self.info(new, u=u)

    def transition(self, state: SwarmState, u: Tensor, setpoint: Tensor | None = None) -> tuple[SwarmState, Tensor]:
        """The next state and the control applied ``(B, N, control_dim)``, without the masks (:meth:`step` adds
        them): integrate every agent for one control period with ``u`` ``(B, N, 4)`` held constant; or, with
        ``setpoint`` (a robot that ``flies_setpoints``: the quadrotor), fly that world acceleration command
        ``(B, N, d)`` through its firmware-like setpoint tracker instead (:func:`advance`; ``u`` is then checked but
        not applied).

        A state that enters the simulator (``state.t == 0``: from :meth:`reset` or built by hand) is validated
        first (:meth:`SwarmState.validate`: finite states, rotation attitudes, finite goals and obstacle centres,
        positive radii); later states come from the simulator itself.

        Raises:
            ValueError: ``u`` has the wrong shape or holds NaN or inf; or the entering state is invalid.
            NonFiniteStateError: the new state holds NaN or inf (one ``isfinite().all()`` per step, which also
                covers ``u``).
        """
        c = self.config
        expected = (*state.x.shape[:2], self.robot.control_dim)
        if not isinstance(u, Tensor) or tuple(u.shape) != expected:
            shape = tuple(u.shape) if isinstance(u, Tensor) else type(u).__name__
            k = self.robot.control_dim
            raise ValueError(f"control u must be {expected} (num_envs, num_agents, {k}), got {shape}")
        if state.t == 0:
            state.validate()
        u_in = u.to(state.x.dtype)
        x, u = advance(self.robot, c, state.x, u_in, state.goals, setpoint)
        if not bool(torch.isfinite(x).all() & torch.isfinite(u_in).all()):
            if not bool(torch.isfinite(u_in).all()):
                bad = (~torch.isfinite(u_in)).any(-1).nonzero()[0].tolist()
                raise NonFiniteInputError(
                    f"control u holds NaN or inf at step {state.t + 1} (first (env, agent) = {tuple(bad)}: "
                    f"{u_in[tuple(bad)].tolist()}); the controller produced a non-finite command"
                )
            bad = (~torch.isfinite(x)).any(-1).nonzero()
            raise NonFiniteStateError(
                f"non-finite state after step {state.t + 1}: {bad.shape[0]} agent(s), first (env, agent) = "
                f"{tuple(bad[0].tolist())}; the control there was {u[tuple(bad[0].tolist())].tolist()}"
            )
        return SwarmState(x, state.goals, state.obstacles, state.t + 1, state.robot), u

    # ---------------------------------------------------------------------------------------------- masks
    def info(
        self, state: SwarmState, u: Tensor | None = None, agent_pairs: tuple[Tensor, Tensor] | None = None
    ) -> StepInfo:
        """The masks of ``state`` (also usable on a reset state); ``agent_pairs``: candidate agent pairs that hold
        every pair closer than the unsafe distance, tested instead of a search (:func:`safety_masks`)."""
        c = self.config
        m = safety_masks(state.positions, state.goals, state.obstacles, c.agent_radius, c.unsafe_agent_distance,
                         c.unsafe_obstacle_distance, agent_pairs)  # fmt: skip
        done = torch.full((state.num_envs,), state.t >= self.config.max_steps, dtype=torch.bool, device=state.x.device)
        return StepInfo(
            collision=m["collision"],
            unsafe=m["unsafe"],
            reached=m["reached"],
            agent_collision=m["agent_collision"],
            obstacle_collision=m["obstacle_collision"],
            done=done,
            t=state.t,
            u=u,
        )

    def approach_unsafe(self, state: SwarmState, scan: LidarScan | None = None) -> Tensor:
        """The approach part of the training labels ``(B, N)`` (``EnvConfig.unsafe_approach_*``; all False when
        off): :func:`approach_unsafe` with the robot's motion direction and ``scan`` (cast here when needed)."""
        c = self.config
        if c.unsafe_approach_agent_distance == 0 and c.unsafe_approach_obstacle_distance == 0:
            return torch.zeros(state.num_envs, state.num_agents, dtype=torch.bool, device=state.x.device)
        if scan is None and c.unsafe_approach_obstacle_distance > 0 and state.obstacles.num_obstacles > 0:
            scan = self.lidar(state)
        return approach_unsafe(state.positions, self.robot.motion_direction(state.x), c.agent_radius,
                               c.unsafe_approach_agent_distance, scan, c.unsafe_approach_obstacle_distance)  # fmt: skip

    # ---------------------------------------------------------------------------------------- perception
    def lidar(self, state: SwarmState) -> LidarScan:
        """LiDAR scan of every agent (rays in the agent's yaw frame; see ``egcbf.env.lidar``)."""
        return cast_lidar(self.config, state.positions, self.robot.heading(state.x), state.obstacles)
