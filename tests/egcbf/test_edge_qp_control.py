"""The per-edge QPs of robots driven through their raw control (:func:`egcbf.algo.edge_qp.edge_qp_controls`, the
``edges`` target of GCBF+'s double integrator, linear drone and Dubins car): each row is the barrier's time
derivative along the robot's control-affine model, every target keeps its rows (up to slack) and the box that acts
at its state, agents whose reference already keeps its rows keep it, the barriers and targets of the frame-averaged
EGCBF+ commute with the quarter turns at every state (hypothesis, float64 within 1e-9; float32 within 1e-4), and the
single integrator (its velocity is its control) is refused."""

import copy

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.algo.edge_qp import edge_barriers, edge_qp_controls
from egcbf.algo.interface import ControlInterface
from egcbf.env import EnvConfig, SwarmEnv
from egcbf.env.graph import KIND_AGENT, build_graph
from egcbf.nn import CBFNet
from groupcanon import FieldType
from groupcanon.features import Vector

F64 = torch.float64
ROBOTS = ["double_integrator", "linear_drone", "dubins_car"]


def _cbf(algo: str, name: str) -> CBFNet:
    model = TrainConfig.preset(algo, "gcbfplus", robot=name).model
    torch.manual_seed(0)
    cbf = CBFNet(model).double()
    with torch.no_grad():  # move the zero-initialized correction off the prior
        for p in cbf.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return cbf


def _scene(name: str, seed: int, steps: int = 6, dtype=F64, n: int = 8, envs: int = 2, area: float = 1.0):
    env_cfg = EnvConfig.for_robot(name, num_agents=n, num_obstacles=3, num_envs=envs, area_size=area)
    env = SwarmEnv(env_cfg, dtype=dtype)
    state = env.reset(seed)
    robot = env_cfg.make_robot()
    for _ in range(steps):
        state, _ = env.step(state, robot.nominal_control(state.x, state.goals))
    return env, env_cfg, state, robot


def _controls(cbf, env, env_cfg, state, robot, alpha=10.0):
    itf = ControlInterface(robot)
    graph = build_graph(state, env_cfg, lidar=env.lidar(state))
    c_ref = itf.nominal(state.x, state.goals)
    mc = cbf.config
    c, info = edge_qp_controls(graph, state.x, itf, c_ref, alpha=alpha, margin=0.0, cbf=cbf, distance=mc.cbf_distance,
                               horizon=mc.closest_approach_horizon)  # fmt: skip
    return itf, graph, c_ref, c, info


@pytest.mark.parametrize("name", ROBOTS)
def test_the_barrier_gradients_are_finite_differences(name):
    """``grad_p``, ``grad_v`` (which make the rows) are the derivatives of the head's per-edge values in ``dp`` and
    ``dv`` (the receiver's summary ``z`` held, as over a control step): central differences, 1e-6, away from the
    closest approach's kinks (``dv = 0``, and its time reaching 0 or the horizon: a car's LiDAR ray square to its
    heading sees a hit whose closest approach is now)."""
    from egcbf.env.graph import KIND_GOAL
    from egcbf.nn.models import frames_for

    cbf = _cbf("gcbf+", name)
    env, env_cfg, state, robot = _scene(name, 3)
    graph = build_graph(state, env_cfg, lidar=env.lidar(state))
    e = edge_barriers(graph, cbf, cbf.config.cbf_distance, cbf.config.closest_approach_horizon)
    assert e.value.numel() > 0
    sel = graph.edge_kind != KIND_GOAL
    dp0 = graph.edge_attr[sel].to(F64)
    dv0 = graph.relative_velocity(graph.edge_index[:, sel]).to(F64)
    with torch.no_grad():
        z = cbf.encoder(graph)
        frames = frames_for(cbf.encoder.group, graph)

        def b(dp, dv):
            return cbf.head.edge_values(graph, z, frames, dp, dv)[0]

        assert (b(dp0, dv0) - e.value).abs().max() <= 1e-12
        eps = 1e-6
        for k in range(robot.dim):
            step = torch.zeros_like(dp0)
            step[:, k] = eps
            fd_p = (b(dp0 + step, dv0) - b(dp0 - step, dv0)) / (2 * eps)
            fd_v = (b(dp0, dv0 + step) - b(dp0, dv0 - step)) / (2 * eps)
            horizon = cbf.config.closest_approach_horizon
            t_free = -(dp0 * dv0).sum(-1) / dv0.square().sum(-1).clamp_min(1e-12)
            smooth = (dv0.norm(dim=-1) > 1e-2) & (t_free.abs() > 1e-4) & ((t_free - horizon).abs() > 1e-4)
            assert int(smooth.sum()) > 5
            assert (fd_p - e.grad_p[:, k])[smooth].abs().max() <= 1e-6
            assert (fd_v - e.grad_v[:, k])[smooth].abs().max() <= 1e-6


