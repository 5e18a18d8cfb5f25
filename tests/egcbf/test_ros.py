"""egcbf.ros: the codecs round-trip float64-exactly, a rosbag2 of an episode reads back to the same agent inputs and
commands, the bridge's tick is the deployed controller on the decoded inputs, and ``egcbf eval --record`` writes an
MCAP file that reads back to the trajectory. Skipped without the ``ros`` extra."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("rosbags")
pytest.importorskip("mcap")

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from egcbf.ros import codecs
from egcbf.ros.messages import AGENT_STATE, BODY_RATE_THRUST, DEFINITIONS, FULL_STATE, typestore

CKPT = Path(__file__).resolve().parents[2] / "checkpoints" / "egcbf+"
TOL = 1e-12
finite = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)


def cdr(msg):
    """``msg`` through CDR bytes and back: what a bag or the wire holds."""
    store = typestore()
    return store.deserialize_cdr(bytes(store.serialize_cdr(msg, msg.__msgtype__)), msg.__msgtype__)


@st.composite
def rotations(draw):
    q = draw(arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1))
    return codecs.quaternion_to_rotation(q / np.linalg.norm(q))


@st.composite
def quad_states(draw):
    p, v, w = (draw(arrays(np.float64, 3, elements=finite)) for _ in range(3))
    return np.concatenate((p, draw(rotations()).reshape(9), v, w))


stamps = st.integers(0, 2**40)


# ------------------------------------------------------------------------------------------------ codecs
@settings(max_examples=150, deadline=None)
@given(quad_states(), stamps)
def test_odometry_round_trips_a_state_float64_exactly(x, stamp):
    msg = cdr(codecs.state_to_odometry(x, stamp=stamp, child_frame_id="cf1"))
    assert codecs.stamp_ns(msg) == stamp and msg.child_frame_id == "cf1"
    np.testing.assert_allclose(codecs.odometry_to_state(msg, frame_id="world"), x, rtol=0, atol=TOL)
    R = x[3:12].reshape(3, 3)  # the twist is in the body frame: linear R^T v, angular w as it is
    t = msg.twist.twist
    np.testing.assert_allclose([t.linear.x, t.linear.y, t.linear.z], R.T @ x[12:15], atol=TOL)
    np.testing.assert_array_equal([t.angular.x, t.angular.y, t.angular.z], x[15:18])


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 40).flatmap(lambda h: st.tuples(arrays(np.float64, (h, 3), elements=finite),
                                                      arrays(np.bool_, h))), stamps)  # fmt: skip
def test_cloud_round_trips_hits_and_mask(hm, stamp):
    hits, mask = hm
    h = len(hits)
    msg = cdr(codecs.hits_to_cloud(hits, mask, stamp=stamp))
    out, valid = codecs.cloud_to_hits(msg, size=h)
    k = int(mask.sum())
    assert out.shape == (h, 3) and valid.tolist() == [True] * k + [False] * (h - k)
    np.testing.assert_array_equal(out[valid], hits[mask])
    np.testing.assert_array_equal(out[~valid], 0.0)
    f32 = hits.astype(np.float32).astype(np.float64)  # a float32 cloud holds float32 values exactly
    back, _ = codecs.cloud_to_hits(cdr(codecs.hits_to_cloud(f32, mask, stamp=stamp, dtype="float32")))
    np.testing.assert_array_equal(back, f32[mask])


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), stamps, arrays(np.float64, st.integers(1, 30), elements=finite))
def test_agent_state_round_trips(agent, stamp, x):
    assert_same = np.testing.assert_array_equal
    got = codecs.agent_state_to_state(cdr(codecs.agent_state(agent, x, stamp=stamp)), state_dim=None)
    assert got[:2] == (agent, stamp)
    assert_same(got[2], x)


@settings(max_examples=100, deadline=None)
@given(quad_states(), arrays(np.float64, 4, elements=st.floats(-0.01, 0.6)), arrays(np.float64, 3, elements=finite),
       st.floats(0, 0.2))  # fmt: skip
def test_commands_round_trip(x, u, accel, horizon):
    dt = 0.025
    msg = cdr(codecs.body_rate_thrust(u, x, dt, stamp=7))
    np.testing.assert_allclose(codecs.body_rate_thrust_to_control(msg, x, dt), u, rtol=0, atol=TOL)
    # one explicit Euler step of Euler's equation from the state's rate
    J = np.array([1.395e-5, 1.395e-5, 2.173e-5])
    w = x[15:18]
    rate = np.array([msg.body_rate.x, msg.body_rate.y, msg.body_rate.z])
    np.testing.assert_allclose(rate, w + dt * (u[:3] - np.cross(w, J * w)) / J, rtol=1e-12, atol=1e-9)
    sp = codecs.full_state_setpoint(cdr(codecs.full_state(x, accel, stamp=7, horizon=horizon)))
    p, v = x[:3], x[12:15]
    np.testing.assert_array_equal(sp["acceleration"], accel)
    np.testing.assert_allclose(sp["position"], p + v * horizon + accel * horizon**2 / 2, rtol=0, atol=TOL)
    np.testing.assert_allclose(sp["velocity"], v + accel * horizon, rtol=0, atol=TOL)
    yaw = codecs.yaw_of(x[3:12].reshape(3, 3))
    assert abs(math.remainder(sp["yaw"] - yaw, 2 * math.pi)) < 1e-12
    np.testing.assert_array_equal(sp["body_rate"], 0.0)


def test_codecs_refuse_bad_input():
    x = np.concatenate((np.zeros(3), np.eye(3).reshape(9), np.zeros(6)))
    odom = codecs.state_to_odometry(x, stamp=0)
    with pytest.raises(TypeError, match="nav_msgs/msg/Odometry"):
        codecs.odometry_to_state(codecs.agent_state(1, x, stamp=0))
    with pytest.raises(ValueError, match="frame"):
        codecs.odometry_to_state(odom, frame_id="map")
    bad = x.copy()
    bad[0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        codecs.state_to_odometry(bad, stamp=0)
    with pytest.raises(ValueError, match="not a rotation"):
        codecs.state_to_odometry(np.concatenate((np.zeros(3), 2 * np.eye(3).reshape(9), np.zeros(6))), stamp=0)
    odom.pose.pose.orientation.w = 2.0
    with pytest.raises(ValueError, match="norm"):
        codecs.odometry_to_state(odom)
    with pytest.raises(ValueError, match="NaN"):
        codecs.agent_state_to_state(_with_nan_state())
    with pytest.raises(ValueError, match="expected 18"):
        codecs.agent_state_to_state(codecs.agent_state(2, np.zeros(5), stamp=0))
    with pytest.raises(ValueError, match="stamp"):
        codecs.agent_state(2, np.zeros(5), stamp=-1)
    cloud = codecs.hits_to_cloud(np.ones((3, 3)), stamp=0)
    cloud.fields = [f for f in cloud.fields if f.name != "z"]
    with pytest.raises(ValueError, match="fields x, y, z"):
        codecs.cloud_to_hits(cloud)
    short = codecs.hits_to_cloud(np.ones((3, 3)), stamp=0)
    short.data = short.data[:-1]
    with pytest.raises(ValueError, match="data bytes"):
        codecs.cloud_to_hits(short)
    with pytest.raises(ValueError, match="more than size"):
        codecs.cloud_to_hits(codecs.hits_to_cloud(np.ones((3, 3)), stamp=0), size=2)


def _with_nan_state():
    msg = codecs.agent_state(2, np.zeros(18), stamp=0)
    msg.state[4] = np.nan
    return msg


def test_a_cloud_with_rays_without_return_masks_them_and_a_dense_one_refuses_nan():
    pts = np.array([[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [4.0, 5.0, 6.0]])
    msg = codecs.hits_to_cloud(np.nan_to_num(pts), stamp=0)
    data = msg.data.view(np.float64).reshape(3, 3)
    data[1] = np.nan
    msg.is_dense = False
    hits, mask = codecs.cloud_to_hits(msg)
    assert mask.tolist() == [True, False, True] and hits[1].tolist() == [0, 0, 0]
    msg.is_dense = True
    with pytest.raises(ValueError, match="dense"):
        codecs.cloud_to_hits(msg)


def test_a_body_frame_cloud_is_placed_in_the_world_and_organized_padded_clouds_read():
    R = codecs.quaternion_to_rotation(np.array([0.1, -0.3, 0.5, 0.8]) / math.sqrt(0.99))
    p = np.array([1.0, -2.0, 0.5])
    body = np.array([[0.3, 0.0, 0.1], [-0.2, 0.4, 0.0]])
    hits, _ = codecs.cloud_to_hits(codecs.hits_to_cloud(body, stamp=0, frame_id="cf1"), body_pose=(p, R))
    np.testing.assert_allclose(hits, p + body @ R.T, atol=TOL)
    # a 2 x 2 organized float32 cloud with a padded point and row: other drivers' layout
    t = typestore().types
    field = t["sensor_msgs/msg/PointField"]
    rec = np.zeros((2, 2), dtype=np.dtype({"names": ["x", "y", "z", "i"], "formats": [">f4"] * 4,
                                           "offsets": [0, 4, 8, 16], "itemsize": 20}))  # fmt: skip
    rec["x"], rec["y"], rec["z"] = [[1, 2], [3, 4]], [[5, 6], [7, 8]], [[9, 10], [11, 12]]
    raw = np.concatenate([np.concatenate((r.view(np.uint8), np.zeros(8, np.uint8))) for r in rec])
    msg = t["sensor_msgs/msg/PointCloud2"](
        header=codecs._header(0, "world"), height=2, width=2, is_bigendian=True, point_step=20, row_step=48,
        fields=[field(name=n, offset=o, datatype=7, count=1) for n, o in (("x", 0), ("y", 4), ("z", 8), ("i", 16))],
        data=raw, is_dense=True,
    )  # fmt: skip
    hits, mask = codecs.cloud_to_hits(cdr(msg))
    assert mask.all() and hits.tolist() == [[1, 5, 9], [2, 6, 10], [3, 7, 11], [4, 8, 12]]


def test_message_definitions_parse_and_the_packages_are_written(tmp_path):
    from egcbf.ros.messages import write_msg_packages

    store = typestore()
    for name in DEFINITIONS:
        assert name in store.types
    full = store.types[FULL_STATE].__dataclass_fields__
    assert [f for f in full if not f.startswith("__")] == ["header", "pose", "twist", "acc"]
    files = {p.relative_to(tmp_path).as_posix() for p in write_msg_packages(tmp_path)}
    assert {"egcbf_msgs/msg/AgentState.msg", "egcbf_msgs/msg/BodyRateThrust.msg", "egcbf_msgs/package.xml",
            "crazyflie_interfaces/msg/FullState.msg", "crazyflie_interfaces/CMakeLists.txt"} <= files  # fmt: skip


# ------------------------------------------------------------------------------------------------ rosbag2
def test_a_rosbag2_of_an_episode_reads_back_to_the_same_agent_inputs_and_commands(tmp_path):
    """10 steps of 3 quadrotors among 2 obstacles (nominal control, float64): every agent's odometry, every
    neighbour broadcast, every cloud and every command, per step, into a rosbag2 and back."""
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.rosbag2.enums import StoragePlugin

    from egcbf.env import EnvConfig, SwarmEnv
    from egcbf.robots.quadrotor.nominal import nominal_acceleration, track_acceleration

    cfg = EnvConfig(num_agents=3, num_obstacles=2, area_size=2.0, max_steps=10)
    env = SwarmEnv(cfg, dtype=torch.float64)
    state = env.reset(3)
    store = typestore()
    expected, conns = [], {}
    bag = tmp_path / "episode"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:

        def put(topic, msg, stamp):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=store)
            w.write(conns[topic], stamp, store.serialize_cdr(msg, msg.__msgtype__))

        for step in range(cfg.max_steps):
            stamp = codecs.seconds_to_ns(step * cfg.dt)
            x = state.x[0]
            accel = nominal_acceleration(x, state.goals[0])
            u = track_acceleration(x, accel)
            scan = env.lidar(state)
            for i in range(cfg.num_agents):
                xi = x[i].numpy()
                put(f"/cf{i}/odom", codecs.state_to_odometry(xi, stamp=stamp, child_frame_id=f"cf{i}"), stamp)
                put("/swarm/agent_states", codecs.agent_state(i, xi, stamp=stamp), stamp)
                put(f"/cf{i}/lidar", codecs.hits_to_cloud(scan.points[0, i].numpy(), scan.valid[0, i].numpy(),
                                                          stamp=stamp), stamp)  # fmt: skip
                put(f"/cf{i}/cmd_body_rate_thrust", codecs.body_rate_thrust(u[i].numpy(), xi, cfg.dt, stamp=stamp),
                    stamp)  # fmt: skip
                put(f"/cf{i}/cmd_full_state", codecs.full_state(xi, accel[i].numpy(), stamp=stamp), stamp)
                expected.append((step, i, xi, np.delete(x.numpy(), i, 0), scan.points[0, i][scan.valid[0, i]].numpy(),
                                 u[i].numpy(), accel[i].numpy()))  # fmt: skip
            state, _ = env.step(state, u[None])
    got: dict = {}
    with Reader(bag) as r:
        assert r.message_count == cfg.max_steps * cfg.num_agents * 5
        for conn, stamp, raw in r.messages():
            step = round(stamp / (cfg.dt * 1e9))
            msg = store.deserialize_cdr(raw, conn.msgtype)
            assert codecs.stamp_ns(msg) == stamp
            topic = conn.topic
            if topic == "/swarm/agent_states":
                agent, _, xs = codecs.agent_state_to_state(msg)
                got.setdefault(step, {}).setdefault("heard", {})[agent] = xs
                continue
            agent, kind = int(topic.split("/")[1][2:]), topic.split("/")[2]
            got.setdefault(step, {}).setdefault(agent, {})[kind] = msg
    for step, i, xi, nbrs, hits, u, accel in expected:
        g = got[step][i]
        own = codecs.odometry_to_state(g["odom"])
        np.testing.assert_allclose(own, xi, rtol=0, atol=TOL)
        heard = got[step]["heard"]
        np.testing.assert_array_equal(np.stack([heard[j] for j in sorted(heard) if j != i]), nbrs)
        cloud, mask = codecs.cloud_to_hits(g["lidar"])
        assert mask.all()
        np.testing.assert_array_equal(cloud, hits)
        np.testing.assert_allclose(codecs.body_rate_thrust_to_control(g["cmd_body_rate_thrust"], own, cfg.dt), u,
                                   rtol=0, atol=TOL)  # fmt: skip
        np.testing.assert_array_equal(codecs.full_state_setpoint(g["cmd_full_state"])["acceleration"], accel)


# ------------------------------------------------------------------------------------------------ bridge
@pytest.fixture(scope="module")
def agent_controller():
    from egcbf.deploy.agent import AgentController

    return AgentController.from_checkpoint(CKPT, dtype=torch.float64)


def _scene(seed: int = 0):
    from egcbf.env import EnvConfig, SwarmEnv

    cfg = EnvConfig(num_agents=4, num_obstacles=3, area_size=1.5)
    env = SwarmEnv(cfg, dtype=torch.float64)
    state = env.reset(seed)
    return state, env.lidar(state)


def test_the_bridge_ticks_the_controller_on_the_decoded_inputs(agent_controller):
    from egcbf.ros.bridge import AgentBridge, Topics

    state, scan = _scene()
    x = state.x[0]
    sent = []
    bridge = AgentBridge(agent_controller, 0, publish=lambda topic, msg: sent.append((topic, cdr(msg))))
    now = codecs.seconds_to_ns(10.0)
    bridge.on_odometry(cdr(codecs.state_to_odometry(x[0].numpy(), stamp=now - 5_000_000, child_frame_id="cf0")))
    assert bridge.tick(now).keys() == {Topics.neighbours} and bridge.skipped == "no goal yet"
    sent.clear()
    bridge.on_goal(cdr(codecs.goal_to_point(state.goals[0, 0].numpy(), stamp=now)))
    for j in (1, 2):
        bridge.on_neighbour(cdr(codecs.agent_state(j, x[j].numpy(), stamp=now - 10_000_000)))
    bridge.on_neighbour(cdr(codecs.agent_state(3, x[3].numpy(), stamp=now - 500_000_000)))  # stale: dropped
    bridge.on_neighbour(cdr(codecs.agent_state(0, x[1].numpy(), stamp=now)))  # its own, heard back: ignored
    bridge.on_neighbour(cdr(codecs.agent_state(2, x[3].numpy(), stamp=now - 20_000_000)))  # older than held
    assert "cloud" in bridge.not_ready(now)
    bridge.on_cloud(cdr(codecs.hits_to_cloud(scan.points[0, 0].numpy(), scan.valid[0, 0].numpy(), stamp=now)))
    out = bridge.tick(now)
    assert bridge.skipped is None and set(out) == {Topics.body_rate_thrust, Topics.full_state, Topics.neighbours}
    assert [t for t, _ in sent] == list(out)
    hits = scan.points[0, 0][scan.valid[0, 0]]
    u, info = agent_controller(x[0], state.goals[0, 0], x[1:3], hits)  # the controller on the same inputs
    msgs = dict(sent)
    own = bridge.inputs(now)["state"].numpy()
    np.testing.assert_allclose(own, x[0].numpy(), rtol=0, atol=TOL)
    np.testing.assert_allclose(bridge.inputs(now)["neighbours"].numpy(), x[1:3].numpy(), rtol=0, atol=TOL)
    np.testing.assert_allclose(
        codecs.body_rate_thrust_to_control(msgs[Topics.body_rate_thrust], own, agent_controller.env_config.dt),
        u.numpy(), rtol=0, atol=TOL,
    )  # fmt: skip
    accel = bridge.accel_unit * info["command"].numpy()
    np.testing.assert_allclose(codecs.full_state_setpoint(msgs[Topics.full_state])["acceleration"], accel, atol=TOL)
    assert msgs[Topics.body_rate_thrust].header.frame_id == "cf0"
    agent, stamp, broadcast = codecs.agent_state_to_state(msgs[Topics.neighbours])
    assert (agent, stamp) == (0, now - 5_000_000)
    np.testing.assert_allclose(broadcast, x[0].numpy(), atol=TOL)
    assert bridge.tick(now + codecs.seconds_to_ns(1.0)) == {} and "odometry" in bridge.skipped
    with pytest.raises(TypeError, match="PointStamped"):
        bridge.on_goal(codecs.agent_state(1, x[1].numpy(), stamp=now))
    with pytest.raises(ValueError, match="frame"):
        bridge.on_cloud(codecs.hits_to_cloud(hits.numpy(), stamp=now, frame_id="map"))


def test_the_bridge_behind_the_filter_passes_obstacles_and_accelerations(agent_controller):
    from egcbf.deploy.agent import AgentFilteredController
    from egcbf.ros.bridge import AgentBridge

    state, _ = _scene(1)
    x = state.x[0].clone()
    ctrl = AgentFilteredController(agent_controller)
    obstacles = (state.obstacles.centers[0], state.obstacles.radii[0])
    bridge = AgentBridge(ctrl, 0, goal=state.goals[0, 0].numpy(), obstacles=obstacles, require_cloud=False)
    t0, dt = 1_000_000_000, 25_000_000
    for k, scale in enumerate((0.0, 1.0)):  # two messages each, the velocities changed by 0.1 m/s per axis
        xs = x.clone()
        xs[:, 12:15] += 0.1 * scale
        bridge.on_odometry(codecs.state_to_odometry(xs[0].numpy(), stamp=t0 + k * dt))
        bridge.on_neighbour(codecs.agent_state(1, xs[1].numpy(), stamp=t0 + k * dt))
    bridge.on_neighbour(codecs.agent_state(2, x[2].numpy(), stamp=t0 + dt))  # heard once: zero acceleration
    inputs = bridge.inputs(t0 + dt)
    np.testing.assert_allclose(inputs["accelerations"].numpy(), [[4.0] * 3, [4.0] * 3, [0.0] * 3], atol=1e-9)
    out = bridge.tick(t0 + dt)
    u, info = ctrl(**inputs)
    sent = codecs.body_rate_thrust_to_control(out["cmd_body_rate_thrust"], inputs["state"].numpy(), bridge.dt)
    np.testing.assert_allclose(sent, u.numpy(), rtol=0, atol=TOL)
    np.testing.assert_allclose(codecs.full_state_setpoint(out["cmd_full_state"])["acceleration"],
                               bridge.accel_unit * info["command"].numpy(), atol=TOL)  # fmt: skip


def test_the_node_module_imports_without_ros_and_says_what_to_install():
    from egcbf.ros import node

    try:
        import rclpy  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="ROS 2"):
            node.make_node(None)
    subscribed, published = node.topic_types(__import__("egcbf.ros.bridge", fromlist=["Topics"]).Topics())
    assert published["cmd_full_state"] == FULL_STATE and published["cmd_body_rate_thrust"] == BODY_RATE_THRUST
    assert subscribed["/swarm/agent_states"] == AGENT_STATE


# ------------------------------------------------------------------------------------------------ recording
def test_eval_record_writes_an_mcap_of_the_first_episode(tmp_path):
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader
    from typer.testing import CliRunner

    from egcbf.cli import app
    from egcbf.control.filters import FilterConfig
    from egcbf.control.resolve import resolve
    from egcbf.evaluate.episodes import evaluate
    from egcbf.ros.record import TOPICS, read_recording

    steps, n = 6, 4
    path = tmp_path / "episode.mcap"
    args = ["eval", "--num-agents", f"{n},5", "--episodes", "2", "--max-steps", str(steps), "--obstacles", "2",
            "--area", "2", "--checkpoint", str(CKPT), "--filter", "dcbf", "--no-progress"]  # fmt: skip
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "out"), "--record", str(path), "--record-cbf"])
    assert res.exit_code == 0, res.output
    assert f"wrote {path}" in res.output and path.exists() and not list(tmp_path.glob(".*partial*"))
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts = {summary.channels[c].topic: k for c, k in summary.statistics.channel_message_counts.items()}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert reader.get_header().profile == "ros2"
    want = {TOPICS[k][0]: steps + 1 for k in ("poses", "goals", "states", "obstacles", "lidar", "cbf")}
    assert counts == {**want, TOPICS["filter_active"][0]: steps}  # h: the checkpoint's CBF, though dcbf filters
    rec = read_recording(path)
    dt = 0.025
    assert rec.stamps.tolist() == [codecs.seconds_to_ns(t * dt) for t in range(steps + 1)]
    assert rec.metadata["num_agents"] == str(n) and rec.metadata["dt"] == repr(dt)
    built = resolve("egcbf+:dcbf", CKPT, filter_config=FilterConfig.for_kind("dcbf"))  # the same episode again
    _, records = evaluate(lambda cfg: built.controller, [n], episodes=2, max_steps=steps, num_obstacles=2,
                          area_size=2.0, record=True, show_progress=False)  # fmt: skip
    traj = torch.stack(records[n].positions).double().numpy()
    np.testing.assert_array_equal(rec.positions, traj)
    np.testing.assert_array_equal(rec.states[..., :3], traj)
    np.testing.assert_allclose(rec.attitudes.reshape(steps + 1, n, 9), rec.states[..., 3:12], atol=1e-6)
    np.testing.assert_array_equal(rec.goals[0], records[n].goals.double().numpy())
    np.testing.assert_allclose(rec.radii, records[n].radii.double().numpy(), rtol=1e-15)
    assert rec.filter_active.shape == (steps, n) and rec.h.shape == (steps + 1, n) and np.isfinite(rec.h).all()
    assert all(len(h) == len(a) for h, a in zip(rec.hits, rec.hit_agent, strict=True))
    with Reader(path) as bag:  # rosbag2's MCAP storage reads it as a bag
        assert bag.message_count == sum(counts.values())


def test_eval_record_writes_the_cbf_only_when_asked(tmp_path):
    from typer.testing import CliRunner

    from egcbf.cli import app
    from egcbf.ros.record import TOPICS, read_recording

    path = tmp_path / "episode.mcap"
    args = ["eval", "--num-agents", "3", "--episodes", "1", "--max-steps", "2", "--area", "2", "--checkpoint",
            str(CKPT), "--no-progress", "--out", str(tmp_path / "out"), "--record", str(path)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rec = read_recording(path)
    assert rec.h is None and TOPICS["cbf"][0] not in rec.counts and rec.counts[TOPICS["poses"][0]] == 3


def test_eval_record_refuses_a_bad_name_and_a_missing_extra(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import egcbf.ros.messages as messages
    from egcbf.cli import app

    base = ["eval", "--num-agents", "2", "--episodes", "1", "--max-steps", "2", "--no-progress", "--out",
            str(tmp_path / "out")]  # fmt: skip
    res = CliRunner().invoke(app, [*base, "--record", str(tmp_path / "episode.bag")])
    assert res.exit_code != 0 and "must end with .mcap" in res.output
    res = CliRunner().invoke(app, [*base, "--record-cbf"])
    assert res.exit_code != 0 and "pass --record FILE.mcap too" in res.output
    res = CliRunner().invoke(app, [*base, "--record", str(tmp_path / "episode.mcap"), "--record-cbf"])
    assert res.exit_code != 0 and "needs a --checkpoint" in res.output and not (tmp_path / "episode.mcap").exists()

    def missing(what="egcbf.ros"):
        raise messages.MissingExtraError(f"{what} needs the 'ros' extra (mcap missing): pip install 'egcbf[ros]'")

    monkeypatch.setattr(messages, "require_extra", missing)
    res = CliRunner().invoke(app, [*base, "--record", str(tmp_path / "episode.mcap")])
    assert res.exit_code != 0 and "egcbf[ros]" in res.output and not (tmp_path / "episode.mcap").exists()


def test_rotation_to_quaternion_takes_every_branch_and_batches():
    half_turns = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    near = np.array([[1, 0.1, 0, 0.05], [0, 1, 0.2, 0.1], [0.1, 0, 1, 0.1], [0, 0, 0.1, 1]])
    tilted = [codecs.quaternion_to_rotation(q / np.linalg.norm(q)) for q in near]
    R = np.stack(half_turns + tilted)
    q = codecs.rotation_to_quaternion(R)
    assert q.shape == (8, 4) and (q[:, 3] >= 0).all()
    for r, qi in zip(R, q, strict=True):
        np.testing.assert_allclose(codecs.quaternion_to_rotation(qi), r, rtol=0, atol=TOL)
        np.testing.assert_array_equal(codecs.rotation_to_quaternion(r), qi)


@given(st.integers(0, 40), st.integers(0, 2**40), st.integers(1, 20), st.sampled_from(["float64", "uint8"]))
@settings(max_examples=30, deadline=None)
def test_the_recorders_direct_cdr_is_what_rosbags_writes(n, stamp, width, kind):
    """The recorder writes its per-step array messages' CDR directly (egcbf.ros.record._CDR): byte for byte what
    rosbags' serializer writes for the same PoseArray and MultiArray messages."""
    from egcbf.ros import record

    store, t = typestore(), typestore().types
    rng = np.random.default_rng(n * 7919 + width)
    positions, quats = rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    poses = [t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                         orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
             for p, q in zip(positions.tolist(), quats.tolist(), strict=True)]  # fmt: skip
    msg = t["geometry_msgs/msg/PoseArray"](header=codecs._header(stamp, record.WORLD), poses=poses)
    assert record._pose_array_cdr(positions, quats, stamp) == bytes(store.serialize_cdr(msg, msg.__msgtype__))
    typename = "std_msgs/msg/Float64MultiArray" if kind == "float64" else "std_msgs/msg/UInt8MultiArray"
    data = rng.normal(size=(n, width)) if kind == "float64" else rng.integers(0, 2, size=(n, width)).astype(np.uint8)
    dim = t["std_msgs/msg/MultiArrayDimension"]
    layout = t["std_msgs/msg/MultiArrayLayout"](
        dim=[dim(label="agent", size=n, stride=n * width), dim(label="state", size=width, stride=width)], data_offset=0
    )
    ref = t[typename](layout=layout, data=np.ascontiguousarray(data.reshape(-1)))
    assert record._multiarray_cdr(typename, data, ("agent", "state")) == bytes(store.serialize_cdr(ref, typename))


