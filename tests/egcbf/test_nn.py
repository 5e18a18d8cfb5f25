"""The CBF and policy networks: EGCBF is invariant under a global SE2xR transform of the scene, GCBF is not."""

import dataclasses
import functools
import math

import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.algo.actions import control_bounds, control_scale
from egcbf.algo.config import TrainConfig
from egcbf.algo.interface import make_interface
from egcbf.algo.learner import LearnedController, policy_command
from egcbf.env import EnvConfig, SwarmState
from egcbf.env.graph import GROUP, KIND_GOAL, build_graph
from egcbf.nn import CBFNet, GraphTransformerLayer, ModelConfig, PolicyNet, frames_for
from egcbf.robots.quadrotor import dynamics as dyn
from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.testing import strategies as gst

F64 = torch.float64


@functools.cache
def _nets(group: str, preset: str | None = None):
    """Networks of the default ModelConfig (``preset=None``) or of a TrainConfig preset's model, over ``group``."""
    torch.manual_seed(0)
    if preset is None:
        cfg = ModelConfig(group=group, hidden=32, heads=4, head_hidden=32)
    else:
        cfg = dataclasses.replace(TrainConfig.preset("egcbf+", preset).model, group=group)
    cbf, pol = CBFNet(cfg).double(), PolicyNet(cfg).double()
    if preset is not None:  # equivariance holds for any weights: move zero-initialized last layers off their priors
        with torch.no_grad():
            for p in (*cbf.parameters(), *pol.parameters()):
                p.add_(0.05 * torch.randn_like(p))
    return cbf, pol, cfg


def _outputs(group: str, state: SwarmState, cfg: EnvConfig, preset: str | None = None):
    """CBF values, the policy's raw output (own frame) and features, the applied body control and the command."""
    cbf, pol, mcfg = _nets(group, preset)
    graph = build_graph(state, cfg)
    with torch.no_grad():
        u, _ = LearnedController(pol, mcfg)(state, cfg)
        itf = make_interface(mcfg.interface)
        c, _ = policy_command(pol, mcfg, itf, graph, state.x, state.goals)
        return cbf(graph), pol.raw(graph), pol.encoder(graph), u, c


@st.composite
def scenes(draw):
    cfg = EnvConfig(
        num_agents=draw(st.integers(1, 6)),
        num_envs=draw(st.integers(1, 2)),
        area_size=draw(st.floats(1.0, 2.0)),
        num_obstacles=draw(st.integers(0, 3)),
        n_rays=8,
        lidar_max_hits=4,
    )
    return cfg, draw(st.integers(0, 2**20))


@given(scene=scenes(), g=gst.elements(GROUP, batch=(2,)))
@settings(max_examples=25)
def test_egcbf_is_invariant_and_gcbf_is_not(scene, g):
    cfg, seed = scene
    state = moving_scene(cfg, seed)
    g = g[: cfg.num_envs]
    g_agents = g[:, None].expand(cfg.num_envs, cfg.num_agents, 5)
    # the default networks (torque interface), the cpu preset's (acceleration command; CBF on positions and
    # velocities only) and the cpu-torque preset's (no body rates, no goal edges, mirror-symmetric CBF)
    for preset in (None, "cpu", "cpu-torque"):
        a = _outputs("se2xr", state, cfg, preset)
        b = _outputs("se2xr", state.transform(g), cfg, preset)
        # invariant: h, the raw output and features (own frame), the body torque and thrust
        for name, x, y in zip(("h", "policy raw", "policy features", "control"), a, b):
            assert (x - y).abs().max() <= 1e-9, (preset, name)
        # the command transforms with the scene: an acceleration as a world-frame vector, a torque not at all
        out_type = _nets("se2xr", preset)[1].out_type
        assert (out_type.act(g_agents, a[4]) - b[4]).abs().max() <= 1e-9, preset
    assert isinstance(_nets("se2xr", "cpu")[1].out_type.features[0], Vector)
    # the same test fails for GCBF (the same layers over the trivial group) under a quarter turn
    quarter = torch.tensor([[0.0, 1.0, 0.5, -0.5, 0.2]], dtype=F64).expand(cfg.num_envs, 5)
    a = _outputs("trivial", state, cfg)
    b = _outputs("trivial", state.transform(quarter), cfg)
    assert (a[0] - b[0]).abs().max() > 1e-6 and (a[2] - b[2]).abs().max() > 1e-4
    # the cpu preset's untrained heads start at invariant priors (closest approach; zero residual), its features not
    a = _outputs("trivial", state, cfg, "cpu")
    b = _outputs("trivial", state.transform(quarter), cfg, "cpu")
    assert (a[2] - b[2]).abs().max() > 1e-4


