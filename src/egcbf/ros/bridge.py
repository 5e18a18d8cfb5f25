"""One agent's ROS 2 node logic without ROS: messages in, the deployed controller, command messages out.

:class:`AgentBridge` holds what one quadrotor knows (its latest odometry, its goal, the latest broadcast of every
neighbour it hears, its latest LiDAR cloud) and, at each :meth:`AgentBridge.tick`, turns it into the inputs of an
:mod:`egcbf.deploy` agent controller, calls it, and returns the messages to publish::

    bridge = AgentBridge(AgentController.from_checkpoint("checkpoints/egcbf+"), agent_id=3)
    bridge.on_odometry(odom); bridge.on_goal(goal); bridge.on_neighbour(state_of_7); bridge.on_cloud(cloud)
    out = bridge.tick(now_ns)       # {topic: message}: the commands and this agent's own broadcast

The inputs are exactly what the controller takes (:meth:`AgentBridge.inputs`, float64 tensors, world frame): its
state ``(18,)`` from the odometry, the goal ``(3,)``, the neighbours' broadcast states ``(K, 18)`` (every fresh
one, by id; the controller keeps those within its communication radius, the nearest ``max_neighbours``), the hits
``(H, 3)`` of the latest cloud (the controller keeps those within its LiDAR range). Behind the ``dcbf`` filter
(:class:`egcbf.deploy.agent.AgentFilteredController`) it also passes the obstacle map given at construction and the
accelerations ``(1 + K, 3)`` realized since each sender's previous message, ``(v - v_prev) / (t - t_prev)`` (zero
for one heard once), the filter's look-ahead.

Freshness: a neighbour's broadcast older than ``timeout_s`` at a tick is dropped (it may have left, or its radio
may be down: the controller no longer counts on where it was); a broadcast older than the one held is ignored
(messages out of order). Without fresh odometry, a goal and (with ``require_cloud``) a fresh cloud, a tick
publishes no command, only the broadcast if the odometry is fresh, and says why in :attr:`AgentBridge.skipped`:
the vehicle's own failsafe (hover, land) is then in charge. The callbacks raise ``TypeError`` / ``ValueError``
(:mod:`egcbf.ros.codecs`) on a message of another type, another frame, a bad layout or NaN, and keep nothing of it.

Outputs (topic names :class:`Topics`, relative, so a ROS namespace such as ``/cf3`` applies):
``egcbf_msgs/msg/BodyRateThrust`` of the body control (:func:`egcbf.ros.codecs.body_rate_thrust`),
``crazyflie_interfaces/msg/FullState`` of the ``accel`` interface's command (:func:`egcbf.ros.codecs.full_state`;
a policy of the ``torque`` interface has no acceleration command and publishes none) and the agent's own
``egcbf_msgs/msg/AgentState``, stamped with its odometry's stamp.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..deploy.agent import AgentController, AgentFilteredController
from ..robots.quadrotor import Quadrotor
from ..robots.quadrotor.dynamics import ROT
from ..robots.quadrotor.dynamics import P as POS
from ..robots.quadrotor.dynamics import V as VEL
from . import codecs

__all__ = ["AgentBridge", "Topics"]


@dataclass(frozen=True)
class Topics:
    """The bridge's topic names: relative ones resolve in the node's namespace (``/cf3/odom``), absolute ones
    (``/swarm/...``) are shared by the swarm."""

    odometry: str = "odom"
    goal: str = "goal"
    cloud: str = "lidar"
    neighbours: str = "/swarm/agent_states"
    full_state: str = "cmd_full_state"
    body_rate_thrust: str = "cmd_body_rate_thrust"


@dataclass
class _Heard:
    stamp: int
    state: np.ndarray
    previous: tuple[int, np.ndarray] | None = None

    def acceleration(self) -> np.ndarray:
        """``(v - v_prev) / (t - t_prev)`` (world, m/s^2) since the previous message, zero without one."""
        if self.previous is None or self.stamp <= self.previous[0]:
            return np.zeros(3)
        return (self.state[VEL] - self.previous[1][VEL]) / ((self.stamp - self.previous[0]) * 1e-9)

    def update(self, stamp: int, state: np.ndarray) -> _Heard:
        return _Heard(stamp, state, (self.stamp, self.state))


class AgentBridge:
    """One agent's node logic (module doc).

    Args:
        controller: an :class:`~egcbf.deploy.agent.AgentController` or
            :class:`~egcbf.deploy.agent.AgentFilteredController` of a quadrotor policy.
        agent_id: this agent's id (its broadcasts carry it; its own broadcasts heard back are ignored).
        goal: the goal position ``(3,)`` (world, m), or ``None`` until :meth:`on_goal`.
        obstacles: the obstacle map ``(centers (O, 3), radii (O,))`` (world, m) the ``dcbf`` filter reads; ``None``:
            none.
        topics: the topic names; world_frame: the world ``frame_id`` every message must be in (clouds may also
            be in ``body_frame``); body_frame: the body ``frame_id`` (default: the odometry's ``child_frame_id``).
        timeout_s: how old (s) odometry, a broadcast or a cloud may be at a tick.
        require_cloud: command only with a fresh cloud (a robot without LiDAR: ``False``, no hits).
        linear_frame: the frame of the odometry's linear twist (:func:`egcbf.ros.codecs.odometry_to_state`).
        setpoint_horizon: the ``FullState`` set point's horizon (s, :func:`egcbf.ros.codecs.full_state`).
        publish: called as ``publish(topic, message)`` for every message a tick returns (``None``: not called).
    """

    def __init__(
        self,
        controller: AgentController | AgentFilteredController,
        agent_id: int,
        *,
        goal=None,
        obstacles: tuple | None = None,
        topics: Topics = Topics(),
        world_frame: str = codecs.WORLD_FRAME,
        body_frame: str | None = None,
        timeout_s: float = 0.1,
        require_cloud: bool = True,
        linear_frame: str = "body",
        setpoint_horizon: float = 0.0,
        publish: Callable[[str, object], None] | None = None,
    ):
        if not isinstance(controller, (AgentController, AgentFilteredController)):
            raise TypeError(f"AgentBridge needs an egcbf.deploy agent controller, got {type(controller).__name__}")
        if not isinstance(controller.robot, Quadrotor):
            raise ValueError(f"AgentBridge's messages carry a quadrotor's state; the controller drives a "
                             f"{type(controller.robot).__name__}")  # fmt: skip
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if linear_frame not in ("body", "world"):
            raise ValueError(f"linear_frame must be 'body' or 'world', got {linear_frame!r}")
        self.controller, self.agent_id = controller, int(agent_id)
        codecs.agent_state(self.agent_id, np.zeros(1), stamp=0)  # checks the id's range
        self.robot = controller.robot
        self.dt = float(controller.env_config.dt)
        policy = controller.controller if isinstance(controller, AgentFilteredController) else controller
        self.accel_unit: float | None = getattr(policy.module.interface, "accel_unit", None)
        self.topics, self.world_frame, self.body_frame = topics, world_frame, body_frame
        self.timeout_ns = codecs.seconds_to_ns(timeout_s)
        self.require_cloud, self.linear_frame = require_cloud, linear_frame
        self.setpoint_horizon, self.publish = float(setpoint_horizon), publish
        self.goal = None if goal is None else codecs._array(goal, (3,), "goal")
        if obstacles is not None:
            centers, radii = (torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in obstacles)
            if centers.dim() != 2 or centers.shape[-1] != 3 or tuple(radii.shape) != (centers.shape[0],):
                raise ValueError(f"obstacles must be (centers (O, 3), radii (O,)), got {tuple(centers.shape)}, "
                                 f"{tuple(radii.shape)}")  # fmt: skip
            obstacles = (centers, radii)
        self.obstacles = obstacles
        self.own: _Heard | None = None
        self.neighbours: dict[int, _Heard] = {}
        self.cloud: tuple[int, np.ndarray] | None = None
        #: why the last tick published no command (``None``: it did)
        self.skipped: str | None = None
        #: the last tick's controller inputs (``inputs()``'s dict) and ``info``
        self.last_inputs: dict | None = None
        self.last_info: dict | None = None

    # ------------------------------------------------------------------------------------------- callbacks
    def on_odometry(self, msg) -> None:
        """This agent's ``nav_msgs/msg/Odometry`` (world frame, twist in the body frame)."""
        state = codecs.odometry_to_state(msg, frame_id=self.world_frame, linear_frame=self.linear_frame)
        stamp = codecs.stamp_ns(msg)
        if self.own is not None and stamp < self.own.stamp:
            return
        self.own = _Heard(stamp, state) if self.own is None else self.own.update(stamp, state)
        if self.body_frame is None:
            self.body_frame = msg.child_frame_id or None

    def on_goal(self, msg) -> None:
        """The goal, a ``geometry_msgs/msg/PointStamped`` in the world frame."""
        self.goal = codecs.point_to_goal(msg, frame_id=self.world_frame)

    def on_neighbour(self, msg) -> None:
        """A broadcast ``egcbf_msgs/msg/AgentState`` (this agent's own is ignored; an older one than held too)."""
        agent, stamp, state = codecs.agent_state_to_state(msg, state_dim=self.robot.state_dim,
                                                          frame_id=self.world_frame)  # fmt: skip
        if agent == self.agent_id:
            return
        held = self.neighbours.get(agent)
        if held is not None and stamp < held.stamp:
            return
        self.neighbours[agent] = _Heard(stamp, state) if held is None else held.update(stamp, state)

    def on_cloud(self, msg) -> None:
        """The LiDAR's ``sensor_msgs/msg/PointCloud2``, in the world frame or in the body frame (then turned into
        the world frame with the latest odometry's pose)."""
        frame = msg.header.frame_id
        if frame == self.world_frame:
            hits, valid = codecs.cloud_to_hits(msg)
        elif self.body_frame is not None and frame == self.body_frame:
            if self.own is None:
                raise ValueError(f"a cloud in the body frame {frame!r} before any odometry: no pose to place it")
            pose = (self.own.state[POS], self.own.state[ROT].reshape(3, 3))
            hits, valid = codecs.cloud_to_hits(msg, body_pose=pose)
        else:
            raise ValueError(f"PointCloud2 in frame {frame!r}; expected the world frame {self.world_frame!r} or the "
                             f"body frame {self.body_frame!r}")  # fmt: skip
        self.cloud = (codecs.stamp_ns(msg), hits[valid])

    # ------------------------------------------------------------------------------------------- the tick
    def _fresh(self, stamp: int, now: int) -> bool:
        return now - stamp <= self.timeout_ns

    def _expire(self, now: int) -> None:
        for agent in [a for a, h in self.neighbours.items() if not self._fresh(h.stamp, now)]:
            del self.neighbours[agent]

    def not_ready(self, now: int) -> str | None:
        """Why a tick at ``now`` (ns) cannot command (``None``: it can)."""
        if self.own is None:
            return "no odometry yet"
        if not self._fresh(self.own.stamp, now):
            return f"odometry {(now - self.own.stamp) * 1e-9:.3f} s old (timeout {self.timeout_ns * 1e-9:g} s)"
        if self.goal is None:
            return "no goal yet"
        if self.require_cloud and (self.cloud is None or not self._fresh(self.cloud[0], now)):
            return (
                "no fresh LiDAR cloud"
                if self.cloud is None
                else (f"LiDAR cloud {(now - self.cloud[0]) * 1e-9:.3f} s old (timeout {self.timeout_ns * 1e-9:g} s)")
            )
        return None

    def inputs(self, now: int) -> dict[str, Tensor]:
        """The controller's inputs at ``now`` (ns, after dropping stale broadcasts): ``state (18,)``, ``goal (3,)``,
        ``neighbours (K, 18)`` (by id), ``hits (H, 3)``, float64 tensors (world frame, SI), and for the ``dcbf``
        filter ``obstacles`` and ``accelerations (1 + K, 3)``. ``RuntimeError`` if :meth:`not_ready` says why not."""
        why = self.not_ready(now)
        if why is not None:
            raise RuntimeError(f"agent {self.agent_id} cannot command at {now} ns: {why}")
        self._expire(now)
        heard = [self.neighbours[a] for a in sorted(self.neighbours)]
        s = self.robot.state_dim
        nbr = np.stack([h.state for h in heard]) if heard else np.zeros((0, s))
        fresh = self.cloud is not None and self._fresh(self.cloud[0], now)
        hits = self.cloud[1] if fresh else np.zeros((0, 3))
        out = {name: torch.as_tensor(a, dtype=torch.float64) for name, a in
               (("state", self.own.state), ("goal", self.goal), ("neighbours", nbr), ("hits", hits))}  # fmt: skip
        if isinstance(self.controller, AgentFilteredController):
            acc = np.stack([self.own.acceleration(), *(h.acceleration() for h in heard)])
            out["accelerations"] = torch.as_tensor(acc, dtype=torch.float64)
            out["obstacles"] = self.obstacles
        return out

    def tick(self, now: int) -> dict[str, object]:
        """One control step at ``now`` (integer ns): ``{topic: message}`` to publish (module doc), also passed to
        ``publish`` if given. Without what it needs (:meth:`not_ready`) only the broadcast, if any."""
        out: dict[str, object] = {}
        why = self.not_ready(now)
        self.skipped = why
        if why is None:
            inputs = self.inputs(now)
            u, info = self.controller(**inputs)
            self.last_inputs, self.last_info = inputs, info
            state = self.own.state
            u64 = u.detach().to(torch.float64).cpu().numpy()
            out[self.topics.body_rate_thrust] = codecs.body_rate_thrust(
                u64, state, self.dt, self.robot.params, stamp=now, frame_id=self.body_frame or "base_link"
            )
            if self.accel_unit is not None:
                accel = self.accel_unit * info["command"].detach().to(torch.float64).cpu().numpy()
                out[self.topics.full_state] = codecs.full_state(state, accel, stamp=now, frame_id=self.world_frame,
                                                                horizon=self.setpoint_horizon)  # fmt: skip
        if self.own is not None and self._fresh(self.own.stamp, now):
            out[self.topics.neighbours] = codecs.agent_state(self.agent_id, self.own.state, stamp=self.own.stamp,
                                                             frame_id=self.world_frame)  # fmt: skip
        if self.publish is not None:
            for topic, msg in out.items():
                self.publish(topic, msg)
        return out
