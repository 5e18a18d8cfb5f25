"""Message faults in the decentralized CBF-QP (egcbf.faults + egcbf.robots.quadrotor.cbf_qp): each agent's pair rows
read its own estimate against the messages it received, directed, delayed and lost exactly as the graph's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from egcbf.cli import app
from egcbf.control.controllers import NominalController
from egcbf.control.filters import FilterConfig, FilteredController, filter_reads_sensing
from egcbf.env import EnvConfig, Obstacles, SwarmEnv, SwarmState
from egcbf.env.graph import KIND_AGENT, build_graph
from egcbf.evaluate.episodes import evaluate, fault_support_error
from egcbf.faults import DEFAULT_FIELD, FaultConfig, FaultProcess, Sensing, draws
from egcbf.faults.sensing import STREAMS, unread_faults
from egcbf.robots import make_robot
from egcbf.robots.quadrotor import dynamics as dyn
from egcbf.robots.quadrotor.barriers import BarrierConfig, build_constraints, perceived_constraints, split_for_agents
from egcbf.robots.quadrotor.cbf_qp import CentralizedCBFQP
from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP
from egcbf.robots.quadrotor.so3 import yaw_rotation

F64 = torch.float64
ROBOT = make_robot("quadrotor")
#: the interior-point solver stops at ~1e-10 m/s^2; a different row order moves the optimum by that much
ATOL = 1e-8


def _scene(seed: int, n: int = 12, envs: int = 2, area: float = 1.2, obstacles: int = 2):
    """A reset swarm (float64) with random velocities (agents closer than the comm radius, so that pairs bind)."""
    cfg = EnvConfig(num_agents=n, num_envs=envs, area_size=area, num_obstacles=obstacles)
    state = SwarmEnv(cfg, dtype=F64).reset(seed)
    v = 0.8 * torch.randn(envs, n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
    x = state.x.clone()
    x[..., 12:15] = v
    return SwarmState(x, state.goals, state.obstacles), cfg


def _with_sensing(state: SwarmState, faults: FaultConfig, x_sent=None, t: int = 0, seeds=None) -> SwarmState:
    """``state`` as the agents perceive it with the message faults ``faults`` and no estimation error: each message
    carries ``x_sent`` (default: the current state)."""
    seeds = torch.arange(state.num_envs) + 100 if seeds is None else torch.as_tensor(seeds)
    x_sent = state.x if x_sent is None else x_sent
    sensing = Sensing(faults, ROBOT, seeds, t, state.x, state.x, x_sent, state.obstacles)
    return dataclasses.replace(state, t=t, sensing=sensing)


def _pair(gap: float = 0.3, speed: float = 1.0, yaw: float = 0.0) -> tuple[SwarmState, EnvConfig]:
    """Two agents flying head-on at each other along x (their goals behind each other), ``gap`` apart: both QPs
    bind on the pair row."""
    p = torch.tensor([[1.0, 1.0, 1.0], [1.0 + gap, 1.0, 1.0]], dtype=F64)
    v = torch.tensor([[speed, 0.0, 0.0], [-speed, 0.0, 0.0]], dtype=F64)
    R = yaw_rotation(torch.tensor([yaw, -yaw], dtype=F64))
    x = dyn.state_from_parts(p, R, v, torch.zeros(2, 3, dtype=F64))[None]
    goals = torch.tensor([[[3.0, 1.0, 1.0], [-1.0, 1.0, 1.0]]], dtype=F64)
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    return SwarmState(x, goals, obs), EnvConfig(num_agents=2, area_size=2.0, num_obstacles=0)


def _a(ctrl, state, cfg) -> np.ndarray:
    """The safe accelerations ``(B, N, 3)``."""
    return ctrl(state, cfg)[1]["a_safe"]


# ------------------------------------------------------------------------------------------ (a) no loss, no delay
@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_without_lost_or_late_messages_the_qp_is_the_fault_free_one(seed):
    """Sensing without message faults (here: a LiDAR fault) is the fault-free QP bit for bit; the perceived rows of
    messages that carry the current estimates, all received, are the fault-free rows (``msg_delay = 1`` with a
    sender that did not move: the directed path runs)."""
    state, cfg = _scene(seed)
    ctrl = DecentralizedCBFQP()
    u0, info0 = ctrl(state, cfg)
    u1, info1 = ctrl(_with_sensing(state, FaultConfig(lidar_noise=0.05)), cfg)
    assert torch.equal(u0, u1) and np.array_equal(info0["a_safe"], info1["a_safe"]) and "links" not in info1
    u2, info2 = ctrl(_with_sensing(state, FaultConfig(msg_delay=1)), cfg)
    assert info2["links"].shape[1] > 0  # the scene has neighbours
    np.testing.assert_allclose(info2["a_safe"], info0["a_safe"], rtol=0, atol=ATOL)
    torch.testing.assert_close(u2, u0, rtol=0, atol=ATOL)
    assert np.abs(info0["a_safe"] - info0["a_nom"]).max() > 0.1  # the QP did act


def test_the_perceived_rows_of_current_messages_are_the_split_rows():
    """Row by row: ``perceived_constraints`` of every directed link with the current states gives each agent the
    half rows ``split_for_agents`` gives it (including the +z convention of coincident agents at rest)."""
    pos = np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0], [0.0, 0.0, 0.0], [2.0, 2.0, 2.0]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.5, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    cfg = BarrierConfig(cull_radius=1.0)
    cons = build_constraints(pos, vel, cfg)
    i, j = cons.i, cons.j
    links = np.stack((np.concatenate((i, j)), np.concatenate((j, i))))
    perceived = perceived_constraints(pos, vel, links, pos[links[1]], vel[links[1]], cfg)
    with pytest.raises(ValueError, match="one per link"):
        perceived_constraints(pos, vel, links, pos, vel, cfg)  # per agent, not per link
    expected = {(int(o), tuple(nr), r) for o, nr, r in zip(*split_for_agents(cons))}
    got = {(int(o), tuple(nr), r) for o, nr, r in zip(*split_for_agents(perceived, num_agents=4))}
    assert len(cons) == 3 and got == expected  # agents 0 and 2 coincide and move together: +z for 0, -z for 2


# --------------------------------------------------------------------------------------------- (b) every message lost
@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_with_every_message_lost_no_agent_has_a_pair_row(seed):
    """``msg_loss = 1``: each agent's QP holds its obstacle rows and its bounds only, the QP of a barrier that culls
    every neighbour (and keeps the obstacles within the comm radius, as the default does)."""
    state, cfg = _scene(seed)
    _, lost = DecentralizedCBFQP()(_with_sensing(state, FaultConfig(msg_loss=1.0)), cfg)
    alone = DecentralizedCBFQP(cull_radius=1e-6, obstacle_cull=float(cfg.comm_radius))
    _, ref = alone(state, cfg)
    assert lost["links"].shape == (2, 0) and lost["num_constraints"] == ref["num_constraints"]
    np.testing.assert_allclose(lost["a_safe"], ref["a_safe"], rtol=0, atol=ATOL)
    _, full = DecentralizedCBFQP()(state, cfg)
    assert full["num_constraints"] > ref["num_constraints"]  # there were pairs to lose


# ------------------------------------------------------------------------------------------------- (c) directed loss
def _one_way_step(seed: int, loss: float) -> int:
    """The first step at which agent 0 loses agent 1's message while agent 1 receives agent 0's."""
    for t in range(1000):
        lost_01 = float(draws.uniform(STREAMS["loss"], seed, t, 0, 1)) < loss
        lost_10 = float(draws.uniform(STREAMS["loss"], seed, t, 1, 0)) < loss
        if lost_01 and not lost_10:
            return t
    raise AssertionError("no such step")


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**40), gap=st.floats(0.2, 0.45), yaw=st.floats(-3.0, 3.0))
def test_a_lost_message_removes_the_pair_from_the_receivers_qp_only(seed, gap, yaw):
    state, cfg = _pair(gap, yaw=yaw)
    t = _one_way_step(seed, 0.5)
    ctrl = DecentralizedCBFQP()
    _, info = ctrl(_with_sensing(state, FaultConfig(msg_loss=0.5), t=t, seeds=[seed]), cfg)
    assert info["links"].tolist() == [[1], [0]]  # receiver 1 <- sender 0 only
    free = _a(ctrl, state, cfg)[0]
    alone = _a(ctrl, _with_sensing(state, FaultConfig(msg_loss=1.0)), cfg)[0]
    a = info["a_safe"][0]
    np.testing.assert_allclose(a[0], alone[0], rtol=0, atol=ATOL)  # agent 0 flies as if agent 1 were not there
    np.testing.assert_allclose(a[1], free[1], rtol=0, atol=ATOL)  # agent 1 keeps its half of the pair
    assert np.abs(free[0] - alone[0]).max() > 0.1  # the pair row bound agent 0 without the loss


# ------------------------------------------------------------------------------------------------------- (d) delay
@settings(max_examples=5, deadline=None)
@given(k=st.integers(1, 3), step=st.floats(0.02, 0.05))
def test_delayed_messages_carry_the_senders_estimate_of_k_steps_ago(k, step):
    """With ``msg_delay = k`` agent ``i``'s command is the fault-free one in the scene where its neighbour is where
    it was ``k`` steps ago (and agent ``i`` where it is now); it differs from the command without delay."""
    state, cfg = _pair(0.9)  # 0.6 m to 0.9 m apart over the steps: the pair row binds below the bounds
    proc = FaultProcess(FaultConfig(msg_delay=k), cfg, ROBOT, [3], dtype=F64)
    xs = []
    for t in range(k + 1):  # both agents close in, `step` m per step each
        x = state.x.clone()
        x[0, 0, 0] += step * t
        x[0, 1, 0] -= step * t
        xs.append(x)
        seen = proc.observe(dataclasses.replace(state, x=x, t=t))
    assert torch.equal(seen.sensing.x_sent, xs[0])
    now = dataclasses.replace(state, x=xs[-1], t=k)
    ctrl = DecentralizedCBFQP()
    a = _a(ctrl, seen, cfg)[0]
    for i, j in ((0, 1), (1, 0)):
        x = xs[-1].clone()
        x[0, j] = xs[0][0, j]  # agent i's view: the neighbour's message is k steps old
        view = _a(ctrl, dataclasses.replace(now, x=x), cfg)[0]
        np.testing.assert_allclose(a[i], view[i], rtol=0, atol=ATOL)
    assert np.abs(a - _a(ctrl, now, cfg)[0]).max() > 1e-3  # the delay changed the commands


def test_a_delayed_neighbour_out_of_range_is_dropped():
    """A message whose sender was outside the comm radius of the receiver's current estimate ``k`` steps ago is
    dropped (as the graph's edge): agent 1 was one comm radius further away one step ago, so agent 0 drops it, while
    agent 1 still hears agent 0 (who did not move)."""
    state, cfg = _pair(0.3)
    old = state.x.clone()
    old[0, 1, 0] += cfg.comm_radius
    ctrl = DecentralizedCBFQP()
    _, info = ctrl(_with_sensing(state, FaultConfig(msg_delay=1), x_sent=old), cfg)
    assert info["links"].tolist() == [[1], [0]]
    alone = _a(ctrl, _with_sensing(state, FaultConfig(msg_loss=1.0)), cfg)[0]
    np.testing.assert_allclose(info["a_safe"][0, 0], alone[0], rtol=0, atol=ATOL)
    np.testing.assert_allclose(info["a_safe"][0, 1], _a(ctrl, state, cfg)[0, 1], rtol=0, atol=ATOL)


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 1000), hold=st.booleans())
def test_the_lookahead_predicts_a_neighbour_from_its_message(seed, hold):
    """The dcbf filter's look-ahead under message faults: agent ``i`` predicts itself from its estimate with
    ``accel`` and its neighbour from the message with the acceleration the message carries (the sender's over the
    step before it sent it, from its own estimates): exactly the fault-free filter of that view. Delayed messages
    (one step), or held ones (lost in this step, the last step's kept), two steps old either way."""
    state, cfg = _pair(0.9)
    gen = torch.Generator().manual_seed(seed)
    old, older = state.x.clone(), state.x.clone()
    for x in (old, older):
        x[0, :, 0:3] += 0.05 * torch.randn(2, 3, generator=gen, dtype=F64)
        x[0, :, 12:15] += 0.3 * torch.randn(2, 3, generator=gen, dtype=F64)
    a_ref = torch.randn(1, 2, 3, generator=gen, dtype=F64).numpy()
    acc = torch.randn(1, 2, 3, generator=gen, dtype=F64)
    T = 0.05

    def ahead(x, a):
        x = x.clone()
        x[..., 0:3] += T * x[..., 12:15] + 0.5 * T * T * a
        x[..., 12:15] += T * a
        return x

    if hold:  # step 7 of seeds chosen so that both links lost their message of step 7 and kept the one of step 6
        faults, t, seeds = FaultConfig(msg_loss=0.5, msg_hold=1), 7, [_seed_losing_both(7)]
    else:
        faults, t, seeds = FaultConfig(msg_delay=1), 7, [100]
    sensing = Sensing(faults, ROBOT, torch.tensor(seeds), t, state.x, state.x, old, state.obstacles,
                      (state.x, old, older), cfg.dt)  # fmt: skip
    qp = DecentralizedCBFQP()
    _, info = qp.filter(dataclasses.replace(state, t=t, sensing=sensing), cfg, a_ref, lookahead=T, accel=acc.numpy())
    assert info["links"].shape[1] == 2
    carried = (ROBOT.velocities(old) - ROBOT.velocities(older)) / cfg.dt
    for i, j in ((0, 1), (1, 0)):
        x = ahead(state.x, acc)
        x[0, j] = ahead(old, carried)[0, j]
        _, view = qp.filter(dataclasses.replace(state, x=x), cfg, a_ref)
        np.testing.assert_allclose(info["a_safe"][0, i], view["a_safe"][0, i], rtol=0, atol=ATOL)


def _seed_losing_both(t: int) -> int:
    """An episode seed whose two links (0 <- 1, 1 <- 0) lose their message of step ``t`` at loss 0.5 and keep
    the one of step ``t - 1``."""
    for seed in range(10_000):
        s = torch.tensor([seed, seed])
        i, j = torch.tensor([0, 1]), torch.tensor([1, 0])
        now = draws.uniform(STREAMS["loss"], s, t, i, j) >= 0.5
        before = draws.uniform(STREAMS["loss"], s, t - 1, i, j) >= 0.5
        if not now.any() and before.all():
            return seed
    raise AssertionError("no such seed")


# ------------------------------------------------------------------------------- (e) the graph and the QP agree
@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 10_000), loss=st.sampled_from([0.1, 0.3, 0.7]), delay=st.integers(0, 2),
       hold=st.integers(0, 2), predict=st.integers(0, 1))  # fmt: skip
