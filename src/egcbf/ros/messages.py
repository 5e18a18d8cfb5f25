"""The ROS 2 message types the bridge and the recordings use: ROS 2 Humble's standard ones and three of our own.

Everything is pure Python on :mod:`rosbags` (the ``ros`` extra): :func:`typestore` is a ``rosbags`` typestore of
ROS 2 Humble's messages (``std_msgs``, ``geometry_msgs``, ``nav_msgs``, ``sensor_msgs``, ``visualization_msgs``, ...)
with :data:`DEFINITIONS` registered, from their ``.msg`` text:

* ``egcbf_msgs/msg/AgentState``: what an agent broadcasts to its neighbours, its state vector as the simulator
  writes it (quadrotor: ``[p, R row-major, v, w]``, :mod:`egcbf.robots.quadrotor.dynamics`);
* ``egcbf_msgs/msg/BodyRateThrust``: a body-rate and collective-thrust command (our own layout:
  ``geometry_msgs/Vector3 body_rate`` in rad/s in the body frame, ``float64 thrust`` in N along the body z axis;
  not ``mavros_msgs/AttitudeTarget``, whose thrust is normalized to ``[0, 1]`` by a vehicle-specific factor);
* ``crazyflie_interfaces/msg/FullState``: Crazyswarm2's full-state set point, with its field layout (``header``,
  ``geometry_msgs/Pose pose``, ``geometry_msgs/Twist twist``, ``geometry_msgs/Vector3 acc``), so that a recording
  or a bridge speaks to ``crazyflie_server``'s ``cmd_full_state`` topic without conversion.

A real ROS 2 node needs the two custom packages built in its workspace: :func:`write_msg_packages` writes them
(``package.xml``, ``CMakeLists.txt``, ``msg/*.msg``) from the same text.
"""

from __future__ import annotations

import functools
from pathlib import Path

__all__ = [
    "AGENT_STATE",
    "BODY_RATE_THRUST",
    "DEFINITIONS",
    "FULL_STATE",
    "MissingExtraError",
    "require_extra",
    "typestore",
    "write_msg_packages",
]

AGENT_STATE = "egcbf_msgs/msg/AgentState"
BODY_RATE_THRUST = "egcbf_msgs/msg/BodyRateThrust"
FULL_STATE = "crazyflie_interfaces/msg/FullState"

#: ``type name -> .msg text`` of the types registered on top of ROS 2 Humble's
DEFINITIONS = {
    AGENT_STATE: """\
# One agent's state as it broadcasts it to its neighbours.
# header.stamp: when the state was estimated; header.frame_id: the world frame (z up, SI units)
std_msgs/Header header
# the agent's id (unique in the swarm)
uint32 id
# the robot's state vector (quadrotor: p (3, world, m), R (9, body-to-world, row-major),
# v (3, world, m/s), w (3, body, rad/s))
float64[] state
""",
    BODY_RATE_THRUST: """\
# A body-rate and collective-thrust command.
# header.frame_id: the body frame (x forward, y left, z up)
std_msgs/Header header
# desired angular velocity of the body, in the body frame (rad/s)
geometry_msgs/Vector3 body_rate
# collective thrust along the body z axis (N)
float64 thrust
""",
    FULL_STATE: """\
std_msgs/Header header
geometry_msgs/Pose pose
geometry_msgs/Twist twist
geometry_msgs/Vector3 acc
""",
}


class MissingExtraError(ImportError):
    """The ``ros`` extra (``rosbags``, ``mcap``) is not installed; the message says how to install it."""


def require_extra(what: str = "egcbf.ros") -> None:
    """Raise :class:`MissingExtraError` naming ``what`` if ``rosbags`` or ``mcap`` cannot be imported."""
    missing = []
    for name in ("rosbags", "mcap"):
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise MissingExtraError(
            f"{what} needs the 'ros' extra ({', '.join(missing)} missing): pip install 'egcbf[ros]' "
            "(or: pip install 'rosbags>=0.10' 'mcap>=1.1')"
        )


@functools.cache
def typestore():
    """The ``rosbags`` typestore of ROS 2 Humble with :data:`DEFINITIONS` registered (one per process: it is
    read-only after this call). ``typestore().types[name]`` is a message class, ``serialize_cdr(msg, name)`` and
    ``deserialize_cdr(data, name)`` turn messages into CDR bytes and back."""
    require_extra()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def write_msg_packages(root: str | Path) -> list[Path]:
    """Write the ROS 2 packages ``egcbf_msgs`` (and ``crazyflie_interfaces``, only for a workspace without
    Crazyswarm2) under ``root`` (a workspace's ``src/``): ``package.xml``, ``CMakeLists.txt`` and ``msg/*.msg``
    from :data:`DEFINITIONS`, ready for ``colcon build``. Returns the files written; existing files are
    overwritten."""
    root = Path(root)
    written = []
    packages: dict[str, dict[str, str]] = {}
    for name, text in DEFINITIONS.items():
        pkg, _, msg = name.split("/")
        packages.setdefault(pkg, {})[msg] = text
    for pkg, msgs in packages.items():
        files = {f"msg/{m}.msg": t for m, t in msgs.items()}
        listed = "\n".join(f'  "msg/{m}.msg"' for m in msgs)
        files["CMakeLists.txt"] = (
            f"cmake_minimum_required(VERSION 3.8)\nproject({pkg})\nfind_package(ament_cmake REQUIRED)\n"
            "find_package(rosidl_default_generators REQUIRED)\nfind_package(std_msgs REQUIRED)\n"
            "find_package(geometry_msgs REQUIRED)\n"
            f"rosidl_generate_interfaces(${{PROJECT_NAME}}\n{listed}\n  DEPENDENCIES std_msgs geometry_msgs\n)\n"
            "ament_export_dependencies(rosidl_default_runtime)\nament_package()\n"
        )
        files["package.xml"] = (
            '<?xml version="1.0"?>\n<package format="3">\n'
            f"  <name>{pkg}</name>\n  <version>0.0.0</version>\n"
            f"  <description>{pkg} messages as egcbf.ros defines them</description>\n"
            '  <maintainer email="egcbf@example.invalid">egcbf</maintainer>\n  <license>MIT</license>\n'
            "  <buildtool_depend>ament_cmake</buildtool_depend>\n"
            "  <buildtool_depend>rosidl_default_generators</buildtool_depend>\n"
            "  <depend>std_msgs</depend>\n  <depend>geometry_msgs</depend>\n"
            "  <exec_depend>rosidl_default_runtime</exec_depend>\n"
            "  <member_of_group>rosidl_interface_packages</member_of_group>\n"
            "  <export><build_type>ament_cmake</build_type></export>\n</package>\n"
        )
        for rel, text in files.items():
            path = root / pkg / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            written.append(path)
    return written
