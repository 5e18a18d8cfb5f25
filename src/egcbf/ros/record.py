"""Episode recordings as MCAP files of ROS 2 messages, and reading them back.

:class:`EpisodeRecorder` is an ``on_step`` callback of :func:`egcbf.evaluate.episodes.evaluate` (``egcbf eval
--record FILE.mcap``): it writes the first episode (environment 0) of the first swarm size it watches, one message
per topic per step, stamped ``t * dt`` (integer nanoseconds, the MCAP log and publish times and the headers'
stamps alike; the goals' and obstacles' messages, which do not change in an episode, are the first step's, header
stamp included), all in the world frame ``"world"`` (z up, SI units):

===========================  ====================================  ================================================
topic                        type                                  contents (per step ``t = 0 .. T``)
===========================  ====================================  ================================================
``/egcbf/poses``             ``geometry_msgs/msg/PoseArray``       every agent's position and attitude (its
                                                                   body-to-world quaternion; a planar robot's
                                                                   heading as a yaw), in agent order
``/egcbf/goals``             ``geometry_msgs/msg/PoseArray``       every agent's goal position (identity attitude)
``/egcbf/states``            ``std_msgs/msg/Float64MultiArray``    the full states ``(N, S)`` row-major (dims
                                                                   ``agent``, ``state``), float64
``/egcbf/obstacles``         ``visualization_msgs/msg/MarkerArray``  one marker per obstacle: a sphere of diameter
                                                                   ``2 r`` (a cylinder or a box for planar ones)
``/egcbf/lidar``             ``sensor_msgs/msg/PointCloud2``       every agent's LiDAR hits (``x, y, z`` float64 and
                                                                   the owner's index ``agent``, uint32)
``/egcbf/cbf``               ``std_msgs/msg/Float64MultiArray``    each agent's learned CBF value ``h`` ``(N,)``,
                                                                   where the controller has a CBF
``/egcbf/filter_active``     ``std_msgs/msg/UInt8MultiArray``      1 where the run-time filter changed the agent's
                                                                   command (``t < T``), where there is a filter
===========================  ====================================  ================================================

The schemas are the ``ros2msg`` text of the types (``profile = "ros2"``, message encoding ``cdr``: what rosbag2's
MCAP storage writes), so Foxglove opens the file as it is and ``ros2 bag play FILE.mcap`` plays it. A metadata record
``egcbf`` holds ``dt``, ``num_agents``, ``robot`` and what the caller adds (the command, the controller). The file
is written beside its final name and moved there by :meth:`EpisodeRecorder.close` (a failed run leaves none).

:func:`read_recording` reads one back into arrays (:class:`Recording`); :func:`iter_messages` yields the
deserialized messages of any ``ros2msg``/``cdr`` MCAP file whose types the typestore knows.
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..env import EnvConfig, SwarmState
from ..env.obstacles import Obstacles
from . import codecs
from .messages import require_extra, typestore

__all__ = [
    "BATCH_AGENT_STEPS",
    "TOPICS",
    "EpisodeRecorder",
    "Recording",
    "RecordingWriter",
    "iter_messages",
    "read_recording",
]

#: ``key -> (topic, message type)`` of a recording (module doc)
TOPICS = {
    "poses": ("/egcbf/poses", "geometry_msgs/msg/PoseArray"),
    "goals": ("/egcbf/goals", "geometry_msgs/msg/PoseArray"),
    "states": ("/egcbf/states", "std_msgs/msg/Float64MultiArray"),
    "obstacles": ("/egcbf/obstacles", "visualization_msgs/msg/MarkerArray"),
    "lidar": ("/egcbf/lidar", "sensor_msgs/msg/PointCloud2"),
    "cbf": ("/egcbf/cbf", "std_msgs/msg/Float64MultiArray"),
    "filter_active": ("/egcbf/filter_active", "std_msgs/msg/UInt8MultiArray"),
}
WORLD = codecs.WORLD_FRAME
_METADATA = "egcbf"


class RecordingWriter:
    """An MCAP file of ROS 2 messages (``ros2msg`` schemas, CDR messages): :meth:`write` ``(topic, type, message,
    stamp_ns)``, then :meth:`close`. Schemas and channels are registered on first use. ``path`` is written under a
    temporary name and moved into place by :meth:`close` (``abort`` removes it)."""

    def __init__(self, path: str | Path):
        require_extra("recording an episode (--record)")
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(self._tmp, "wb")
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="egcbf.ros")
        self._store = typestore()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        #: messages written per topic
        self.counts: dict[str, int] = {}

    def _channel(self, topic: str, typename: str) -> int:
        if topic not in self._channels:
            if typename not in self._schemas:
                text, _ = self._store.generate_msgdef(typename, ros_version=2)
                self._schemas[typename] = self._writer.register_schema(typename, "ros2msg", text.encode())
            self._channels[topic] = self._writer.register_channel(topic, "cdr", self._schemas[typename],
                                                                  {"offered_qos_profiles": ""})  # fmt: skip
        return self._channels[topic]

    def write(self, topic: str, typename: str, msg, stamp: int) -> None:
        """Write ``msg`` (a ``rosbags`` message of ``typename``, or its CDR bytes) on ``topic`` at ``stamp``
        (integer ns)."""
        channel = self._channel(topic, typename)
        data = msg if isinstance(msg, bytes) else bytes(self._store.serialize_cdr(msg, typename))
        self._sequence += 1
        self._writer.add_message(channel, log_time=stamp, data=data, publish_time=stamp, sequence=self._sequence)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self, metadata: dict[str, str] | None = None) -> Path:
        """Finish the file (with the metadata record ``egcbf``, string values) and move it to :attr:`path`."""
        if metadata:
            self._writer.add_metadata(_METADATA, {str(k): str(v) for k, v in metadata.items()})
        self._writer.finish()
        self._stream.close()
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the file being written."""
        self._stream.close()
        self._tmp.unlink(missing_ok=True)


