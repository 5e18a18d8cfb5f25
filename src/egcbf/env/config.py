"""The configuration of a batch of swarm environments (:class:`EnvConfig`): sizes, radii, sensing, time step and
the robot (:mod:`egcbf.robots`), validated when made, with a JSON round trip."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from ..robots import DEFAULT_ROBOT, Robot, make_robot
from ..robots.quadrotor import dynamics as dyn
from .scenes import SCENES

__all__ = ["EnvConfig"]


#: Largest arena side in communication radii: the neighbour search hashes grid cells of side ``comm_radius`` into
#: 63-bit keys, which overflow for ``(area_size / comm_radius)^3`` cells of several batches near 1e18.
MAX_AREA_CELLS = 1e5


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
        obstacle_shape: ``"round"`` (spheres, discs) or ``"rectangle"`` (2-D robots: GCBF+'s rotated rectangles,
            each side uniform in ``obstacle_side_range``, orientation uniform).
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
        unsafe_agent_distance, unsafe_obstacle_distance: the training labels' unsafe set (``StepInfo.unsafe``), in
            units of ``agent_radius``: another agent closer than the first (>= 2, GCBF+: 2.5), an obstacle surface
            closer than the second (>= 1, GCBF+: 1.5). Collisions, and so every metric, stay at 2 r and r.
        unsafe_approach_agent_distance, unsafe_approach_obstacle_distance: the training labels' *approach* part
            (the GCBF+ reference's double integrator and Dubins car, "unsafe direction", ``Robot.reference_labels``;
            0 = off, the default), in agent radii: an agent is
            also unsafe when another agent closer than the first (>= 2; GCBF+: 3), or a LiDAR hit closer than the
            second (>= 1; GCBF+: 2), lies in its collision cone: its motion direction
            (:meth:`Robot.motion_direction`) within ``asin(2 r / d)`` (agents) or ``asin(r / d)`` (hits) of the
            direction to it (:func:`egcbf.env.swarm.approach_unsafe`). Labels only, like the distances above.
        max_sampling_rounds: bound on the rejection-sampling rounds before ``reset`` gives up with ``ValueError``.
        scene: where starts and goals are drawn (:data:`egcbf.env.scenes.SCENES`): ``"uniform"`` (the arena; GCBF+'s
            and the paper's) or ``"crossing"`` (starts in ``x < l / 2``, goals in ``x > l / 2``).
        scene_yaw: degrees; the sampled scene (starts, goals, obstacles, yaws) rotated about the vertical axis
            through the arena's centre (:mod:`egcbf.env.scenes`), for the rotated-world test.
        max_travel: ``None`` (goals anywhere in the arena) or ``> 0`` (m): each goal within this distance of its own
            start (GCBF+'s ``--max-travel``; uniform scene only).
        robot: the robot's name (:data:`egcbf.robots.ROBOTS`); ``make_robot()`` builds it.
        params: the robot's parameters (``None``: its defaults; for the quadrotor a ``QuadrotorParams``).
    """

    num_agents: int = 8
    area_size: float = 2.0
    num_obstacles: int = 5
    obstacle_radius_range: tuple[float, float] = (0.05, 0.3)
    obstacle_shape: str = "round"
    obstacle_side_range: tuple[float, float] = (0.1, 0.6)
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
    unsafe_agent_distance: float = 2.5
    unsafe_obstacle_distance: float = 1.5
    unsafe_approach_agent_distance: float = 0.0
    unsafe_approach_obstacle_distance: float = 0.0
    max_sampling_rounds: int = 200
    scene: str = "uniform"
    scene_yaw: float = 0.0
    max_travel: float | None = None
    params: Any = None
    robot: str = DEFAULT_ROBOT

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, what: str) -> None:
            if not ok:
                raise ValueError(f"EnvConfig.{name} must be {what}, got {getattr(self, name)!r}")

        need(_is_int(self.num_agents) and self.num_agents >= 1, "num_agents", "an integer >= 1")
        need(_is_num(self.area_size) and self.area_size > 0, "area_size", "a finite number > 0")
        comm_ok = _is_num(self.comm_radius) and self.comm_radius > 0  # else the comm_radius check below names it
        need(self.area_size <= MAX_AREA_CELLS * self.comm_radius if comm_ok else True, "area_size",
             f"at most {MAX_AREA_CELLS:g} x comm_radius (the neighbour search's grid keys would overflow)")  # fmt: skip
        need(_is_int(self.num_obstacles) and self.num_obstacles >= 0, "num_obstacles", "an integer >= 0")
        rr = self.obstacle_radius_range
        need(
            isinstance(rr, (tuple, list)) and len(rr) == 2 and all(_is_num(v) for v in rr) and 0 < rr[0] <= rr[1],
            "obstacle_radius_range",
            "a pair (lo, hi) of finite numbers with 0 < lo <= hi",
        )
        object.__setattr__(self, "obstacle_radius_range", (float(rr[0]), float(rr[1])))
        need(self.obstacle_shape in ("round", "rectangle"), "obstacle_shape", "'round' or 'rectangle'")
        sr = self.obstacle_side_range
        need(
            isinstance(sr, (tuple, list)) and len(sr) == 2 and all(_is_num(v) for v in sr) and 0 < sr[0] <= sr[1],
            "obstacle_side_range",
            "a pair (lo, hi) of finite numbers with 0 < lo <= hi",
        )
        object.__setattr__(self, "obstacle_side_range", (float(sr[0]), float(sr[1])))
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
        need(_is_num(self.unsafe_agent_distance) and self.unsafe_agent_distance >= 2, "unsafe_agent_distance",
             "a number >= 2 (agent radii)")  # fmt: skip
        need(_is_num(self.unsafe_obstacle_distance) and self.unsafe_obstacle_distance >= 1,
             "unsafe_obstacle_distance", "a number >= 1 (agent radii)")  # fmt: skip
        for name, least in (("unsafe_approach_agent_distance", 2), ("unsafe_approach_obstacle_distance", 1)):
            value = getattr(self, name)
            need(
                _is_num(value) and (value == 0 or value >= least), name, f"0 (off) or a number >= {least} (agent radii)"
            )
        need(
            _is_int(self.max_sampling_rounds) and self.max_sampling_rounds >= 1,
            "max_sampling_rounds",
            "an integer >= 1",
        )
        need(self.scene in SCENES, "scene", f"one of {SCENES}")
        need(_is_num(self.scene_yaw), "scene_yaw", "a finite number (degrees)")
        need(self.max_travel is None or (_is_num(self.max_travel) and self.max_travel > 0), "max_travel",
             "None or a number > 0 (m)")  # fmt: skip
        need(self.max_travel is None or self.scene == "uniform", "max_travel", "None with a non-uniform scene")
        try:
            robot = make_robot(self.robot, self.params)
        except (ValueError, TypeError) as err:
            raise ValueError(f"EnvConfig.robot / params: {err}") from None
        if self.params is None:
            object.__setattr__(self, "params", robot.params)
        need(type(self.params) is type(robot.params), "params", f"a {type(robot.params).__name__}")
        if self.params.radius != self.agent_radius:
            object.__setattr__(self, "params", replace(self.params, radius=float(self.agent_radius)))
        order = getattr(robot.group, "n", 1)
        need(not robot.world_fixed_lidar or self.n_rays % order == 0, "n_rays",
             f"a multiple of {order} for the {robot.name}: its world-fixed rays must be invariant under its "
             f"{order} rotations")  # fmt: skip
        need(self.obstacle_shape == "round" or robot.dim == 2, "obstacle_shape",
             f"'round' for a {robot.dim}-D robot (rectangles are planar)")  # fmt: skip

    @classmethod
    def for_robot(cls, robot: str, **changes) -> EnvConfig:
        """The config of ``robot`` with its own defaults (``Robot.env_defaults``), then ``changes``."""
        kw = dict(make_robot(robot).env_defaults)
        kw.update(changes)
        return cls(robot=robot, **kw)

    def make_robot(self) -> Robot:
        """The :class:`egcbf.robots.Robot` of this config (cached: equal configs share one)."""
        return make_robot(self.robot, self.params)

    @property
    def dim(self) -> int:
        """The spatial dimension ``d`` of the robot's world (2 or 3)."""
        return self.make_robot().dim

    @property
    def resolved_lidar_range(self) -> float:
        """The LiDAR ray length: ``lidar_range``, or ``comm_radius`` when it is ``None``."""
        return float(self.comm_radius if self.lidar_range is None else self.lidar_range)

    def scan(self, positions, heading, obstacles, ray_faults=None):
        """:func:`egcbf.env.lidar.lidar_scan` with this configuration's ray pattern, range and hit count: a
        :class:`~egcbf.env.lidar.LidarScan` of the agents at ``positions`` ``(B, N, d)`` with headings ``heading``
        ``(B, N, d)`` (``Robot.heading``) among ``obstacles`` (``B`` environments); ``ray_faults``: the sensor's
        faults on single rays."""
        from .lidar import lidar_scan

        return lidar_scan(
            positions,
            heading,
            obstacles,
            n_rays=self.n_rays,
            max_range=self.resolved_lidar_range,
            max_hits=self.lidar_max_hits,
            ray_faults=ray_faults,
        )

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
            d["params"] = type(make_robot(d.get("robot", DEFAULT_ROBOT)).params)(**d["params"])
        return cls(**d)
