"""Scene layouts and the scene rotation (egcbf.env.scenes): where starts and goals are drawn, that a rotated scene is
the rotated scene, and that an equivariant policy's whole episode from a rotated scene is the rotated episode (the
rotated-world test of docs/equivariance.md rests on it) while a world-frame policy's is not."""

from __future__ import annotations

import dataclasses
import functools
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.learner import LearnedController
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.obstacles import Obstacles
from egcbf.env.sampling import packing_feasible, sample_separated_points
from egcbf.env.scenes import SCENES, rotate_about_center, scene_boxes
from egcbf.nn import PolicyNet

F64 = torch.float64


def _env(scene="uniform", yaw=0.0, n=6, area=1.5, obstacles=2, envs=2, robot="quadrotor", dtype=F64) -> SwarmEnv:
    extra = {"n_rays": 8, "lidar_max_hits": 4} if robot == "quadrotor" else {}
    cfg = EnvConfig.for_robot(
        robot, num_agents=n, area_size=area, num_obstacles=obstacles, num_envs=envs, scene=scene, scene_yaw=yaw, **extra
    )
    return SwarmEnv(cfg, dtype=dtype)


def _yaw_matrix(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]], dtype=F64)


# ------------------------------------------------------------------------------------------------------- layouts
@given(seed=st.integers(0, 2**20), n=st.integers(1, 40), area=st.floats(1.5, 4.0))
@settings(max_examples=15, deadline=None)
def test_crossing_layout_draws_starts_left_and_goals_right(seed, n, area):
    """Starts in x < l/2, goals in x > l/2 (y, z in [0, l]); each set separated by more than 4 r and clear of the
    obstacles by more than 4 r, as in the uniform layout."""
    env = _env("crossing", n=n, area=area, obstacles=3)
    s = env.reset(seed)
    c = env.config
    p, g = s.positions, s.goals
    assert (p[..., 0] >= 0).all() and (p[..., 0] <= area / 2).all()
    assert (g[..., 0] >= area / 2).all() and (g[..., 0] <= area).all()
    assert ((p[..., 1:] >= 0) & (p[..., 1:] <= area)).all() and ((g[..., 1:] >= 0) & (g[..., 1:] <= area)).all()
    sep = c.start_separation * c.agent_radius
    for pts in (p, g):
        d = torch.cdist(pts, pts) + torch.eye(n, dtype=F64) * 1e9
        assert (d > sep).all()
        clearance = torch.cdist(pts, s.obstacles.centers) - s.obstacles.radii[:, None, :]
        assert (clearance > c.obstacle_clearance * c.agent_radius).all()


def test_uniform_layout_is_the_unchanged_stream():
    """The default layout draws starts and goals together, as every earlier release did: the same seed gives the
    same scene as drawing them by hand."""
    env = _env(n=10, area=2.0, obstacles=3)
    s = env.reset(11)
    c = env.config
    gen = torch.Generator().manual_seed(11)
    from egcbf.env.obstacles import sample_obstacles

    obs = sample_obstacles(c.num_envs, c.num_obstacles, c.area_size, c.obstacle_radius_range, generator=gen)
    pts = sample_separated_points(c.num_envs, 2, c.num_agents, c.area_size, 0.2, obs, 0.2, generator=gen)
    assert torch.equal(s.positions, pts[:, 0]) and torch.equal(s.goals, pts[:, 1])
    assert scene_boxes("uniform", 2.0, 3) is None


def test_scene_and_box_inputs_are_checked():
    with pytest.raises(ValueError, match=r"EnvConfig\.scene must be one of"):
        EnvConfig(scene="diagonal")
    with pytest.raises(ValueError, match=r"EnvConfig\.scene_yaw must be a finite number"):
        EnvConfig(scene_yaw=float("nan"))
    with pytest.raises(ValueError, match="unknown scene 'x'"):
        scene_boxes("x", 2.0, 3)
    obs = Obstacles(torch.zeros(1, 0, 3, dtype=F64), torch.zeros(1, 0, dtype=F64))
    with pytest.raises(ValueError, match="box must be 3 pairs"):
        sample_separated_points(1, 1, 2, 1.0, 0.1, obs, 0.1, box=((0, 1), (0, 1)))
    with pytest.raises(ValueError, match=r"in the area \[0, 0.1\] x \[0, 0.1\] x \[0, 0.1\]"):
        sample_separated_points(1, 1, 50, 1.0, 0.2, obs, 0.1, box=((0, 0.1),) * 3)
    assert set(SCENES) == {"uniform", "crossing"}