class _CDR:
    """A little-endian CDR (XCDR1) message being written: the encapsulation header, then fields aligned to their
    size relative to the message's start (what ``rosbags``' ``serialize_cdr`` writes, byte for byte: tested). Used
    for the per-step array messages, whose ``rosbags`` objects would be built element by element."""

    def __init__(self):
        self.parts: list[bytes] = [b"\x00\x01\x00\x00"]
        self.size = 0
        #: the byte offsets in the message of the fields written with a ``mark``
        self.marks: dict[str, int] = {}

    def _put(self, data: bytes, align: int, mark: str | None = None) -> None:
        pad = -self.size % align
        if pad:
            self.parts.append(bytes(pad))
        if mark is not None:
            self.marks[mark] = 4 + self.size + pad
        self.parts.append(data)
        self.size += pad + len(data)

    def u8(self, value: int) -> _CDR:
        self._put(int(value).to_bytes(1, "little", signed=False), 1)
        return self

    def u32(self, value: int, mark: str | None = None) -> _CDR:
        self._put(int(value).to_bytes(4, "little", signed=False), 4, mark)
        return self

    def header(self, stamp: int, frame_id: str) -> _CDR:
        """``std_msgs/msg/Header``: its stamp's ``sec`` and ``nanosec`` (marked ``"stamp"``), then ``frame_id``."""
        sec, nanosec = divmod(int(stamp), 1_000_000_000)
        self._put(int(sec).to_bytes(4, "little", signed=True), 4, "stamp")
        self.u32(nanosec)
        return self.string(frame_id)

    def string(self, text: str) -> _CDR:
        data = text.encode() + b"\x00"
        self.u32(len(data))
        self._put(data, 1)
        return self

    def raw(self, data: bytes) -> _CDR:
        """``data`` as a ``uint8`` sequence (its length first, marked ``"raw"``)."""
        self.u32(len(data), "raw")
        if data:
            self._put(data, 1)
        return self

    def array(self, values: np.ndarray, dtype, count: int | None = None) -> _CDR:
        """``values`` as consecutive elements of ``dtype`` (a sequence's body: ``count`` first if given)."""
        values = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder("<"))
        if count is not None:
            self.u32(count)
        if values.size:
            self._put(values.tobytes(), values.dtype.itemsize)
        return self

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def _pose_array_cdr(positions: np.ndarray, quaternions: np.ndarray, stamp: int) -> bytes:
    """``geometry_msgs/msg/PoseArray`` of ``positions`` ``(N, 3)`` and quaternions ``(N, 4)`` ``(x, y, z, w)``, as
    CDR bytes (each ``Pose`` is seven float64)."""
    rows = np.concatenate((positions, quaternions), -1)
    return _CDR().header(stamp, WORLD).array(rows, np.float64, count=rows.shape[0]).bytes()