@given(st.lists(st.integers(0, 12), min_size=1, max_size=5), st.lists(stamps, min_size=5, max_size=5),
       st.integers(1, 9))  # fmt: skip
@settings(max_examples=30, deadline=None)
def test_the_recorders_batched_cdr_is_the_per_step_cdr_and_what_rosbags_writes(counts, stamp_list, n):
    """The recorder makes a batch of steps' messages at once (egcbf.ros.record._same_layout_cdrs, _cloud_cdrs): each
    is the per-step message's bytes, and a cloud is what rosbags writes for codecs.hits_to_cloud's message."""
    from egcbf.ros import record

    store = typestore()
    rng = np.random.default_rng(sum(counts) * 31 + n)
    stamps_, steps = stamp_list[: len(counts)], len(counts)
    hits, owner = rng.normal(size=(sum(counts), 3)), rng.integers(0, 2**32, sum(counts)).astype(np.uint32)
    points = record._cloud_points(hits, owner)
    clouds = record._cloud_cdrs(points, counts, stamps_)
    ends = np.cumsum(counts)
    for k in range(steps):
        part = slice(ends[k] - counts[k], ends[k])
        ref = codecs.hits_to_cloud(hits[part], stamp=stamps_[k], frame_id=record.WORLD, agent=owner[part])
        assert clouds[k] == record._cloud_cdr(points[part], stamps_[k])
        assert clouds[k] == bytes(store.serialize_cdr(ref, ref.__msgtype__))
    pos, quats, x = rng.normal(size=(steps, n, 3)), rng.normal(size=(steps, n, 4)), rng.normal(size=(steps, n, 5))
    rows = record._array_bytes(np.concatenate((pos, quats), -1), np.float64)
    poses = record._same_layout_cdrs(record._pose_array_cdr(np.zeros((n, 3)), np.zeros((n, 4)), 0), rows, stamps_)
    f64, u8 = "std_msgs/msg/Float64MultiArray", "std_msgs/msg/UInt8MultiArray"
    states = record._same_layout_cdrs(record._multiarray_cdr(f64, np.zeros((n, 5)), ("agent", "state")),
                                      record._array_bytes(x, np.float64))  # fmt: skip
    active = rng.integers(0, 2, size=(steps, n)).astype(np.uint8)
    flags = record._same_layout_cdrs(record._multiarray_cdr(u8, np.zeros(n, np.uint8), ("agent",)),
                                     record._array_bytes(active, np.uint8))  # fmt: skip
    for k in range(steps):
        assert poses[k] == record._pose_array_cdr(pos[k], quats[k], stamps_[k])
        assert states[k] == record._multiarray_cdr(f64, x[k], ("agent", "state"))
        assert flags[k] == record._multiarray_cdr(u8, active[k], ("agent",))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_recording_holds_what_each_step_computes(tmp_path, monkeypatch, dtype):
    """The recorder keeps the steps and makes their messages in batches (several steps as environments of one LiDAR
    scan and one CBF forward): the file holds what a direct computation at each step gives. float64: the states
    exactly, the LiDAR hits to 1e-12 m (the batched ray products round alike up to an ulp); float32: the hits to
    1e-6 m; the learned CBF (a float32 network) to 1e-6 either way. A step whose goals and obstacles are other
    objects (equal values) takes the per-step path and agrees too."""
    from egcbf.control.filters import FilterConfig
    from egcbf.control.resolve import resolve
    from egcbf.env import EnvConfig, SwarmState
    from egcbf.env.graph import build_graph
    from egcbf.env.obstacles import Obstacles
    from egcbf.evaluate.episodes import run_episodes
    from egcbf.ros import record

    n, steps = 6, 11
    monkeypatch.setattr(record, "BATCH_AGENT_STEPS", 4 * n)  # flushes of 4 steps, and a partial one at the end
    ctrl = resolve("egcbf+:cbf", CKPT, filter_config=FilterConfig.for_kind("cbf")).controller
    cfg = EnvConfig.for_robot("quadrotor", num_agents=n, area_size=1.5, num_obstacles=3, max_steps=steps)
    rec = record.EpisodeRecorder(tmp_path / "episode.mcap", cbf=ctrl.cbf)
    seen = []

    def watch(config, state, u, info):
        if state.t % 3 == 2:  # the same scene as other objects
            obs = state.obstacles
            state = SwarmState(state.x, state.goals.clone(), Obstacles(obs.centers.clone(), obs.radii.clone()),
                               state.t, state.robot)  # fmt: skip
        seen.append((config, state, None if info is None else np.asarray(info["active_mask"])[0].copy()))
        rec(config, state, u, info)

    run_episodes(ctrl, cfg, [3, 4], on_step=watch, dtype=dtype)
    got = record.read_recording(rec.close())
    assert len(seen) == steps + 1 and got.h.shape == (steps + 1, n) and got.filter_active.shape == (steps, n)
    assert got.stamps.tolist() == rec.stamps == [codecs.seconds_to_ns(k * cfg.dt) for k in range(steps + 1)]
    hit_tol = 1e-12 if dtype == torch.float64 else 1e-6
    p = next(ctrl.cbf.parameters())
    total_hits = 0
    for k, (config, state, active) in enumerate(seen):
        one = SwarmState(state.x[:1], state.goals[:1], Obstacles(state.obstacles.centers[:1],
                         state.obstacles.radii[:1]), state.t, state.robot)  # fmt: skip
        np.testing.assert_array_equal(got.states[k], state.x[0].double().numpy())
        np.testing.assert_array_equal(got.positions[k], state.positions[0].double().numpy())
        np.testing.assert_allclose(got.attitudes[k], state.attitudes[0].double().numpy(), rtol=0, atol=1e-6)
        scan = config.scan(one.positions, state.robot.heading(one.x), one.obstacles)
        valid = scan.valid[0].numpy()
        np.testing.assert_array_equal(got.hit_agent[k], np.nonzero(valid)[0])
        np.testing.assert_allclose(got.hits[k], scan.points[0].double().numpy()[valid], rtol=0, atol=hit_tol)
        total_hits += int(valid.sum())
        with torch.no_grad():
            h = ctrl.cbf(build_graph(one.to(p.device, dtype=p.dtype), config)).double().numpy()
        np.testing.assert_allclose(got.h[k], h, rtol=0, atol=1e-6)
        if active is not None:
            np.testing.assert_array_equal(got.filter_active[k], active)
    assert total_hits > 0  # the scene is dense enough for the LiDAR to see something


def test_an_aborted_recording_leaves_no_file(tmp_path):
    from egcbf.control.resolve import resolve
    from egcbf.env import EnvConfig
    from egcbf.evaluate.episodes import run_episodes
    from egcbf.ros.record import EpisodeRecorder

    path = tmp_path / "episode.mcap"
    rec = EpisodeRecorder(path)

    def fail(config, state, u, info):
        rec(config, state, u, info)
        if state.t == 3:
            raise RuntimeError("the run fails")

    with pytest.raises(RuntimeError, match="the run fails"):
        run_episodes(resolve("nominal").controller, EnvConfig(num_agents=3, max_steps=6), [0], on_step=fail)
    rec.abort()
    assert rec.close() is None and not list(tmp_path.iterdir())