@given(n=st.integers(1, 400), sides=st.lists(st.floats(0.1, 3.0), min_size=3, max_size=3), sep=st.floats(0.05, 0.5))
@settings(max_examples=40, deadline=None)
def test_packing_bound_of_a_box_is_that_of_its_cube_when_the_sides_agree(n, sides, sep):
    """The box form of the densest-packing bound agrees with the cube form for equal sides and is monotone in each
    side (a larger box never holds fewer points)."""
    l = sides[0]
    assert packing_feasible(n, l, sep, 3, (l, l, l)) == packing_feasible(n, l, sep, 3)
    if packing_feasible(n, 1.0, sep, 3, tuple(sides)):
        assert packing_feasible(n, 1.0, sep, 3, tuple(s + 0.1 for s in sides))


# ------------------------------------------------------------------------------------------------------ rotation
@pytest.mark.parametrize("robot", ["quadrotor", "unicycle"])
@given(seed=st.integers(0, 2**20), yaw=st.one_of(st.sampled_from([90.0, 180.0, 270.0, -90.0]), st.floats(-360, 360)))
@settings(max_examples=12, deadline=None)
def test_a_rotated_scene_is_the_rotated_scene(robot, seed, yaw):
    """scene_yaw rotates starts, goals, obstacle centres and headings about the arena's vertical centre axis
    (float64, 1e-12); z, radii and the unrotated draw are unchanged."""
    area = 2.0
    a, b = (
        _env("crossing", 0.0, robot=robot, area=area).reset(seed),
        _env("crossing", yaw, robot=robot, area=area).reset(seed),
    )
    d = a.positions.shape[-1]
    rot = _yaw_matrix(yaw)[:d, :d]
    center = torch.full((d,), area / 2, dtype=F64)
    if d == 3:
        center[2] = 0.0

    def turn(p):
        return (p - center) @ rot.T + center

    assert torch.allclose(turn(a.positions), b.positions, atol=1e-12, rtol=0)
    assert torch.allclose(turn(a.goals), b.goals, atol=1e-12, rtol=0)
    assert torch.allclose(turn(a.obstacles.centers), b.obstacles.centers, atol=1e-12, rtol=0)
    assert torch.equal(a.obstacles.radii, b.obstacles.radii)
    heading_a, heading_b = a.robot.heading(a.x)[..., :2], b.robot.heading(b.x)[..., :2]
    assert torch.allclose(heading_a @ rot[:2, :2].T, heading_b, atol=1e-12, rtol=0)


def test_rotation_by_quarter_turns_is_exact():
    p = torch.rand(5, 3, dtype=F64) * 4
    for k in range(4):
        q = p
        for _ in range(k):
            q = rotate_about_center(q, 90.0, 4.0)
        assert torch.equal(rotate_about_center(p, 90.0 * k, 4.0), q)
    assert torch.equal(rotate_about_center(p, 360.0, 4.0), p)


# ------------------------------------------------------------------------------------------------ whole episodes
@functools.cache
def _policy(group: str) -> tuple[PolicyNet, object]:
    """The cpu preset's policy over ``group``, moved off its zero-initialized prior (the property holds for any
    weights)."""
    torch.manual_seed(1)
    cfg = dataclasses.replace(TrainConfig.preset("egcbf+", "cpu").model, group=group, hidden=16, head_hidden=16)
    pol = PolicyNet(cfg).double()
    with torch.no_grad():
        for p in pol.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return pol.eval(), cfg


def _episode(group: str, yaw: float, steps: int, seed: int = 3, dtype=F64) -> tuple[list[torch.Tensor], torch.Tensor]:
    pol, cfg = _policy(group)
    ctrl = LearnedController(pol.to(dtype), cfg)
    env = _env("crossing", yaw, n=6, area=1.5, obstacles=2, envs=2, dtype=dtype)
    state = env.reset(seed)
    positions, unsafe = [state.positions], []
    for _ in range(steps):
        u, _ = ctrl(state, env.config)
        state, info = env.step(state, u)
        positions.append(state.positions)
        unsafe.append(info.unsafe)
    pol.double()
    return positions, torch.stack(unsafe)


