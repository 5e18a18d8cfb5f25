"""SwarmEnv: config validation, sampling, masks on hand-made scenes, stepping, errors."""

import dataclasses
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.env import EnvConfig, NonFiniteStateError, Obstacles, SwarmEnv, SwarmState, safety_masks
from egcbf.env.sampling import sample_separated_points
from egcbf.robots.quadrotor import dynamics as dyn

F64 = torch.float64
R = 0.05


# --------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"num_agents": 0}, "num_agents"),
        ({"num_agents": 2.5}, "num_agents"),
        ({"num_agents": True}, "num_agents"),
        ({"area_size": 0.0}, "area_size"),
        ({"area_size": float("inf")}, "area_size"),
        ({"num_obstacles": -1}, "num_obstacles"),
        ({"obstacle_radius_range": (-0.1, 0.2)}, "obstacle_radius_range"),
        ({"obstacle_radius_range": (0.3, 0.2)}, "obstacle_radius_range"),
        ({"obstacle_radius_range": (0.1,)}, "obstacle_radius_range"),
        ({"agent_radius": -0.05}, "agent_radius"),
        ({"agent_radius": 0.0}, "agent_radius"),
        ({"comm_radius": 0.0}, "comm_radius"),
        ({"lidar_range": 2.0}, "lidar_range"),
        ({"n_rays": 7}, "n_rays"),
        ({"lidar_max_hits": 0}, "lidar_max_hits"),
        ({"dt": -0.01}, "dt"),
        ({"substeps": 0}, "substeps"),
        ({"integrator": "rk45"}, "integrator"),
        ({"max_steps": 0}, "max_steps"),
        ({"num_envs": 0}, "num_envs"),
        ({"max_sampling_rounds": 0}, "max_sampling_rounds"),
    ],
)
def test_config_rejects_bad_values(kwargs, field):
    with pytest.raises(ValueError, match=rf"EnvConfig\.{field} must be"):
        EnvConfig(**kwargs)


