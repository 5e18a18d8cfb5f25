"""SwarmGraph: structure, and invariance of the receiver-frame features under a global SE2xR transform."""

import math

import pytest
import torch
from dyn_helpers import moving_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from egcbf.env import EnvConfig, SwarmEnv, SwarmState
from egcbf.env.graph import (
    EDGE_TYPE,
    GROUP,
    KIND_AGENT,
    KIND_GOAL,
    KIND_HIT,
    NODE_TYPE,
    build_graph,
    refresh_graph,
)
from egcbf.geometry.neighbors import brute_force_neighbors
from egcbf.robots.quadrotor import dynamics as dyn
from groupcanon import FieldType
from groupcanon.features import Scalar
from groupcanon.testing import strategies as gst

F64 = torch.float64


def _local(graph):
    """Every edge's sender features and edge vector, and every receiver's features, in the receiver's frame."""
    inv = GROUP.inverse(graph.frames)
    src, dst = graph.edge_index
    return (
        NODE_TYPE.act(inv[dst], graph.x_src[src]),
        EDGE_TYPE.act(inv[dst], graph.edge_attr),
        NODE_TYPE.act(inv, graph.x_dst),
    )


@st.composite
def configs(draw):
    return EnvConfig(
        num_agents=draw(st.integers(1, 12)),
        num_envs=draw(st.integers(1, 3)),
        area_size=draw(st.floats(1.0, 2.5)),
        num_obstacles=draw(st.integers(0, 5)),
        comm_radius=draw(st.floats(0.3, 1.2)),
        n_rays=draw(st.sampled_from([8, 16, 32])),
        lidar_max_hits=draw(st.integers(1, 16)),
    )


@given(cfg=configs(), seed=st.integers(0, 2**20), g=gst.elements(GROUP, batch=(3,)))
@settings(max_examples=20)
def test_receiver_frame_features_are_invariant(cfg, seed, g):
    state = moving_scene(cfg, seed)
    g = g[: cfg.num_envs]
    g1, g2 = build_graph(state, cfg), build_graph(state.transform(g), cfg)
    assert torch.equal(g1.edge_index, g2.edge_index)  # identical edge set, identical order
    assert torch.equal(g1.edge_kind, g2.edge_kind) and torch.equal(g1.src_kind, g2.src_kind)
    for a, b in zip(_local(g1), _local(g2)):
        assert torch.allclose(a, b, atol=1e-9, rtol=0)
    # the frames transform as g . frame, the world-frame features as typed
    assert torch.allclose(GROUP.compose(g[g1.batch], g1.frames), g2.frames, atol=1e-9)
    assert torch.allclose(EDGE_TYPE.act(g[g1.batch[g1.edge_index[1]]], g1.edge_attr), g2.edge_attr, atol=1e-9)


@given(cfg=configs(), seed=st.integers(0, 2**20))
@settings(max_examples=15)
def test_structure(cfg, seed):
    state = moving_scene(cfg, seed)
    gr = build_graph(state, cfg)
    b, n = cfg.num_envs, cfg.num_agents
    m = b * n
    src, dst = gr.edge_index
    lidar = SwarmEnv(cfg, dtype=F64).lidar(state)
    h = int(lidar.valid.sum())
    assert gr.num_dst == m and gr.num_hits == h and gr.num_src == 2 * m + h
    assert gr.x_src.shape == (2 * m + h, NODE_TYPE.dim) and gr.x_dst.shape == (m, NODE_TYPE.dim)
    assert gr.edge_attr.shape == (gr.num_edges, 3) and gr.frames.shape == (m, 5)
    assert torch.equal(gr.x_src[:m], gr.x_dst)
    assert (dst < m).all() and (src < gr.num_src).all()
    key = dst * gr.num_src + src
    assert (key.diff() > 0).all()  # sorted by (receiver, sender), no duplicates
    # agent-agent edges: exactly the brute-force radius graph, within environments, no self loops
    aa = gr.edge_index[:, gr.edge_kind == KIND_AGENT]
    batch = torch.arange(b).repeat_interleave(n)
    assert torch.equal(aa, brute_force_neighbors(state.positions.reshape(m, 3), cfg.comm_radius, batch))
    # one goal edge per agent, from its own goal; hit edges from own valid hits
    ge = gr.edge_index[:, gr.edge_kind == KIND_GOAL]
    assert torch.equal(ge[1], torch.arange(m)) and torch.equal(ge[0], torch.arange(m) + m)
    he = gr.edge_index[:, gr.edge_kind == KIND_HIT]
    assert he.shape[1] == h and torch.equal(gr.hit_owner[he[0] - 2 * m], he[1])
    assert torch.equal(gr.pos_src[2 * m :], lidar.points[lidar.valid])
    # kinds: one-hot; goals and hits carry zero v, R, w
    assert torch.equal(gr.x_src[:, :3].argmax(-1), gr.src_kind) and (gr.x_src[:, :3].sum(-1) == 1).all()
    assert (gr.x_src[m:, 3:] == 0).all()
    assert torch.equal(gr.src_batch[:m], batch) and torch.equal(gr.src_batch[m : 2 * m], batch)
    # features: v, R, w of the agents; no absolute position anywhere
    xf = state.x.reshape(m, 18)
    assert torch.equal(NODE_TYPE.get(gr.x_dst, "v"), xf[:, dyn.V])
    assert torch.equal(NODE_TYPE.get(gr.x_dst, "R"), xf[:, dyn.ROT])
    assert torch.equal(NODE_TYPE.get(gr.x_dst, "w"), xf[:, dyn.W])
    # edge vectors: sender minus receiver; goal edges clipped to comm radius, same direction
    dp = gr.pos_src[src] - gr.pos_dst[dst]
    not_goal = gr.edge_kind != KIND_GOAL
    assert torch.allclose(gr.edge_attr[not_goal], dp[not_goal])
    ga, gd = gr.edge_attr[~not_goal], dp[~not_goal]
    assert (ga.norm(dim=-1) <= cfg.comm_radius * (1 + 1e-12)).all()
    assert torch.allclose(ga.norm(dim=-1), gd.norm(dim=-1).clamp(max=cfg.comm_radius))
    assert torch.allclose(torch.linalg.cross(ga, gd, dim=-1), torch.zeros_like(ga), atol=1e-12)
    assert (gr.edge_attr[gr.edge_kind == KIND_AGENT].norm(dim=-1) < cfg.comm_radius).all()
    # frames: yaw of the body x axis and the position
    yaw = torch.atan2(xf[:, 6], xf[:, 3])  # R[1, 0], R[0, 0]
    assert torch.allclose(gr.frames[:, :2], torch.stack((yaw.cos(), yaw.sin()), -1))
    assert torch.equal(gr.frames[:, 2:], xf[:, :3])