def test_gcbf_is_not_rotation_invariant_but_translation_invariant():
    cfg = EnvConfig(num_agents=5, num_envs=1, area_size=1.5, num_obstacles=2, n_rays=8, lidar_max_hits=4)
    state = moving_scene(cfg, 3)
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    rot = torch.tensor([[c, s, 0.3, -0.2, 0.1]], dtype=F64)
    shift = torch.tensor([[1.0, 0.0, 0.3, -0.2, 0.1]], dtype=F64)
    a = _outputs("trivial", state, cfg)
    b = _outputs("trivial", state.transform(rot), cfg)
    errors = {name: float((x - y).abs().max()) for name, x, y in zip(("h", "raw", "features", "u"), a, b)}
    assert errors["h"] > 1e-3 and errors["features"] > 1e-2 and errors["raw"] > 1e-5, errors
    # its features carry no absolute position: translations alone leave it unchanged
    t = _outputs("trivial", state.transform(shift), cfg)
    for x, y in zip(a, t):
        assert (x - y).abs().max() <= 1e-9
    # and the equivariant network is invariant under the same rotation
    for x, y in zip(_outputs("se2xr", state, cfg), _outputs("se2xr", state.transform(rot), cfg)):
        assert (x - y).abs().max() <= 1e-9
    # with the acceleration command (cpu preset) GCBF's command does not rotate with the scene, EGCBF's does
    rotate = FieldType(GROUP, [Vector(3)])
    rot_agents = rot[:, None].expand(1, cfg.num_agents, 5)
    for group, equivariant in (("trivial", False), ("se2xr", True)):
        c0 = _outputs(group, state, cfg, "cpu")[4]
        c1 = _outputs(group, state.transform(rot), cfg, "cpu")[4]
        err = float((rotate.act(rot_agents, c0) - c1).abs().max())
        assert (err <= 1e-9) if equivariant else (err > 1e-5), (group, err)


def test_outputs_are_bounded_and_shaped():
    cfg = EnvConfig(num_agents=4, num_envs=3, n_rays=8, lidar_max_hits=4)
    state = moving_scene(cfg, 1)
    for group in ("se2xr", "trivial"):
        cbf, pol, mcfg = _nets(group)
        graph = build_graph(state, cfg)
        h, pi = cbf(graph), pol(graph)
        assert h.shape == (12,) and pi.shape == (12, 4)
        assert (h.abs() < 1).all() and (pi.abs() <= 1).all()
        # the same parameter count for both groups: canonicalization adds none
        assert sum(p.numel() for p in cbf.parameters()) == sum(p.numel() for p in _nets("se2xr")[0].parameters())
        u, info = LearnedController(pol, mcfg)(state, cfg)
        lo, hi = control_bounds(u)
        un = u / control_scale(cfg.params, u)
        assert u.shape == (3, 4, 4) and (un >= lo - 1e-12).all() and (un <= hi + 1e-12).all()
        assert info["u_ref"].shape == u.shape


class _FixedPolicy(torch.nn.Module):
    """A stand-in policy that outputs the same residual for every agent."""

    def __init__(self, residual):
        super().__init__()
        self.residual = residual

    def forward(self, graph):
        return self.residual.expand(graph.num_dst, -1)


def _command(mcfg: ModelConfig, residual):
    cfg = EnvConfig(num_agents=5, num_envs=1, n_rays=8, lidar_max_hits=4, num_obstacles=0)
    state = moving_scene(cfg, 0)
    itf = make_interface(mcfg.interface)
    c, c_nom = policy_command(_FixedPolicy(residual), mcfg, itf, build_graph(state, cfg), state.x, state.goals)
    return c, c_nom, itf, state


