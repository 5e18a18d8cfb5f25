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


def _nearest_by_brute_force(p, batch, radius, k):
    """Per agent ``i``: ``(d2, j)`` of the other agents of its environment closer than ``radius``, sorted by
    ``(d2, j)``, the first ``k``; ``d2 = (p_j - p_i)^2`` summed over the coordinates in the tensors' dtype."""
    out = []
    for i in range(p.shape[0]):
        d2 = (p - p[i]).square().sum(-1)
        near = [(float(d2[j]), j) for j in range(p.shape[0]) if j != i and batch[j] == batch[i] and d2[j] < radius**2]
        out.append(sorted(near)[:k])
    return out


@st.composite
def neighbour_scenes(draw):
    """Points of several environments (ids in any order) in a box; on a lattice half the time (coincident
    points and equal distances); radii and ``k`` from none to many neighbours per point."""
    b, n, d = draw(st.integers(1, 4)), draw(st.integers(0, 30)), draw(st.sampled_from([2, 3]))
    gen = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    dtype = draw(st.sampled_from([torch.float32, F64]))
    p = (torch.rand(b * n, d, generator=gen, dtype=F64) * draw(st.floats(0.05, 3.0))).to(dtype)
    lattice = draw(st.booleans())
    if lattice:
        p = torch.round(p * 4) / 4
    batch = (
        torch.randint(0, b, (b * n,), generator=gen) if draw(st.booleans()) else torch.arange(b).repeat_interleave(n)
    )
    walk = [(torch.rand(b * n, d, generator=gen, dtype=F64) - 0.5).to(dtype) * 0.1 for _ in range(2)]
    return p, batch, draw(st.floats(0.05, 1.5)), draw(st.integers(1, 8)), lattice, walk


@settings(max_examples=80, deadline=None)
@given(scene=neighbour_scenes(), search=st.sampled_from(["k-d tree", "cell list"]), skin=st.sampled_from([0.0, 0.1]))
def test_nearest_neighbours_equal_a_brute_force_reading(scene, search, skin):
    """The neighbour list's ``k`` nearest within the radius equal a brute-force reading, over a short random walk,
    with either candidate search: the same neighbours in the same order, masks a prefix of each row and index
    ``M`` past it. Equal distances: ordered by index for float32 (the packed sort key), in any order otherwise
    (then the rows' distances equal the reading's)."""
    from unittest import mock

    from egcbf.env import observations
    from egcbf.geometry import neighbors

    p, batch, radius, k, lattice, walk = scene
    pairs = neighbors._kd_tree_pairs if search == "k-d tree" else neighbors._cell_list_pairs
    kept = observations.NeighbourList(radius, skin * radius)
    m = p.shape[0]
    with mock.patch.object(neighbors, "_kd_tree_pairs", pairs):
        for step in (None, *walk):
            p = p if step is None else p + step
            index, mask = kept.nearest(p, batch, k)
            assert index.shape == mask.shape == (m, k) and index.dtype == torch.long and mask.dtype == torch.bool
            for i, want in enumerate(_nearest_by_brute_force(p, batch, radius, k)):
                got = index[i][mask[i]].tolist()
                assert mask[i].tolist() == [True] * len(want) + [False] * (k - len(want))
                assert (index[i][~mask[i]] == m).all()
                if p.dtype == torch.float32 or not lattice:
                    assert got == [j for _, j in want]
                else:
                    assert len(set(got)) == len(got) and all(batch[j] == batch[i] and j != i for j in got)
                    assert [float((p[j] - p[i]).square().sum()) for j in got] == [d2 for d2, _ in want]