def test_the_graph_and_the_qp_lose_the_same_messages(seed, loss, delay, hold, predict):
    """Every link the graph keeps, the QP keeps, and each reads the same sender state (with held messages the
    graph's sender rows are per edge: compared by receiver and position)."""
    cfg = EnvConfig(num_agents=16, num_envs=2, area_size=1.5, num_obstacles=1, n_rays=8, lidar_max_hits=4)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(seed)
    faults = FaultConfig(msg_loss=loss, msg_delay=delay, pos_noise=0.02, msg_hold=hold, msg_predict=predict)
    proc = FaultProcess(faults, cfg, ROBOT, [seed, seed + 1], dtype=F64)
    ctrl = DecentralizedCBFQP()
    for t in range(delay + hold + 2):
        x = state.x.clone()
        x[..., 0:3] += 0.1 * t * x[..., 12:15] + 0.05 * t
        seen = proc.observe(dataclasses.replace(state, x=x, t=t))
        graph = build_graph(seen, cfg)
        assert graph.src_kind.shape[0] == graph.src_batch.shape[0] == graph.x_src.shape[0] == graph.pos_src.shape[0]
        assert torch.equal(graph.src_batch[graph.edge_index[0]], graph.batch[graph.edge_index[1]])
        src, dst = graph.edge_index[:, graph.edge_kind == KIND_AGENT]
        from_graph = sorted(zip(dst.tolist(), graph.pos_src[src].round(decimals=9).tolist()))
        info = ctrl(seen, cfg)[1]
        recv, send = torch.from_numpy(info["links"])
        _, states, _ = seen.sensing.received(recv, send, cfg.comm_radius)  # the same draws: what each link carried
        from_qp = sorted(zip(recv.tolist(), ROBOT.positions(states).round(decimals=9).tolist()))
        assert from_qp == from_graph
    assert 0 < len(from_graph)