def test_untrained_policy_stays_near_nominal():
    _, pol, mcfg = _nets("se2xr")
    assert mcfg.policy_init_scale < 1
    assert torch.equal(pol.head[-1].bias, torch.zeros_like(pol.head[-1].bias))
    for interface in ("torque", "accel"):
        mcfg = ModelConfig(interface=interface)
        c, c_nom, itf, state = _command(mcfg, torch.zeros(mcfg.action_dim, dtype=F64))
        assert torch.allclose(c, c_nom, atol=1e-12, rtol=0)
        big, _, _, _ = _command(mcfg, torch.ones(mcfg.action_dim, dtype=F64))
        lo, hi = itf.bounds(big)
        local = itf.to_local(state.x, big)
        assert (local <= hi + 1e-12).all() and (local >= lo - 1e-12).all()  # clipped to the box
        assert torch.isclose(local, hi).any()


def test_layer_is_an_ordinary_pair_layer():
    layer = GraphTransformerLayer(18, 3, hidden=16, heads=2)
    x_src, x_dst = torch.randn(7, 18), torch.randn(3, 18)
    edge_index = torch.tensor([[0, 1, 2, 3, 4, 5, 6], [0, 0, 1, 1, 2, 2, 2]])
    out = layer((x_src, x_dst), edge_index, torch.randn(7, 3))
    assert out.shape == (3, 16) and torch.isfinite(out).all()


def test_per_channel_action_scale():
    assert ModelConfig().action_scales == (2.0, 2.0, 2.0, 2.0)  # GCBF+: one scale
    mcfg = ModelConfig(torque_action_scale=0.25)
    assert mcfg.action_scales == (0.25, 0.25, 0.25, 2.0)
    c, c_nom, _, _ = _command(mcfg, torch.full((4,), 0.1, dtype=F64))
    expected = c_nom + torch.tensor([0.025, 0.025, 0.025, 0.2], dtype=F64)
    assert torch.allclose(c, expected.clamp(max=1.0))
    accel = ModelConfig(interface="accel", accel_action_scale=0.5)
    assert accel.action_scales == (0.5, 0.5, 0.5) and accel.action_dim == 3


@pytest.mark.parametrize("group", ["se2xr", "trivial"])
def test_cbf_without_body_rates_ignores_them(group):
    cfg = EnvConfig(num_agents=4, num_envs=2, n_rays=8, lidar_max_hits=4)
    state = moving_scene(cfg, 2)
    p, rot, v, w = dyn.unpack(state.x)
    spun = SwarmState(dyn.state_from_parts(p, rot, v, torch.randn_like(w)), state.goals, state.obstacles)
    torch.manual_seed(0)
    mcfg = ModelConfig(group=group, hidden=16, heads=2, head_hidden=16, cbf_body_rates=False)
    cbf, pol = CBFNet(mcfg).double(), PolicyNet(mcfg).double()
    g0, g1 = build_graph(state, cfg), build_graph(spun, cfg)
    assert torch.equal(cbf(g0), cbf(g1))
    assert not torch.allclose(pol(g0), pol(g1))  # the policy still reads w


@pytest.mark.parametrize("group", ["se2xr", "trivial"])
def test_cbf_without_goal_edges_ignores_goals(group):
    cfg = EnvConfig(num_agents=4, num_envs=2, n_rays=8, lidar_max_hits=4)
    state = moving_scene(cfg, 3)
    moved = SwarmState(state.x, state.goals + torch.randn_like(state.goals), state.obstacles)
    torch.manual_seed(0)
    mcfg = ModelConfig(group=group, hidden=16, heads=2, head_hidden=16, cbf_goal_edges=False)
    cbf, pol = CBFNet(mcfg).double(), PolicyNet(mcfg).double()
    g0, g1 = build_graph(state, cfg), build_graph(moved, cfg)
    assert torch.equal(cbf(g0), cbf(g1))
    assert not torch.allclose(pol(g0), pol(g1))  # the policy still reads its goal


