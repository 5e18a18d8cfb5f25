"""The CBF and policy networks: one graph transformer layer made equivariant by canonicalization, plus an MLP head.

Both follow the paper (Architecture & Training)::

    h_phi(G_i)    = m_phi2 ( phi_{g_i^-1} M_phi1(G_i) )                    (invariant scalar, tanh-bounded)
    pi_theta(G_i) = psi_{g_i} m_theta2 ( phi_{g_i^-1} M_theta1(G_i) )      (command residual)

``M`` is :class:`~egcbf.nn.layers.GraphTransformerLayer` wrapped with ``groupcanon.Canonicalize`` over the group
named in the config: the robot's symmetry group (EGCBF, EGCBF+: ``"se2xr"`` for the quadrotor, ``"se2"`` for the
planar unicycle) or ``"trivial"`` (GCBF, GCBF+). The node and edge feature types and the frames come from the
robot named in the config (``ModelConfig.robot``, :mod:`egcbf.robots`). It is the *same code*: with the
trivial group every action is the identity, so the layer sees world-frame features and the network is the
ordinary non-equivariant GNN. The layer's output type is ``Scalar(hidden)`` (invariant features expressed in the
receiver's frame), so the heads are plain MLPs. The CBF value is invariant by construction. The policy's output
depends on the control interface (``ModelConfig.interface``, :mod:`egcbf.algo.interface`):

* ``"accel"``: a desired-acceleration residual, produced in the agent's own frame and mapped back to the world by
  the agent's frame, ``psi_{g_i}`` acting on a ``Vector(3)``: the command rotates with the scene. The attitude loop
  then turns it into body torque and thrust, which are invariant.
* ``"torque"``: a body torque and thrust residual; the body-frame control is invariant (``psi_g(u) = u``,
  :data:`egcbf.robots.quadrotor.dynamics.CONTROL_TYPE`).

Either way the whole controller ``state -> (tau, F3)`` is SE(2) x R equivariant (tested).

CBF and policy are separate networks (GCBF+), each with its own graph layer.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from groupcanon import Canonicalize, FieldType, Group
from groupcanon.features import Scalar, Vector
from groupcanon.groups import SE2, CyclicSE2, CyclicSE2xR, SE2xR, Trivial

from ..env.graph import KIND_GOAL, SwarmGraph
from ..robots import DEFAULT_ROBOT, make_robot
from .edge_min import EdgeMinHead, closest_approach
from .edge_sum import EdgeSumHead
from .layers import GraphTransformerLayer, mlp

__all__ = [
    "BASE_LAWS",
    "GROUPS",
    "CBFNet",
    "GraphEncoder",
    "ModelConfig",
    "PolicyNet",
    "closest_approach",
    "edge_type",
    "frames_for",
    "make_group",
    "node_type",
    "sensing",
]

GROUPS = {
    "se2xr": SE2xR,
    "se2": SE2,
    "se2c4": functools.partial(CyclicSE2, 4),
    "se2xrc4": functools.partial(CyclicSE2xR, 4),
    "trivial": Trivial,
}


#: the laws a policy's residual may act around (``ModelConfig.base_law``)
BASE_LAWS = ("nominal", "brisk", "brisk_isolated")


def make_group(name: str) -> Group:
    """The group of a config name: ``"se2xr"``, ``"se2"``, ``"se2c4"`` / ``"se2xrc4"`` (rotations about z by
    multiples of 90 degrees with planar / 3-D translations: the networks average over each agent's four frames) or
    ``"trivial"``."""
    try:
        return GROUPS[name]()
    except KeyError:
        raise ValueError(f"unknown group {name!r}; choose one of {sorted(GROUPS)}") from None


def node_type(group: Group, robot: str = DEFAULT_ROBOT) -> FieldType:
    """The node features of ``robot`` declared over ``group`` (quadrotor: kind one-hot, world velocity, attitude,
    body rate; :data:`egcbf.env.graph.NODE_TYPE`)."""
    return make_robot(robot).node_type(group)


def edge_type(group: Group, velocity: bool = False, closest_approach: bool = False, dim: int = 3) -> FieldType:
    """The edge features declared over ``group``: the relative position ``dp`` (a ``dim``-vector), with the
    relative velocity ``dv = v_sender - v_receiver`` (a vector) appended if ``velocity``, and the closest approach
    ``(d_min, t_min)`` (two invariant scalars, :func:`closest_approach`) after it if ``closest_approach``."""
    fields = {"dp": Vector(dim)}
    if velocity:
        fields["dv"] = Vector(dim)
        if closest_approach:
            fields["approach"] = Scalar(2)
    return FieldType(group, fields)


def frames_for(group: Group, graph: SwarmGraph) -> Tensor:
    """The receivers' frames as elements of ``group``: the graph's frames (in its robot's group), or identities of
    the trivial group."""
    if isinstance(group, Trivial):
        return group.identity(graph.num_dst, dtype=graph.x_dst.dtype, device=graph.x_dst.device)
    if graph.frames_per_agent > 1:
        raise ValueError("these agents carry frame sets: average over them first (SwarmGraph.expand_frames)")
    if type(group) is type(graph.robot.group) and getattr(group, "n", None) == getattr(graph.robot.group, "n", None):
        return graph.frames
    raise ValueError(f"no frames for {group}: the {graph.robot.name} graph carries {graph.robot.group} frames")


@dataclass
class ModelConfig:
    """Architecture of the CBF and policy networks.

    Attributes:
        robot: the robot the networks read (:data:`egcbf.robots.ROBOTS`): its node features, frames and commands.
        group: the robot's group (equivariant: EGCBF, EGCBF+; ``"se2xr"`` for the quadrotor, ``"se2"`` for the
            unicycle) or ``"trivial"`` (GCBF, GCBF+).
        hidden: width of the graph layer (encoders, attention, output).
        heads: attention heads.
        head_hidden: width of the two hidden layers of the MLP heads.
        self_loops: let each receiver attend to itself as well (Canonicalize's ``self_loops``); off by default
            because every agent always has its goal edge and the residual already carries its own features.
        action_scale: the policy output ``tanh(.)`` in ``[-1, 1]^4`` is multiplied by this (in units of the
            actuator box) and added to the nominal control (GCBF+: 2, so the residual can cross the whole box).
        torque_action_scale: the scale of the three torque channels, if not ``None`` (``None``: ``action_scale``
            for all four). The nominal attitude loop is stiff: a residual of ``1`` (one torque box) held against it
            tilts the drone by ``~1.3 rad`` and shifts its hover point by ``~1.9 m``, and the CBF's one-step
            derivative pushes torques hardest (they change the body rates ``w`` within one step), so a small
            state-independent torque bias from the policy ruins goal reaching (docs/learning.md, "cpu-torque recipe").
            The ``cpu-torque`` preset uses ``0.25``: still ``~0.3 rad`` of sustained tilt authority, far more than
            collision avoidance needs.
        cbf_body_rates: whether the CBF reads the body rates ``w`` (the policy always does). ``w`` is a fast
            internal state of the attitude loop (torque changes it by ``~17`` rad/s per unit of normalized torque
            within one control step), so a CBF that reads it has a huge ``Lg h`` on the torques, and the derivative
            term and the QP correct safety through torque (docs/learning.md, "cpu-torque recipe").
        cbf_goal_edges: whether the CBF sees the goal edge (the policy always does). Safety does not depend on
            where the goal is; a CBF that reads it can make ``h`` depend on the goal offset and the vertical
            velocity of an agent hovering alone at its goal, and the derivative term then pushes a thrust bias
            that shifts every hover point (docs/learning.md, "cpu-torque recipe"). GCBF+ feeds the goal to both.
        cbf_z_symmetric: average the CBF over the mirror image of the scene in a horizontal plane,
            ``h = tanh((m(G) + m(sigma G)) / 2)`` (:meth:`egcbf.env.graph.SwarmGraph.reflect_z`). The safe set
            (distances) is mirror-symmetric; without this, an untrained CBF's ``dh/dv_z`` has one sign almost
            everywhere, and
            since the learned-CBF QP can only act through thrust within one step (the CBF has relative degree 2 in
            the torques), ``u_QP`` pushes every agent up (or every agent down) whenever anything approaches: a
            global thrust bias that shifts hover points out of the goal radius (docs/learning.md, "cpu-torque recipe").
            Mirror symmetry makes ``dh/dv_z`` odd in the vertical arrangement (climb if the neighbour is below,
            descend if above) and zero for a level scene. Costs a second CBF evaluation.
        cbf_attitude: whether the CBF reads the attitude ``R`` (zeroed otherwise: the zero matrix is fixed by the
            group action, so equivariance is untouched). With the acceleration interface and its ideal model the
            CBF is a function of positions and velocities, the states that model moves.
        edge_velocity: edges also carry the relative velocity ``dv = v_sender - v_receiver`` (a vector, rotated into
            the receiver's frame like ``dp``), so that one edge's message can tell an approaching neighbour from a
            receding one (GCBF+'s edge feature is the whole state difference). Without it, the layer combines
            ``dp`` and the sender's velocity only additively per edge (TransformerConv's value is
            ``W_v h_src + W_e e``), and closing speed is hard to express in one layer.
        edge_closest_approach: with ``edge_velocity``, edges also carry the distance and time of closest approach
            of sender and receiver moving straight, within ``closest_approach_horizon`` seconds (two invariant
            scalars, :func:`closest_approach`): the quantities a collision depends on, which one graph layer
            otherwise has to synthesise from ``dp`` and ``dv`` (docs/learning.md, "Edge features").
        cbf_head: ``"mlp"`` (the paper's: an MLP on the receiver's graph-transformer features) or ``"edge_min"``
            (:class:`egcbf.nn.edge_min.EdgeMinHead`: a smooth minimum over learned per-edge barrier values that start
            at the closest-approach distance minus ``cbf_distance`` (m), temperature ``cbf_temperature`` (m)).
        cbf_correction_bound: ``None`` or ``> 0`` (m): the edge-min head's learned correction passes through
            ``bound * tanh(. / bound)``, so the barrier stays within ``bound`` of its closest-approach prior and
            keeps its gradient (labels alone flatten an unbounded one; docs/robots.md).
        policy_init_scale: the last layer of the policy head is initialised with weights scaled by this and zero
            bias, so that an untrained policy stays close to the nominal controller.
        interface: what the policy commands (:mod:`egcbf.algo.interface`): ``"accel"``, a desired acceleration
            (a world-frame vector, produced in the agent's frame and mapped back by the group: ``psi_{g_i}``)
            tracked by the attitude loop; ``"torque"``, body torque and thrust (invariant); or ``"control"``, the
            robot's normalized raw control (the planar unicycle's). ``robot.interfaces`` lists a robot's.
        accel_action_scale: with ``"accel"``, the residual ``pi`` in ``[-1, 1]^3`` is multiplied by this (in units
            of ``AccelInterface.accel_unit``, 5 m/s^2) and added to the nominal command.
        policy_head: ``"mlp"`` (the paper's: an MLP on the agent's graph-transformer features) or ``"edge_sum"``
            (with ``"accel"``: that MLP plus :class:`egcbf.nn.edge_sum.EdgeSumHead`, a soft-min weighted sum over
            the agent's edges of learned coefficients times the edge's relative position, relative velocity and
            closest-approach vectors, with soft-min temperature ``policy_temperature`` (m) and a free slot at
            ``policy_free_distance`` (m); with ``"control"``: learned invariant coefficients summed with the same
            weights).
        policy_gate_isolated: the residual is zero for an agent that senses nothing (no neighbour agent and no
            LiDAR hit): with nothing to avoid there is no reason to leave the nominal controller, and the data
            says little about such agents (docs/learning.md, "isolated agents"). The gate is a function of edge
            kinds, an invariant.
        base_law: the law the policy's residual is added to, which is also the QP teacher's target: ``"nominal"``
            (GCBF+'s: the robot's nominal controller) or ``"brisk"`` (``"control"`` interface only: the robot's
            :meth:`~egcbf.robots.base.Robot.brisk_control`, its nominal law retuned to cruise at the speed limits;
            docs/gcbfplus.md, "Brisk base law") or ``"brisk_isolated"`` (``"control"`` interface: the brisk law
            while the agent senses nothing, no neighbour agent and no LiDAR hit, the nominal law otherwise; an
            invariant switch, :func:`sensing`).
        brisk_weight: how far the base law moves from the nominal law towards the brisk one, ``nominal + w (brisk -
            nominal)`` in ``(0, 1]`` (1: the brisk law itself). Both laws are equivariant and the group acts
            linearly on commands, so the blend is too; it stays inside the command box, a convex set. For the Dubins
            car, whose laws are affine in the speed gain, ``w`` sets the cruise between 0.46 and 0.6 m/s.
    """

    group: str = "se2xr"
    robot: str = DEFAULT_ROBOT
    hidden: int = 64
    heads: int = 4
    head_hidden: int = 64
    self_loops: bool = False
    action_scale: float = 2.0
    torque_action_scale: float | None = None
    cbf_body_rates: bool = True
    cbf_goal_edges: bool = True
    cbf_z_symmetric: bool = False
    cbf_attitude: bool = True
    edge_velocity: bool = False
    edge_closest_approach: bool = False
    closest_approach_horizon: float = 1.0
    cbf_head: str = "mlp"
    cbf_distance: float = 0.15
    cbf_temperature: float = 0.05
    cbf_correction_bound: float | None = None
    policy_init_scale: float = 0.1
    interface: str = "torque"
    accel_action_scale: float = 1.0
    policy_gate_isolated: bool = False
    policy_head: str = "mlp"
    policy_temperature: float = 0.1
    policy_free_distance: float = 1.0
    base_law: str = "nominal"
    brisk_weight: float = 1.0

    def __post_init__(self) -> None:
        make_group(self.group)
        robot = make_robot(self.robot)
        if self.group not in ("trivial", robot.group_name):
            raise ValueError(
                f"ModelConfig.group must be the {self.robot}'s group {robot.group_name!r} or 'trivial', "
                f"got {self.group!r}"
            )
        if self.cbf_z_symmetric and robot.dim != 3:
            raise ValueError(f"ModelConfig.cbf_z_symmetric mirrors a 3-D scene; the {self.robot} is planar")
        if self.interface not in robot.interfaces:
            raise ValueError(
                f"ModelConfig.interface: the {self.robot} offers {robot.interfaces}, not {self.interface!r}"
            )
        if self.hidden < 1 or self.heads < 1 or self.hidden % self.heads:
            raise ValueError(f"ModelConfig: hidden ({self.hidden}) must be a positive multiple of heads ({self.heads})")
        if self.head_hidden < 1:
            raise ValueError(f"ModelConfig.head_hidden must be >= 1, got {self.head_hidden}")
        if not self.action_scale > 0:
            raise ValueError(f"ModelConfig.action_scale must be > 0, got {self.action_scale}")
        if self.torque_action_scale is not None and not self.torque_action_scale > 0:
            raise ValueError(f"ModelConfig.torque_action_scale must be > 0 or None, got {self.torque_action_scale}")
        if self.interface not in ("accel", "torque", "control"):
            raise ValueError(f"ModelConfig.interface must be 'accel', 'torque' or 'control', got {self.interface!r}")
        if self.cbf_correction_bound is not None and not self.cbf_correction_bound > 0:
            raise ValueError(f"ModelConfig.cbf_correction_bound must be > 0 or None, got {self.cbf_correction_bound}")
        if self.cbf_head not in ("mlp", "edge_min"):
            raise ValueError(f"ModelConfig.cbf_head must be 'mlp' or 'edge_min', got {self.cbf_head!r}")
        if self.policy_head not in ("mlp", "edge_sum"):
            raise ValueError(f"ModelConfig.policy_head must be 'mlp' or 'edge_sum', got {self.policy_head!r}")
        if self.policy_head == "edge_sum" and self.interface == "torque":
            raise ValueError("ModelConfig.policy_head = 'edge_sum' needs interface 'accel' or 'control', not 'torque'")
        if not (self.policy_temperature > 0 and self.policy_free_distance > 0):
            raise ValueError("ModelConfig.policy_temperature and policy_free_distance must be > 0")
        if self.base_law not in BASE_LAWS:
            raise ValueError(f"ModelConfig.base_law must be one of {BASE_LAWS}, got {self.base_law!r}")
        if self.base_law != "nominal" and self.interface != "control":
            raise ValueError(
                f"ModelConfig.base_law = {self.base_law!r} needs interface 'control', not {self.interface!r}"
            )
        if not 0.0 < self.brisk_weight <= 1.0:
            raise ValueError(f"ModelConfig.brisk_weight must be in (0, 1], got {self.brisk_weight}")
        if self.brisk_weight != 1.0 and self.base_law == "nominal":
            raise ValueError("ModelConfig.brisk_weight blends towards the brisk law; base_law 'nominal' has none")
        if not self.accel_action_scale > 0:
            raise ValueError(f"ModelConfig.accel_action_scale must be > 0, got {self.accel_action_scale}")

    @property
    def action_dim(self) -> int:
        """Channels of the command (quadrotor: 3, acceleration, or 4, torque and thrust; unicycle: 2)."""
        return make_robot(self.robot).command_feature(self.interface).dim

    @property
    def action_scales(self) -> tuple[float, ...]:
        """The per-channel residual scale: ``(torque (3), thrust)`` in units of the actuator box, the
        acceleration residual's scale (3 equal channels, so scaling commutes with rotations) in ``accel_unit``, or
        ``action_scale`` on every channel of a ``"control"`` command (in units of the actuator box)."""
        if self.interface == "accel":
            return (self.accel_action_scale,) * 3
        if self.interface == "control":
            return (self.action_scale,) * self.action_dim
        t = self.action_scale if self.torque_action_scale is None else self.torque_action_scale
        return (t, t, t, self.action_scale)

    def to_dict(self) -> dict:
        return asdict(self)


class GraphEncoder(nn.Module):
    """The canonicalized graph transformer layer: ``SwarmGraph -> (M, hidden)`` invariant agent features.

    ``body_rates=False`` / ``attitude=False`` zero the node fields ``w`` / ``R`` (where the robot has them)."""

    def __init__(self, config: ModelConfig, body_rates: bool = True, goal_edges: bool = True, attitude: bool = True):
        super().__init__()
        self.robot = make_robot(config.robot)
        self.body_rates = body_rates
        self.attitude = attitude
        self.goal_edges = goal_edges
        self.edge_velocity = config.edge_velocity
        self.closest_approach = config.edge_closest_approach
        self.horizon = config.closest_approach_horizon
        self.group = make_group(config.group)
        if not isinstance(self.group, Trivial) and type(self.group) is not type(self.robot.group):
            raise ValueError(
                f"ModelConfig.group {config.group!r} is not the {self.robot.name}'s symmetry group "
                f"({self.robot.group_name!r}) or 'trivial'"
            )
        self.dim = self.robot.dim
        nt = self.robot.node_type(self.group)
        et = edge_type(self.group, self.edge_velocity, self.closest_approach, self.dim)
        self.masked_fields = [n for n, keep in (("w", body_rates), ("R", attitude)) if not keep and n in nt.names]
        self._node_type = nt
        out = FieldType(self.group, [Scalar(config.hidden)])
        canon = Canonicalize(
            self.group, in_type=(nt, nt), out_type=out, edge_type=et, mode="pair", self_loops=config.self_loops
        )
        self.layer = canon(GraphTransformerLayer(nt.dim, et.dim, config.hidden, config.heads))

    def forward(self, graph: SwarmGraph) -> Tensor:
        frames = frames_for(self.group, graph)
        x_src, x_dst = graph.x_src, graph.x_dst
        if self.masked_fields:
            # w is an invariant scalar block and the zero matrix is fixed by R -> Rz R: zeroing commutes with the action
            keep = torch.ones(self._node_type.dim, dtype=x_src.dtype, device=x_src.device)
            for name in self.masked_fields:
                keep[self._node_type.slice(name)] = 0
            x_src, x_dst = x_src * keep, x_dst * keep
        edge_index, edge_attr = graph.edge_index, graph.edge_attr
        if not self.goal_edges:  # an edge subset chosen by kind (an invariant): commutes with the group action
            sel = graph.edge_kind != KIND_GOAL
            edge_index, edge_attr = edge_index[:, sel], edge_attr[sel]
        if self.edge_velocity:  # world-frame velocities of sender and receiver (goals and hits: 0): a vector
            dv = graph.relative_velocity(edge_index).to(edge_attr.dtype)
            edge_attr = torch.cat((edge_attr, dv), -1)
            if self.closest_approach:
                edge_attr = torch.cat((edge_attr, closest_approach(edge_attr[:, : self.dim], dv, self.horizon)), -1)
        return self.layer((x_src, x_dst), edge_index, frames=frames, edge_attr=edge_attr)


class CBFNet(nn.Module):
    """The graph CBF ``h_i = tanh(m(M(G_i)))`` in ``(-1, 1)``: one invariant scalar per agent, ``(M,)``."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.encoder = GraphEncoder(
            config, body_rates=config.cbf_body_rates, goal_edges=config.cbf_goal_edges, attitude=config.cbf_attitude
        )
        if config.cbf_head == "edge_min":
            self.head = EdgeMinHead(
                self.encoder.group, config.hidden, config.head_hidden, config.cbf_distance,
                config.cbf_temperature, config.closest_approach_horizon, self.encoder.dim,
                correction_bound=config.cbf_correction_bound,
            )  # fmt: skip
        else:
            self.head = mlp([config.hidden, config.head_hidden, config.head_hidden, 1])

    def _value(self, graph: SwarmGraph) -> Tensor:
        z = self.encoder(graph)
        if self.config.cbf_head == "edge_min":
            return self.head(graph, z, frames_for(self.encoder.group, graph))
        return self.head(z).squeeze(-1)

    def raw(self, graph: SwarmGraph) -> Tensor:
        """The pre-``tanh`` value ``(M,)`` (mirror-averaged with ``cbf_z_symmetric``; averaged over each agent's
        frames when it has several, :meth:`egcbf.env.graph.SwarmGraph.expand_frames`)."""
        f = graph.frames_per_agent if not isinstance(self.encoder.group, Trivial) else 1
        if f > 1:
            return self.raw(graph.expand_frames()).view(-1, f).mean(1)
        out = self._value(graph)
        if self.config.cbf_z_symmetric:
            out = 0.5 * (out + self._value(graph.reflect_z()))
        return out

    def forward(self, graph: SwarmGraph) -> Tensor:
        return torch.tanh(self.raw(graph))


class PolicyNet(nn.Module):
    """The policy residual ``pi_i``: ``(M, 4)`` body-frame torque/thrust residual in ``[-1, 1]^4`` (``"torque"``),
    or ``(M, 3)`` world-frame acceleration residual ``psi_{g_i}(tanh(m(M(G_i))))`` (``"accel"``: the head's output
    is the residual in the agent's own frame, each component in ``[-1, 1]``, rotated back to the world by the
    agent's frame: a ``Vector(3)`` output of the group).

    The applied command is ``clip(c_nom + action_scales * pi)``: see :mod:`egcbf.algo.interface`.
    """

    def __init__(self, config: ModelConfig, action_dim: int | None = None):
        super().__init__()
        self.config = config
        self.encoder = GraphEncoder(config)
        feature = self.encoder.robot.command_feature(config.interface)
        if action_dim is not None and action_dim != feature.dim:
            feature = Scalar(action_dim)
        dim = feature.dim
        self.out_type = FieldType(self.encoder.group, [feature])
        self.head = mlp([config.hidden, config.head_hidden, config.head_hidden, dim])
        last = self.head[-1]
        with torch.no_grad():
            last.weight.mul_(config.policy_init_scale)
            last.bias.zero_()
        self.edge_head = None
        if config.policy_head == "edge_sum":
            self.edge_head = EdgeSumHead(
                self.encoder.group, config.hidden, config.head_hidden, config.policy_temperature,
                config.policy_free_distance, config.closest_approach_horizon, dim=self.encoder.dim,
                scalar_out=None if isinstance(feature, Vector) else dim,
            )  # fmt: skip

    def raw(self, graph: SwarmGraph) -> Tensor:
        """The pre-``tanh`` output ``(M, k)`` in the agents' own frames (one frame per agent)."""
        if graph.frames_per_agent > 1 and not isinstance(self.encoder.group, Trivial):
            raise ValueError("PolicyNet.raw is per frame: with several frames per agent, call the policy itself")
        z = self.encoder(graph)
        out = self.head(z)
        if self.edge_head is not None:
            out = out + self.edge_head(graph, z, frames_for(self.encoder.group, graph))
        return out

    def forward(self, graph: SwarmGraph) -> Tensor:
        f = graph.frames_per_agent if not isinstance(self.encoder.group, Trivial) else 1
        if f > 1:  # frame averaging: the world-frame outputs of each agent's frames, averaged
            out = self(graph.expand_frames())
            return out.view(-1, f, out.shape[-1]).mean(1)
        out = self.out_type.act(frames_for(self.encoder.group, graph), torch.tanh(self.raw(graph)))
        if self.config.policy_gate_isolated:
            out = out * sensing(graph).to(out.dtype)[:, None]
        return out


def sensing(graph: SwarmGraph) -> Tensor:
    """``(M,)`` bool: the agent has an incoming edge from another agent or a LiDAR hit."""
    sensed = (graph.edge_kind != KIND_GOAL).to(graph.edge_attr.dtype)
    count = graph.edge_attr.new_zeros(graph.num_dst).index_add(0, graph.edge_index[1], sensed)
    return count > 0  # a sum over the edges, not index_fill: traceable (egcbf.deploy.export)
