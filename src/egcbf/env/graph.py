"""SwarmState -> SwarmGraph: the bipartite message-passing graph the CBF and policy networks read.

Receivers are the agents (all ``M = B * N`` agents of all environments, flattened env-major: agent ``i`` of
environment ``b`` is row ``b * N + i``). Senders are agents, goals and LiDAR hits, stacked in ``x_src``::

    rows [0, M)          agents   (x_src[:M] == x_dst)
    rows [M, 2M)         goals    (goal of agent a is row M + a)
    rows [2M, 2M + H)    LiDAR hits that are valid (hit_owner[h] = the agent that sensed it)

Edges ``sender -> receiver`` (row 0 sender index into ``x_src``, row 1 receiver index into ``x_dst``):

* agent -> agent if ``||p_j - p_i|| < comm_radius`` (strict), ``j != i``, same environment (cell-list search);
* goal -> its agent, always;
* hit -> the agent that sensed it, for each valid hit (within the LiDAR range).

They are sorted by (receiver, sender), so each receiver's edges are contiguous and the order depends only on the
edge set. ``edge_kind`` is ``KIND_AGENT`` / ``KIND_GOAL`` / ``KIND_HIT`` (the sender's kind).

Features carry no absolute position, so that the graph is invariant to translations by construction. The robot
(:mod:`egcbf.robots`, ``graph.robot``) declares them:

* nodes (``robot.node_type(group)``): ``kind`` one-hot (agent, goal, hit) | the robot's ``node_fields``. For the
  quadrotor (:data:`NODE_TYPE`, 18 channels): ``v`` world velocity | ``R`` attitude (body-to-world, row-major) |
  ``w`` body angular velocity; for the unicycle (7 channels): ``v`` world velocity | ``h`` unit heading. Goals and
  hits hold zeros after the kind (the zero matrix, not the identity, for ``R``, so that the group action
  ``R -> R_z R`` keeps it fixed).
* edges (:data:`EDGE_TYPE` in 3-D): ``dp = p_sender - p_receiver`` (world frame, ``d`` components); for goal edges
  it is rescaled to norm ``<= comm_radius`` (GCBF+), so a far goal looks like one at the edge of the neighbourhood.

``frames`` are the agents' frames ``robot.frames(x)``: for the quadrotor the SE2xR frames ``se2xr_frame(R[:, 0],
p)`` (yaw of the body x axis, position), for the unicycle the SE(2) frames ``(h, p)``. With
``groupcanon.Canonicalize(group, in_type=(node_type, node_type), edge_type=edge_type, ...)`` every receiver sees
its neighbourhood in its own frame, which is invariant under a global transform of the scene (tested).

Everything is differentiable with respect to the state (the topology is not): gradients of a network output
with respect to ``state.x`` flow through the features, edge vectors and frames.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from groupcanon import FieldType
from groupcanon.features import Vector
from groupcanon.groups import SE2xR

from ..geometry.neighbors import radius_neighbors
from ..robots import DEFAULT_ROBOT, Robot, make_robot
from .config import EnvConfig
from .lidar import LidarScan
from .swarm import SwarmState, cast_lidar

__all__ = [
    "EDGE_TYPE",
    "GROUP",
    "KIND_AGENT",
    "KIND_GOAL",
    "KIND_HIT",
    "NODE_DIM",
    "NODE_TYPE",
    "SwarmGraph",
    "agent_features",
    "build_graph",
    "edge_vectors",
    "refresh_graph",
    "static_features",
    "with_agent_states",
]

#: the quadrotor's graph types (other robots: ``robot.node_type(group)``, ``FieldType(group, {"dp": Vector(d)})``)
GROUP = SE2xR()
NODE_TYPE = make_robot(DEFAULT_ROBOT).node_type(GROUP)  # kind 3 | v 3 | R 9 | w 3 (declared by the robot)
EDGE_TYPE = FieldType(GROUP, {"dp": Vector(3)})
NODE_DIM = NODE_TYPE.dim  # 18
KIND_AGENT, KIND_GOAL, KIND_HIT = 0, 1, 2


@dataclass
class SwarmGraph:
    """The bipartite graph of a batch of swarms (see the module doc for the layout).

    Attributes:
        x_src: ``(N_src, F)`` sender features (``robot.node_type``; quadrotor ``F = 18``), ``N_src = 2M + H``.
        x_dst: ``(M, F)`` receiver (agent) features; equal to ``x_src[:M]``.
        edge_index: ``(2, E)`` long, (sender row in ``x_src``, receiver row in ``x_dst``).
        edge_attr: ``(E, d)``: sender position minus receiver position (goal edges clipped).
        edge_kind: ``(E,)`` long, the sender's kind.
        frames: ``(M, *element)`` frames of the agents in the robot's group (quadrotor: SE2xR, ``(M, 5)``).
        pos_src: ``(N_src, d)`` world positions of the senders; ``pos_dst`` ``(M, d)`` of the agents.
        src_kind: ``(N_src,)`` long kind of each sender.
        batch: ``(M,)`` environment of each agent; ``src_batch`` ``(N_src,)`` of each sender.
        hit_owner: ``(H,)`` the agent (row of ``x_dst``) that sensed each hit node.
        num_envs, num_agents: ``B`` and ``N`` (``M = B * N``); comm_radius: the goal-clipping radius.
        robot: the robot whose states the agents are (``None``: the quadrotor).
    """

    x_src: Tensor
    x_dst: Tensor
    edge_index: Tensor
    edge_attr: Tensor
    edge_kind: Tensor
    frames: Tensor
    pos_src: Tensor
    pos_dst: Tensor
    src_kind: Tensor
    batch: Tensor
    src_batch: Tensor
    hit_owner: Tensor
    num_envs: int
    num_agents: int
    comm_radius: float
    robot: Robot | None = None

    def __post_init__(self) -> None:
        if self.robot is None:
            self.robot = make_robot(DEFAULT_ROBOT)

    @property
    def num_dst(self) -> int:
        return self.x_dst.shape[0]

    @property
    def num_src(self) -> int:
        return self.x_src.shape[0]

    @property
    def num_edges(self) -> int:
        return self.edge_index.shape[1]

    @property
    def goal_offset(self) -> int:
        return self.num_dst

    @property
    def hit_offset(self) -> int:
        return 2 * self.num_dst

    @property
    def num_hits(self) -> int:
        return self.hit_owner.shape[0]

    def reflect_z(self) -> SwarmGraph:
        """The graph of the scene mirrored in a horizontal plane, ``sigma = diag(1, 1, -1)`` (same edges).

        Vectors flip their z component (``v``, ``dp``, positions), attitudes are conjugated ``R -> sigma R sigma``
        (a rotation again; the body x axis keeps its yaw), body rates become ``(-wx, -wy, wz)`` (``R^T dR/dt``
        conjugated by the improper ``sigma``), frames keep their yaw and flip ``tz``. The reflection commutes with
        every SE(2) x R element, so averaging a network over ``{G, G.reflect_z()}`` keeps SE2xR invariance.
        Quadrotor graphs only.
        """
        if not self.robot.mirror_z:
            raise ValueError(f"reflect_z is defined for quadrotor graphs (Robot.mirror_z), not for a {self.robot.name}")
        like = self.x_src
        layout = self.robot.node_layout
        v, r, w = layout.slice("v").start, layout.slice("R").start, layout.slice("w").start
        flip = torch.ones(layout.dim, dtype=like.dtype, device=like.device)
        flip[[v + 2, r + 2, r + 5, r + 6, r + 7, w, w + 1]] = -1  # v_z; R_02, R_12, R_20, R_21 (row-major); w_x, w_y
        vec = torch.tensor((1.0, 1.0, -1.0), dtype=like.dtype, device=like.device)
        frame = torch.tensor((1.0, 1.0, 1.0, 1.0, -1.0), dtype=like.dtype, device=like.device)
        return replace(
            self,
            x_src=self.x_src * flip,
            x_dst=self.x_dst * flip,
            edge_attr=self.edge_attr * vec,
            pos_src=self.pos_src * vec,
            pos_dst=self.pos_dst * vec,
            frames=self.frames * frame,
        )

    def relative_velocity(self, edge_index: Tensor) -> Tensor:
        """``(E, d)`` world-frame ``v_sender - v_receiver`` of the edges ``edge_index`` (goals and hits: ``v = 0``),
        read from the node features (so it follows :func:`refresh_graph` and the edge-expanded Jacobian graph)."""
        v = self.robot.node_layout.slice("v")
        return self.x_src[:, v].index_select(0, edge_index[0]) - self.x_dst[:, v].index_select(0, edge_index[1])

    def with_receivers(self, keep: Tensor) -> SwarmGraph:
        """The same graph with only the edges into the receivers where ``keep`` ``(M,)`` is true.

        A network's output for a kept receiver is unchanged (it reads only its own incoming edges); the others
        see no neighbour. Used to evaluate a network only where its output is needed.
        """
        sel = keep[self.edge_index[1]]
        return replace(
            self, edge_index=self.edge_index[:, sel], edge_attr=self.edge_attr[sel], edge_kind=self.edge_kind[sel]
        )

    @property
    def frames_per_agent(self) -> int:
        """1, or ``F`` when every agent has a set of ``F`` frames to average over (``frames`` ``(M, F, *element)``:
        robots of a finite-rotation group, :func:`groupcanon.frames.cyclic_frames`)."""
        rank = len(self.robot.group.element_shape)
        return 1 if self.frames.dim() == 1 + rank else self.frames.shape[1]

    def expand_frames(self) -> SwarmGraph:
        """For a graph whose agents carry ``F`` frames each: the same graph with every receiver copied ``F`` times
        (receiver ``i * F + k`` is agent ``i`` in its ``k``-th frame, with a copy of each of its incoming edges) and
        one frame per receiver. A network run on it and averaged over each agent's ``F`` rows is frame-averaged:
        equivariant under the finite group (:meth:`frames_per_agent`). The senders are unchanged, so the sender
        layout of the module doc (``goal_offset``, ``hit_offset``, ``hit_owner``) no longer describes the graph: only
        networks read it, and they read ``edge_index``."""
        f = self.frames_per_agent
        if f == 1:
            return self
        m = self.num_dst
        rep = functools.partial(torch.repeat_interleave, repeats=f, dim=0)
        k = torch.arange(f, device=self.edge_index.device)
        dst = (self.edge_index[1][:, None] * f + k).reshape(-1)
        element = self.frames.shape[2:]
        return replace(
            self, x_dst=rep(self.x_dst), edge_index=torch.stack((rep(self.edge_index[0]), dst)),
            edge_attr=rep(self.edge_attr), edge_kind=rep(self.edge_kind), frames=self.frames.reshape(m * f, *element),
            pos_dst=rep(self.pos_dst), batch=rep(self.batch), hit_owner=self.hit_owner * f,
        )  # fmt: skip

    def to(self, *args, **kwargs) -> SwarmGraph:
        """Move (and for floating tensors cast) every tensor, like ``Tensor.to``; index tensors stay long."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Tensor):
                v = v.to(*args, **kwargs) if v.is_floating_point() else v.to(device=_device_of(args, kwargs, v))
            out[f.name] = v
        return SwarmGraph(**out)


