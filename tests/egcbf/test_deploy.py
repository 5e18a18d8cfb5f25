"""egcbf.deploy.agent.AgentController: one agent's control from its own observation equals the swarm-level evaluation's
for that agent (every agent of random scenes), with no neighbours, with more than its limit, and far agents
ignored."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.deploy.agent import AgentController, AgentFilteredController
from egcbf.env import EnvConfig, SwarmEnv, SwarmState
from egcbf.train.checkpoint import load_controller

ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
F64 = torch.float64


@functools.cache
def _controllers(method: str, dtype: torch.dtype = F64):
    swarm, cfg = load_controller(ROOT / method, dtype=dtype)
    return swarm, cfg, AgentController.from_checkpoint(ROOT / method, dtype=dtype)


def _scene(cfg, n: int, area: float, obstacles: int, seed: int, dtype=F64, steps: int = 6):
    env_cfg = EnvConfig.for_robot(
        cfg.robot, num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=1, **cfg.env_overrides
    )
    env = SwarmEnv(env_cfg, dtype=dtype)
    state = env.reset(seed)
    swarm = _controllers(cfg.algo, dtype)[0]
    for _ in range(steps):  # moving agents: non-zero velocities and rates
        u, _ = swarm(state, env_cfg)
        state, _ = env.step(state, u)
    return env, env_cfg, state


def _observation(env, state, i: int):
    lidar = env.lidar(state)
    others = torch.cat((state.x[0, :i], state.x[0, i + 1 :]))
    return state.x[0, i], state.goals[0, i], others, lidar.points[0, i][lidar.valid[0, i]]


@pytest.mark.parametrize("method", ["egcbf+", "gcbf+"])
@given(seed=st.integers(0, 2**16), n=st.integers(2, 14), area=st.floats(1.0, 2.5), obstacles=st.integers(0, 3))
@settings(max_examples=4, deadline=None)
def test_every_agents_control_is_the_swarm_evaluations(method, seed, n, area, obstacles):
    """float64, 1e-9: the per-agent call reproduces LearnedController's control of every agent of the scene."""
    swarm, cfg, agent = _controllers(method)
    env, env_cfg, state = _scene(cfg, n, area, obstacles, seed)
    u_all, _ = swarm(state, env_cfg)
    for i in range(n):
        u, info = agent(*_observation(env, state, i))
        assert u.shape == u_all[0, i].shape and (u - u_all[0, i]).abs().max() <= 1e-9, (i, info)


def test_float32_within_a_stated_tolerance():
    """float32 networks and observations: within 1e-4 of the swarm evaluation's float32 control (the summation
    order of the attention over neighbours differs)."""
    swarm, cfg, agent = _controllers("egcbf+", torch.float32)
    env, env_cfg, state = _scene(cfg, 10, 1.6, 2, 3, dtype=torch.float32)
    u_all, _ = swarm(state, env_cfg)
    worst = max(float((agent(*_observation(env, state, i))[0] - u_all[0, i]).abs().max()) for i in range(10))
    assert worst <= 1e-4


def test_an_agent_alone_and_far_agents():
    """No neighbours and no hits (empty tensors) is the swarm evaluation of the agent alone; agents beyond the
    communication radius change nothing."""
    swarm, cfg, agent = _controllers("egcbf+")
    _env, env_cfg, state = _scene(cfg, 4, 2.0, 0, 11)
    alone = SwarmState(state.x[:, :1], state.goals[:, :1], state.obstacles, robot=state.robot)
    u_alone, _ = swarm(alone, env_cfg)
    x, goal = state.x[0, 0], state.goals[0, 0]
    u, info = agent(x, goal, x.new_zeros(0, x.shape[0]), x.new_zeros(0, 3))
    assert info["num_neighbours"] == info["num_hits"] == 0 and (u - u_alone[0, 0]).abs().max() <= 1e-9
    far = state.x[0, 1:].clone()
    far[:, :3] += 50.0  # far outside the communication radius
    assert torch.equal(agent(x, goal, far, x.new_zeros(0, 3))[0], u)