@pytest.mark.parametrize("name", ROBOTS)
def test_targets_keep_their_rows_and_the_acting_box(name):
    cbf = _cbf("gcbf+", name)
    env, env_cfg, state, robot = _scene(name, 5)
    itf, graph, c_ref, c, info = _controls(cbf, env, env_cfg, state, robot)
    x = state.x.reshape(-1, robot.state_dim).to(F64)
    lo, hi = itf.state_bounds(x)
    cf = c.reshape(x.shape[0], -1)
    assert bool((cf >= lo - 1e-9).all() and (cf <= hi + 1e-9).all())
    # the rows: -gv . (A_i + B_i s c_i) >= rhs (halved for agent edges), rebuilt here from the barriers
    from egcbf.robots.point_mass_qp import acceleration_affine

    e = edge_barriers(graph, cbf, cbf.config.cbf_distance, cbf.config.closest_approach_horizon)
    drift, gain = acceleration_affine(robot, x)
    acc = drift + (gain @ itf.apply(x, cf)[..., None])[..., 0]
    rhs = -10.0 * e.value - (e.grad_p * e.dv).sum(-1)
    rhs = torch.where(e.kind == KIND_AGENT, 0.5 * rhs, rhs)
    lhs = -(e.grad_v * acc[e.receiver]).sum(-1)
    short = (rhs - lhs).clamp_min(0)
    norm = (e.grad_v[:, None, :] @ gain[e.receiver])[:, 0].mul(itf.scale(x)).norm(dim=-1)
    per_row = torch.where(norm > 1e-9, short / norm.clamp_min(1e-12), torch.zeros_like(short))
    assert float(per_row.max()) <= info["max_slack"] + 1e-6
    # an agent whose projected reference keeps all its rows keeps it
    ref = torch.maximum(torch.minimum(c_ref.reshape(x.shape[0], -1), hi), lo)
    acc_ref = drift + (gain @ itf.apply(x, ref)[..., None])[..., 0]
    broken = (rhs - -(e.grad_v * acc_ref[e.receiver]).sum(-1)) > 1e-9
    ok = torch.ones(x.shape[0], dtype=torch.bool)
    ok[e.receiver[broken & (norm > 1e-9)]] = False
    assert bool(ok.any()) and (cf[ok] - ref[ok]).abs().max() <= 1e-6
    assert bool((~ok).any()) and info["num_slack"] <= int((~ok).sum())


@pytest.mark.parametrize("name", ["double_integrator", "linear_drone"])
@given(seed=st.integers(0, 2**16), k=st.integers(1, 3), t=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
       moving=st.booleans())  # fmt: skip
@settings(max_examples=8, deadline=None)
def test_egcbf_plus_barriers_and_targets_commute_with_quarter_turns(name, seed, k, t, moving):
    """Frame-averaged per-edge barriers are invariant and the targets (invariant per-axis boxes, world-frame
    controls) rotate with the scene, at rest (no vector to build a frame from) and moving; float64 within 1e-9."""
    cbf = _cbf("egcbf+", name)
    env, env_cfg, state, robot = _scene(name, seed, steps=5 if moving else 0, n=6, envs=1, area=1.5)
    group, d = robot.group, robot.dim
    g = torch.cat((group.rotation_element(torch.tensor([k]), dtype=F64)[:, :2], torch.tensor([t[:d]], dtype=F64)), -1)
    moved = state.transform(g)
    _, ga, _, ca, _ = _controls(cbf, env, env_cfg, state, robot)
    _, gb, _, cb, _ = _controls(cbf, env, env_cfg, moved, robot)
    assert ga.frames_per_agent == 4
    horizon = cbf.config.closest_approach_horizon
    ba = edge_barriers(ga, cbf, cbf.config.cbf_distance, horizon)
    bb = edge_barriers(gb, cbf, cbf.config.cbf_distance, horizon)
    assert (ba.value - bb.value).abs().max() <= 1e-9
    rotate = FieldType(group, [Vector(d)])
    m = ca.shape[0] * ca.shape[1]
    assert (rotate.act(g.expand(m, g.shape[-1]), ca.reshape(m, d)) - cb.reshape(m, d)).abs().max() <= 1e-9


def test_float32_targets_match_float64():
    """The same scene through float32 networks: the targets agree within 1e-3 (the QP itself is float64)."""
    cbf64 = _cbf("egcbf+", "double_integrator")
    cbf32 = copy.deepcopy(cbf64).float()
    env, env_cfg, state, robot = _scene("double_integrator", 11)
    itf, graph, c_ref, c64, _ = _controls(cbf64, env, env_cfg, state, robot)
    mc = cbf32.config
    c32, _ = edge_qp_controls(graph.to(torch.float32), state.x.float(), itf, c_ref.float(), alpha=10.0, margin=0.0,
                              cbf=cbf32, distance=mc.cbf_distance, horizon=mc.closest_approach_horizon)  # fmt: skip
    assert (c64 - c32).abs().max() <= 1e-3


def test_the_single_integrator_is_refused():
    with pytest.raises(ValueError, match="whose state holds its velocity"):
        TrainConfig.preset("gcbf+", "gcbfplus", robot="single_integrator", qp_constraints="edges")
    cfg = TrainConfig.preset("gcbf+", "gcbfplus", robot="double_integrator", qp_constraints="edges")
    assert cfg.qp_constraints == "edges"


def test_a_double_integrator_run_with_the_per_edge_target_trains(tmp_path):
    from egcbf.train.loop import train

    cfg = TrainConfig.preset(
        "egcbf+", "tiny", robot="double_integrator", steps=2, qp_constraints="edges", area_size=1.5, area_sizes=None
    )
    learner = train(cfg, tmp_path, progress=False, log=lambda s: None)
    assert learner.step == 2
    assert "qp/num_slack" in (tmp_path / "scalars.csv").read_text()
