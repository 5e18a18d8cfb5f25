"""Per-agent observations and the multi-agent task: the observation against a brute-force per-agent reading, its
equivariance under the robot's group, and the reward's and cost's definitions."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.observations import OBSERVATION_KEYS, ObservationLayout
from egcbf.env.task import SwarmTask, TaskConfig
from egcbf.robots import ROBOTS

F64 = torch.float64


def _brute_force(state, scan, comm_radius, k):
    """Each agent's neighbour rows by a loop over agents: every other agent closer than ``comm_radius``, sorted by
    distance (then index), the first ``k``."""
    b, n, s = state.x.shape
    rows = torch.zeros(b, n, k, s, dtype=F64)
    mask = torch.zeros(b, n, k, dtype=torch.bool)
    p = state.positions
    for e in range(b):
        for i in range(n):
            d2 = (p[e] - p[e, i]).square().sum(-1)
            order = sorted((float(d2[j]), j) for j in range(n) if j != i and d2[j].sqrt() < comm_radius)
            for slot, (_, j) in enumerate(order[:k]):
                rows[e, i, slot], mask[e, i, slot] = state.x[e, j], True
    hits = torch.where(scan.valid[..., None], scan.points, torch.zeros((), dtype=F64))
    return rows, mask, hits


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_observation_equals_a_per_agent_reading(robot):
    cfg = EnvConfig.for_robot(robot, num_agents=12, num_envs=2, area_size=1.5, num_obstacles=3, max_steps=8)
    task = SwarmTask(cfg, TaskConfig(max_neighbours=3), dtype=F64)  # 3 slots in a dense arena: truncation happens
    obs = task.reset(seed=4)
    for _ in range(3):
        u = task.robot.nominal_control(task.state.x, task.state.goals)
        obs = task.step(u).observation
    rows, mask, hits = _brute_force(task.state, task.env.lidar(task.state), cfg.comm_radius, 3)
    assert tuple(obs) == OBSERVATION_KEYS
    assert mask.sum(-1).max() == 3 and (mask.sum(-1) < 3).any()  # full and partly empty rows both occur
    assert torch.equal(obs["neighbour_mask"], mask)
    torch.testing.assert_close(obs["neighbours"], rows, rtol=0, atol=0)
    torch.testing.assert_close(obs["hits"], hits, rtol=0, atol=0)
    assert torch.equal(obs["state"], task.state.x) and torch.equal(obs["goal"], task.state.goals)
    layout = ObservationLayout.of(cfg, 3)
    for key, shape in layout.shapes().items():
        assert tuple(obs[key].shape) == (2, 12, *shape), key


@settings(max_examples=10)
@given(seed=st.integers(0, 2**16), robot=st.sampled_from(["quadrotor", "unicycle", "double_integrator"]))
def test_observation_moves_with_the_scene(seed, robot):
    """Under a global group element g (the robot's symmetry group), each observation moves with the scene: states
    by the robot's state action, goals and hits as points; masks and neighbour order unchanged (float64, 1e-10)."""
    cfg = EnvConfig.for_robot(robot, num_agents=10, num_envs=2, area_size=2.0, num_obstacles=2)
    task = SwarmTask(cfg, TaskConfig(max_neighbours=4), dtype=F64)
    task.reset(seed)
    state = task.state
    robot_ = task.robot
    g = robot_.group.sample(2, generator=torch.Generator().manual_seed(seed), dtype=F64)
    moved = state.transform(g)
    a, b = task.observe(state), task.observe(moved)
    assert torch.equal(a["neighbour_mask"], b["neighbour_mask"]) and torch.equal(a["hit_mask"], b["hit_mask"])
    ge = g[:, None]
    act = robot_.state_type.act
    torch.testing.assert_close(b["state"], act(ge, a["state"]), rtol=0, atol=1e-10)
    torch.testing.assert_close(b["goal"], robot_.group.transform(ge, a["goal"]), rtol=0, atol=1e-10)
    m = a["neighbour_mask"][..., None]
    torch.testing.assert_close(b["neighbours"] * m, act(g[:, None, None], a["neighbours"]) * m, rtol=0, atol=1e-10)
    h = a["hit_mask"][..., None]
    torch.testing.assert_close(b["hits"] * h, robot_.group.transform(g[:, None, None], a["hits"]) * h, rtol=0,
                               atol=1e-9)  # fmt: skip


def test_reward_and_cost_follow_their_definition():
    cfg = EnvConfig(num_agents=16, num_envs=2, area_size=1.0, max_steps=20)
    task = SwarmTask(cfg, TaskConfig(deviation_weight=2.0, progress_weight=0.5, collision_cost=3.0), dtype=F64)
    task.reset(seed=1)
    lo, hi = task.control_bounds()
    before = task.state
    nominal = task.robot.clip_control(task.robot.nominal_control(before.x, before.goals))
    u = nominal + 0.3 * (hi - lo) * torch.randn(nominal.shape, dtype=F64, generator=torch.Generator().manual_seed(0))
    out = task.step(u)
    applied = task.robot.clip_control(u)
    gap = lambda s: torch.linalg.vector_norm(s.positions - s.goals, dim=-1)  # noqa: E731
    expected = -2.0 * ((applied - nominal) / ((hi - lo) / 2)).square().mean(-1)
    expected = expected + 0.5 * (gap(before) - gap(out.state)) / cfg.agent_radius
    torch.testing.assert_close(out.reward, expected, rtol=0, atol=1e-12)
    assert torch.equal(out.cost, 3.0 * out.info["collision"].to(F64))
    # following the nominal command exactly costs nothing in the deviation term
    task.reset(seed=1)
    follow = task.step(nominal)
    torch.testing.assert_close(follow.reward, 0.5 * (gap(before) - gap(follow.state)) / cfg.agent_radius, rtol=0,
                               atol=1e-12)  # fmt: skip


def test_every_scene_truncates_at_max_steps_and_then_refuses_to_step():
    cfg = EnvConfig(num_agents=4, num_envs=3, max_steps=3)
    task = SwarmTask(cfg, dtype=F64)
    with pytest.raises(RuntimeError, match="before reset"):
        task.step(torch.zeros(3, 4, 4, dtype=F64))
    task.reset(seed=0)
    flags = [task.step(task.robot.nominal_control(task.state.x, task.state.goals)).truncated for _ in range(3)]
    assert [bool(f.all()) for f in flags] == [False, False, True] and not any(bool(f.any()) for f in flags[:2])
    with pytest.raises(RuntimeError, match="episode has ended"):
        task.step(torch.zeros(3, 4, 4, dtype=F64))


def test_bad_task_settings_are_refused():
    with pytest.raises(ValueError, match="max_neighbours"):
        SwarmTask(EnvConfig(num_agents=4), TaskConfig(max_neighbours=0))
    with pytest.raises(ValueError, match="deviation_weight"):
        TaskConfig(deviation_weight=-1.0)
    with pytest.raises(TypeError, match="TaskConfig"):
        SwarmTask(EnvConfig(num_agents=4), task={"max_neighbours": 3})


def test_observations_do_not_depend_on_the_env_wrapper():
    """SwarmTask's states are SwarmEnv's: the same seed and controls give the same trajectory."""
    cfg = EnvConfig(num_agents=8, num_envs=2, num_obstacles=2)
    env, task = SwarmEnv(cfg, dtype=F64), SwarmTask(cfg, dtype=F64)
    state = env.reset(7)
    task.reset(7)
    for _ in range(5):
        u = env.robot.nominal_control(state.x, state.goals)
        state, _ = env.step(state, u)
        task.step(u)
        assert torch.equal(task.state.x, state.x)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), skin=st.sampled_from([0.0, 0.05, 0.3]), k=st.integers(1, 6))