def test_beyond_the_limit_the_nearest_neighbours_are_kept():
    """With max_neighbours = 2 the control equals the swarm evaluation of the agent with its two nearest in-range
    neighbours only (the documented limit; the swarm evaluation itself has none)."""
    _swarm, cfg, agent = _controllers("egcbf+")
    limited = AgentController(agent.policy, agent.model_config, agent.env_config, max_neighbours=2)
    env, env_cfg, state = _scene(cfg, 14, 1.0, 0, 7)
    x = state.x[0]
    i = int(torch.argmax(((x[:, None, :3] - x[None, :, :3]).norm(dim=-1) < env_cfg.comm_radius).sum(1)))
    obs = _observation(env, state, i)
    assert obs[2].shape[0] >= 3
    u, info = limited(*obs)
    d = (x[:, :3] - x[i, :3]).norm(dim=-1)
    d[i] = float("inf")
    nearest = torch.argsort(d)[:2]
    rows = torch.cat((torch.tensor([i]), nearest))
    sub = SwarmState(state.x[:, rows], state.goals[:, rows], state.obstacles, robot=state.robot)
    lidar = env.lidar(state)
    from egcbf.env.lidar import LidarScan

    sub_lidar = LidarScan(lidar.points[:, rows], lidar.valid[:, rows], lidar.distance[:, rows])
    from egcbf.algo.interface import make_interface
    from egcbf.algo.learner import policy_command
    from egcbf.env.graph import build_graph

    graph = build_graph(sub, env_cfg, lidar=sub_lidar)
    itf = make_interface(agent.model_config.interface, state.robot)
    command, _ = policy_command(agent.policy, agent.model_config, itf, graph, sub.x, sub.goals)
    expected = itf.apply(sub.x, command)[0, 0]
    assert info["num_neighbours"] == 2 and (u - expected).abs().max() <= 1e-9


def test_bad_observations_are_named():
    _, _, agent = _controllers("egcbf+")
    x, goal = torch.zeros(18, dtype=F64), torch.zeros(3, dtype=F64)
    with pytest.raises(ValueError, match=r"state must be a tensor of shape \(18,\)"):
        agent(torch.zeros(17, dtype=F64), goal, x.new_zeros(0, 18), x.new_zeros(0, 3))
    with pytest.raises(ValueError, match=r"neighbours must be a tensor of shape \(K, 18\)"):
        agent(x, goal, x.new_zeros(18), x.new_zeros(0, 3))
    with pytest.raises(ValueError, match="goal holds NaN or inf"):
        agent(x, torch.full((3,), float("nan"), dtype=F64), x.new_zeros(0, 18), x.new_zeros(0, 3))
    with pytest.raises(ValueError, match="max_neighbours must be an integer >= 1"):
        AgentController(agent.policy, agent.model_config, agent.env_config, max_neighbours=-1)


@functools.cache
def _filtered(method: str = "egcbf+"):
    from egcbf.control.resolve import resolve

    built = resolve(f"{method}:dcbf", ROOT / method, dtype=F64)
    swarm, cfg = built.controller, built.train_config
    return swarm, cfg, AgentFilteredController.from_checkpoint(ROOT / method, dtype=F64)


@pytest.mark.parametrize("method", ["egcbf+", "gcbf+"])
@given(seed=st.integers(0, 2**16), n=st.integers(2, 12), area=st.floats(0.8, 2.0), obstacles=st.integers(0, 3))
@settings(max_examples=3, deadline=None)
def test_every_agents_filtered_control_is_the_swarm_filters(method, seed, n, area, obstacles):
    """float64, 1e-9: the per-agent policy behind the dcbf filter, given the neighbours' states, the obstacles it
    senses and the realized accelerations of the last step, reproduces the swarm-level filtered control (with its
    look-ahead) of every agent, the braking fallback included."""
    swarm, cfg, agent = _filtered(method)
    env, env_cfg, state = _scene(cfg, n, area, obstacles, seed)
    swarm(state, env_cfg)  # the swarm filter keeps the velocities of its previous call: two calls in a row
    v_prev = state.x[0, :, 12:15].clone()
    state, _ = env.step(state, swarm(state, env_cfg)[0])
    u_all, info = swarm(state, env_cfg)
    acc = (state.x[0, :, 12:15] - v_prev) / env_cfg.dt
    obstacles_seen = (state.obstacles.centers[0], state.obstacles.radii[0])
    for i in range(n):
        x, goal, others, hits = _observation(env, state, i)
        order = torch.cat((torch.tensor([i]), torch.tensor([j for j in range(n) if j != i], dtype=torch.long)))
        u, out = agent(x, goal, others, hits, obstacles=obstacles_seen, accelerations=acc[order])
        assert (u - u_all[0, i]).abs().max() <= 1e-9, (i, out)
        a_safe = info["a_safe"][0, i] / 5.0
        assert (out["command"] - a_safe).abs().max() <= 1e-9