def _multiarray_cdr(typename: str, data: np.ndarray, labels: tuple[str, ...]) -> bytes:
    """``std_msgs/msg/Float64MultiArray`` or ``UInt8MultiArray`` of ``data`` (row-major, one dimension per label),
    as CDR bytes (the layout of :func:`_multiarray`)."""
    out = _CDR().u32(len(labels))
    for k, (label, size) in enumerate(zip(labels, data.shape, strict=True)):
        out.string(label).u32(size).u32(int(np.prod(data.shape[k:])))  # ROS's stride: the sizes from here on
    dtype = np.float64 if typename.endswith("Float64MultiArray") else np.uint8
    return out.u32(0).array(data.reshape(-1), dtype, count=data.size).bytes()


#: a recording's LiDAR cloud: ``x, y, z`` float64 and the owner ``agent`` uint32 per point (:func:`_cloud_cdr`)
_CLOUD_FIELDS = (("x", 0, codecs._FLOAT64), ("y", 8, codecs._FLOAT64), ("z", 16, codecs._FLOAT64),
                 ("agent", 24, codecs._UINT32))  # fmt: skip
_CLOUD_POINT = np.dtype({"names": ["x", "y", "z", "agent"], "formats": ["<f8", "<f8", "<f8", "<u4"],
                         "offsets": [0, 8, 16, 24], "itemsize": 28})  # fmt: skip


def _cloud_points(hits: np.ndarray, agent: np.ndarray) -> np.ndarray:
    """The points ``(H,)`` (:data:`_CLOUD_POINT`) of hits ``(H, 3)`` float64 and their owners ``(H,)``
    (``ValueError`` if a hit holds NaN or inf, as :func:`egcbf.ros.codecs.hits_to_cloud`)."""
    if not np.isfinite(hits).all():
        raise ValueError("hits: a valid hit holds NaN or inf")
    rec = np.zeros(len(hits), dtype=_CLOUD_POINT)
    rec["x"], rec["y"], rec["z"], rec["agent"] = hits[:, 0], hits[:, 1], hits[:, 2], agent
    return rec


def _stamp_bytes(stamps) -> np.ndarray:
    """``(T, 8)`` uint8: the header stamps' ``sec`` (int32) and ``nanosec`` (uint32), little-endian, of ``stamps``
    ``(T,)`` (integer ns, ``0 <= stamp < 2**31`` s)."""
    sec, nanosec = np.divmod(np.asarray(stamps, dtype=np.int64).reshape(-1), 1_000_000_000)
    if sec.size and not (sec.min() >= 0 and sec.max() < 2**31):
        raise ValueError("a stamp must lie in [0, 2**31) s")
    out = np.empty((sec.size, 2), dtype="<u4")
    out[:, 0], out[:, 1] = sec, nanosec
    return out.view(np.uint8)