def test_the_verlet_neighbour_list_answers_as_a_fresh_search(seed, skin, k):
    """Over a random walk (steps up to 0.08 m, so some steps outrun half the skin and some do not), the kept list's
    k nearest neighbours within the radius equal a brute-force reading at every step; it searches anew only when
    some point has moved more than skin / 2 since its last search."""
    from egcbf.env.observations import NeighbourList

    gen = torch.Generator().manual_seed(seed)
    b, n, radius = 2, 30, 0.5
    p = torch.rand(b * n, 3, generator=gen, dtype=F64) * 1.5
    batch = torch.arange(b).repeat_interleave(n)
    kept = NeighbourList(radius, skin)
    for _ in range(8):
        p = p + (torch.rand(b * n, 3, generator=gen, dtype=F64) - 0.5) * 0.16 * torch.rand((), generator=gen)
        index, mask = kept.nearest(p, batch, k)
        for i in range(b * n):
            d2 = (p - p[i]).square().sum(-1)
            order = sorted(
                (float(d2[j]), j) for j in range(b * n) if j != i and batch[j] == batch[i] and d2[j] < radius**2
            )
            want = [j for _, j in order[:k]]
            assert index[i][mask[i]].tolist() == want
            assert (index[i][~mask[i]] == b * n).all()
    assert 1 <= kept.searches <= 8 and (skin > 0 or kept.searches == 8)