def _mirror(state: SwarmState, height: float) -> SwarmState:
    """The scene mirrored in the plane z = height / 2: p_z -> height - p_z, R -> S R S, v_z -> -v_z,
    w -> (-wx, -wy, wz)."""
    sig = torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    shift = torch.tensor([0.0, 0.0, height], dtype=F64)
    p, rot, v, w = dyn.unpack(state.x)
    rot = sig[:, None] * rot * sig[None, :]
    x = dyn.state_from_parts(p * sig + shift, rot, v * sig, w * -sig)
    obs = type(state.obstacles)(state.obstacles.centers * sig + shift, state.obstacles.radii)
    return SwarmState(x, state.goals * sig + shift, obs)


@given(seed=st.integers(0, 2**16), n=st.integers(2, 6))
@settings(max_examples=10)
def test_reflect_z_is_the_mirrored_scene_and_the_symmetric_cbf_ignores_it(seed, n):
    cfg = EnvConfig(num_agents=n, num_envs=2, area_size=2.0, num_obstacles=0)
    state = moving_scene(cfg, seed)
    g0, g1 = build_graph(state, cfg), build_graph(_mirror(state, 2.0), cfg)
    assert torch.equal(g0.edge_index, g1.edge_index)
    r = g0.reflect_z()
    assert torch.allclose(r.x_src, g1.x_src, atol=1e-12) and torch.allclose(r.edge_attr, g1.edge_attr, atol=1e-12)
    assert torch.allclose(r.frames[:, :2], g1.frames[:, :2], atol=1e-12)  # same yaw (tz differs by the shift)
    torch.manual_seed(seed)
    for group in ("se2xr", "trivial"):
        sym = CBFNet(ModelConfig(group=group, hidden=16, heads=2, head_hidden=16, cbf_z_symmetric=True)).double()
        assert (sym(g0) - sym(g1)).abs().max() <= 1e-9
    plain = CBFNet(ModelConfig(hidden=16, heads=2, head_hidden=16)).double()
    assert (plain(g0) - plain(g1)).abs().max() > 1e-6


@pytest.mark.parametrize(
    "kwargs", [{"group": "so3"}, {"hidden": 30, "heads": 4}, {"action_scale": 0.0}, {"torque_action_scale": 0.0}]
)
def test_model_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        ModelConfig(**kwargs)


@pytest.mark.parametrize("preset", [None, "cpu", "cpu-torque"])
def test_networks_on_a_receiver_subset_are_exact(preset):
    """``SwarmGraph.with_receivers`` (the loss's split of h(x') into labelled and unlabelled agents): the kept
    receivers' outputs are the full graph's, bit for bit up to reduction order."""
    cfg = EnvConfig(num_agents=6, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.2, num_obstacles=2)
    state = moving_scene(cfg, 5)
    cbf, pol, _ = _nets("se2xr", preset)
    graph = build_graph(state, cfg)
    keep = torch.arange(graph.num_dst) % 3 != 0
    with torch.no_grad():
        for net in (cbf, pol):
            full, part = net(graph), net(graph.with_receivers(keep))
            assert (full[keep] - part[keep]).abs().max() <= 1e-12


def test_edge_velocity_reads_closing_speed():
    """With ``edge_velocity`` the CBF changes when a neighbour's velocity changes relative to the agent's own (and
    its encoder's edge type carries the relative velocity as a vector)."""
    cfg = EnvConfig(num_agents=4, num_envs=1, n_rays=8, lidar_max_hits=4, area_size=1.0, num_obstacles=0)
    state = moving_scene(cfg, 6)
    torch.manual_seed(0)
    mcfg = ModelConfig(hidden=16, heads=2, head_hidden=16, edge_velocity=True, cbf_attitude=False)
    cbf = CBFNet(mcfg).double()
    assert cbf.encoder.layer.spec.edge_type.names == ("dp", "dv")
    p, rot, v, w = dyn.unpack(state.x)
    v2 = v.clone()
    v2[:, 1] += 0.5
    moved = SwarmState(dyn.state_from_parts(p, rot, v2, w), state.goals, state.obstacles)
    with torch.no_grad():
        assert not torch.allclose(cbf(build_graph(state, cfg)), cbf(build_graph(moved, cfg)))