def _check_velocity_field(robot: Robot) -> None:
    names = list(robot.node_fields)
    if "v" not in names:
        raise ValueError(f"{robot.name}: the node fields must include 'v' (the world velocity), got {names}")


def _device_of(args, kwargs, like: Tensor):
    if "device" in kwargs:
        return kwargs["device"]
    for a in args:
        if isinstance(a, (str, torch.device)):
            return a
        if isinstance(a, Tensor):
            return a.device
    return like.device


def agent_features(robot: Robot, x: Tensor) -> Tensor:
    """``(M, F)`` node features of agents from states ``(M, S)``: kind one-hot | ``robot.agent_features``."""
    kind = torch.zeros(x.shape[0], 3, dtype=x.dtype, device=x.device)
    kind[:, KIND_AGENT] = 1
    return torch.cat((kind, robot.agent_features(x)), dim=-1)


def static_features(num: int, kind: int, like: Tensor) -> Tensor:
    """``(num, F)`` node features of goals or hits (``kind``): the kind one-hot, zeros after it (like ``like``)."""
    f = torch.zeros(num, like.shape[1], dtype=like.dtype, device=like.device)
    f[:, kind] = 1
    return f


def _clip_norm(v: Tensor, max_norm: float) -> Tensor:
    n = v.norm(dim=-1, keepdim=True)
    scale = max_norm / torch.where(n > max_norm, n, torch.full_like(n, max_norm))
    return v * scale