def test_the_filtered_agent_refuses_bad_inputs():
    _, _, agent = _filtered()
    x, goal = torch.zeros(18, dtype=F64), torch.zeros(3, dtype=F64)
    x[3:12] = torch.eye(3, dtype=F64).flatten()
    with pytest.raises(ValueError, match=r"accelerations must have shape \(1, 3\)"):
        agent(x, goal, x.new_zeros(0, 18), x.new_zeros(0, 3), accelerations=x.new_zeros(2, 3))
    with pytest.raises(ValueError, match="obstacles must be"):
        agent(x, goal, x.new_zeros(0, 18), x.new_zeros(0, 3), obstacles=(x.new_zeros(1, 2), x.new_zeros(1)))
    from egcbf.control.filters import FilterConfig

    with pytest.raises(NotImplementedError, match="'dcbf' filter"):
        AgentFilteredController(agent.controller, FilterConfig.for_kind("prior"))


def test_corrupt_far_and_surplus_rows_are_left_out_and_counted():
    """A robot's observation as it comes: a corrupt message (NaN), LiDAR hits beyond the training range, more
    neighbours than slots. Each is left out of the policy's input and counted in ``info``; the control is the
    one of the clean, in-range, nearest rows."""
    _, cfg, _ = _controllers("egcbf+")
    agent = AgentController.from_checkpoint(ROOT / "egcbf+", dtype=F64, max_neighbours=2)
    env, _, state = _scene(cfg, 6, 1.2, 2, seed=3)
    x, goal, others, hits = _observation(env, state, 0)
    reach = agent.env_config.resolved_lidar_range
    near = others[(others[:, :3] - x[:3]).square().sum(-1) < agent.env_config.comm_radius**2]
    assert near.shape[0] >= 3
    u_ref, ref = agent(x, goal, others, hits)
    bad = torch.full((1, 18), float("nan"), dtype=F64)
    far = x[:3] + torch.tensor([[reach * 3, 0.0, 0.0], [0.0, reach * 1.5, 0.0]], dtype=F64)
    with pytest.warns(UserWarning, match="slots were dropped"):
        fresh = AgentController.from_checkpoint(ROOT / "egcbf+", dtype=F64, max_neighbours=2)
        u, info = fresh(x, goal, torch.cat((bad, others)), torch.cat((hits, far, bad[:, :3])))
    assert torch.equal(u, u_ref) and info["num_hits"] == ref["num_hits"] == hits.shape[0]
    assert info["rejected_neighbours"] == 1 and info["rejected_hits"] == 1
    assert info["dropped_neighbours"] == near.shape[0] - 2 and info["dropped_hits"] == 0
    # the fixed-shape module (what ONNX runs) ignores a far hit marked valid as well
    inputs = list(agent.pad(x, goal, others, hits))
    pts, valid = inputs[4].clone(), inputs[5].clone()
    free = int(valid.sum())
    if free < pts.shape[0]:
        pts[free], valid[free] = far[0], True
        u2, _ = agent.module(*inputs[:4], pts, valid)
        assert torch.equal(u2, agent.module(*inputs)[0])


def test_more_hit_slots_than_training_warn_and_the_filtered_agent_has_the_robot():
    with pytest.warns(UserWarning, match="exceeds the 16 LiDAR hits"):
        AgentController.from_checkpoint(ROOT / "egcbf+", dtype=F64, max_hits=32)
    _, _, agent = _filtered()
    assert agent.robot.name == "quadrotor" and agent.env_config.comm_radius == agent.controller.env_config.comm_radius
