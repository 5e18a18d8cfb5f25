"""One agent's learned controller from its own observations: what a robot runs on board.

The paper's controllers are trained centrally and executed distributed: each robot runs its own copy of the policy
on what it senses and hears. :class:`AgentController` is that copy, built from a checkpoint. One call takes one
agent's observation and returns its control; nothing swarm-sized is involved::

    ctrl = AgentController.from_checkpoint("checkpoints/egcbf+")
    u, info = ctrl(state, goal, neighbours, hits)   # u: (control_dim,) body control; info["command"]: (k,)

Inputs (world frame, SI units, float tensors of one dtype):

* ``state`` ``(S,)``: the agent's own state (quadrotor: ``[p, R row-major, v, w]``, 18 numbers);
* ``goal`` ``(d,)``: its goal position;
* ``neighbours`` ``(K, S)``: the states its neighbours broadcast (any K >= 0; the other agents', not its own). The
  policy reads those within the communication radius (squared distance strictly below ``comm_radius^2``, as in the
  simulator); farther ones are ignored. At most ``max_neighbours`` of them are used, the nearest (documented
  limit; the swarm evaluation has none, so beyond it the two differ: tested);
* ``hits`` ``(H, d)``: its LiDAR hit points (any H >= 0). Those farther than the LiDAR range the policy was trained
  with (``env_config.resolved_lidar_range``; the simulator's rays end there) are ignored, and at most ``max_hits``,
  the nearest, are used (the simulator keeps ``lidar_max_hits`` per agent, 16 by default).

A neighbour or hit row holding NaN or inf (a corrupt message) is dropped, not used, and counted; a non-finite
``state`` or ``goal`` raises.

Output: the body control ``u`` (quadrotor: torque and thrust, through the attitude loop of the checkpoint's command
interface), and ``info`` with ``"command"`` (the policy's command in the interface's units), ``"num_neighbours"``,
``"num_hits"`` (how many were used), ``"dropped_neighbours"``, ``"dropped_hits"`` (in range but beyond the
``max_neighbours`` / ``max_hits`` slots; the first time this happens a warning says so) and
``"rejected_neighbours"``, ``"rejected_hits"`` (non-finite rows).

How: the network has one message-passing layer, so an agent's output reads only its own incoming edges (its
neighbours, its goal, its hits). :class:`AgentPolicy` is that computation with **fixed shapes**: exactly
``max_neighbours`` neighbour rows and ``max_hits`` hit rows, each with a validity mask. Its graph has two
receivers, the agent and a sink: every neighbour, goal and hit is an edge, valid ones into the agent and masked
ones (and neighbours out of range) into the sink, whose output is dropped. So the masked rows change nothing, the
tensor shapes never depend on the data, and the same module is what :mod:`egcbf.deploy.export` writes to TorchScript and
ONNX. :class:`AgentController` pads a variable-size observation into it (the nearest rows first). It is the same
computation as the swarm-level :class:`egcbf.algo.learner.LearnedController` for that agent
(``tests/egcbf/test_deploy.py``: every agent of random scenes within 1e-9 in float64).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from ..algo.interface import make_interface
from ..algo.learner import policy_command
from ..env import EnvConfig
from ..env.graph import KIND_AGENT, KIND_GOAL, KIND_HIT, SwarmGraph, agent_features, edge_vectors, static_features
from ..nn import ModelConfig, PolicyNet
from ..robots import Robot

if TYPE_CHECKING:
    from ..control.filters import FilterConfig

__all__ = ["AgentController", "AgentFilteredController", "AgentPolicy"]


class AgentPolicy(nn.Module):
    """One agent's policy on fixed-shape inputs (module doc): traceable, exportable, no data-dependent shapes.

    ``forward(state (S,), goal (d,), neighbours (K, S), neighbour_valid (K,) bool, hits (H, d), hit_valid (H,) bool)
    -> (u (control_dim,), command (k,))`` with ``K = max_neighbours`` and ``H = max_hits`` fixed at construction.
    A neighbour row is used if it is valid and its squared distance to the agent is strictly below
    ``comm_radius^2``; a hit row if it is valid and within ``lidar_range`` (``None``: ``comm_radius``) of the agent.
    Invalid rows may hold any finite numbers.
    """

    def __init__(self, policy: PolicyNet, model_config: ModelConfig, robot: Robot, comm_radius: float,
                 max_neighbours: int, max_hits: int, lidar_range: float | None = None):  # fmt: skip
        super().__init__()
        for name, v in (("max_neighbours", max_neighbours), ("max_hits", max_hits)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"AgentPolicy.{name} must be an integer >= 0, got {v!r}")
        self.policy, self.model_config, self.robot = policy, model_config, robot
        self.interface = make_interface(model_config.interface, robot)
        self.comm_radius = float(comm_radius)
        self.lidar_range = self.comm_radius if lidar_range is None else float(lidar_range)
        if not 0 < self.lidar_range <= self.comm_radius:
            raise ValueError(f"AgentPolicy.lidar_range must be in (0, comm_radius = {self.comm_radius:g}], got "
                             f"{lidar_range!r}")  # fmt: skip
        self.max_neighbours, self.max_hits = max_neighbours, max_hits

    @property
    def hit_reach(self) -> float:
        """The farthest hit used: ``lidar_range`` and a relative 1e-6 (a hit the simulator's ray finds at exactly
        its length lies there up to rounding)."""
        return self.lidar_range * (1 + 1e-6)

    def graph(self, state: Tensor, goal: Tensor, neighbours: Tensor, neighbour_valid: Tensor, hits: Tensor,
              hit_valid: Tensor) -> tuple[SwarmGraph, Tensor, Tensor]:  # fmt: skip
        """The agent's graph (receivers: the agent, the sink), the receivers' states ``(1, 2, S)`` and goals
        ``(1, 2, d)``. Senders: the two receivers, the ``K`` neighbours, the goal, the ``H`` hits (only
        ``edge_index`` says who sends to whom: the networks read nothing else of the layout)."""
        robot, k, h = self.robot, self.max_neighbours, self.max_hits
        dev = state.device
        x = torch.stack((state, state))  # the agent and the sink (a copy: finite features, output dropped)
        p = robot.positions(x)
        p_nbr = robot.positions(neighbours)
        in_range = neighbour_valid & ((p_nbr - p[:1]).square().sum(-1) < self.comm_radius**2)
        hit_valid = hit_valid & (torch.linalg.vector_norm(hits.to(p.dtype) - p[:1], dim=-1) <= self.hit_reach)
        feat = agent_features(robot, x)
        x_src = torch.cat((feat, agent_features(robot, neighbours), static_features(1, KIND_GOAL, feat),
                           static_features(h, KIND_HIT, feat)))  # fmt: skip
        pos_src = torch.cat((p, p_nbr, goal[None].to(p.dtype), hits.to(p.dtype)))
        sink = torch.ones((), dtype=torch.long, device=dev)
        zero = torch.zeros((), dtype=torch.long, device=dev)
        senders = torch.arange(2, 2 + k + 1 + h, device=dev)
        receivers = torch.cat((torch.where(in_range, zero, sink), zero[None], torch.where(hit_valid, zero, sink)))
        edge_index = torch.stack((senders, receivers))
        kinds = (KIND_AGENT,) * (2 + k) + (KIND_GOAL,) + (KIND_HIT,) * h
        src_kind = torch.tensor(kinds, dtype=torch.long, device=dev)
        edge_kind = src_kind[2:]
        graph = SwarmGraph(
            x_src=x_src, x_dst=feat, edge_index=edge_index,
            edge_attr=edge_vectors(pos_src, p, edge_index, edge_kind, self.comm_radius), edge_kind=edge_kind,
            frames=robot.frames(x), pos_src=pos_src, pos_dst=p, src_kind=src_kind,
            batch=torch.zeros(2, dtype=torch.long, device=dev), src_batch=torch.zeros_like(src_kind),
            hit_owner=torch.zeros(h, dtype=torch.long, device=dev), num_envs=1, num_agents=2,
            comm_radius=self.comm_radius, robot=robot,
        )  # fmt: skip
        return graph, x[None], torch.stack((goal, goal))[None].to(x.dtype)

    def forward(self, state: Tensor, goal: Tensor, neighbours: Tensor, neighbour_valid: Tensor, hits: Tensor,
                hit_valid: Tensor) -> tuple[Tensor, Tensor]:  # fmt: skip
        graph, x, goals = self.graph(state, goal, neighbours, neighbour_valid, hits, hit_valid)
        command, _ = policy_command(self.policy, self.model_config, self.interface, graph, x, goals)
        u = self.interface.apply(x[:, :1], command[:, :1])  # as egcbf.algo.learner.act, for the agent only
        return u[0, 0], command[0, 0]


@dataclass
class AgentController:
    """A learned policy as one agent's controller (module doc): pads a variable-size observation into
    :attr:`module`, the fixed-shape :class:`AgentPolicy`. ``env_config`` carries the sensing settings the policy was
    trained with (communication radius, LiDAR range)."""

    policy: PolicyNet
    model_config: ModelConfig
    env_config: EnvConfig
    max_neighbours: int = 64
    max_hits: int = 16

    def __post_init__(self) -> None:
        env = self.env_config
        m = self.max_neighbours
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(f"AgentController.max_neighbours must be an integer >= 1 (a controller that hears no "
                             f"neighbour would not avoid them), got {m!r}")  # fmt: skip
        self.module = AgentPolicy(self.policy, self.model_config, env.make_robot(), env.comm_radius,
                                  self.max_neighbours, self.max_hits, env.resolved_lidar_range)  # fmt: skip
        if self.max_hits > env.lidar_max_hits:
            warnings.warn(f"AgentController: max_hits = {self.max_hits} exceeds the {env.lidar_max_hits} LiDAR hits "
                          "per agent the policy was trained with: it will read more hits than it ever saw",
                          stacklevel=3)  # fmt: skip
        self._warned_truncation = False

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        *,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        max_neighbours: int = 64,
        max_hits: int | None = None,
    ) -> AgentController:
        """The controller of a checkpoint directory (or run directory: its ``best/``), loaded safely; ``max_hits``
        defaults to the training environment's ``lidar_max_hits``."""
        from ..control.resolve import POLICY, resolve

        built = resolve(POLICY, path, device=device, dtype=dtype)
        learned, train_cfg = built.controller, built.train_config
        env = EnvConfig.for_robot(train_cfg.robot, num_agents=1, **dict(train_cfg.env_overrides))
        hits = env.lidar_max_hits if max_hits is None else max_hits
        return cls(learned.policy, learned.model_config, env, max_neighbours=max_neighbours, max_hits=hits)

    @property
    def robot(self) -> Robot:
        return self.module.robot

    def _check(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor) -> None:
        s, d = self.robot.state_dim, self.robot.dim
        for name, t, shape in (("state", state, (s,)), ("goal", goal, (d,))):
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(f"{name} must be a tensor of shape {shape}, got {got}")
        for name, t, width in (("neighbours", neighbours, s), ("hits", hits, d)):
            if not isinstance(t, Tensor) or t.dim() != 2 or t.shape[1] != width:
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(f"{name} must be a tensor of shape (K, {width}) (K >= 0), got {got}")
        for name, t in (("state", state), ("goal", goal)):
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} holds NaN or inf")
        try:  # the simulator's own check: a quadrotor's attitude must be a rotation (not zeros, not 2 I)
            self.robot.check_state(state[None].to(torch.float64))
        except ValueError as err:
            raise ValueError(f"state: {err}") from None

    def pad(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor) -> tuple[Tensor, ...]:
        """The fixed-shape inputs of :attr:`module`: ``(state, goal, neighbours (max_neighbours, S),
        neighbour_valid, hits (max_hits, d), hit_valid)``, the nearest in-range neighbours and the nearest in-range
        hits first, the remaining rows zero and invalid (non-finite rows dropped)."""
        return self._select(state, goal, neighbours, hits)[0]

    def _select(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor) -> tuple[tuple[Tensor, ...], dict]:
        """:meth:`pad`'s inputs and the counts of rows dropped (beyond the slots) and rejected (non-finite)."""
        self._check(state, goal, neighbours, hits)
        robot, env = self.robot, self.env_config
        p = next(self.policy.parameters())
        state, goal, neighbours, hits = (t.to(device=p.device, dtype=p.dtype) for t in (state, goal, neighbours, hits))
        finite_n, finite_h = torch.isfinite(neighbours).all(-1), torch.isfinite(hits).all(-1)
        counts = {"rejected_neighbours": int((~finite_n).sum()), "rejected_hits": int((~finite_h).sum())}
        neighbours, hits = neighbours[finite_n], hits[finite_h]
        pos = robot.positions(state)
        d2 = (robot.positions(neighbours) - pos).square().sum(-1)
        order = torch.argsort(d2)
        heard = order[d2[order] < env.comm_radius**2]
        hit_d = torch.linalg.vector_norm(hits - pos, dim=-1)
        hit_order = torch.argsort(hit_d)
        seen = hit_order[hit_d[hit_order] <= self.module.hit_reach]
        order, hit_order = heard[: self.max_neighbours], seen[: self.max_hits]
        counts["dropped_neighbours"] = int(heard.shape[0] - order.shape[0])
        counts["dropped_hits"] = int(seen.shape[0] - hit_order.shape[0])
        if (counts["dropped_neighbours"] or counts["dropped_hits"]) and not self._warned_truncation:
            self._warned_truncation = True
            warnings.warn(f"AgentController: {counts['dropped_neighbours']} neighbour(s) and {counts['dropped_hits']} "
                          f"hit(s) in range beyond the max_neighbours = {self.max_neighbours} / max_hits = "
                          f"{self.max_hits} slots were dropped (the nearest are kept; info counts them every call)",
                          stacklevel=3)  # fmt: skip
        near, kept = neighbours[order], hits[hit_order]
        k, h = self.max_neighbours, self.max_hits
        nbr = neighbours.new_zeros(k, neighbours.shape[1])
        nbr[: near.shape[0]] = near
        pts = hits.new_zeros(h, hits.shape[1])
        pts[: kept.shape[0]] = kept
        nbr_valid = torch.arange(k, device=p.device) < near.shape[0]
        hit_valid = torch.arange(h, device=p.device) < kept.shape[0]
        return (state, goal, nbr, nbr_valid, pts, hit_valid), counts

    @torch.no_grad()
    def __call__(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor) -> tuple[Tensor, dict]:
        """The agent's body control ``(control_dim,)`` and ``info`` (module doc)."""
        inputs, counts = self._select(state, goal, neighbours, hits)
        u, command = self.module(*inputs)
        return u, {"command": command, "num_neighbours": int(inputs[3].sum()), "num_hits": int(inputs[5].sum()),
                   **counts}  # fmt: skip