def edge_vectors(pos_src: Tensor, pos_dst: Tensor, edge_index: Tensor, edge_kind: Tensor, comm: float) -> Tensor:
    """``(E, d)`` edge features ``p_sender - p_receiver``, goal edges clipped to norm ``<= comm`` (module doc)."""
    dp = pos_src.index_select(0, edge_index[0]) - pos_dst.index_select(0, edge_index[1])
    is_goal = (edge_kind == KIND_GOAL)[:, None]
    return torch.where(is_goal, _clip_norm(dp, comm), dp)


def build_graph(state: SwarmState, config: EnvConfig, *, lidar: LidarScan | None = None) -> SwarmGraph:
    """Build the :class:`SwarmGraph` of ``state`` (all environments of the batch at once).

    Args:
        state: the swarm state (``B`` environments of ``N`` agents).
        config: the environment config (comm radius, LiDAR pattern and range).
        lidar: a precomputed scan of ``state`` (e.g. from :meth:`SwarmEnv.lidar`); cast here if ``None``.
    """
    robot = state.robot
    _check_velocity_field(robot)
    x = state.x
    b, n, _ = x.shape
    d = robot.dim
    m = b * n
    device = x.device
    xf = x.reshape(m, -1)
    p = robot.positions(xf)
    sensing = state.sensing  # faults (egcbf.faults): the scan and the messages as the agents receive them
    if lidar is None:
        if sensing is not None:
            lidar = sensing.scan(config)
        else:
            lidar = cast_lidar(config, state.positions, robot.heading(x), state.obstacles)
    valid = lidar.valid.reshape(m, -1)
    owner, _slot = valid.nonzero(as_tuple=True)  # row-major: owner-major, closest first
    hit_pos = lidar.points.reshape(m, -1, d)[valid]  # same order as nonzero
    h = owner.shape[0]

    agent_feat = agent_features(robot, xf)
    x_src = torch.cat((agent_feat, static_features(m, KIND_GOAL, agent_feat), static_features(h, KIND_HIT, agent_feat)))
    pos_src = torch.cat((p, state.goals.reshape(m, d).to(p.dtype), hit_pos))
    agent_ids = torch.arange(m, device=device)
    batch = agent_ids // n
    src_kind = torch.cat(
        (
            torch.full((m,), KIND_AGENT, device=device),
            torch.full((m,), KIND_GOAL, device=device),
            torch.full((h,), KIND_HIT, device=device),
        )
    )
    src_batch = torch.cat((batch, batch, batch[owner]))

    # cells of half the radius: ~40 % fewer candidate pairs at swarm densities; the edges are sorted below anyway
    aa = radius_neighbors(p, config.comm_radius, batch, sort=False, cells_per_radius=2)
    goal_e = torch.stack((agent_ids + m, agent_ids))
    hit_e = torch.stack((torch.arange(h, device=device) + 2 * m, owner))
    edge_index = torch.cat((aa, goal_e, hit_e), dim=1)
    n_src = 2 * m + h
    perm = torch.argsort(edge_index[1] * n_src + edge_index[0])
    edge_index = edge_index.index_select(1, perm)
    edge_kind = src_kind.index_select(0, edge_index[0])
    edge_attr = edge_vectors(pos_src, p, edge_index, edge_kind, config.comm_radius)

    graph = SwarmGraph(
        x_src=x_src,
        x_dst=agent_feat,
        edge_index=edge_index,
        edge_attr=edge_attr,
        edge_kind=edge_kind,
        frames=robot.frames(xf),
        pos_src=pos_src,
        pos_dst=p,
        src_kind=src_kind,
        batch=batch,
        src_batch=src_batch,
        hit_owner=owner,
        num_envs=b,
        num_agents=n,
        comm_radius=float(config.comm_radius),
        robot=robot,
    )
    return graph if sensing is None else sensing.messages(graph)