def _same_layout_cdrs(one: bytes, payload: np.ndarray, stamps=None) -> list[bytes]:
    """The CDR bytes of ``T`` messages laid out as ``one``, whose last field is an array of ``payload.shape[1]``
    bytes: ``one`` with that array's bytes replaced by each row of ``payload`` ``(T, nbytes)`` uint8, and its
    header's stamp (``one`` starts with a header) by each of ``stamps`` ``(T,)`` (ns) where given."""
    buf = np.empty((payload.shape[0], len(one)), dtype=np.uint8)
    buf[:] = np.frombuffer(one, dtype=np.uint8)
    if payload.shape[1]:
        buf[:, len(one) - payload.shape[1] :] = payload
    if stamps is not None:
        buf[:, 4:12] = _stamp_bytes(stamps)
    return [row.tobytes() for row in buf]


def _array_bytes(values: np.ndarray, dtype) -> np.ndarray:
    """``(T, ...)`` values as ``(T, nbytes)`` uint8, little-endian ``dtype``."""
    values = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder("<"))
    return values.reshape(values.shape[0], -1).view(np.uint8)


@functools.cache
def _cloud_head() -> tuple[bytes, dict[str, int]]:
    """A cloud's CDR bytes up to its data (the data's length included; stamp, width and lengths 0) and the offsets of
    the fields :func:`_cloud_cdrs` fills in."""
    step = _CLOUD_POINT.itemsize
    out = _CDR().header(0, WORLD).u32(1).u32(0, "width").u32(len(_CLOUD_FIELDS))
    for name, offset, datatype in _CLOUD_FIELDS:
        out.string(name).u32(offset).u8(datatype).u32(1)
    out.u8(0).u32(step).u32(0, "row_step").raw(b"")  # is_bigendian, point_step, row_step, the data's length
    return out.bytes(), out.marks


def _cloud_cdrs(points: np.ndarray, counts, stamps) -> list[bytes]:
    """``sensor_msgs/msg/PointCloud2`` messages, as CDR bytes, of consecutive runs of ``points``
    (:func:`_cloud_points`): ``counts[k]`` points stamped ``stamps[k]``, for each ``k``. Each is the cloud
    :func:`egcbf.ros.codecs.hits_to_cloud` makes of the same hits and owners (unorganized, dense, little-endian)."""
    head, marks = _cloud_head()
    stamp_bytes, step = _stamp_bytes(stamps), _CLOUD_POINT.itemsize
    out, start = [], 0
    for k, count in enumerate(counts):
        msg = bytearray(head)
        msg[marks["stamp"] : marks["stamp"] + 8] = stamp_bytes[k].tobytes()
        struct.pack_into("<I", msg, marks["width"], count)
        struct.pack_into("<I", msg, marks["row_step"], step * count)
        struct.pack_into("<I", msg, marks["raw"], step * count)
        msg += points[start : start + count].tobytes()
        msg += b"\x01"  # is_dense
        out.append(bytes(msg))
        start += count
    return out


def _cloud_cdr(points: np.ndarray, stamp: int) -> bytes:
    """One cloud of :func:`_cloud_cdrs`: all of ``points``, stamped ``stamp``."""
    return _cloud_cdrs(points, [len(points)], [stamp])[0]


def _markers(obstacles: Obstacles, stamp: int):
    t = typestore().types
    marker = t["visualization_msgs/msg/Marker"]
    centers = obstacles.centers[0].detach().double().cpu().numpy()
    radii = obstacles.radii[0].detach().double().cpu().numpy()
    boxes = None if obstacles.boxes is None else obstacles.boxes[0].detach().double().cpu().numpy()
    planar = centers.shape[-1] == 2
    out = []
    for k, (c, r) in enumerate(zip(centers, radii, strict=True)):
        c3 = np.append(c, 0.0) if planar else c
        yaw, scale = 0.0, (2 * r, 2 * r, 0.2 if planar else 2 * r)
        kind = marker.CYLINDER if planar else marker.SPHERE
        if boxes is not None:
            kind, scale, yaw = (
                marker.CUBE,
                (2 * boxes[k, 0], 2 * boxes[k, 1], 0.2),
                float(np.arctan2(boxes[k, 3], boxes[k, 2])),
            )
        out.append(marker(
            header=codecs._header(stamp, WORLD), ns="obstacles", id=k, type=kind, action=marker.ADD,
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=float(c3[0]), y=float(c3[1]), z=float(c3[2])),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=float(np.sin(yaw / 2)),
                                                              w=float(np.cos(yaw / 2)))),
            scale=t["geometry_msgs/msg/Vector3"](x=float(scale[0]), y=float(scale[1]), z=float(scale[2])),
            color=t["std_msgs/msg/ColorRGBA"](r=0.5, g=0.5, b=0.55, a=0.6),
            lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False, points=[],
            colors=[], texture_resource="", texture=t["sensor_msgs/msg/CompressedImage"](
                header=codecs._header(0, ""), format="", data=np.zeros(0, dtype=np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, dtype=np.uint8)),
            mesh_use_embedded_materials=False,
        ))  # fmt: skip
    return t["visualization_msgs/msg/MarkerArray"](markers=out)