@pytest.mark.parametrize("yaw", [90.0, 180.0, 37.0])
def test_an_equivariant_policy_drives_the_rotated_episode(yaw):
    """EGCBF+'s policy (SE2xR canonicalization) from the rotated scene: every position of 40 steps is the rotated
    position of the unrotated episode (float64, 1e-8 m), and so are the safety masks. The same world-frame policy
    (GCBF+, trivial group) departs by more than a millimetre: the test can tell the two apart."""
    rot, center = _yaw_matrix(yaw), torch.tensor([0.75, 0.75, 0.0], dtype=F64)
    a, ua = _episode("se2xr", 0.0, 40)
    b, ub = _episode("se2xr", yaw, 40)
    err = max(((pa - center) @ rot.T + center - pb).abs().max().item() for pa, pb in zip(a, b))
    assert err <= 1e-8 and torch.equal(ua, ub)
    a, _ = _episode("trivial", 0.0, 40)
    b, _ = _episode("trivial", yaw, 40)
    err = max(((pa - center) @ rot.T + center - pb).abs().max().item() for pa, pb in zip(a, b))
    assert err > 1e-3


def test_an_equivariant_policy_drives_the_rotated_episode_in_float32():
    """The same in float32 (networks, states and simulation): within 1e-3 m over 20 steps."""
    rot, center = _yaw_matrix(90.0), torch.tensor([0.75, 0.75, 0.0], dtype=F64)
    a, _ = _episode("se2xr", 0.0, 20, dtype=torch.float32)
    b, _ = _episode("se2xr", 90.0, 20, dtype=torch.float32)
    err = max(((pa.double() - center) @ rot.T + center - pb.double()).abs().max().item() for pa, pb in zip(a, b))
    assert err <= 1e-3


# ------------------------------------------------------------------------------------------------------- training
def test_the_training_scene_is_the_runs_own():
    """TrainConfig.scene sets the rollouts' and the validation's layout; it cannot hide in env_overrides, which
    `egcbf eval` inherits from a checkpoint (an evaluation's scene is its own --scene)."""
    cfg = TrainConfig.preset("egcbf+", "tiny", scene="crossing")
    assert cfg.env_config().scene == cfg.eval_env_config().scene == "crossing"
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match=r"env_overrides must be free of \['scene_yaw'\]"):
        TrainConfig.preset("egcbf+", "tiny", env_overrides={"scene_yaw": 90.0})
    with pytest.raises(ValueError, match="scene must be one of"):
        TrainConfig.preset("egcbf+", "tiny", scene="diagonal")


@pytest.mark.parametrize("algo", ["egcbf+", "gcbf+", "egcbf", "gcbf"])
def test_paper_cpu_presets_are_the_papers_training_regime(algo):
    """8 agents, l = 2, 5 obstacles (the paper's Section V-C), validated on that distribution, 30 minutes; the -mlp
    variant has the paper's heads and edge features, the other the cpu recipe's; the group follows the method."""
    for name in ("paper-cpu", "paper-cpu-mlp"):
        cfg = TrainConfig.preset(algo, name)
        assert (cfg.num_agents, cfg.area_size, cfg.area_sizes, cfg.num_obstacles) == (8, 2.0, None, 5)
        ev = cfg.eval_env_config()
        assert (ev.num_agents, ev.area_size, ev.num_obstacles, cfg.max_wall_minutes) == (8, 2.0, 5, 30.0)
        heads = (cfg.model.cbf_head, cfg.model.policy_head, cfg.model.edge_closest_approach)
        assert heads == (("mlp", "mlp", False) if name.endswith("mlp") else ("edge_min", "edge_sum", True))
        assert cfg.model.group == ("se2xr" if algo.startswith("e") else "trivial")
        cpu = TrainConfig.preset(algo, "cpu")
        assert (cfg.lr_cbf, cfg.lr_policy, cfg.eta_c, cfg.model.interface) == (
            cpu.lr_cbf,
            cpu.lr_policy,
            cpu.eta_c,
            cpu.model.interface,
        )
