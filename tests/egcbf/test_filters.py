"""Run-time safety filters of a learned policy (egcbf.control.filters): SE2xR equivariance of the filtered controller
(hypothesis, float64 within 1e-7 m/s^2: the per-agent QPs are solved by an interior-point method to 1e-12, and the
solution moves continuously with its data; float32 within 1e-3), decentralization (an agent's filtered command does
not depend on agents outside its sensing radius), the rows against finite differences, and that the filter keeps
its rows."""

import dataclasses
import functools

import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.config import TrainConfig
from egcbf.control.filters import FILTERS, FilterConfig, FilteredController, edge_rows
from egcbf.env import EnvConfig, SwarmState
from egcbf.env.graph import GROUP, KIND_AGENT, KIND_GOAL, KIND_HIT, build_graph
from egcbf.nn import CBFNet, PolicyNet
from egcbf.nn.edge_min import closest_approach
from egcbf.nn.models import frames_for
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

F64 = torch.float64
KINDS = [k for k in FILTERS if k != "none"]


@functools.cache
def _nets(group: str = "se2xr"):
    """The cpu preset's networks over ``group``, moved off their zero-initialized priors (equivariance and
    decentralization hold for any weights)."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(TrainConfig.preset("egcbf+", "cpu").model, group=group, hidden=16, head_hidden=16)
    cbf, pol = CBFNet(cfg).double(), PolicyNet(cfg).double()
    with torch.no_grad():
        for p in (*cbf.parameters(), *pol.parameters()):
            p.add_(0.05 * torch.randn_like(p))
    return cbf.eval(), pol.eval(), cfg


def _controller(kind: str, group: str = "se2xr", **kw) -> FilteredController:
    cbf, pol, cfg = _nets(group)
    return FilteredController(pol, cfg, FilterConfig(kind=kind, **kw), cbf if kind == "cbf" else None)


def _scene(num_agents: int, area: float, seed: int, envs: int = 2, obstacles: int = 2) -> tuple[SwarmState, EnvConfig]:
    cfg = EnvConfig(
        num_agents=num_agents, num_envs=envs, area_size=area, num_obstacles=obstacles, n_rays=8, lidar_max_hits=4
    )
    state = moving_scene(cfg, seed)
    # slow the random velocities down so that the scenes hold both active and inactive rows
    x = state.x.clone()
    x[..., 12:15] *= 0.5
    return SwarmState(x, state.goals, state.obstacles), cfg


@pytest.mark.parametrize("kind", KINDS)
@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20))
@settings(max_examples=8, deadline=None)
def test_filtered_controller_is_equivariant(kind, g, seed):
    """Transforming the whole scene by SE2xR leaves the body controls unchanged and rotates the filtered
    acceleration (float64, 1e-7)."""
    state, cfg = _scene(6, 1.2, seed)
    ctrl = _controller(kind)
    u_a, info_a = ctrl(state, cfg)
    u_b, info_b = ctrl(state.transform(g), cfg)
    rotate = FieldType(GROUP, [Vector(3)])
    g_agents = g[:, None].expand(2, 6, 5)
    assert (u_a - u_b).abs().max() <= 1e-7 * (1 + u_a.abs().max())
    assert (rotate.act(g_agents, info_a["a_safe"]) - info_b["a_safe"]).abs().max() <= 1e-7
    assert info_a["num_active"] == info_b["num_active"]


@pytest.mark.parametrize("kind", ["cbf", "dcbf"])
def test_filtered_controller_is_equivariant_in_float32(kind):
    """The same in float32 networks and states: within 1e-3 m/s^2 (the QPs are solved in float64 either way)."""
    cbf, pol, cfg = _nets()
    ctrl = FilteredController(pol.float(), cfg, FilterConfig(kind=kind), cbf.float() if kind == "cbf" else None)
    try:
        state, ecfg = _scene(6, 1.2, 5)
        g = torch.tensor([[0.6, 0.8, 0.3, -0.2, 0.1], [0.0, -1.0, 1.0, 0.5, -0.3]], dtype=F64)
        _, a = ctrl(state.to("cpu", dtype=torch.float32), ecfg)
        _, b = ctrl(state.transform(g).to("cpu", dtype=torch.float32), ecfg)
        rotate = FieldType(GROUP, [Vector(3)])
        ga = g[:, None].expand(2, 6, 5)
        assert (rotate.act(ga, a["a_safe"]) - b["a_safe"]).abs().max() <= 1e-3
    finally:
        pol.double(), cbf.double()


@pytest.mark.parametrize("kind", KINDS)
def test_an_agent_outside_the_sensing_radius_changes_nothing(kind):
    """Decentralization: moving one agent (within the region where it stays out of the others' range) leaves the
    filtered command of every agent that does not sense it, before or after, unchanged."""
    state, cfg = _scene(12, 3.0, 11, envs=1, obstacles=1)
    ctrl = _controller(kind)
    _, base = ctrl(state, cfg)
    pos = state.positions[0]
    radius = cfg.comm_radius
    checked = 0
    for k in range(12):
        x = state.x.clone()
        x[0, k, 12:15] += torch.tensor([0.3, -0.2, 0.1], dtype=F64)  # a new velocity
        x[0, k, 0:3] += torch.tensor([0.02, 0.01, -0.01], dtype=F64)  # and a small move
        moved = SwarmState(x, state.goals, state.obstacles)
        _, out = ctrl(moved, cfg)
        far = ((pos - pos[k]).norm(dim=-1) > radius + 0.05) & ((pos - x[0, k, 0:3]).norm(dim=-1) > radius + 0.05)
        far[k] = False
        checked += int(far.sum())
        diff = float((out["a_safe"][0, far] - base["a_safe"][0, far]).abs().amax()) if far.any() else 0.0
        # not bit-exact: the batched solver pads every agent's QP to the batch's largest row count, and the
        # padding moves an agent's iterates at the solver's tolerance (measured up to ~1e-8 m/s^2)
        assert diff <= 1e-7, (kind, k)
    assert checked > 50  # the scene is sparse enough to test something


@pytest.mark.parametrize("learned", [True, False])
def test_edge_rows_are_the_barrier_condition(learned):
    """Each row ``n . a_i >= rhs`` is agent ``i``'s share of the edge's condition ``db/dt + alpha (b - margin) >= 0``
    under the ideal model (``dp' = dv``, ``dv' = a_j - a_i``): its own acceleration's term and half of the rest
    (all of it for a LiDAR hit), divided by ``|g_v|``; checked against central finite differences of ``b`` along
    that motion with the sender holding its velocity (float64, 1e-6)."""
    cbf, _, _ = _nets()
    state, cfg = _scene(6, 1.0, 3, envs=1, obstacles=2)
    graph = build_graph(state, cfg)
    alpha, margin = 2.0, 0.05
    rows = edge_rows(graph, alpha, margin, cbf if learned else None, distance=0.25, horizon=1.0)
    assert len(rows.rhs) > 5 and (graph.edge_kind[graph.edge_kind != KIND_GOAL] == KIND_HIT).any()
    sel = graph.edge_kind != KIND_GOAL
    kind = graph.edge_kind[sel][rows.edge]
    dp0 = graph.edge_attr[sel].detach()[rows.edge]
    dv0 = graph.relative_velocity(graph.edge_index[:, sel])[rows.edge]
    a = torch.randn(len(rows.rhs), 3, generator=torch.Generator().manual_seed(0), dtype=F64)

    def barrier(dp, dv):
        if not learned:
            return closest_approach(dp, dv, 1.0)[:, 0] - 0.25
        with torch.no_grad():
            z = cbf.encoder(graph)
            # all edges, with this row's values in place (the head reads its own edge only)
            full_dp = graph.edge_attr[sel].clone()
            full_dv = graph.relative_velocity(graph.edge_index[:, sel]).clone()
            full_dp[rows.edge], full_dv[rows.edge] = dp, dv
            b, _ = cbf.head.edge_values(graph, z, frames_for(cbf.encoder.group, graph), full_dp, full_dv)
        return b[rows.edge]

    h = 1e-5

    def bdot(acc):  # central difference of b along dp' = dv, dv' = -acc
        plus = barrier(dp0 + h * dv0 - 0.5 * h * h * acc, dv0 - h * acc)
        minus = barrier(dp0 - h * dv0 - 0.5 * h * h * acc, dv0 + h * acc)
        return (plus - minus) / (2 * h)

    b0 = barrier(dp0, dv0)
    assert (b0 - rows.value).abs().max() <= 1e-12
    # the agent's share: half of the drift and class-K terms (all of them for a hit), all of its own acceleration
    share = torch.where(kind == KIND_AGENT, 0.5, 1.0).to(F64)
    drift = bdot(torch.zeros_like(a))
    lhs = (share * (drift + alpha * (b0 - margin)) + (bdot(a) - drift)) / rows.gain
    rhs = (rows.normal * a).sum(-1) - rows.rhs
    # rows whose closest approach is at a kink (t_min clipped at 0 or at the horizon) are skipped
    t = closest_approach(dp0, dv0, 1.0)[:, 1]
    smooth = (t > 1e-3) & (t < 1.0 - 1e-3)
    assert smooth.sum() >= 3
    assert (lhs - rhs)[smooth].abs().max() <= 1e-6


def test_filter_config_rejects_bad_values():
    for kw in ({"kind": "none"}, {"kind": "bogus"}, {"alpha": 0.0}, {"alpha": float("inf")}, {"margin": float("nan")}):
        with pytest.raises(ValueError):
            FilterConfig(**kw)


def test_the_cbf_filter_needs_its_network_and_the_acceleration_interface():
    _, pol, cfg = _nets()
    with pytest.raises(ValueError, match="CBF network"):
        FilteredController(pol, cfg, FilterConfig(kind="cbf"))
    with pytest.raises(ValueError, match="acceleration"):
        FilteredController(
            pol, dataclasses.replace(cfg, interface="torque", policy_head="mlp"), FilterConfig(kind="dcbf")
        )


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    from egcbf.train.loop import train

    root = tmp_path_factory.mktemp("ckpt") / "egcbf+"
    train(TrainConfig.preset("egcbf+", "tiny", steps=1), root, progress=False, log=lambda s: None)
    return root


@pytest.mark.parametrize("kind", KINDS)
def test_eval_filter_writes_its_results_and_says_which_filter(tiny_checkpoint, tmp_path, kind):
    import json

    from typer.testing import CliRunner

    from egcbf.cli import app

    out = tmp_path / kind
    args = ["eval", "--checkpoint", str(tiny_checkpoint), "--filter", kind, "--num-agents", "3", "--area", "1.5",
            "--obstacles", "1", "--episodes", "1", "--max-steps", "6", "--no-progress", "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    run = json.loads((out / "run.json").read_text())
    assert run["filter"] == kind and run["controller"] == f"egcbf+:{kind}" and run["complete"]
    row = json.loads((out / "metrics.json").read_text())[0]
    assert row["num_agents"] == 3 and 0 <= row["safe_rate"] <= 1 and "filter_active" in row


def test_eval_filter_refuses_what_it_cannot_do(tiny_checkpoint, tmp_path):
    from typer.testing import CliRunner

    from egcbf.cli import app

    base = ["eval", "--num-agents", "3", "--episodes", "1", "--no-progress", "--out", str(tmp_path / "o")]
    res = CliRunner().invoke(app, [*base, "--filter", "dcbf"], env={"COLUMNS": "200"})
    assert res.exit_code == 2 and "--checkpoint" in res.output
    res = CliRunner().invoke(
        app, [*base, "--checkpoint", str(tiny_checkpoint), "--filter", "cbf", "--filter-alpha", "0"],
        env={"COLUMNS": "200"},
    )  # fmt: skip
    assert res.exit_code == 2 and "--filter-alpha" in res.output
    res = CliRunner().invoke(app, [*base, "--checkpoint", str(tiny_checkpoint), "--filter-alpha", "2"],
                             env={"COLUMNS": "200"})  # fmt: skip
    assert res.exit_code == 2 and "pass --filter KIND too" in res.output
    for kind, solver in (("none", "ipm"), ("dcbf", "ipm"), ("cbf", "simplex")):  # no choice, or not one offered
        res = CliRunner().invoke(app, [*base, "--checkpoint", str(tiny_checkpoint), "--filter", kind,
                                       "--filter-qp-solver", solver], env={"COLUMNS": "200"})  # fmt: skip
        assert res.exit_code == 2 and "--filter-qp-solver" in res.output, (kind, res.output)
    assert not (tmp_path / "o").exists()


def test_eval_filter_qp_solver_is_used_and_recorded(tiny_checkpoint, tmp_path):
    """``--filter-qp-solver ipm`` runs the prior filter on the interior-point method and run.json says so; without
    it, the filter's default (the active set) is recorded."""
    import json

    from typer.testing import CliRunner

    from egcbf.cli import app
    from egcbf.control.filters import QP_SOLVERS

    for solver in (None, "ipm"):
        out = tmp_path / str(solver)
        args = ["eval", "--checkpoint", str(tiny_checkpoint), "--filter", "prior", "--num-agents", "3", "--area",
                "1.5", "--episodes", "1", "--max-steps", "4", "--no-progress", "--out", str(out)]  # fmt: skip
        if solver is not None:
            args += ["--filter-qp-solver", solver]
        res = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
        assert res.exit_code == 0, res.output
        run = json.loads((out / "run.json").read_text())
        assert run["filter_config"]["qp_solver"] == (solver or QP_SOLVERS[0])


def test_lookahead_reads_the_predicted_state():
    """The dcbf filter with ``lookahead T`` and accelerations ``a`` solves the QPs of the state moved to
    ``p + T v + T^2 a / 2``, ``v + T a`` (same reference), exactly."""
    from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP

    state, cfg = _scene(8, 1.0, 4, envs=2, obstacles=2)
    qp = DecentralizedCBFQP()
    gen = torch.Generator().manual_seed(1)
    a_ref = torch.randn(2, 8, 3, generator=gen, dtype=F64).numpy()
    acc = torch.randn(2, 8, 3, generator=gen, dtype=F64)
    T = 0.05
    x = state.x.clone()
    x[..., 0:3] += T * x[..., 12:15] + 0.5 * T * T * acc
    x[..., 12:15] += T * acc
    moved = SwarmState(x, state.goals, state.obstacles)
    _, a = qp.filter(state, cfg, a_ref, lookahead=T, accel=acc.numpy())
    _, b = qp.filter(moved, cfg, a_ref)
    assert abs(a["a_safe"] - b["a_safe"]).max() <= 1e-12


def test_the_realized_acceleration_is_remembered_within_an_episode_only():
    ctrl = _controller("dcbf", lookahead=0.05)
    state, cfg = _scene(4, 1.0, 2, envs=1, obstacles=0)
    assert ctrl._realized_acceleration(state, cfg) is None  # first step: nothing seen before
    x = state.x.clone()
    x[..., 12:15] += 0.1
    later = SwarmState(x, state.goals, state.obstacles, t=1)
    acc = ctrl._realized_acceleration(later, cfg)
    assert acc is not None and abs(acc - 0.1 / cfg.dt).max() <= 1e-9
    assert ctrl._realized_acceleration(SwarmState(x, state.goals, state.obstacles, t=0), cfg) is None  # new episode
    assert _controller("dcbf", lookahead=0.0)._realized_acceleration(later, cfg) is None  # without lookahead: never
    with pytest.raises(ValueError, match="lookahead"):
        FilterConfig(kind="dcbf", lookahead=-0.1)


def test_the_nominal_controller_behind_the_dcbf_filter_is_the_dcbf_qp_with_the_filters_barrier(tmp_path):
    """``--controller nominal --filter dcbf`` (the ablation without a policy) runs the dCBF-QP's QPs around the
    nominal command, with the filter's barrier: the same accelerations as ``DecentralizedCBFQP.filter``."""
    import json

    from typer.testing import CliRunner

    from egcbf.cli import app
    from egcbf.control.filters import DCBF_FILTER_BARRIER
    from egcbf.robots.quadrotor.dcbf_qp import DecentralizedCBFQP

    state, cfg = _scene(6, 1.0, 9, envs=1, obstacles=1)
    ctrl = FilteredController(None, None, FilterConfig(kind="dcbf", lookahead=0.0))
    _, a = ctrl(state, cfg)
    from egcbf.algo.interface import make_interface

    itf = make_interface("accel")
    a_ref = (itf.accel_unit * itf.nominal(state.x, state.goals)).numpy()
    _, b = DecentralizedCBFQP(barrier=DCBF_FILTER_BARRIER).filter(state, cfg, a_ref)
    assert abs(a["a_safe"].numpy() - b["a_safe"]).max() <= 1e-12
    with pytest.raises(ValueError, match="checkpoint"):
        FilteredController(None, None, FilterConfig(kind="cbf"))
    out = tmp_path / "n"
    args = ["eval", "--controller", "nominal", "--filter", "dcbf", "--num-agents", "3", "--area", "1.5",
            "--episodes", "1", "--max-steps", "4", "--no-progress", "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert json.loads((out / "run.json").read_text())["controller"] == "nominal:dcbf"
    res = CliRunner().invoke(app, [*args[:-1], str(tmp_path / "m"), "--filter", "cbf"], env={"COLUMNS": "200"})
    assert res.exit_code == 2 and "checkpoint" in res.output