def _pad3(a: np.ndarray) -> np.ndarray:
    return a if a.shape[-1] == 3 else np.concatenate((a, np.zeros((*a.shape[:-1], 3 - a.shape[-1]))), -1)


#: the recorded environment's steps are turned into messages this many agent-steps at a time (one LiDAR scan and
#: one CBF forward over the steps together, :class:`EpisodeRecorder`): the memory held stays bounded at any size
BATCH_AGENT_STEPS = 4096


@dataclass
class _Step:
    """What :class:`EpisodeRecorder` keeps of a step until it writes it: environment 0's state ``(N, S)``, its stamp,
    the filter's activity ``(N,)`` uint8 (or ``None``), and the goals and obstacles when they are not the first
    step's (``None``: the first step's)."""

    x: torch.Tensor
    stamp: int
    active: np.ndarray | None
    scene: tuple[torch.Tensor, Obstacles] | None


def _first_env(obstacles: Obstacles) -> Obstacles:
    return Obstacles(obstacles.centers[:1], obstacles.radii[:1],
                     None if obstacles.boxes is None else obstacles.boxes[:1])  # fmt: skip


class EpisodeRecorder:
    """An ``on_step`` callback (:data:`egcbf.evaluate.episodes.StepCallback`) writing environment 0 of the first
    episode batch it watches to an MCAP file (module doc); later sizes and episodes are ignored.

    Each call keeps environment 0's state (and the filter's activity); the messages of the kept steps are made
    together, :data:`BATCH_AGENT_STEPS` agent-steps at a time and at the episode's end (one LiDAR scan and one CBF
    forward over those steps as environments of one batch), and written in step order: the messages, in the order,
    that making each step's own at its call would write, with the same values (the batched ray products and network
    layers may round the LiDAR hits and ``h`` differently in the last bit). :meth:`close` writes what is still kept.

    Args:
        path: the ``.mcap`` file to write (replaced if it exists, at :meth:`close`).
        cbf: the controller's learned CBF (an :class:`egcbf.nn.models.CBFNet`), whose per-agent value ``h`` is
            recorded; ``None``: no ``/egcbf/cbf`` topic.
        metadata: strings added to the file's ``egcbf`` metadata record.
    """

    def __init__(self, path: str | Path, *, cbf=None, metadata: dict[str, str] | None = None):
        path = Path(path)
        if path.suffix != ".mcap":
            raise ValueError(f"a recording is an MCAP file: its name must end with .mcap, got {path}")
        self.path, self.cbf, self.metadata = path, cbf, dict(metadata or {})
        self._writer: RecordingWriter | None = None
        self._config: EnvConfig | None = None
        self.done = False
        self._static: dict = {}
        self._pending: list[_Step] = []
        #: the log times recorded (ns), one per step (written to the file by the episode's end)
        self.stamps: list[int] = []

    @property
    def num_agents(self) -> int | None:
        """The swarm size being recorded (``None`` before the first call)."""
        return None if self._config is None else self._config.num_agents

    def __call__(self, config: EnvConfig, state: SwarmState, u, info: dict | None) -> None:
        if self.done:
            return
        if self._config is None:
            self._config = config
            self._writer = RecordingWriter(self.path)
        elif config.num_agents != self._config.num_agents:
            return
        try:
            self._keep(config, state, info)
            if info is None or len(self._pending) * config.num_agents >= BATCH_AGENT_STEPS:
                self._flush()
        except BaseException:
            self.abort()
            raise
        if info is None:
            self.done = True

    def _keep(self, config: EnvConfig, state: SwarmState, info: dict | None) -> None:
        """Keep what the step's messages are made of (cheap: environment 0's state, copied)."""
        stamp = codecs.seconds_to_ns(state.t * config.dt)
        if not self._static:  # goals and obstacles stay for the episode: serialized once, stamped with the first step
            self._robot, self._goals, self._obstacles = state.robot, state.goals, state.obstacles
            self._scene = (state.goals[:1].detach(), _first_env(state.obstacles.detach()))
            goals = _pad3(state.goals[0].detach().double().cpu().numpy())
            self._static = {
                "goals": _pose_array_cdr(goals, np.tile([0.0, 0.0, 0.0, 1.0], (len(goals), 1)), stamp),
                "obstacles": bytes(typestore().serialize_cdr(_markers(self._scene[1], stamp), TOPICS["obstacles"][1])),
            }
        scene = None
        if state.goals is not self._goals or state.obstacles is not self._obstacles:
            scene = (state.goals[:1].detach().clone(), _first_env(state.obstacles.detach()))
        active = None
        if info is not None and "active_mask" in info:
            active = np.asarray(info["active_mask"])[0].astype(np.uint8)  # a copy
        self.stamps.append(stamp)
        self._pending.append(_Step(state.x[0].detach().clone(), stamp, active, scene))

    def _flush(self) -> None:
        """Make and write the messages of the kept steps."""
        from ..env.graph import build_graph

        steps, self._pending = self._pending, []
        if not steps:
            return
        w, config, robot, t = self._writer, self._config, self._robot, TOPICS
        x = torch.stack([s.x for s in steps])  # (T, N, S): the steps as environments
        n = x.shape[1]
        if all(s.scene is None for s in steps):
            goals0, obs0 = self._scene
            goals = goals0.expand(len(steps), -1, -1)
            obstacles = Obstacles(obs0.centers.expand(len(steps), -1, -1), obs0.radii.expand(len(steps), -1),
                                  None if obs0.boxes is None else obs0.boxes.expand(len(steps), -1, -1))  # fmt: skip
        else:
            scenes = [self._scene if s.scene is None else s.scene for s in steps]
            goals = torch.cat([g for g, _ in scenes])
            obstacles = Obstacles.cat([o for _, o in scenes])
        x64 = x.double().cpu().numpy()
        positions = robot.positions(x)
        pos64 = _pad3(positions.double().cpu().numpy())
        heading = robot.heading(x)
        try:
            quats = codecs.rotation_to_quaternion(robot.attitudes(x).double().cpu().numpy().reshape(-1, 3, 3))
            quats = quats.reshape(len(steps), n, 4)
        except AttributeError:  # a planar robot: its heading as a yaw
            head = heading.double().cpu().numpy()
            yaw = np.arctan2(head[..., 1], head[..., 0])
            quats = np.stack((0 * yaw, 0 * yaw, np.sin(yaw / 2), np.cos(yaw / 2)), -1)
        scan = config.scan(positions, heading, obstacles)
        valid = scan.valid.reshape(len(steps), -1).cpu().numpy()  # (T, N * H), agent-major, closest first
        hits = _pad3(scan.points.detach().double().cpu().numpy()).reshape(len(steps), -1, 3)
        owner = np.broadcast_to(np.repeat(np.arange(n, dtype=np.uint32), valid.shape[1] // max(n, 1)), valid.shape)
        points = _cloud_points(hits[valid], owner[valid])
        h = None
        if self.cbf is not None:
            p = next(self.cbf.parameters())
            batch = SwarmState(x, goals, obstacles, 0, robot)
            same = p.dtype == x.dtype and p.device == x.device  # then the graph's LiDAR is the scan above
            with torch.no_grad():
                graph = build_graph(batch if same else batch.to(p.device, dtype=p.dtype), config,
                                    lidar=scan if same else None)  # fmt: skip
                h = self.cbf(graph).double().cpu().numpy().reshape(len(steps), n)
        stamps = [s.stamp for s in steps]
        poses = _same_layout_cdrs(_pose_array_cdr(np.zeros((n, 3)), np.zeros((n, 4)), 0),
                                  _array_bytes(np.concatenate((pos64, quats), -1), np.float64), stamps)  # fmt: skip
        states = _same_layout_cdrs(_multiarray_cdr(t["states"][1], np.zeros(x64.shape[1:]), ("agent", "state")),
                                   _array_bytes(x64, np.float64))  # fmt: skip
        clouds = _cloud_cdrs(points, valid.sum(1).tolist(), stamps)
        cbf = [None] * len(steps)
        if h is not None:
            cbf = _same_layout_cdrs(_multiarray_cdr(t["cbf"][1], np.zeros(n), ("agent",)), _array_bytes(h, np.float64))
        active = [k for k, s in enumerate(steps) if s.active is not None]
        filtered = dict.fromkeys(range(len(steps)))
        if active:
            one = _multiarray_cdr(t["filter_active"][1], np.zeros(n, dtype=np.uint8), ("agent",))
            msgs = _same_layout_cdrs(one, _array_bytes(np.stack([steps[k].active for k in active]), np.uint8))
            filtered.update(zip(active, msgs, strict=True))
        for k, stamp in enumerate(stamps):  # in step order, each step's messages in the order of TOPICS
            w.write(*t["poses"], poses[k], stamp)
            w.write(*t["goals"], self._static["goals"], stamp)
            w.write(*t["states"], states[k], stamp)
            w.write(*t["obstacles"], self._static["obstacles"], stamp)
            w.write(*t["lidar"], clouds[k], stamp)
            if cbf[k] is not None:
                w.write(*t["cbf"], cbf[k], stamp)
            if filtered[k] is not None:
                w.write(*t["filter_active"], filtered[k], stamp)

    def close(self) -> Path | None:
        """Write the steps still kept, finish and move the file into place; ``None`` if nothing was recorded."""
        if self._writer is None:
            return None
        try:
            self._flush()
        except BaseException:
            self.abort()
            raise
        cfg = self._config
        meta = {"dt": repr(cfg.dt), "num_agents": str(cfg.num_agents), "robot": cfg.robot,
                "steps": str(len(self.stamps) - 1), **self.metadata}  # fmt: skip
        path, self._writer = self._writer.close(meta), None
        return path

    def abort(self) -> None:
        """Drop the file being written (a failed run)."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
        self._pending = []
        self.done = True


# ----------------------------------------------------------------------------------------------- reading
def iter_messages(path: str | Path, topics: tuple[str, ...] | None = None) -> Iterator[tuple[str, int, object]]:
    """``(topic, log_time (ns), message)`` of every message of an MCAP file of ``cdr`` ROS 2 messages (in log
    time order; ``topics``: only those), deserialized with :func:`egcbf.ros.messages.typestore` (``ValueError``
    for a type it does not know or another encoding)."""
    require_extra("reading a recording")
    from mcap.reader import make_reader

    store = typestore()
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=topics, log_time_order=True):
            if channel.message_encoding != "cdr" or schema is None or schema.name not in store.types:
                name = getattr(schema, "name", None)
                raise ValueError(f"{path}: topic {channel.topic} holds {channel.message_encoding!r} messages of "
                                 f"schema {name!r}, not ROS 2 CDR of a known type")  # fmt: skip
            yield channel.topic, message.log_time, store.deserialize_cdr(message.data, schema.name)


def _metadata(path: str | Path) -> dict[str, str]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        for record in make_reader(f).iter_metadata():
            if record.name == _METADATA:
                return dict(record.metadata)
    return {}


@dataclass
class Recording:
    """A recording read back (:func:`read_recording`): ``T + 1`` steps of ``N`` agents, world frame, float64.

    Attributes:
        stamps: ``(T + 1,)`` log times (ns), ``t * dt``.
        positions: ``(T + 1, N, 3)``; attitudes: ``(T + 1, N, 3, 3)`` body-to-world rotations (of the quaternions).
        states: ``(T + 1, N, S)``; goals: ``(T + 1, N, 3)``.
        centers, radii: ``(K, 3)``, ``(K,)`` the obstacles of the first step (half the marker's x scale).
        hits: ``T + 1`` arrays ``(M_t, 3)``; hit_agent: ``T + 1`` arrays ``(M_t,)``, each hit's owner.
        h: ``(T + 1, N)`` the learned CBF, or ``None``; filter_active: ``(T, N)`` bool, or ``None``.
        counts: messages per topic; metadata: the ``egcbf`` metadata record.
    """

    stamps: np.ndarray
    positions: np.ndarray
    attitudes: np.ndarray
    states: np.ndarray
    goals: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    hits: list[np.ndarray] = field(default_factory=list)
    hit_agent: list[np.ndarray] = field(default_factory=list)
    h: np.ndarray | None = None
    filter_active: np.ndarray | None = None
    counts: dict[str, int] = field(default_factory=dict)
    metadata: dict[str, str] = field(default_factory=dict)


def _pose_rows(msg) -> tuple[np.ndarray, np.ndarray]:
    p = np.array([(q.position.x, q.position.y, q.position.z) for q in msg.poses], dtype=np.float64).reshape(-1, 3)
    rot = np.array([codecs.quaternion_to_rotation((q.orientation.x, q.orientation.y, q.orientation.z,
                                                   q.orientation.w)) for q in msg.poses]).reshape(-1, 3, 3)  # fmt: skip
    return p, rot


def read_recording(path: str | Path) -> Recording:
    """The arrays of a recording written by :class:`EpisodeRecorder` (:class:`Recording`)."""
    by = {topic: key for key, (topic, _) in TOPICS.items()}
    seen: dict[str, list] = {key: [] for key in TOPICS}
    stamps: list[int] = []
    counts: dict[str, int] = {}
    for topic, stamp, msg in iter_messages(path):
        counts[topic] = counts.get(topic, 0) + 1
        key = by.get(topic)
        if key is None:
            continue
        if key == "poses":
            stamps.append(stamp)
        seen[key].append(msg)
    if not seen["poses"]:
        raise ValueError(f"{path}: no {TOPICS['poses'][0]} messages: not an egcbf recording")
    poses = [_pose_rows(m) for m in seen["poses"]]
    states = np.stack([np.asarray(m.data, dtype=np.float64).reshape(m.layout.dim[0].size, m.layout.dim[1].size)
                       for m in seen["states"]])  # fmt: skip
    markers = seen["obstacles"][0].markers if seen["obstacles"] else []
    clouds = seen["lidar"]
    return Recording(
        stamps=np.asarray(stamps, dtype=np.int64),
        positions=np.stack([p for p, _ in poses]),
        attitudes=np.stack([r for _, r in poses]),
        states=states,
        goals=np.stack([_pose_rows(m)[0] for m in seen["goals"]]),
        centers=np.array([(m.pose.position.x, m.pose.position.y, m.pose.position.z) for m in markers]).reshape(-1, 3),
        radii=np.array([m.scale.x / 2 for m in markers], dtype=np.float64),
        hits=[codecs.cloud_to_hits(c)[0] for c in clouds],
        hit_agent=[codecs.cloud_field(c, "agent").astype(np.int64) for c in clouds],
        h=np.stack([np.asarray(m.data, dtype=np.float64) for m in seen["cbf"]]) if seen["cbf"] else None,
        filter_active=(
            np.stack([np.asarray(m.data).astype(bool) for m in seen["filter_active"]])
            if seen["filter_active"]
            else None
        ),
        counts=counts,
        metadata=_metadata(path),
    )