def test_nearest_neighbours_edge_cases():
    """No neighbours (alone, or everyone farther than the radius), more than ``k`` (the ``k`` nearest kept), points
    that coincide, and two environments on top of each other (never neighbours across them)."""
    from egcbf.env.observations import NeighbourList

    for dtype in (torch.float32, F64):
        alone = torch.zeros(1, 3, dtype=dtype)
        index, mask = NeighbourList(1.0).nearest(alone, torch.zeros(1, dtype=torch.long), 4)
        assert index.tolist() == [[1] * 4] and not mask.any()
        far = torch.arange(5, dtype=dtype)[:, None].expand(5, 3) * 2.0
        index, mask = NeighbourList(1.0).nearest(far, torch.zeros(5, dtype=torch.long), 3)
        assert (index == 5).all() and not mask.any()
        line = torch.zeros(10, 3, dtype=dtype)
        line[:, 0] = torch.arange(10, dtype=dtype) * 0.1  # agent 0 hears 1..9, nearest first; k = 4 keeps 1..4
        index, mask = NeighbourList(1.0).nearest(line, torch.zeros(10, dtype=torch.long), 4)
        assert index[0].tolist() == [1, 2, 3, 4] and mask.all()
        three = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.35, 0.0, 0.0]], dtype=dtype)
        twins = torch.cat((three, three))  # environments 0 and 1 at the same three points
        index, mask = NeighbourList(1.0).nearest(twins, torch.tensor([0, 0, 0, 1, 1, 1]), 3)
        assert index.tolist() == [[1, 2, 6], [0, 2, 6], [1, 0, 6], [4, 5, 6], [3, 5, 6], [4, 3, 6]]
        same = torch.zeros(3, 2, dtype=dtype)  # coincident points: distance 0 < radius
        index, mask = NeighbourList(0.5).nearest(same, torch.zeros(3, dtype=torch.long), 2)
        assert mask.all() and all(sorted(row) == sorted({0, 1, 2} - {i}) for i, row in enumerate(index.tolist()))


@pytest.mark.parametrize("comm_radius", [None, 0.1])
@pytest.mark.parametrize("robot", ["quadrotor", "unicycle"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_task_masks_are_the_simulator_s(robot, dtype, comm_radius):
    """SwarmTask's step masks, tested on the neighbour search's pairs, equal SwarmEnv.step's own (a dense scene:
    unsafe pairs and collisions every step); with a communication radius below the unsafe distance the masks
    search for themselves."""
    area = {"quadrotor": 1.0, "unicycle": 1.3}[robot]
    radius = {} if comm_radius is None else {"comm_radius": comm_radius}
    cfg = EnvConfig.for_robot(robot, num_agents=24, num_envs=3, area_size=area, num_obstacles=2, max_steps=30,
                              **radius)  # fmt: skip
    env, task = SwarmEnv(cfg, dtype=dtype), SwarmTask(cfg, dtype=dtype)
    state = env.reset(5)
    task.reset(5)
    assert (task._unsafe_pairs() is None) == (comm_radius is not None)
    seen = torch.zeros(2, dtype=torch.long)
    for _ in range(30):
        u = env.robot.nominal_control(state.x, state.goals)
        state, info = env.step(state, u)
        out = task.step(u)
        assert torch.equal(out.state.x, state.x) and torch.equal(out.truncated, info.done)
        for key in ("collision", "agent_collision", "obstacle_collision", "unsafe", "reached"):
            assert torch.equal(out.info[key], getattr(info, key)), key
        seen += torch.stack((info.unsafe.sum(), info.agent_collision.sum()))
    assert (seen > 0).all()


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    b=st.integers(1, 4),
    n=st.integers(0, 60),
    d=st.sampled_from([2, 3]),
    dtype=st.sampled_from([torch.float32, F64]),
    skin=st.sampled_from([0.0, 0.05, 0.2, 0.5]),
    k=st.integers(1, 12),
    speed=st.floats(0.0, 0.2),
)
def test_the_neighbour_list_equals_the_previous_implementation(seed, b, n, d, dtype, skin, k, speed):
    """Over a walk that drifts (so that the leading anchors are used) and jitters (so that they sometimes miss),
    the neighbour list's rows, masks and unsafe pairs equal the previous implementation's
    (``previous_env.NeighbourList``: anchors at the positions, one sort of both directions' keys), bit for bit;
    the pairs as a set (their order follows the search)."""
    from previous_env import NeighbourList as PreviousNeighbourList

    from egcbf.env.observations import NeighbourList

    gen = torch.Generator().manual_seed(seed)
    radius = 0.4
    p = (torch.rand(b * n, d, generator=gen, dtype=F64) * 1.2).to(dtype)
    batch = torch.arange(b).repeat_interleave(n)
    velocity = (torch.randn(b * n, d, generator=gen, dtype=F64) * speed).to(dtype)
    new, old = NeighbourList(radius, skin), PreviousNeighbourList(radius, skin)
    for _ in range(10):
        jitter = (torch.rand(b * n, d, generator=gen, dtype=F64) - 0.5).to(dtype) * 0.02
        p = p + velocity + jitter
        (index, mask), (ref_index, ref_mask) = new.nearest(p, batch, k), old.nearest(p, batch, k)
        assert torch.equal(index, ref_index) and torch.equal(mask, ref_mask)
        for distance in (0.1, radius):
            u, v = new.pairs_within(distance)
            ru, rv = old.pairs_within(distance)
            assert sorted(zip(u.tolist(), v.tolist())) == sorted(zip(ru.tolist(), rv.tolist()))


def test_leading_anchors_serve_steady_motion_longer():
    """In steady motion a search anchored ahead of the agents serves about twice as many steps (the same answers:
    the test above); a walk that turns every step is anchored at the positions."""
    from previous_env import NeighbourList as PreviousNeighbourList

    from egcbf.env.observations import NeighbourList

    gen = torch.Generator().manual_seed(0)
    p0 = torch.rand(200, 3, generator=gen, dtype=F64) * 2
    velocity = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen, dtype=F64), dim=-1) * 0.02
    batch = torch.zeros(200, dtype=torch.long)
    new, old = NeighbourList(0.5, 0.1), PreviousNeighbourList(0.5, 0.1)
    for t in range(60):
        for kept in (new, old):
            kept.nearest(p0 + t * velocity, batch, 8)
    assert old.searches == 20 and new.searches <= 13, (old.searches, new.searches)
    zigzag = NeighbourList(0.5, 0.1)
    for t in range(60):
        zigzag.nearest(p0 + (t % 2) * velocity * 3, batch, 8)
    assert zigzag._anchor is not None and torch.equal(zigzag._anchor, zigzag._last[-1])


