"""An rclpy node around :class:`egcbf.ros.bridge.AgentBridge`: one quadrotor's controller on a ROS 2 graph.

The node subscribes to its odometry, goal, LiDAR cloud and the swarm's broadcasts (:class:`~egcbf.ros.bridge.Topics`),
ticks the bridge every control period (``EnvConfig.dt`` of the policy, 25 ms by default) on the node's clock
(``use_sim_time`` applies), and publishes what the tick returns. Messages travel serialized: subscriptions are raw
(CDR bytes, decoded by :func:`egcbf.ros.messages.typestore`) and the publishers publish CDR bytes, so the bridge's
pure-Python messages are the node's, bit for bit, and nothing here depends on the generated Python classes beyond
the type registration ROS needs.

This module imports without ROS; :func:`make_node` and :func:`main` need ROS 2 Humble or later, sourced
(``source /opt/ros/humble/setup.bash``: ``rclpy``, ``rosidl_runtime_py``, ``nav_msgs``, ``sensor_msgs``,
``geometry_msgs``), the message packages ``egcbf_msgs`` and ``crazyflie_interfaces`` built in the workspace
(:func:`egcbf.ros.messages.write_msg_packages`, or Crazyswarm2's own ``crazyflie_interfaces``), and the ``ros`` extra
(``pip install 'egcbf[ros]'``). Run one node per vehicle::

    python -m egcbf.ros.node --checkpoint checkpoints/egcbf+ --id 3 --goal 1,2,1 --ros-args -r __ns:=/cf3

Not tested here (no ROS in the test environment): the bridge it wraps is (``tests/egcbf/test_ros.py``).
"""

from __future__ import annotations

import argparse
import sys

from . import codecs
from .bridge import AgentBridge, Topics
from .messages import AGENT_STATE, BODY_RATE_THRUST, FULL_STATE, typestore

__all__ = ["ROS_MISSING", "main", "make_node", "topic_types"]

#: what to install when rclpy is missing
ROS_MISSING = (
    "egcbf.ros.node needs ROS 2 (Humble or later) sourced in this shell: rclpy and rosidl_runtime_py (e.g. "
    "`source /opt/ros/humble/setup.bash`), and the message packages egcbf_msgs and crazyflie_interfaces built in "
    "the workspace (egcbf.ros.messages.write_msg_packages writes them). The offline parts of egcbf.ros (codecs, "
    "bridge, recordings) need only the 'ros' extra: pip install 'egcbf[ros]'."
)


def topic_types(topics: Topics) -> tuple[dict[str, str], dict[str, str]]:
    """``({topic: type} subscribed, {topic: type} published)`` of the bridge's topics."""
    subscribed = {
        topics.odometry: codecs.ODOMETRY,
        topics.goal: codecs.POINT_STAMPED,
        topics.cloud: codecs.POINT_CLOUD,
        topics.neighbours: AGENT_STATE,
    }
    published = {
        topics.full_state: FULL_STATE,
        topics.body_rate_thrust: BODY_RATE_THRUST,
        topics.neighbours: AGENT_STATE,
    }
    return subscribed, published


def _ros():
    try:
        import rclpy
        from rclpy.node import Node
        from rosidl_runtime_py.utilities import get_message
    except ImportError as err:
        raise ImportError(ROS_MISSING) from err
    return rclpy, Node, get_message


def make_node(bridge: AgentBridge, *, node_name: str = "egcbf_agent", qos_depth: int = 10):
    """The rclpy node of ``bridge`` (``rclpy.init()`` must have been called): raw subscriptions feeding its
    callbacks, a timer of period ``bridge.dt`` calling its tick, CDR publishers. A message the bridge refuses
    (wrong frame, NaN, ...) is dropped with a throttled warning; the node keeps running. ``ImportError`` saying
    what to install without ROS."""
    _, Node, get_message = _ros()
    store = typestore()
    subscribed, published = topic_types(bridge.topics)
    callbacks = {
        bridge.topics.odometry: bridge.on_odometry,
        bridge.topics.goal: bridge.on_goal,
        bridge.topics.cloud: bridge.on_cloud,
        bridge.topics.neighbours: bridge.on_neighbour,
    }

    class AgentNode(Node):
        def __init__(self):
            super().__init__(node_name)
            self.bridge = bridge
            self._subs = [
                self.create_subscription(
                    get_message(typename),
                    topic,
                    lambda raw, t=topic, n=typename: self._receive(t, n, raw),
                    qos_depth,
                    raw=True,
                )
                for topic, typename in subscribed.items()
            ]
            self._pubs = {
                topic: self.create_publisher(get_message(t), topic, qos_depth) for topic, t in published.items()
            }
            self._types = published
            self._timer = self.create_timer(bridge.dt, self._tick)

        def _receive(self, topic: str, typename: str, raw: bytes) -> None:
            try:
                callbacks[topic](store.deserialize_cdr(raw, typename))
            except (TypeError, ValueError) as err:
                self.get_logger().warning(f"{topic}: message dropped: {err}", throttle_duration_sec=1.0)

        def _tick(self) -> None:
            out = self.bridge.tick(self.get_clock().now().nanoseconds)
            if self.bridge.skipped is not None:
                self.get_logger().info(f"no command: {self.bridge.skipped}", throttle_duration_sec=2.0)
            for topic, msg in out.items():
                self._pubs[topic].publish(bytes(store.serialize_cdr(msg, self._types[topic])))

    return AgentNode()


def main(argv: list[str] | None = None) -> None:
    """``python -m egcbf.ros.node``: one agent's node from a checkpoint (``--help``); ROS arguments after
    ``--ros-args`` go to rclpy."""
    rclpy, _, _ = _ros()
    argv = sys.argv[1:] if argv is None else argv
    ours, ros_args = (argv[: argv.index("--ros-args")], argv[argv.index("--ros-args"):]) if "--ros-args" in argv \
        else (argv, [])  # fmt: skip
    parser = argparse.ArgumentParser(prog="python -m egcbf.ros.node", description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="a checkpoint or run directory (egcbf train)")
    parser.add_argument("--id", type=int, required=True, help="this agent's id in the swarm's broadcasts")
    parser.add_argument("--goal", default=None, help="x,y,z (m, world frame); else from the goal topic")
    parser.add_argument("--filter", choices=("none", "dcbf"), default="dcbf", help="the run-time filter (default dcbf)")
    parser.add_argument("--world-frame", default=codecs.WORLD_FRAME)
    parser.add_argument("--timeout", type=float, default=0.1, help="seconds a message stays fresh")
    parser.add_argument("--no-lidar", action="store_true", help="command without LiDAR clouds (no hits)")
    args = parser.parse_args(ours)
    from ..deploy.agent import AgentController, AgentFilteredController

    ctrl = AgentController.from_checkpoint(args.checkpoint)
    if args.filter == "dcbf":
        ctrl = AgentFilteredController(ctrl)
    goal = None if args.goal is None else [float(v) for v in args.goal.split(",")]
    bridge = AgentBridge(ctrl, args.id, goal=goal, world_frame=args.world_frame, timeout_s=args.timeout,
                         require_cloud=not args.no_lidar)  # fmt: skip
    rclpy.init(args=["egcbf_agent", *ros_args])
    node = make_node(bridge)
    try:
        rclpy.spin(node)
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