def test_config_defaults_and_roundtrip():
    c = EnvConfig()
    assert (c.num_agents, c.area_size, c.num_obstacles, c.agent_radius, c.comm_radius) == (8, 2.0, 5, 0.05, 1.0)
    assert c.obstacle_radius_range == (0.05, 0.3)
    assert c.dt == dyn.DEFAULT_DT and c.max_steps == dyn.DEFAULT_MAX_STEPS and c.substeps == dyn.DEFAULT_SUBSTEPS
    assert c.resolved_lidar_range == c.comm_radius
    assert EnvConfig.from_dict(c.to_dict()) == c
    c2 = EnvConfig(agent_radius=0.07, obstacle_radius_range=[0.1, 0.2])
    assert c2.params.radius == 0.07 and c2.obstacle_radius_range == (0.1, 0.2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.num_agents = 3


# ------------------------------------------------------------------------------------------- sampling
def _min_pairwise(p):
    d = (p[..., :, None, :] - p[..., None, :, :]).norm(dim=-1)
    n = p.shape[-2]
    return (d + torch.eye(n, dtype=p.dtype) * 1e9).amin(dim=(-1, -2))


@given(
    n=st.integers(1, 24),
    k=st.integers(0, 6),
    l=st.floats(1.0, 3.0),
    b=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
)
@settings(max_examples=15)
def test_reset_respects_separations(n, k, l, b, seed):
    env = SwarmEnv(EnvConfig(num_agents=n, num_obstacles=k, area_size=l, num_envs=b), dtype=F64)
    s = env.reset(seed)
    assert s.x.shape == (b, n, 18) and s.goals.shape == (b, n, 3) and s.t == 0
    assert s.obstacles.centers.shape == (b, k, 3) and s.obstacles.radii.shape == (b, k)
    for pts in (s.positions, s.goals):
        assert ((pts >= 0) & (pts <= l)).all()
        if n > 1:
            assert (_min_pairwise(pts) > 4 * R).all()
        if k:
            assert (s.obstacles.surface_distance(pts) > 4 * R).all()
    r = s.obstacles.radii
    assert ((r >= 0.05) & (r <= 0.3)).all()
    # at rest, level, random yaw: R = Rz(yaw)
    rot = s.attitudes
    assert torch.equal(s.x[..., dyn.V], torch.zeros_like(s.x[..., dyn.V]))
    assert torch.equal(s.x[..., dyn.W], torch.zeros_like(s.x[..., dyn.W]))
    assert torch.allclose(rot[..., 2, :], torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(b, n, 3))
    dyn.check_state(s.x)


def test_reset_is_seeded_and_yaw_option():
    env = SwarmEnv(EnvConfig(num_envs=2), dtype=F64)
    a, b, c = env.reset(3), env.reset(3), env.reset(4)
    assert torch.equal(a.x, b.x) and torch.equal(a.goals, b.goals) and torch.equal(a.obstacles.radii, b.obstacles.radii)
    assert not torch.equal(a.x, c.x)
    yaw = torch.atan2(a.attitudes[..., 1, 0], a.attitudes[..., 0, 0])
    assert yaw.std() > 0.3  # random yaws
    env0 = SwarmEnv(EnvConfig(num_envs=2, random_yaw=False), dtype=F64)
    assert torch.allclose(env0.reset(3).attitudes, torch.eye(3, dtype=F64).expand(2, 8, 3, 3))
    # float32 on the same seed: the same state up to the cast
    a32 = SwarmEnv(EnvConfig(num_envs=2), dtype=torch.float32).reset(3)
    assert a32.x.dtype == torch.float32 and torch.equal(a32.x, a.x.float())
    with pytest.raises(TypeError, match="seed"):
        env.reset(None)


def test_impossible_area_raises_immediately():
    with pytest.raises(ValueError, match=r"N=500 agents .*\[0, 0\.5\]\^3 .*separation > 0\.2.*densest"):
        SwarmEnv(EnvConfig(num_agents=500, area_size=0.5, num_obstacles=0)).reset(0)


def test_too_crowded_area_raises_after_bounded_rounds():
    # passes the packing bound but is beyond what random sequential placement can reach
    cfg = EnvConfig(num_agents=60, area_size=0.6, num_obstacles=0, max_sampling_rounds=30)
    with pytest.raises(ValueError, match=r"N=60 agents.*after 30 rounds"):
        SwarmEnv(cfg).reset(0)


def test_area_filled_by_obstacles_raises():
    cfg = EnvConfig(
        num_agents=2, area_size=0.4, num_obstacles=40, obstacle_radius_range=(0.3, 0.3), max_sampling_rounds=20
    )
    with pytest.raises(ValueError, match="unplaced after 20 rounds"):
        SwarmEnv(cfg).reset(0)


def test_sampler_many_points_sparse():
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    gen = torch.Generator().manual_seed(0)
    pts = sample_separated_points(1, 2, 2048, 2048 ** (1 / 3), 0.2, obs, 0.2, generator=gen)
    assert pts.shape == (1, 2, 2048, 3)
    from egcbf.geometry.neighbors import radius_neighbors

    for s in range(2):
        assert radius_neighbors(pts[0, s], 0.2).shape[1] == 0


# ---------------------------------------------------------------------------------------------- masks
def _scene(positions, goals=None, centers=(), radii=()):
    p = torch.tensor(positions, dtype=F64)[None]
    g = p.clone() + 1.0 if goals is None else torch.tensor(goals, dtype=F64)[None]
    c = torch.tensor(list(centers), dtype=F64).reshape(1, -1, 3)
    r = torch.tensor(list(radii), dtype=F64).reshape(1, -1)
    return p, g, Obstacles(c, r)


def test_agent_agent_masks():
    # pairs at distance 0.09 (< 2r: collision), 0.11 (< 2.5r: unsafe only), 0.13 (neither)
    pos = [[0, 0, 0], [0.09, 0, 0], [5, 0, 0], [5.11, 0, 0], [9, 0, 0], [9.13, 0, 0]]
    p, g, obs = _scene(pos)
    m = safety_masks(p, g, obs, R)
    assert m["collision"][0].tolist() == [True, True, False, False, False, False]
    assert m["unsafe"][0].tolist() == [True, True, True, True, False, False]
    assert m["agent_collision"].equal(m["collision"]) and not m["obstacle_collision"].any()


def test_agent_obstacle_masks():
    # sphere of radius 0.2: surface distances 0.04 (< r: collision), 0.07 (< 1.5 r: unsafe), 0.1 (neither)
    pos = [[0.24, 0, 0], [0, 0.27, 0], [0, 0, -0.30], [0, 0, 0.1]]
    p, g, obs = _scene(pos, centers=[[0, 0, 0]], radii=[0.2])
    m = safety_masks(p, g, obs, R)
    assert m["obstacle_collision"][0].tolist() == [True, False, False, True]
    assert m["collision"][0].tolist() == [True, False, False, True]
    assert m["unsafe"][0].tolist() == [True, True, False, True]


def test_unsafe_distances_move_the_labels_not_the_collisions():
    """EnvConfig.unsafe_agent_distance / unsafe_obstacle_distance (agent radii) widen the training labels' unsafe
    set; collisions stay at 2 r and r; values below those are refused."""
    pos = [[0, 0, 0], [0.09, 0, 0], [5, 0, 0], [5.14, 0, 0], [9, 0, 0], [9.16, 0, 0], [0, 0, 3.28]]
    p, g, obs = _scene(pos, centers=[[0, 0, 3]], radii=[0.2])  # the last agent 0.08 m from the sphere's surface
    m = safety_masks(p, g, obs, R, 3.0, 2.0)
    assert m["collision"][0].tolist() == [True, True, False, False, False, False, False]
    assert m["unsafe"][0].tolist() == [True, True, True, True, False, False, True]
    assert m["unsafe"][0].tolist() != safety_masks(p, g, obs, R)["unsafe"][0].tolist()
    cfg = EnvConfig(num_envs=1, num_agents=2, unsafe_agent_distance=3.0)
    assert SwarmEnv(cfg, dtype=F64).config.unsafe_agent_distance == 3.0
    with pytest.raises(ValueError, match="unsafe_agent_distance"):
        EnvConfig(unsafe_agent_distance=1.5)
    with pytest.raises(ValueError, match="unsafe_obstacle_distance"):
        EnvConfig(unsafe_obstacle_distance=0.5)


def test_reached_mask():
    pos = [[0, 0, 0], [1, 1, 1], [2, 2, 2]]
    goals = [[0.099, 0, 0], [1, 1.101, 1], [2, 2, 2]]
    p, g, obs = _scene(pos, goals)
    assert safety_masks(p, g, obs, R)["reached"][0].tolist() == [True, False, True]


def test_masks_separate_environments():
    p = torch.zeros(2, 2, 3, dtype=F64)
    p[:, 1, 0] = 1.0
    p[1, 1, 0] = 0.05  # only env 1 has a colliding pair
    obs = Obstacles(torch.zeros(2, 0, 3, dtype=F64), torch.zeros(2, 0, dtype=F64))
    m = safety_masks(p, p + 3, obs, R)
    assert m["collision"].tolist() == [[False, False], [True, True]]


# ----------------------------------------------------------------------------------------------- step
def test_step_hover_done_and_info():
    cfg = EnvConfig(num_envs=2, num_agents=4, max_steps=3)
    env = SwarmEnv(cfg, dtype=F64)
    s = env.reset(0)
    u = dyn.hover_control(cfg.params, 2, 4, dtype=F64)
    dones = []
    for _ in range(3):
        s, info = env.step(s, u)
        dones.append(bool(info.done.all()))
        assert info.collision.shape == (2, 4) and info.done.shape == (2,)
        assert torch.equal(info.u, u)
    assert dones == [False, False, True] and s.t == 3
    assert torch.allclose(s.positions, env.reset(0).positions, atol=1e-12)  # hovering stays put


def test_step_clips_controls_and_checks_shapes():
    cfg = EnvConfig(num_envs=1, num_agents=2)
    env = SwarmEnv(cfg, dtype=F64)
    s = env.reset(0)
    u = torch.full((1, 2, 4), 100.0, dtype=F64)
    _, info = env.step(s, u)
    assert info.u[..., 3].max() == cfg.params.max_thrust
    with pytest.raises(ValueError, match=r"\(1, 2, 4\)"):
        env.step(s, torch.zeros(2, 4, dtype=F64))


def test_non_finite_state_raises():
    env = SwarmEnv(EnvConfig(num_envs=1, num_agents=3), dtype=F64)
    s = env.reset(0)
    u = dyn.hover_control(env.config.params, 1, 3, dtype=F64)
    u[0, 1, 0] = float("nan")
    with pytest.raises(NonFiniteStateError, match=r"\(0, 1\)"):
        env.step(s, u)
    x = s.x.clone()
    x[0, 2, 0] = float("inf")
    with pytest.raises(FloatingPointError):
        env.step(SwarmState(x, s.goals, s.obstacles), dyn.hover_control(env.config.params, 1, 3, dtype=F64))


def test_state_validation():
    obs = Obstacles(torch.zeros(1, 0, 3), torch.zeros(1, 0))
    with pytest.raises(ValueError, match="state x"):
        SwarmState(torch.zeros(1, 2, 17), torch.zeros(1, 2, 3), obs)
    with pytest.raises(ValueError, match="goals"):
        SwarmState(torch.zeros(1, 2, 18), torch.zeros(1, 3, 3), obs)
    with pytest.raises(ValueError, match="radii"):
        Obstacles(torch.zeros(1, 2, 3), torch.zeros(1, 3))


def test_large_swarm_masks_are_sparse_and_fast():
    env = SwarmEnv(EnvConfig(num_agents=4096, area_size=16.0, num_obstacles=8), dtype=torch.float32)
    s = env.reset(0)
    info = env.info(s)
    assert not info.collision.any()  # separated at reset
    assert math.isclose(env.config.density, 1.0)