# ---------------------------------------------------------------------------------------- who reads what, and the CLI
def test_controllers_declare_the_sensing_they_read():
    lidar = FaultConfig(msg_loss=0.1, lidar_noise=0.01)
    assert unread_faults(DecentralizedCBFQP(), DEFAULT_FIELD) == ()
    assert unread_faults(DecentralizedCBFQP(), lidar) == ("lidar_noise",)
    assert unread_faults(CentralizedCBFQP(), DEFAULT_FIELD) == ("msg_loss", "msg_delay")
    assert unread_faults(NominalController(), FaultConfig(pos_noise=0.1)) == ()
    dcbf_filter = FilteredController(None, None, FilterConfig.for_kind("dcbf"))  # of the nominal command
    assert unread_faults(dcbf_filter, DEFAULT_FIELD) == () and unread_faults(dcbf_filter, lidar) == ("lidar_noise",)
    assert filter_reads_sensing("dcbf", has_policy=True) is True  # a policy's graph reads every channel
    with pytest.raises(ValueError, match="unknown filter kind"):
        filter_reads_sensing("qp", has_policy=True)
    assert unread_faults(FilteredController(None, None, FilterConfig(kind="prior")), lidar) == ()  # all in its graph
    why = fault_support_error(CentralizedCBFQP(), DEFAULT_FIELD)
    assert "'ccbf' does not read them" in why and "msg_loss=0.1, msg_delay=1" in why
    with pytest.raises(ValueError, match="does not read them"):
        evaluate(lambda c: DecentralizedCBFQP(), [4], episodes=1, max_steps=2, show_progress=False, faults=lidar)