@dataclass
class AgentFilteredController:
    """One agent's policy behind the decentralized ``dcbf`` run-time filter (:mod:`egcbf.control.filters`,
    docs/safety_filters.md): what the recommended controller runs on board.

    ``u, info = ctrl(state, goal, neighbours, hits, obstacles=(centers (O, 3), radii (O,)), accelerations=None)``.
    The policy reads ``neighbours`` and ``hits`` as :class:`AgentController` does. The filter reads the neighbours'
    states (pass every neighbour heard: it keeps those within its range at the look-ahead positions, as the swarm
    filter does; in simulation without message faults that filter also counts a neighbour not yet within radio
    range but within range at the look-ahead positions, :mod:`egcbf.control.filters`), the sphere obstacles the agent
    senses, and, for the look-ahead, ``accelerations`` ``(1 + K, 3)``: the agent's own and each neighbour's realized
    acceleration over the last control step, ``(v_t - v_{t-1}) / dt`` from two consecutive broadcasts (``None``:
    zero, as at an episode's first step). It solves the agent's own QP
    only in effect (the rows of a pair are split in halves; no command is exchanged).

    ``info``: ``command`` (the filtered command, interface units), ``policy_command``, ``failed`` (the QP failed
    and the agent brakes), ``slack`` (the QP's slack), ``num_neighbours``, ``num_hits``.
    """

    controller: AgentController
    filter_config: FilterConfig | None = None

    def __post_init__(self) -> None:
        from ..control.filters import FilterConfig
        from ..robots.quadrotor.dcbf_qp import DecentralizedCBFQP

        self.filter_config = self.filter_config or FilterConfig.for_kind("dcbf")
        cfg = self.filter_config
        if cfg.kind != "dcbf":
            raise NotImplementedError(f"the per-agent controller runs the 'dcbf' filter, not {cfg.kind!r}")
        if self.controller.model_config.interface != "accel":
            raise ValueError("run-time filters act on the acceleration command (the 'accel' interface)")
        self._qp = DecentralizedCBFQP(barrier=cfg.barrier, penalty=cfg.penalty, brake_gain=cfg.brake_gain)

    @property
    def robot(self) -> Robot:
        return self.controller.robot

    @property
    def env_config(self) -> EnvConfig:
        """The sensing settings and control period the policy was trained with."""
        return self.controller.env_config

    @classmethod
    def from_checkpoint(cls, path: str | Path, filter_config: FilterConfig | None = None, **kwargs):
        """The checkpoint's :class:`AgentController` (``kwargs`` as there) behind ``filter_config`` (default:
        ``FilterConfig.for_kind("dcbf")``, the evaluation's ``--filter dcbf``)."""
        return cls(AgentController.from_checkpoint(path, **kwargs), filter_config)

    @torch.no_grad()
    def __call__(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor,
                 obstacles: tuple[Tensor, Tensor] | None = None,
                 accelerations: Tensor | None = None) -> tuple[Tensor, dict]:  # fmt: skip
        from ..env import SwarmState
        from ..env.obstacles import Obstacles

        ctrl, robot = self.controller, self.controller.robot
        _, info = ctrl(state, goal, neighbours, hits)
        unit = ctrl.module.interface.accel_unit
        dtype = info["command"].dtype
        k = neighbours.shape[0]
        if accelerations is not None and tuple(accelerations.shape) != (1 + k, robot.dim):
            raise ValueError(f"accelerations must have shape {(1 + k, robot.dim)} (the agent, then each neighbour), "
                             f"got {tuple(accelerations.shape)}")  # fmt: skip
        finite = torch.isfinite(neighbours).all(-1)  # a corrupt message: dropped here as the policy drops it
        if accelerations is not None:
            if not bool(torch.isfinite(accelerations[0]).all()):
                raise ValueError("accelerations[0] (the agent's own) holds NaN or inf")
            finite = finite & torch.isfinite(accelerations[1:]).all(-1)
            accelerations = torch.cat((accelerations[:1], accelerations[1:][finite]))
        neighbours = neighbours[finite]
        k = neighbours.shape[0]
        x = torch.cat((state[None], neighbours)).to(torch.float64)
        centers, radii = obstacles if obstacles is not None else (x.new_zeros(0, robot.dim), x.new_zeros(0))
        if centers.dim() != 2 or centers.shape[-1] != robot.dim or tuple(radii.shape) != (centers.shape[0],):
            raise ValueError(f"obstacles must be (centers (O, {robot.dim}), radii (O,)), got "
                             f"{tuple(centers.shape)}, {tuple(radii.shape)}")  # fmt: skip
        if not (bool(torch.isfinite(centers).all()) and bool(torch.isfinite(radii).all())):
            raise ValueError("obstacles hold NaN or inf")
        goals = torch.cat((goal[None].to(x.dtype), robot.positions(x[1:])))
        swarm = SwarmState(x[None], goals[None], Obstacles(centers[None].to(x.dtype), radii[None].to(x.dtype)),
                           robot=robot)  # fmt: skip
        a_ref = torch.zeros(1, 1 + k, robot.dim, dtype=torch.float64)
        a_ref[0, 0] = unit * info["command"].to(torch.float64).cpu()
        acc = None if accelerations is None else accelerations.to(torch.float64).cpu().numpy()[None]
        cfg = self.filter_config
        u, q = self._qp.filter(swarm, ctrl.env_config, a_ref.numpy(), cfg.lookahead, acc)
        command = torch.as_tensor(q["a_safe"][0, 0] / unit, dtype=dtype)
        return u[0, 0].to(dtype), {
            "command": command, "policy_command": info["command"], "failed": bool(q["failed"][0, 0]),
            "slack": float(q["slack"][0, 0]),
            **{key: info[key] for key in ("num_neighbours", "num_hits", "dropped_neighbours", "dropped_hits",
                                          "rejected_neighbours", "rejected_hits")},
        }  # fmt: skip
