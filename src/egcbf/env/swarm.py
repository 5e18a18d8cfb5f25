"""The swarm environment: configuration, batched state, reset (sampling), step, safety masks.

The robot is a plug-in (``EnvConfig.robot``, :mod:`egcbf.robots`): the paper's quadrotor (default, 3-D) or the
planar unicycle (2-D: positions, goals, obstacles and LiDAR live in the plane). ``d`` below is ``robot.dim``.

Everything is batched over ``B = num_envs`` environments of ``N = num_agents`` agents and vectorized: no Python
loop over agents or environments. Agent–agent proximity always goes through the sparse cell-list search
(:func:`egcbf.neighbors.radius_neighbors`), never a dense ``N x N`` matrix.

Conventions (GCBF+, see ``docs/metrics.md``), with ``r`` the agent radius:

* collision (evaluation): agent–agent distance ``< 2 r``, or inside an obstacle inflated by ``r``;
* unsafe (training labels): agent–agent distance ``< 2.5 r``, or inside an obstacle inflated by ``1.5 r``;
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

import functools
import math
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import Tensor

from ..dynamics import quadrotor as dyn
from ..neighbors import radius_neighbors
from ..robots import Robot, make_robot
from .lidar import LidarScan, lidar_scan
from .obstacles import Obstacles, sample_obstacles
from .sampling import sample_separated_points

__all__ = [
    "EnvConfig",
    "NonFiniteInputError",
    "NonFiniteStateError",
    "StepInfo",
    "SwarmEnv",
    "SwarmState",
    "cast_lidar",
    "safety_masks",
]


class NonFiniteStateError(FloatingPointError):
    """Raised when a step produces NaN or inf (the simulation never continues silently)."""


class NonFiniteInputError(NonFiniteStateError, ValueError):
    """A NaN or inf in what a user passes to the simulator (a state entering it, or a control): both a bad input
    (``ValueError``) and a non-finite simulation (:class:`NonFiniteStateError`)."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class EnvConfig:
    """Configuration of a batch of swarm environments (frozen; change it with ``dataclasses.replace``).

    Defaults are the paper's training setting (8 agents, ``l = 2``, 5 obstacles) with GCBF+'s CrazyFlie
    conventions; :meth:`for_robot` starts from another robot's defaults. Lengths in metres, times in seconds.

    Attributes:
        num_agents: ``N >= 1`` agents per environment.
        area_size: side ``l > 0`` of the arena ``[0, l]^3`` in which starts, goals and obstacle centres are drawn.
        num_obstacles: ``K >= 0`` sphere obstacles per environment.
        obstacle_radius_range: ``(lo, hi)``, ``0 < lo <= hi``: sphere radii are uniform in it.
        agent_radius: ``r > 0``, the collision radius of an agent. Authoritative: ``params.radius`` is set to it.
        comm_radius: ``R-hat > 0``, the agent–agent edge radius (and goal-edge clipping radius).
        lidar_range: ``R``, the LiDAR ray length, ``0 < R <= comm_radius``; ``None`` means ``comm_radius`` (GCBF+).
        n_rays: LiDAR azimuths (``n_rays // 2`` elevations, plus up and down), even, ``>= 2``.
        lidar_max_hits: hits kept per agent (the closest ones).
        dt: control period (zero-order hold); substeps: integrator sub-steps per period; integrator: "rk4"/"euler".
        max_steps: episode length in steps (``done`` when reached).
        num_envs: ``B >= 1`` environments simulated together.
        random_yaw: start each agent at a uniformly random yaw (else yaw 0).
        clip_control: clip controls to the actuator box (``dynamics.clip_control``) before integrating.
        start_separation, obstacle_clearance: sampling separations in units of ``agent_radius`` (GCBF+: 4 and 4).
        max_sampling_rounds: bound on the rejection-sampling rounds before ``reset`` gives up with ``ValueError``.
        robot: the robot's name (:data:`egcbf.robots.ROBOTS`); ``make_robot()`` builds it.
        params: the robot's parameters (``None``: its defaults; for the quadrotor a ``QuadrotorParams``).
    """

    num_agents: int = 8
    area_size: float = 2.0
    num_obstacles: int = 5
    obstacle_radius_range: tuple[float, float] = (0.05, 0.3)
    agent_radius: float = 0.05
    comm_radius: float = 1.0
    lidar_range: float | None = None
    n_rays: int = 32
    lidar_max_hits: int = 16
    dt: float = dyn.DEFAULT_DT
    substeps: int = dyn.DEFAULT_SUBSTEPS
    integrator: str = dyn.DEFAULT_METHOD
    max_steps: int = dyn.DEFAULT_MAX_STEPS
    num_envs: int = 1
    random_yaw: bool = True
    clip_control: bool = True
    start_separation: float = 4.0
    obstacle_clearance: float = 4.0
    max_sampling_rounds: int = 200
    params: Any = None
    robot: str = "quadrotor"

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ValueError(f"EnvConfig.{name} must be {what}, got {getattr(self, name)!r}")

        need(_is_int(self.num_agents) and self.num_agents >= 1, "num_agents", "an integer >= 1")
        need(_is_num(self.area_size) and self.area_size > 0, "area_size", "a finite number > 0")
        need(_is_int(self.num_obstacles) and self.num_obstacles >= 0, "num_obstacles", "an integer >= 0")
        rr = self.obstacle_radius_range
        need(
            isinstance(rr, (tuple, list)) and len(rr) == 2 and all(_is_num(v) for v in rr) and 0 < rr[0] <= rr[1],
            "obstacle_radius_range",
            "a pair (lo, hi) of finite numbers with 0 < lo <= hi",
        )
        object.__setattr__(self, "obstacle_radius_range", (float(rr[0]), float(rr[1])))
        need(_is_num(self.agent_radius) and self.agent_radius > 0, "agent_radius", "a finite number > 0")
        need(_is_num(self.comm_radius) and self.comm_radius > 0, "comm_radius", "a finite number > 0")
        if self.lidar_range is not None:
            need(
                _is_num(self.lidar_range) and 0 < self.lidar_range <= self.comm_radius,
                "lidar_range",
                f"None or a number in (0, comm_radius = {self.comm_radius:g}] (the sensing range R <= comm range)",
            )
        need(_is_int(self.n_rays) and self.n_rays >= 2 and self.n_rays % 2 == 0, "n_rays", "an even integer >= 2")
        need(_is_int(self.lidar_max_hits) and self.lidar_max_hits >= 1, "lidar_max_hits", "an integer >= 1")
        need(_is_num(self.dt) and self.dt > 0, "dt", "a finite number > 0")
        need(_is_int(self.substeps) and self.substeps >= 1, "substeps", "an integer >= 1")
        need(self.integrator in ("rk4", "euler"), "integrator", "'rk4' or 'euler'")
        need(_is_int(self.max_steps) and self.max_steps >= 1, "max_steps", "an integer >= 1")
        need(_is_int(self.num_envs) and self.num_envs >= 1, "num_envs", "an integer >= 1")
        need(_is_num(self.start_separation) and self.start_separation >= 0, "start_separation", "a number >= 0")
        need(_is_num(self.obstacle_clearance) and self.obstacle_clearance >= 0, "obstacle_clearance", "a number >= 0")
        need(
            _is_int(self.max_sampling_rounds) and self.max_sampling_rounds >= 1,
            "max_sampling_rounds",
            "an integer >= 1",
        )
        try:
            robot = make_robot(self.robot, self.params)
        except (ValueError, TypeError) as err:
            raise ValueError(f"EnvConfig.robot / params: {err}") from None
        if self.params is None:
            object.__setattr__(self, "params", robot.params)
        need(type(self.params) is type(robot.params), "params", f"a {type(robot.params).__name__}")
        if self.params.radius != self.agent_radius:
            object.__setattr__(self, "params", replace(self.params, radius=float(self.agent_radius)))

    @classmethod
    def for_robot(cls, robot: str, **changes) -> EnvConfig:
        """The config of ``robot`` with its own defaults (``Robot.env_defaults``), then ``changes``."""
        kw = dict(make_robot(robot).env_defaults)
        kw.update(changes)
        return cls(robot=robot, **kw)

    def make_robot(self) -> Robot:
        """The :class:`egcbf.robots.Robot` of this config (cached: equal configs share one)."""
        return _robot(self.robot, self.params)

    @property
    def dim(self) -> int:
        """The spatial dimension ``d`` of the robot's world (2 or 3)."""
        return self.make_robot().dim

    @property
    def resolved_lidar_range(self) -> float:
        """The LiDAR ray length: ``lidar_range``, or ``comm_radius`` when it is ``None``."""
        return float(self.comm_radius if self.lidar_range is None else self.lidar_range)

    @property
    def density(self) -> float:
        """Agents per unit volume (3-D) or area (2-D), ``N / l^d`` (the paper's density axis)."""
        return self.num_agents / self.area_size**self.dim

    def to_dict(self) -> dict:
        """Plain (JSON-friendly) dict of the config; ``params`` as a nested dict."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["params"] = {f.name: getattr(self.params, f.name) for f in fields(self.params)}
        return out

    @classmethod
    def from_dict(cls, d: dict) -> EnvConfig:
        d = dict(d)
        if isinstance(d.get("params"), dict):
            d["params"] = type(make_robot(d.get("robot", "quadrotor")).params)(**d["params"])
        return cls(**d)


@functools.lru_cache(maxsize=64)
def _robot(name: str, params) -> Robot:
    return make_robot(name, params)


@dataclass
class SwarmState:
    """State of ``B`` environments of ``N`` agents.

    Attributes:
        x: ``(B, N, S)`` agent states of ``robot`` (quadrotor: ``S = 18``, ``[p, R (row-major), v, w]``, see
            ``egcbf.dynamics.quadrotor``; unicycle: ``S = 5``, ``[p, h, v]``).
        goals: ``(B, N, d)`` goal positions (``d = robot.dim``).
        obstacles: spheres (discs in 2-D), ``centers`` ``(B, K, d)``, ``radii`` ``(B, K)``.
        t: steps taken since reset (all environments step together).
        robot: the robot the states belong to (``None``: the quadrotor).
    """

    x: Tensor
    goals: Tensor
    obstacles: Obstacles
    t: int = 0
    robot: Robot | None = None

    def __post_init__(self) -> None:
        if self.robot is None:
            self.robot = _robot("quadrotor", None)
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
        if self.robot.name != "quadrotor":
            raise AttributeError(f"a {self.robot.name} has no attitude matrix")
        return self.x[..., dyn.ROT].reshape(*self.x.shape[:2], 3, 3)

    def to(self, *args, **kwargs) -> SwarmState:
        return SwarmState(
            self.x.to(*args, **kwargs), self.goals.to(*args, **kwargs), self.obstacles.to(*args, **kwargs), self.t,
            self.robot,
        )  # fmt: skip

    def detach(self) -> SwarmState:
        obs = Obstacles(self.obstacles.centers.detach(), self.obstacles.radii.detach())
        return SwarmState(self.x.detach(), self.goals.detach(), obs, self.t, self.robot)

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
        obs = Obstacles(group.transform(ge, self.obstacles.centers), self.obstacles.radii)
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


def safety_masks(positions: Tensor, goals: Tensor, obstacles: Obstacles, agent_radius: float) -> dict[str, Tensor]:
    """Collision / unsafe / reached masks ``(B, N)`` (module doc conventions); sparse agent–agent search.

    Returns a dict with keys ``collision``, ``unsafe``, ``reached``, ``agent_collision``, ``obstacle_collision``,
    ``agent_unsafe``, ``obstacle_unsafe``.
    """
    b, n, d = positions.shape
    r = float(agent_radius)
    p = positions.detach().reshape(b * n, d)
    batch = torch.arange(b, device=p.device).repeat_interleave(n)
    src, dst = radius_neighbors(p, 2.5 * r, batch, sort=False)  # every pair closer than 2.5 r
    close = (p.index_select(0, src) - p.index_select(0, dst)).norm(dim=-1) < 2 * r
    agent_unsafe = torch.zeros(b * n, dtype=torch.bool, device=p.device)
    agent_unsafe[dst] = True
    agent_coll = torch.zeros_like(agent_unsafe)
    agent_coll[dst[close]] = True
    agent_unsafe, agent_coll = agent_unsafe.view(b, n), agent_coll.view(b, n)
    obs_coll = torch.zeros(b * n, dtype=torch.bool, device=p.device)
    obs_unsafe = torch.zeros_like(obs_coll)
    if obstacles.num_obstacles > 0:  # sparse agent-obstacle pairs within 1.5 r of a surface
        bi, ni, ki = obstacles.near_pairs(positions.detach(), 1.5 * r)
        obs = obstacles.to(dtype=p.dtype)
        sd = (positions.detach()[bi, ni] - obs.centers[bi, ki]).norm(dim=-1) - obs.radii[bi, ki]
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


def cast_lidar(config: EnvConfig, positions: Tensor, heading: Tensor, obstacles: Obstacles) -> LidarScan:
    """:func:`egcbf.env.lidar.lidar_scan` with the ray pattern, range and hit count of ``config``.

    ``positions`` and ``heading`` (``Robot.heading``: the body x axes of quadrotors, whose horizontal part turns the
    pattern; the unit headings of planar robots) are ``(B, N, d)``; ``obstacles`` has ``B`` environments.
    """
    return lidar_scan(
        positions,
        heading,
        obstacles,
        n_rays=config.n_rays,
        max_range=config.resolved_lidar_range,
        max_hits=config.lidar_max_hits,
    )


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
        obstacles = sample_obstacles(
            c.num_envs, c.num_obstacles, c.area_size, c.obstacle_radius_range, generator=gen, dtype=f64, dim=d
        )
        pts = sample_separated_points(
            c.num_envs,
            2,
            c.num_agents,
            c.area_size,
            c.start_separation * c.agent_radius,
            obstacles,
            c.obstacle_clearance * c.agent_radius,
            generator=gen,
            dtype=f64,
            max_rounds=c.max_sampling_rounds,
            dim=d,
        )
        if c.random_yaw:
            yaw = (torch.rand(c.num_envs, c.num_agents, generator=gen, dtype=f64) * 2 - 1) * math.pi
        else:
            yaw = torch.zeros(c.num_envs, c.num_agents, dtype=f64)
        x = self.robot.rest_state(pts[:, 0], yaw)
        state = SwarmState(x, pts[:, 1], obstacles, 0, self.robot)
        return state.to(device=self.device, dtype=self.dtype)

    # ----------------------------------------------------------------------------------------------- step
    def step(self, state: SwarmState, u: Tensor) -> tuple[SwarmState, StepInfo]:
        """Integrate every agent for one control period with ``u`` ``(B, N, 4)`` held constant.

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
        u_in = u = u.to(state.x.dtype)
        if c.clip_control:
            u = self.robot.clip_control(u)
        x = self.robot.step(state.x, u, c.dt, c.substeps, c.integrator)
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
        new = SwarmState(x, state.goals, state.obstacles, state.t + 1, state.robot)
        return new, self.info(new, u=u)

    # ---------------------------------------------------------------------------------------------- masks
    def info(self, state: SwarmState, u: Tensor | None = None) -> StepInfo:
        """The masks of ``state`` (also usable on a reset state)."""
        m = safety_masks(state.positions, state.goals, state.obstacles, self.config.agent_radius)
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

    # ---------------------------------------------------------------------------------------- perception
    def lidar(self, state: SwarmState) -> LidarScan:
        """LiDAR scan of every agent (rays in the agent's yaw frame; see ``egcbf.env.lidar``)."""
        return cast_lidar(self.config, state.positions, self.robot.heading(state.x), state.obstacles)