def test_the_dcbf_filter_runs_under_message_faults():
    """The nominal command behind the dcbf filter (its look-ahead reads the messages' accelerations) under the default
    field conditions."""
    rows, _ = evaluate(lambda c: FilteredController(None, None, FilterConfig.for_kind("dcbf")), [6], episodes=1,
                       max_steps=4, show_progress=False, faults=DEFAULT_FIELD, dtype=F64)  # fmt: skip
    assert rows[0]["faults"] == DEFAULT_FIELD.spec() and 0 <= rows[0]["safe_rate"] <= 1


def test_eval_runs_the_dcbf_qp_under_message_faults_and_refuses_the_centralized_one(tmp_path):
    base = ["eval", "--faults", "default", "--num-agents", "8", "--episodes", "1", "--max-steps", "5", "--no-progress"]
    res = CliRunner().invoke(app, [*base, "--controller", "dcbf", "--out", str(tmp_path / "d")], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "faults" in res.output and (tmp_path / "d" / "metrics.json").exists()
    res = CliRunner().invoke(app, [*base, "--controller", "ccbf", "--out", str(tmp_path / "c")], env={"COLUMNS": "200"})
    assert res.exit_code == 2 and "ccbf" in res.output and "msg_loss" in res.output and "msg_delay" in res.output
    assert not (tmp_path / "c").exists()


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    from egcbf.algo.config import TrainConfig
    from egcbf.train.loop import train

    root = tmp_path_factory.mktemp("ckpt") / "egcbf+"
    train(TrainConfig.preset("egcbf+", "tiny", steps=1), root, progress=False, log=lambda s: None)
    return root


def test_eval_runs_a_policy_behind_the_dcbf_filter_under_message_faults(tiny_checkpoint, tmp_path):
    base = ["eval", "--checkpoint", str(tiny_checkpoint), "--filter", "dcbf", "--num-agents", "4", "--area", "1.5",
            "--episodes", "1", "--max-steps", "4", "--no-progress"]  # fmt: skip
    res = CliRunner().invoke(app, [*base, "--faults", "default", "--out", str(tmp_path / "d")], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    # the policy behind the filter reads the LiDAR through its graph (the filter's rows read the map): it runs
    res = CliRunner().invoke(app, [*base, "--faults", "lidar=0.05", "--out", str(tmp_path / "l")],
                             env={"COLUMNS": "200"})  # fmt: skip
    assert res.exit_code == 0, res.output


def test_held_messages_without_history_are_refused_not_read_from_the_present():
    state, cfg = _pair(0.5)
    seen = _with_sensing(state, FaultConfig(msg_loss=0.3, msg_hold=1, msg_delay=1))
    with pytest.raises(ValueError, match="history"):
        seen.sensing.received(torch.tensor([0, 1]), torch.tensor([1, 0]), cfg.comm_radius)