@pytest.mark.parametrize("robot", ["quadrotor", "unicycle"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_task_step_equals_the_previous_implementation(robot, dtype):
    """SwarmTask's observations (neighbour rows, LiDAR hits), rewards and costs over an episode with random
    controls and obstacles equal those of the previous implementation (``previous_env``'s neighbour list,
    LiDAR and observation; the reward and cost by their formula, every term formed anew), bit for bit."""
    from previous_env import NeighbourList as PreviousNeighbourList
    from previous_env import agent_observations as previous_observations
    from previous_env import lidar_scan as previous_lidar_scan

    area = {"quadrotor": 2.0, "unicycle": 4.0}[robot]
    cfg = EnvConfig.for_robot(robot, num_agents=48, num_envs=3, area_size=area, num_obstacles=5, max_steps=30)
    task = SwarmTask(cfg, TaskConfig(deviation_weight=1.5, progress_weight=0.7), dtype=dtype)
    task.reset(seed=4)
    robot_ = task.robot
    kept = PreviousNeighbourList(cfg.comm_radius, task.task.neighbour_skin * cfg.comm_radius)
    gen = torch.Generator().manual_seed(2)
    like = torch.zeros((), dtype=dtype)
    lo, hi = robot_.control_bounds(like)
    for _ in range(15):
        before = task.state
        nominal = robot_.clip_control(robot_.nominal_control(before.x, before.goals))
        noise = torch.randn(nominal.shape, generator=gen, dtype=F64).to(dtype)
        u = robot_.nominal_control(before.x, before.goals) + 0.2 * (hi - lo) * noise
        out = task.step(u)
        after = out.state
        scan = previous_lidar_scan(after.positions, robot_.heading(after.x), after.obstacles, n_rays=cfg.n_rays,
                                   max_range=cfg.resolved_lidar_range, max_hits=cfg.lidar_max_hits)  # fmt: skip
        ref = previous_observations(after.x, after.goals, after.positions, scan, cfg.comm_radius,
                                    task.task.max_neighbours, kept)  # fmt: skip
        for key in OBSERVATION_KEYS:
            assert out.observation[key].dtype == ref[key].dtype and torch.equal(out.observation[key], ref[key]), key
        applied = robot_.clip_control(u)
        reward = torch.zeros(before.x.shape[:2], dtype=dtype)
        reward = reward - 1.5 * ((applied - nominal) / ((hi - lo) / 2).to(dtype)).square().mean(-1)
        gap_before = torch.linalg.vector_norm(before.positions - before.goals, dim=-1)
        gap_after = torch.linalg.vector_norm(after.positions - after.goals, dim=-1)
        reward = reward + 0.7 * (gap_before - gap_after) / cfg.agent_radius
        assert torch.equal(out.reward, reward)
        assert torch.equal(out.cost, out.info["collision"].to(dtype) * 1.0)
    assert any(bool(v.any()) for v in (out.observation["hit_mask"], out.observation["neighbour_mask"]))
