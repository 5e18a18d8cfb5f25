"""What the agents perceive under faults: their LiDAR scans and the messages on the graph's edges.

A :class:`Sensing` rides on the observed :class:`egcbf.env.SwarmState` that :class:`egcbf.faults.FaultProcess` hands
to the controller (``state.sensing``); :func:`egcbf.graph.build_graph` takes the scan from :meth:`Sensing.scan` and
passes the graph it built through :meth:`Sensing.messages`. So every controller that builds its graph from the state
(the learned policies and the filters around them) perceives the faults, with no change to the controller.

* **LiDAR**: the rays are cast from the agents' *true* positions and headings (a sensor measures the world as it
  is) and placed around the agents' *estimated* positions (where the agent believes it is); each range gets its
  Gaussian error (``lidar_noise``) and each return is lost with probability ``lidar_drop``.
* **Messages**: an agent-to-agent edge carries the sender's broadcast estimate; with ``msg_delay = k`` it is the
  estimate of ``k`` steps ago (sender features and position), and the edge vector is that position minus the
  receiver's current estimate; an edge whose delayed neighbour lies outside the communication radius is dropped, and
  each edge is lost with probability ``msg_loss`` in each step.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..env.config import EnvConfig
from ..env.lidar import LidarScan
from ..env.obstacles import Obstacles
from ..env.swarm import cast_lidar
from ..graph import KIND_AGENT, SwarmGraph, agent_features, edge_vectors
from ..robots import Robot
from . import draws
from .spec import FaultConfig

__all__ = ["STREAMS", "Sensing"]

#: the random streams of the faults (the second number of every draw's address; :mod:`egcbf.faults.draws`)
STREAMS = {"pos": 1, "vel": 2, "loss": 3, "lidar": 4, "lidar_drop": 5, "gain": 6, "bias": 7, "noncoop": 8,
           "gust": 9}  # fmt: skip


@dataclass
class Sensing:
    """The perception of one step (see the module doc).

    Attributes:
        faults: the fault levels.
        robot: the agents' robot.
        seeds: ``(B,)`` int64, the episode seed of each environment (the root of every draw's address).
        t: the step.
        x_true: ``(B, N, S)`` the true states (where the rays start).
        x_seen: ``(B, N, S)`` the agents' estimates (what they broadcast and where they place their scans).
        x_sent: ``(B, N, S)`` the estimates the messages of this step carry (``x_seen`` of ``msg_delay`` steps ago).
        obstacles: the true obstacles.
    """

    faults: FaultConfig
    robot: Robot
    seeds: Tensor
    t: int
    x_true: Tensor
    x_seen: Tensor
    x_sent: Tensor
    obstacles: Obstacles

    # -------------------------------------------------------------------------------------------------- LiDAR
    def scan(self, config: EnvConfig) -> LidarScan:
        """The scan the agents get: cast from the true poses, placed around the estimates, with range errors and
        lost returns (dtype of the estimates)."""
        robot, f = self.robot, self.faults
        truth = cast_lidar(config, robot.positions(self.x_true), robot.heading(self.x_true), self.obstacles)
        p_true = robot.positions(self.x_true)[:, :, None]
        p_seen = robot.positions(self.x_seen)[:, :, None].to(truth.points.dtype)
        rel = truth.points - p_true
        distance = truth.distance
        valid = truth.valid
        if f.lidar_noise > 0 or f.lidar_drop > 0:
            b, n, h = valid.shape
            address = (self.seeds.view(b, 1, 1), self.t, _arange(n, valid).view(1, n, 1), _arange(h, valid))
        if f.lidar_noise > 0:
            r = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
            err = f.lidar_noise * draws.normal(STREAMS["lidar"], *address, dtype=r.dtype)[..., None]
            noisy = (r + err).clamp_min(0)
            rel = torch.where(r > 0, rel * noisy / r.clamp_min(1e-12), rel)
            distance = torch.where(valid, noisy[..., 0], distance)
        if f.lidar_drop > 0:
            valid = valid & (draws.uniform(STREAMS["lidar_drop"], *address) >= f.lidar_drop)
            distance = torch.where(valid, distance, torch.full_like(distance, float("inf")))
        points = torch.where(valid[..., None], p_seen + rel, p_seen.expand_as(rel))
        dtype = self.x_seen.dtype
        return LidarScan(points.to(dtype), valid, distance.to(dtype))

    # ----------------------------------------------------------------------------------------------- messages
    def messages(self, graph: SwarmGraph) -> SwarmGraph:
        """``graph`` (built from the estimates) with its agent-to-agent edges as the messages arrive: delayed
        senders, out-of-range and lost messages dropped."""
        f = self.faults
        if f.msg_delay == 0 and f.msg_loss == 0:
            return graph
        m, n = graph.num_dst, graph.num_agents
        src, dst = graph.edge_index
        agent_edge = graph.edge_kind == KIND_AGENT
        keep = torch.ones_like(agent_edge)
        x_src, pos_src = graph.x_src, graph.pos_src
        if f.msg_delay > 0:
            sent = self.x_sent.reshape(m, -1).to(x_src.dtype)
            x_src = torch.cat((agent_features(self.robot, sent), x_src[m:]))
            pos_src = torch.cat((self.robot.positions(sent), pos_src[m:]))
            gap = torch.linalg.vector_norm(pos_src[src] - graph.pos_dst[dst], dim=-1)
            keep &= ~agent_edge | (gap < graph.comm_radius)
        if f.msg_loss > 0:
            env = dst // n
            lost = draws.uniform(STREAMS["loss"], self.seeds.to(dst.device)[env], self.t, dst % n, src % n) < f.msg_loss
            keep &= ~(agent_edge & lost)
        edge_index = graph.edge_index[:, keep]
        edge_kind = graph.edge_kind[keep]
        edge_attr = edge_vectors(pos_src, graph.pos_dst, edge_index, edge_kind, graph.comm_radius)
        return replace(graph, x_src=x_src, pos_src=pos_src, edge_index=edge_index, edge_kind=edge_kind,
                       edge_attr=edge_attr)  # fmt: skip


def _arange(n: int, like: Tensor) -> Tensor:
    return torch.arange(n, device=like.device)