def test_edge_min_head_starts_at_the_closest_approach_barrier():
    """Untrained, the soft-min head is ``tanh(-tau log(sum_j exp(-(d_min,j - D) / tau) + exp(-(1 - D) / tau)))``
    over the agent's neighbours and LiDAR hits, computed here independently, agent by agent."""
    cfg = EnvConfig(num_agents=5, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.0, num_obstacles=2)
    state = moving_scene(cfg, 11)
    torch.manual_seed(0)
    mcfg = ModelConfig(hidden=16, heads=2, head_hidden=16, cbf_head="edge_min", cbf_attitude=False)
    cbf = CBFNet(mcfg).double()
    graph = build_graph(state, cfg)
    with torch.no_grad():
        h = cbf(graph)
    d, tau = mcfg.cbf_distance, mcfg.cbf_temperature
    for i in range(graph.num_dst):
        sel = (graph.edge_index[1] == i) & (graph.edge_kind != KIND_GOAL)
        src = graph.edge_index[0, sel]
        dp = graph.pos_src[src] - graph.pos_dst[i]
        dv = graph.x_src[src, 3:6] - graph.x_dst[i, 3:6]
        t = (-(dp * dv).sum(-1) / dv.square().sum(-1).clamp_min(1e-6)).clamp(0, mcfg.closest_approach_horizon)
        dmin = (dp + t[:, None] * dv).norm(dim=-1)
        terms = torch.cat((-(dmin - d) / tau, torch.tensor([-(1 - d) / tau], dtype=F64)))
        assert abs(float(h[i]) - math.tanh(-tau * float(torch.logsumexp(terms, 0)))) <= 1e-12
    assert (h < 0).any() or (h > 0).all()  # well defined either way; the scene decides


@given(seed=st.integers(0, 2**16), bound=st.floats(0.01, 0.2))
@settings(max_examples=10, deadline=None)
def test_edge_min_head_correction_bound_keeps_each_edge_near_its_prior(seed, bound):
    """With ``cbf_correction_bound = B`` every per-edge barrier stays within ``B`` of ``d_min - D``, whatever the
    weights (here large random ones), and equals the unbounded head's at zero correction."""
    cfg = EnvConfig(num_agents=5, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.0, num_obstacles=2)
    state = moving_scene(cfg, seed % 50)
    torch.manual_seed(seed)
    mcfg = ModelConfig(hidden=16, heads=2, head_hidden=16, cbf_head="edge_min", cbf_attitude=False,
                       cbf_correction_bound=bound)  # fmt: skip
    cbf = CBFNet(mcfg).double()
    graph = build_graph(state, cfg)
    frames = frames_for(cbf.encoder.group, graph)
    with torch.no_grad():
        z = cbf.encoder(graph)
        prior, _ = cbf.head.edge_values(graph, z, frames)  # zero-initialized last layer: the prior itself
        for q in cbf.head.edge_mlp.parameters():
            q.add_(3.0 * torch.randn_like(q))
        b, _ = cbf.head.edge_values(graph, z, frames)
    assert (b - prior).abs().max() <= bound + 1e-12 and (b - prior).abs().max() > 0.5 * bound
    with pytest.raises(ValueError, match="cbf_correction_bound"):
        ModelConfig(cbf_correction_bound=0.0)


def test_edge_min_head_gradients_are_finite_for_isolated_agents():
    cfg = EnvConfig(num_agents=1, num_envs=1, n_rays=8, lidar_max_hits=4, num_obstacles=0)
    state = moving_scene(cfg, 1)
    torch.manual_seed(0)
    cbf = CBFNet(ModelConfig(hidden=16, heads=2, head_hidden=16, cbf_head="edge_min")).double()
    x = state.x.clone().requires_grad_(True)
    from egcbf.env.graph import refresh_graph

    h = cbf(refresh_graph(build_graph(state, cfg), x))
    assert torch.allclose(h, torch.tanh(torch.tensor([1 - 0.15], dtype=F64)))
    (grad,) = torch.autograd.grad(h.sum(), x)
    assert torch.isfinite(grad).all()


