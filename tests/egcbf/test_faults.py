"""Fault models (egcbf.faults): zero level is the fault-free simulation bit for bit, the draws follow their
parameters, the metrics read the true states, and the closed loop under faults stays equivariant in distribution."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.learner import LearnedController
from egcbf.env import EnvConfig, SwarmEnv, SwarmState, cast_lidar
from egcbf.env.graph import KIND_AGENT, build_graph
from egcbf.evaluate.episodes import evaluate, run_episodes
from egcbf.faults import DEFAULT_FIELD, FaultConfig, FaultProcess, draws, noncooperative_mask, parse_faults
from egcbf.faults.sensing import STREAMS
from egcbf.nn import ModelConfig, PolicyNet
from egcbf.robots import make_robot

F64 = torch.float64
CFG = EnvConfig(num_agents=6, num_envs=2, area_size=2.0, num_obstacles=2, n_rays=8, lidar_max_hits=4, max_steps=6)
ROBOT = make_robot("quadrotor")


def _nominal(state, env_config):
    return ROBOT.nominal_control(state.x, state.goals), {}


def _policy(dtype=F64):
    torch.manual_seed(0)
    cfg = ModelConfig(group="se2xr", hidden=16, heads=2, head_hidden=16)
    pol = PolicyNet(cfg).to(dtype)
    with torch.no_grad():  # equivariance holds for any weights: move the zero-initialized last layers off zero
        for p in pol.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return LearnedController(pol, cfg)


# ------------------------------------------------------------------------------------------------------ spec
def test_spec_strings_round_trip_and_bad_specs_name_the_problem(tmp_path):
    assert parse_faults(None) == parse_faults("none") == parse_faults("") == FaultConfig()
    assert parse_faults("default") == DEFAULT_FIELD
    f = parse_faults("default,wind=1/0/0.5,noncoop_mode=straight,loss=0.3")
    assert f.msg_loss == 0.3 and f.wind == (1.0, 0.0, 0.5) and f.noncoop_mode == "straight" and f.pos_noise == 0.01
    assert parse_faults(f.spec()) == f and FaultConfig().spec() == "none"
    path = tmp_path / "f.json"
    path.write_text(json.dumps({"pos_noise": 0.02, "wind": [0, 1, 0]}))
    assert parse_faults(str(path)) == FaultConfig(pos_noise=0.02, wind=(0, 1, 0))
    for bad, match in (("posx=1", "unknown"), ("pos", "key=value"), ("pos=abc", "not a number"),
                       ("loss=1.5", "probability"), ("pos=-1", ">= 0"), ("delay=0.5", "not a whole number"),
                       ("delay=x", "not a number"), ("gain=1", "< 1"), ("noncoop_mode=fly", "mode")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            parse_faults(bad)
    assert FaultConfig(wind=(0.0, 0.0, 0.0)).is_null and not DEFAULT_FIELD.is_null
    assert FaultConfig(wind=(0.0, 0.0, 0.0)) == FaultConfig() and parse_faults("wind=0/0/0").spec() == "none"
    assert parse_faults("delay=2.0") == parse_faults("delay=2")  # a whole number however it is written
    assert DEFAULT_FIELD.edge_faults and not FaultConfig(pos_noise=1.0).edge_faults
    # the receivers' message handling: spec keys, and inert (not a fault) on its own
    held = parse_faults("default,hold=3,predict=1")
    assert (held.msg_hold, held.msg_predict) == (3, 1) and parse_faults(held.spec()) == held
    assert FaultConfig(msg_hold=3, msg_predict=1).is_null and not FaultConfig(msg_hold=3).edge_faults
    # the agents' handling of actuation delay: a spec key, inert on its own
    ahead = parse_faults("act_delay=2,act_predict=1")
    assert (ahead.act_delay, ahead.act_predict) == (2, 1) and parse_faults(ahead.spec()) == ahead
    assert FaultConfig(act_predict=1).is_null and not ahead.is_null
    observed = parse_faults("wind=1/0/0,dist_obs=1")
    assert observed.dist_obs == 1 and parse_faults(observed.spec()) == observed
    assert FaultConfig(dist_obs=1).is_null and not observed.is_null
    # the faults' shapes in time: spec keys, inert on their own, not message faults by themselves
    shaped = parse_faults("default,noise_tau=0.2,burst=4")
    assert (shaped.noise_tau, shaped.msg_burst) == (0.2, 4) and parse_faults(shaped.spec()) == shaped
    assert FaultConfig(noise_tau=0.2, msg_burst=4).is_null and not FaultConfig(msg_burst=4).edge_faults
    for bad, match in (("predict=2", "0 or 1"), ("act_predict=2", "0 or 1"), ("dist_obs=2", "0 or 1"),
                       ("hold=-1", "whole number"), ("hold=1.5", "not a whole number"),
                       ("burst=2.5", "not a whole number"), ("burst=-2", "whole number"),
                       ("noise_tau=-0.1", ">= 0")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            parse_faults(bad)


# ----------------------------------------------------------------------------------------------------- draws
def test_draws_are_pure_functions_of_their_address_with_the_right_law():
    a = draws.uniform(3, torch.arange(4), 7)
    assert torch.equal(a, draws.uniform(3, torch.arange(4), 7))
    assert torch.equal(a[2], draws.uniform(3, 2, 7))  # batching does not change a draw
    u = draws.uniform(1, torch.arange(100_000))
    assert 0 <= float(u.min()) and float(u.max()) < 1 and abs(float(u.mean()) - 0.5) < 0.005
    z = draws.normal(2, torch.arange(100_000))
    assert abs(float(z.mean())) < 0.01 and abs(float(z.std()) - 1) < 0.01
    assert abs(float((z.abs() < 1).double().mean()) - math.erf(1 / math.sqrt(2))) < 0.005


# ------------------------------------------------------------------------------------------ zero = fault-free
def test_zero_level_is_the_fault_free_simulation_bit_for_bit():
    seeds = [11, 12]
    plain, _, _ = run_episodes(_nominal, CFG, seeds, dtype=F64)
    for zero in (
        FaultConfig(),
        FaultConfig(wind=(0.0, 0.0, 0.0), noncoop_mode="straight"),
        FaultConfig(noise_tau=0.5, msg_burst=4),
    ):  # fmt: skip  (the shapes in time alone are inert)
        faulty, _, _ = run_episodes(_nominal, CFG, seeds, dtype=F64, faults=zero)
        assert all(torch.equal(v, faulty.per_episode()[k]) for k, v in plain.per_episode().items())
    # the process itself at zero level: observe, actuate and push are identities
    env = SwarmEnv(CFG, dtype=F64)
    state = env.reset(5)
    proc = FaultProcess(FaultConfig(), CFG, ROBOT, [1, 2], dtype=F64)
    u = ROBOT.nominal_control(state.x, state.goals)
    assert torch.equal(proc.observe(state).x, state.x) and proc.observe(state).sensing is None
    assert torch.equal(proc.actuate(u, state), u) and proc.push(state) is state


# ------------------------------------------------------------------------------------------- the laws of faults
def test_sensing_noise_has_its_standard_deviation_and_fresh_draws_each_step():
    cfg = dataclasses.replace(CFG, num_agents=200)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(3)
    proc = FaultProcess(FaultConfig(pos_noise=0.01, vel_noise=0.02), cfg, ROBOT, [1, 2], dtype=F64)
    seen = proc.observe(state)
    dp = ROBOT.positions(seen.x) - ROBOT.positions(state.x)
    dv = ROBOT.velocities(seen.x) - ROBOT.velocities(state.x)
    assert abs(float(dp.std()) / 0.01 - 1) < 0.06 and abs(float(dv.std()) / 0.02 - 1) < 0.06
    assert torch.equal(seen.x[..., 3:12], state.x[..., 3:12])  # attitude and rates untouched
    state.t = 1
    assert not torch.equal(proc.observe(state).x, seen.x)  # a fresh error every step


def test_correlated_estimation_errors_keep_their_std_and_have_their_memory():
    """``noise_tau``: each coordinate's error is a Gauss-Markov process: std ``pos_noise`` (``vel_noise``) at every
    step, lag-k autocorrelation ``exp(-k dt / noise_tau)``; ``noise_tau = 0`` is the white errors, draw for draw."""
    cfg = dataclasses.replace(CFG, num_agents=100, num_obstacles=0)
    state = SwarmEnv(cfg, dtype=F64).reset(3)
    tau, steps = 0.1, 120
    errors = {}
    for t_memory in (0.0, tau):
        proc = FaultProcess(FaultConfig(pos_noise=0.01, vel_noise=0.02, noise_tau=t_memory), cfg, ROBOT, [1, 2],
                            dtype=F64)  # fmt: skip
        runs = [proc.observe(dataclasses.replace(state, t=t)).x - state.x for t in range(steps)]
        errors[t_memory] = torch.stack(runs)  # (T, B, N, S)
    white, red = errors[0.0], errors[tau]
    assert torch.equal(white[0], red[0])  # started from the stationary law: the first step's draws
    rho = math.exp(-cfg.dt / tau)
    for cols, std in ((slice(0, 3), 0.01), (slice(12, 15), 0.02)):
        e = red[..., cols]
        assert abs(float(e.std()) / std - 1) < 0.06
        for lag in (1, 4):
            corr = float((e[lag:] * e[:-lag]).mean() / (e * e).mean())
            assert abs(corr - rho**lag) < 0.05, (lag, corr, rho**lag)
        w = white[..., cols]
        assert abs(float((w[1:] * w[:-1]).mean() / (w * w).mean())) < 0.03  # white: no memory
    assert torch.equal(red[..., 3:12], torch.zeros_like(red[..., 3:12]))  # attitude and rates untouched


def test_bursty_losses_keep_the_loss_rate_and_come_in_runs_of_whole_blocks():
    """``msg_burst = L``: each link loses whole blocks of ``L`` steps (a phase per link) with probability
    ``msg_loss``: the loss rate is ``msg_loss``, every run of losses that starts after the episode's first step and
    ends before its last is a multiple of ``L`` steps, and runs average ``L / (1 - msg_loss)``; ``msg_burst = 1``
    is the independent losses, draw for draw."""
    assert FaultConfig(msg_burst=1) == FaultConfig() and FaultConfig(msg_loss=0.2, msg_burst=1).spec() == "msg_loss=0.2"
    p, burst, steps = 0.3, 4, 80
    series = {}
    for b in (0, burst):
        cfg, _, seen, (src, dst) = _held_run(FaultConfig(msg_loss=p, msg_burst=b), steps=1)
        arrived = []
        for t in range(steps):
            sens = dataclasses.replace(seen.sensing, t=t)
            arrived.append(sens.received(dst, src, cfg.comm_radius)[0])
        series[b] = torch.stack(arrived)  # (T, links)
    lost = ~series[burst]
    assert abs(float(lost.double().mean()) - p) < 0.03
    runs = []
    for link in lost.T.tolist():
        t = 0
        while t < steps:
            if not link[t]:
                t += 1
                continue
            start = t
            while t < steps and link[t]:
                t += 1
            if start > 0 and t < steps:  # a run cut by the episode's ends is not whole
                runs.append(t - start)
    assert runs and all(r % burst == 0 for r in runs)
    assert abs(sum(runs) / len(runs) / (burst / (1 - p)) - 1) < 0.12
    independent = ~series[0]
    assert abs(float(independent.double().mean()) - p) < 0.03
    assert float((independent[1:] & independent[:-1]).double().mean()) < p * p + 0.03  # no memory


def test_message_loss_rate_and_delay_match_their_parameters():
    cfg = dataclasses.replace(CFG, num_agents=60, area_size=1.5, num_obstacles=0)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(9)
    full = build_graph(state, cfg)
    full_agent = int((full.edge_kind == KIND_AGENT).sum())
    lost = []
    for t in range(5):
        proc = FaultProcess(FaultConfig(msg_loss=0.3), cfg, ROBOT, [1, 2], dtype=F64)
        state.t = t
        g = build_graph(proc.observe(state), cfg)
        lost.append(1 - int((g.edge_kind == KIND_AGENT).sum()) / full_agent)
        assert int((g.edge_kind != KIND_AGENT).sum()) == int((full.edge_kind != KIND_AGENT).sum())
    assert abs(sum(lost) / len(lost) - 0.3) < 0.03
    # delay: the senders are the estimates of two steps ago, the receivers the current ones
    proc = FaultProcess(FaultConfig(msg_delay=2, pos_noise=0.01), cfg, ROBOT, [1, 2], dtype=F64)
    xs = []
    for t in range(4):
        s = dataclasses.replace(state, x=state.x + 0.01 * t, t=t)
        seen = proc.observe(s)
        xs.append(seen.x)
        g = build_graph(seen, cfg)
    m = g.num_dst
    sender = ROBOT.positions(xs[1].reshape(m, -1))
    assert torch.allclose(g.pos_src[:m], sender) and torch.allclose(g.pos_dst, ROBOT.positions(xs[3].reshape(m, -1)))
    src, dst = g.edge_index[:, g.edge_kind == KIND_AGENT]
    assert (torch.linalg.vector_norm(g.pos_src[src] - g.pos_dst[dst], dim=-1) < cfg.comm_radius).all()


def _held_run(faults: FaultConfig, steps: int = 5):
    """A swarm whose estimates drift by 1 um per step (so a message's age shows in what it carries, and no link
    crosses the comm radius), observed ``steps`` times; returns the config, the estimates per step, the last
    Sensing and the candidate agent links ``(src, dst)`` of the fault-free graph."""
    cfg = dataclasses.replace(CFG, num_agents=40, area_size=1.5, num_obstacles=0)
    state = SwarmEnv(cfg, dtype=F64).reset(9)
    proc = FaultProcess(faults, cfg, ROBOT, [1, 2], dtype=F64)
    xs = []
    for t in range(steps):
        x = state.x.clone()
        x[..., 0:3] += 1e-6 * t
        seen = proc.observe(dataclasses.replace(state, x=x, t=t))
        xs.append(seen.x)
    clean = build_graph(dataclasses.replace(seen, sensing=None), cfg)
    return cfg, xs, seen, clean.edge_index[:, clean.edge_kind == KIND_AGENT]


def test_receivers_hold_the_last_message_within_hold_steps_and_predict_it_over_its_age():
    """``msg_hold = 2``: a link whose message of this step is lost uses the newest message of the two steps before
    that was not (the draws of those steps), which carries the sender's estimate of ``msg_delay`` steps before it
    was sent; a link lost three steps running has none. The graph gives those edges their own sender rows.
    ``msg_predict``: each message's position moves on at its velocity over its age."""
    f = FaultConfig(msg_loss=0.5, msg_delay=1, msg_hold=2)
    cfg, xs, seen, (src, dst) = _held_run(f)
    sens, n, t = seen.sensing, cfg.num_agents, len(xs) - 1
    keep, states, _ = sens.received(dst, src, cfg.comm_radius)
    seeds = sens.seeds[dst // n]
    arrived = torch.stack([draws.uniform(STREAMS["loss"], seeds, t - k, dst % n, src % n) >= 0.5 for k in range(3)])
    newest = arrived.to(torch.int64).argmax(0)  # the first step back whose message arrived
    assert torch.equal(keep, arrived.any(0))
    assert abs(keep.double().mean().item() - (1 - 0.5**3)) < 0.05 and 0.3 < arrived[0].double().mean() < 0.7
    sent = torch.stack([xs[t - k - 1].reshape(-1, xs[0].shape[-1]) for k in range(3)])  # delay 1 behind sending
    expected = sent[newest, src]
    assert torch.equal(states[keep], expected[keep])
    assert len(set(newest[keep].tolist())) == 3  # messages of every age are in use
    # the graph: every kept edge reads its own message (phantom sender rows), lost ones are gone
    graph = build_graph(seen, cfg)
    g_src = graph.edge_index[0, graph.edge_kind == KIND_AGENT]
    assert g_src.shape[0] == int(keep.sum()) and bool((g_src >= graph.x_src.shape[0] - src.shape[0]).all())
    torch.testing.assert_close(graph.pos_src[g_src], ROBOT.positions(expected[keep]), rtol=0, atol=0)
    # prediction: the same messages moved on at their velocity over their age (steps since sent + delay)
    _, _, seen_p, _ = _held_run(dataclasses.replace(f, msg_predict=1))
    keep_p, states_p, _ = seen_p.sensing.received(dst, src, cfg.comm_radius)
    age = (newest + 1).to(F64)[:, None] * cfg.dt
    moved = ROBOT.positions(expected) + age * ROBOT.velocities(expected)
    assert torch.equal(keep_p, keep)  # nothing crossed the comm radius
    torch.testing.assert_close(ROBOT.positions(states_p)[keep], moved[keep], rtol=0, atol=1e-12)
    torch.testing.assert_close(ROBOT.velocities(states_p), ROBOT.velocities(expected), rtol=0, atol=0)


def test_lidar_faults_act_on_every_ray_with_their_statistics():
    """Each ray's return: range error of std ``lidar_noise``, lost with probability ``lidar_drop`` (draws keyed by
    the ray, not by its rank among the kept hits)."""
    cfg = dataclasses.replace(CFG, num_agents=30, num_obstacles=6, n_rays=16, lidar_max_hits=8)
    state = SwarmEnv(cfg, dtype=F64).reset(4)
    sensing = FaultProcess(FaultConfig(lidar_noise=0.05, lidar_drop=0.4), cfg, ROBOT, [1, 2],
                           dtype=F64).observe(state).sensing  # fmt: skip
    m, rays = 2 * 30, 130
    agent = torch.arange(m).repeat_interleave(rays)
    ray = torch.arange(rays).repeat(m)
    true = torch.full((m * rays,), 0.5, dtype=F64)
    measured, arrived = sensing.ray_faults(agent, ray, true)
    assert abs(float(arrived.double().mean()) - 0.6) < 0.03
    assert abs(float((measured - true).std()) / 0.05 - 1) < 0.05 and abs(float((measured - true).mean())) < 0.003
    again, arrived2 = sensing.ray_faults(agent.flip(0), ray.flip(0), true)  # a pure function of the address
    assert torch.equal(again.flip(0), measured) and torch.equal(arrived2.flip(0), arrived)


def test_lidar_drops_rays_before_keeping_the_closest_returns():
    """A lost ray leaves room for the next closest one: with many rays on the obstacles, the scan stays full, and
    it equals the clean scan of every ray with the lost ones taken out."""
    cfg = dataclasses.replace(CFG, num_agents=30, num_obstacles=6, n_rays=32, lidar_max_hits=8)
    state = SwarmEnv(cfg, dtype=F64).reset(4)
    truth = SwarmEnv(cfg, dtype=F64).lidar(state)
    sensing = FaultProcess(FaultConfig(lidar_drop=0.5), cfg, ROBOT, [1, 2], dtype=F64).observe(state).sensing
    scan = sensing.scan(cfg)
    every = cast_lidar(dataclasses.replace(cfg, lidar_max_hits=32 * 16 + 2), ROBOT.positions(state.x),
                       ROBOT.heading(state.x), state.obstacles)  # fmt: skip
    rays = every.valid.sum(-1)
    assert (rays > 2 * 8).any()  # some agents see many returns: a per-slot drop would empty half their slots
    dropped = cast_lidar(cfg, ROBOT.positions(state.x), ROBOT.heading(state.x), state.obstacles,
                         sensing.ray_faults)  # fmt: skip
    torch.testing.assert_close(scan.points, dropped.points, rtol=0, atol=1e-12)
    assert torch.equal(scan.valid, dropped.valid)
    kept = scan.valid.sum(-1)
    assert (kept <= truth.valid.sum(-1)).all() and float(kept[rays > 2 * 8].double().mean()) > 7.0
    # every kept return is one of the agent's true returns
    d = scan.distance[..., :, None] - every.distance[..., None, :]
    assert (d.abs().amin(-1)[scan.valid] < 1e-12).all()


def test_lidar_measures_from_the_true_pose_under_estimate_noise_alone():
    """Position noise moves where an agent places its scan, not what the sensor measures: the vectors from the
    estimate to the hits are the true ones (a LiDAR on the robot sees the world from where the robot is)."""
    cfg = dataclasses.replace(CFG, num_agents=30, num_obstacles=6, n_rays=16, lidar_max_hits=8)
    state = SwarmEnv(cfg, dtype=F64).reset(4)
    truth = SwarmEnv(cfg, dtype=F64).lidar(state)
    seen = FaultProcess(FaultConfig(pos_noise=0.1), cfg, ROBOT, [1, 2], dtype=F64).observe(state)
    assert seen.sensing is not None
    scan = seen.sensing.scan(cfg)
    assert torch.equal(scan.valid, truth.valid) and truth.valid.sum() > 50
    rel_seen = scan.points - ROBOT.positions(seen.x)[:, :, None]
    rel_true = truth.points - ROBOT.positions(state.x)[:, :, None]
    torch.testing.assert_close(rel_seen[scan.valid], rel_true[truth.valid], rtol=0, atol=1e-12)
    graph = build_graph(seen, cfg)  # the graph reads that scan
    clean = build_graph(state, cfg)
    assert graph.hit_owner.numel() == clean.hit_owner.numel()


def test_lidar_under_prediction_keeps_static_obstacles_where_they_are():
    """With ``act_predict`` the agents command for their predicted state but place their scan at their current
    estimate: the hits stay where the obstacles are (with exact estimates: the true hits)."""
    cfg = dataclasses.replace(CFG, num_agents=30, num_obstacles=6, n_rays=16, lidar_max_hits=8)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(4)
    for loss in (0.0, 0.2):  # with and without message faults
        proc = FaultProcess(FaultConfig(act_delay=2, act_predict=1, msg_loss=loss), cfg, ROBOT, [1, 2], dtype=F64)
        s = state
        for _ in range(3):
            seen = proc.observe(s)
            u, _ = _nominal(seen, cfg)
            s, _ = env.step(s, proc.actuate(u, s))
        seen = proc.observe(s)
        truth = env.lidar(s)
        assert not torch.equal(seen.x, s.x)  # the predicted state
        scan = seen.sensing.scan(cfg)
        assert torch.equal(scan.valid, truth.valid)
        torch.testing.assert_close(scan.points, truth.points, rtol=0, atol=1e-12)


def test_actuation_errors_noncooperative_agents_and_delay():
    cfg = dataclasses.replace(CFG, num_agents=400, num_envs=2)
    state = SwarmEnv(cfg, dtype=F64).reset(2)
    f = FaultConfig(thrust_gain=0.1, torque_bias=1e-3, noncoop=0.05)
    proc = FaultProcess(f, cfg, ROBOT, [7, 8], dtype=F64)
    thrust, torque = proc.gains[..., 3], proc.gains[..., :3]
    assert (
        ((thrust - 1).abs() <= 0.1).all()
        and float((thrust - 1).abs().max()) > 0.09
        and torch.equal(torque, torch.ones_like(torque))
    )
    assert (proc.bias[..., :3].abs() <= 1e-3).all() and (proc.bias[..., 3] == 0).all()
    assert proc.noncoop.sum(1).tolist() == [20, 20]
    assert torch.equal(proc.noncoop, noncooperative_mask(f, torch.tensor([7, 8]), 400))
    u = torch.zeros(2, 400, 4, dtype=F64)
    proc.observe(state)
    out = proc.actuate(u, state)
    hover = ROBOT.nominal_control(state.x, ROBOT.positions(state.x))
    nc = proc.noncoop
    assert torch.allclose(out[nc], hover[nc] * proc.gains[nc] + proc.bias[nc])
    assert torch.allclose(out[~nc], proc.bias[~nc])
    with pytest.raises(ValueError, match="thrust"):
        FaultProcess(FaultConfig(thrust_gain=0.1), CFG, make_robot("double_integrator"), [1], dtype=F64)
    delayed = FaultProcess(FaultConfig(act_delay=1), CFG, ROBOT, [1, 2], dtype=F64)
    s = SwarmEnv(CFG, dtype=F64).reset(1)
    u1 = torch.rand(2, 6, 4, dtype=F64)
    first = delayed.actuate(u1, s)
    assert torch.allclose(first, ROBOT.nominal_control(s.x, ROBOT.positions(s.x)))
    assert torch.equal(delayed.actuate(torch.zeros_like(u1), s), u1)


@pytest.mark.parametrize("delay", [1, 3])
def test_actuation_delay_prediction_sees_the_state_its_command_acts_on(delay):
    """With ``act_predict`` and no other fault, what the agents see at step t is the true state at step t + delay:
    the command of step t acts then (the prediction rolls the estimate through the same dynamics and clip with the
    commands in flight); without it they see the present and the delayed loop differs."""
    env = SwarmEnv(CFG, dtype=F64)
    for predict in (1, 0):
        state = env.reset(3)
        proc = FaultProcess(FaultConfig(act_delay=delay, act_predict=predict), CFG, ROBOT, [1, 2], dtype=F64)
        seen, truth = [], [state.x]
        for _ in range(6):
            seen.append(proc.observe(state).x)
            u, _ = _nominal(SwarmState(seen[-1], state.goals, state.obstacles, state.t, state.robot), CFG)
            state, _ = env.step(state, proc.actuate(u, state))
            truth.append(state.x)
        for t in range(len(truth) - delay):
            if predict:
                assert torch.allclose(seen[t], truth[t + delay], rtol=0, atol=1e-12)
            else:
                assert torch.equal(seen[t], truth[t])
        assert predict == 0 or not torch.equal(seen[0], truth[0])


def test_actuation_delay_destabilizes_the_attitude_loop_and_the_predictor_restores_it():
    """The quadrotor's command is its body torques and thrust, so actuation delay acts inside the attitude loop
    (docs/robustness.md, "Fixes: commanding for the state the command will act on"): the nominal controller's
    agents still tilt over 45 degrees after 60 steps with one step of delay (oscillation; under 20 without), flip
    past 120 with two, and with the predictor fly as without delay. The report's warning that safe rates under
    actuation delay count agents out of control rests on this."""
    cfg = dataclasses.replace(CFG, num_agents=8, num_envs=1, num_obstacles=0, max_steps=100)
    env = SwarmEnv(cfg, dtype=F64)

    def late_tilt(faults: FaultConfig) -> float:
        state = env.reset(0)
        proc = FaultProcess(faults, cfg, ROBOT, [0], dtype=F64)
        tilts = []
        for _ in range(cfg.max_steps):
            u, _ = _nominal(proc.observe(state), cfg)
            state, _ = env.step(state, proc.actuate(u, state))
            body_z_up = state.x[..., 11]  # R[2, 2]: the body z axis against the world's
            tilts.append(float(torch.rad2deg(torch.acos(body_z_up.clamp(-1, 1))).max()))
        return max(tilts[60:])

    assert late_tilt(FaultConfig()) < 20
    assert late_tilt(FaultConfig(act_delay=1)) > 45
    assert late_tilt(FaultConfig(act_delay=2)) > 120
    assert late_tilt(FaultConfig(act_delay=2, act_predict=1)) < 20


def test_prediction_with_the_observer_adds_back_the_disturbance_its_commands_cancel():
    """Agents holding their positions in a steady wind, once the observer has converged: the predicted state is the
    true state ``act_delay`` steps later, as without wind: the commands in flight cancel the wind, so the model adds
    the estimated wind back (without it the prediction would miss ``d * delay * dt`` of velocity)."""
    cfg = dataclasses.replace(CFG, num_agents=4, num_obstacles=0, max_steps=60)
    env = SwarmEnv(cfg, dtype=F64)
    state = env.reset(3)
    hold = ROBOT.positions(state.x).clone()
    wind = 1.0
    proc = FaultProcess(FaultConfig(act_delay=2, act_predict=1, dist_obs=1, wind=(wind, 0.0, 0.0)), cfg, ROBOT,
                        [1, 2], dtype=F64)  # fmt: skip
    seen, truth = [], [state.x]
    for _ in range(60):
        seen.append(proc.observe(state).x)
        state, _ = env.step(state, proc.actuate(ROBOT.nominal_control(seen[-1], hold), state))
        state = proc.push(state)
        truth.append(state.x)
    assert float(proc.disturbance[..., 0].mean()) == pytest.approx(wind, abs=0.01)
    err = ROBOT.velocities(seen[-3]) - ROBOT.velocities(truth[-1])  # seen at t, for the state at t + 2
    assert float(err.abs().max()) < 0.1 * wind * 2 * cfg.dt, err


@pytest.mark.parametrize("mode", ["hover", "straight"])
def test_noncooperative_agents_predict_over_the_actuation_delay_like_the_others(mode):
    """A non-cooperative agent's autopilot commands for its state over the commands in flight when the agents
    predict: under two steps of delay it flies the path it flies without delay (it does not oscillate away)."""
    cfg = dataclasses.replace(CFG, num_agents=8, num_envs=1, area_size=4.0, num_obstacles=0, max_steps=240)
    ends = []
    for spec in (f"noncoop=0.5,noncoop_mode={mode}", f"noncoop=0.5,noncoop_mode={mode},act_delay=2,act_predict=1"):
        env = SwarmEnv(cfg, dtype=F64)
        state = env.reset(11)
        proc = FaultProcess(parse_faults(spec), cfg, ROBOT, [11], dtype=F64)
        for _ in range(240):
            seen = proc.observe(state)
            state, _ = env.step(state, proc.actuate(ROBOT.nominal_control(seen.x, seen.goals), state))
        ends.append(ROBOT.positions(state.x)[proc.noncoop])
    assert torch.allclose(ends[1], ends[0], atol=0.05), (ends[1] - ends[0]).norm(dim=-1)


def test_wind_pushes_with_its_acceleration():
    env = SwarmEnv(CFG, dtype=F64)
    state = env.reset(1)
    proc = FaultProcess(FaultConfig(wind=(0.5, 0.0, 0.0)), CFG, ROBOT, [1, 2], dtype=F64)
    pushed = proc.push(state)
    dt = CFG.dt
    dv = ROBOT.velocities(pushed.x) - ROBOT.velocities(state.x)
    dp = ROBOT.positions(pushed.x) - ROBOT.positions(state.x)
    assert torch.allclose(dv[..., 0], torch.full_like(dv[..., 0], 0.5 * dt)) and torch.allclose(
        dv[..., 1:], torch.zeros_like(dv[..., 1:])
    )
    assert torch.allclose(dp[..., 0], torch.full_like(dp[..., 0], 0.25 * dt * dt))
    with pytest.raises(ValueError, match="wind needs 3"):
        FaultProcess(FaultConfig(wind=(1.0, 0.0)), CFG, ROBOT, [1], dtype=F64)


# --------------------------------------------------------------------------------------- metrics see the truth
def test_metrics_read_true_states_and_count_cooperative_agents_only():
    """A controller that ignores what it sees flies the same trajectory under sensing noise: the metrics (true
    states) are those of the fault-free run. Non-cooperative agents are left out of the rates."""
    seeds = [3, 4]
    seen_log = []

    def blind(state, env_config):
        seen_log.append(state.x)
        return torch.zeros(*state.x.shape[:2], 4, dtype=state.x.dtype), {}

    plain, _, _ = run_episodes(blind, CFG, seeds, dtype=F64)
    n_plain = len(seen_log)
    noisy, _, _ = run_episodes(blind, CFG, seeds, dtype=F64, faults=FaultConfig(pos_noise=0.5, vel_noise=0.5))
    assert not torch.equal(seen_log[0], seen_log[n_plain])  # it did see noise
    same = {k: torch.equal(v, noisy.per_episode()[k]) for k, v in plain.per_episode().items()}
    assert same == {**same, "safe_rate": True, "reach_rate": True, "cost": True, "collision_steps": True}
    assert not same["reward"]  # the reward compares with the nominal control at the state the agent believes in
    nc, _, _ = run_episodes(blind, CFG, seeds, dtype=F64, faults=FaultConfig(noncoop=0.34))
    assert nc.counted is not None and nc.counted.sum(1).tolist() == [4, 4]


def test_message_faults_are_refused_for_controllers_that_do_not_read_them():
    with pytest.raises(ValueError, match="does not read them"):
        evaluate(lambda c: _nominal, [4], episodes=1, max_steps=2, show_progress=False, faults=DEFAULT_FIELD)
    rows, _ = evaluate(lambda c: _policy(), [4], episodes=1, max_steps=2, show_progress=False, faults=DEFAULT_FIELD,
                       dtype=F64)  # fmt: skip
    assert rows[0]["faults"] == DEFAULT_FIELD.spec()


# ------------------------------------------------------------------------------------------------- equivariance
def _rollout(ctrl, env, state, proc, steps):
    traj = []
    for _ in range(steps):
        u, _ = ctrl(proc.observe(state), env.config)
        state, _ = env.step(state, proc.actuate(u, state))
        state = proc.push(state)
        traj.append(state.x)
    return traj


#: float64: a tight tolerance; float32: what four steps of a rigid body and a transformer keep (stated)
_TOL = {F64: 1e-8, torch.float32: 2e-3}


@settings(max_examples=6, deadline=None)
@given(yaw=st.floats(-math.pi, math.pi), shift=st.tuples(*[st.floats(-2, 2)] * 3),
       dtype=st.sampled_from([F64, torch.float32]), act_predict=st.sampled_from([0, 1]),
       dist_obs=st.sampled_from([0, 1]), shaped=st.booleans())  # fmt: skip
def test_closed_loop_under_faults_is_equivariant(yaw, shift, dtype, act_predict, dist_obs, shaped):
    """The rotated scene with the same draws rotated gives the rotated trajectory (every fault on; with and without
    the agents predicting over their actuation delay, with and without their disturbance observer, with white or
    correlated estimation errors and independent or bursty losses)."""
    faults = FaultConfig(pos_noise=0.01, vel_noise=0.02, msg_loss=0.2, msg_delay=1, lidar_noise=0.01,
                         lidar_drop=0.2, thrust_gain=0.1, torque_gain=0.05, torque_bias=1e-4, act_delay=1,
                         wind=(0.3, -0.2, 0.1), gust=0.2, noncoop=0.2, msg_hold=2, msg_predict=1,
                         act_predict=act_predict, dist_obs=dist_obs, noise_tau=0.1 if shaped else 0.0,
                         msg_burst=3 if shaped else 0)  # fmt: skip
    env = SwarmEnv(CFG, dtype=dtype)
    state = env.reset(21)
    c, s = math.cos(yaw), math.sin(yaw)
    g = torch.tensor([[c, s, *shift]] * CFG.num_envs, dtype=dtype)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    ctrl = _policy(dtype)
    a = _rollout(ctrl, env, state, FaultProcess(faults, CFG, ROBOT, [1, 2], dtype=dtype), 4)
    b = _rollout(ctrl, env, state.transform(g), FaultProcess(faults, CFG, ROBOT, [1, 2], dtype=dtype, rotation=rot), 4)
    for xa, xb in zip(a, b):
        assert torch.allclose(dataclasses.replace(state, x=xa).transform(g).x, xb, atol=_TOL[dtype])


def test_noncooperative_count_rounds_half_up_and_leaves_someone_to_measure():
    seeds = torch.tensor([1, 2])
    assert noncooperative_mask(FaultConfig(noncoop=0.05), seeds, 10).sum(1).tolist() == [1, 1]  # 0.5 -> 1
    assert noncooperative_mask(FaultConfig(noncoop=0.05), seeds, 30).sum(1).tolist() == [2, 2]  # 1.5 -> 2
    with pytest.raises(ValueError, match="no cooperative agent"):
        noncooperative_mask(FaultConfig(noncoop=1.0), seeds, 8)


def test_spec_strings_keep_every_digit_of_a_vector():
    f = FaultConfig(wind=(0.1234567891, 1.0, 0.5))
    assert parse_faults(f.spec()) == f and "wind=0.1234567891/1/0.5" in f.spec()


def test_a_json_file_and_a_string_give_one_spec(tmp_path):
    path = tmp_path / "f.json"
    path.write_text(json.dumps({"pos_noise": 1, "msg_delay": 2.0, "wind": [1, 0, 0]}))
    from_file = parse_faults(str(path))
    assert from_file == parse_faults("pos=1,delay=2,wind=1/0/0")
    assert from_file.spec() == parse_faults("pos=1,delay=2,wind=1/0/0").spec()


def test_velocity_faults_are_refused_for_a_robot_without_velocity_state():
    robot = make_robot("single_integrator")
    cfg = EnvConfig.for_robot("single_integrator", num_agents=4, num_envs=1)
    FaultProcess(FaultConfig(pos_noise=0.01, msg_loss=0.1), cfg, robot, [1])  # these act on it
    for faults, name in ((FaultConfig(vel_noise=0.1), "vel_noise"), (FaultConfig(msg_delay=1, msg_predict=1),
                         "msg_predict"), (FaultConfig(wind=(1.0, 0.0)), "wind")):  # fmt: skip
        with pytest.raises(ValueError, match=f"{name} acts on a velocity the single_integrator does not have"):
            FaultProcess(faults, cfg, robot, [1])