def test_refresh_graph_matches_and_is_differentiable():
    cfg = EnvConfig(num_envs=2, num_agents=6)
    state = moving_scene(cfg, 0)
    gr = build_graph(state, cfg)
    same = refresh_graph(gr, state.x)
    for name in ("x_src", "x_dst", "edge_attr", "frames", "pos_src", "pos_dst"):
        assert torch.equal(getattr(same, name), getattr(gr, name)), name
    x = state.x.clone().requires_grad_(True)
    moved = refresh_graph(gr, x + 0.01)
    assert torch.equal(moved.edge_index, gr.edge_index)
    (moved.edge_attr.square().sum() + moved.x_dst.sum() + moved.frames.sum()).backward()
    assert torch.isfinite(x.grad).all() and x.grad[..., dyn.P].abs().sum() > 0
    # build_graph is differentiable with respect to the state as well
    x2 = state.x.clone().requires_grad_(True)
    g2 = build_graph(SwarmState(x2, state.goals, state.obstacles), cfg)
    g2.edge_attr.sum().backward()
    assert torch.isfinite(x2.grad).all()


def test_canonicalized_layer_on_the_graph_is_invariant():
    """End to end: a PyG layer wrapped by groupcanon gives invariant per-agent outputs (the CBF use case)."""
    from torch_geometric.nn import TransformerConv

    from groupcanon import Canonicalize

    torch.manual_seed(0)
    cfg = EnvConfig(num_envs=2, num_agents=8, comm_radius=1.0)
    state = moving_scene(cfg, 1)
    out_type = FieldType(GROUP, [Scalar(4)])
    layer = TransformerConv((NODE_TYPE.dim, NODE_TYPE.dim), 4, edge_dim=3).double()
    eq = Canonicalize(GROUP, in_type=(NODE_TYPE, NODE_TYPE), out_type=out_type, edge_type=EDGE_TYPE)(layer)
    g = torch.tensor([[math.cos(1.0), math.sin(1.0), 3.0, -2.0, 0.5], [-1.0, 0.0, 0.1, 0.2, -7.0]], dtype=F64)
    outs = []
    for s in (state, state.transform(g)):
        gr = build_graph(s, cfg)
        outs.append(eq((gr.x_src, gr.x_dst), gr.edge_index, frames=gr.frames, edge_attr=gr.edge_attr))
    assert outs[0].shape == (16, 4)
    assert torch.allclose(outs[0], outs[1], atol=1e-9)


def test_graph_to_and_float32():
    cfg = EnvConfig(num_envs=1, num_agents=4)
    s = SwarmEnv(cfg, dtype=torch.float32).reset(0)
    gr = build_graph(s, cfg)
    assert gr.x_src.dtype == torch.float32 and gr.edge_index.dtype == torch.long
    g64 = gr.to(torch.float64)
    assert g64.x_src.dtype == torch.float64 and g64.edge_index.dtype == torch.long
    assert g64.frames.dtype == torch.float64


@pytest.mark.parametrize("n", [1, 3])
def test_single_agent_and_no_obstacles(n):
    cfg = EnvConfig(num_agents=n, num_obstacles=0)
    gr = build_graph(SwarmEnv(cfg, dtype=F64).reset(0), cfg)
    assert gr.num_hits == 0 and (gr.edge_kind == KIND_GOAL).sum() == n
    if n == 1:
        assert gr.num_edges == 1