def refresh_graph(graph: SwarmGraph, x: Tensor) -> SwarmGraph:
    """The same graph (same edges, goals and LiDAR hit points) with new agent states ``x`` ``(B, N, S)``.

    This is GCBF+'s way of evaluating ``h`` at the next state for the ``h-dot`` loss: the topology and the world
    positions of goals and hits are kept, the agent features, agent positions, frames and edge vectors are
    recomputed from ``x`` (differentiably). Same as ``with_agent_states(graph, x.reshape(M, S))``.
    """
    return with_agent_states(graph, x.reshape(graph.num_dst, -1))


def with_agent_states(graph: SwarmGraph, x_recv: Tensor, x_edge: Tensor | None = None) -> SwarmGraph:
    """``graph`` with new agent states (topology, goals and LiDAR hits held fixed; differentiable in the states).

    Args:
        x_recv: ``(M, S)`` the receivers' (agents') states.
        x_edge: ``None``: every agent sender reads ``x_recv`` (the same agents). Else ``(E_a, S)``: each
            agent-to-agent edge, in edge order, reads its own copy of its sender's state; the result then has one
            source row per edge (``edge_index[0] = arange(E)``), so that the gradient of ``sum_i h_i`` with respect
            to the copies holds every ``dh_i / dx_j`` at once (:func:`egcbf.algo.qp.cbf_jacobian`).
    """
    m = graph.num_dst
    robot = graph.robot
    p_recv = robot.positions(x_recv)
    agent_feat = agent_features(robot, x_recv)
    if x_edge is None:
        x_src = torch.cat((agent_feat, graph.x_src[m:].to(x_recv.dtype)))
        pos_src = torch.cat((p_recv, graph.pos_src[m:].to(p_recv.dtype)))
        edge_index, extra = graph.edge_index, {}
    else:
        src, dst = graph.edge_index
        rows = (src < m).nonzero()[:, 0]
        x_src = graph.x_src[src].to(x_recv.dtype).index_put((rows,), agent_features(robot, x_edge))
        pos_src = graph.pos_src[src].to(x_recv.dtype).index_put((rows,), robot.positions(x_edge))
        edge_index = torch.stack((torch.arange(src.shape[0], device=src.device), dst))
        extra = {"src_kind": graph.src_kind[src], "src_batch": graph.src_batch[src]}
    edge_attr = edge_vectors(pos_src, p_recv, edge_index, graph.edge_kind, graph.comm_radius)
    return replace(
        graph, x_src=x_src, x_dst=agent_feat, pos_src=pos_src, pos_dst=p_recv, edge_index=edge_index,
        edge_attr=edge_attr, frames=robot.frames(x_recv), **extra,
    )  # fmt: skip