def _edge_sum_policy(seed: int = 0) -> PolicyNet:
    torch.manual_seed(seed)
    mcfg = ModelConfig(hidden=16, heads=2, head_hidden=16, interface="accel", policy_head="edge_sum",
                       edge_velocity=True, edge_closest_approach=True)  # fmt: skip
    return PolicyNet(mcfg).double()


def test_edge_sum_head_starts_at_zero_and_is_the_weighted_sum_of_edge_vectors():
    """Untrained, the edge-sum head adds nothing (the policy is the paper's MLP head). With its last layer set to
    fixed coefficients ``(a, b, c)``, its output is ``sum_j w_j (a dp^ + b dv^ + c q^)`` in the agent's own frame,
    ``w`` the soft-min weights of the closest-approach distances, computed here independently, agent by agent."""
    cfg = EnvConfig(num_agents=5, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.0, num_obstacles=2)
    state = moving_scene(cfg, 13)
    pol = _edge_sum_policy()
    head, mcfg = pol.edge_head, pol.config
    graph = build_graph(state, cfg)
    frames = graph.frames
    z = pol.encoder(graph)
    with torch.no_grad():
        assert head(graph, z, frames).abs().max() == 0
        coef = torch.tensor([0.3, -0.7, 1.1], dtype=F64)
        head.edge_mlp[-1].bias.copy_(coef)
        out = head(graph, z, frames)
    tau, free, eps = mcfg.policy_temperature, mcfg.policy_free_distance, head.eps
    horizon = mcfg.closest_approach_horizon
    to_local = FieldType(GROUP, [Vector(3, 3)])
    for i in range(graph.num_dst):
        sel = (graph.edge_index[1] == i) & (graph.edge_kind != KIND_GOAL)
        src = graph.edge_index[0, sel]
        dp = graph.pos_src[src] - graph.pos_dst[i]
        dv = graph.x_src[src, 3:6] - graph.x_dst[i, 3:6]
        t = (-(dp * dv).sum(-1) / dv.square().sum(-1).clamp_min(1e-6)).clamp(0, horizon)
        q = dp + t[:, None] * dv
        dmin = q.norm(dim=-1)
        w = torch.softmax(torch.cat((-dmin / tau, torch.tensor([-free / tau], dtype=F64))), 0)[:-1]
        inv = GROUP.inverse(frames[i : i + 1]).expand(len(src), 5)
        local = to_local.act(inv, torch.cat((dp, dv, q), -1)).view(-1, 3, 3)
        unit = local / (local.square().sum(-1, keepdim=True) + eps**2).sqrt()
        expected = (w[:, None] * (coef[:, None] * unit).sum(1)).sum(0)
        assert (out[i] - expected).abs().max() <= 1e-12


@given(g=gst.elements(GROUP, batch=(2,)), seed=st.integers(0, 2**20))
@settings(max_examples=20, deadline=None)
def test_edge_sum_policy_is_equivariant(g, seed):
    """The whole policy with the edge-sum head (perturbed off its zero start): its command rotates with the scene
    (float64, 1e-10)."""
    cfg = EnvConfig(num_agents=5, num_envs=2, n_rays=8, lidar_max_hits=4, area_size=1.2, num_obstacles=2)
    pol = _perturbed_edge_sum_policy()
    rotate = FieldType(GROUP, [Vector(3)])
    state = moving_scene(cfg, seed)
    with torch.no_grad():
        a = pol(build_graph(state, cfg)).view(2, 5, 3)
        b = pol(build_graph(state.transform(g), cfg)).view(2, 5, 3)
    assert (rotate.act(g[:, None].expand(2, 5, 5), a) - b).abs().max() <= 1e-10


@functools.cache
def _perturbed_edge_sum_policy() -> PolicyNet:
    pol = _edge_sum_policy(1)
    with torch.no_grad():
        for p in pol.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return pol


def test_edge_sum_head_needs_the_acceleration_interface():
    with pytest.raises(ValueError, match="edge_sum"):
        ModelConfig(policy_head="edge_sum", interface="torque")
    with pytest.raises(ValueError, match="policy_head"):
        ModelConfig(policy_head="mean", interface="accel")
