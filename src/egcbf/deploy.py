"""One agent's learned controller from its own observations: what a robot runs on board (issue 28, part 1).

The paper's controllers are trained centrally and executed distributed: each robot runs its own copy of the policy
on what it senses and hears. :class:`AgentController` is that copy, built from a checkpoint. One call takes one
agent's observation and returns its control; nothing swarm-sized is involved::

    ctrl = AgentController.from_checkpoint("checkpoints/egcbf+")
    u, info = ctrl(state, goal, neighbours, hits)   # u: (control_dim,) body control; info["command"]: (k,)

Inputs (world frame, SI units, float tensors of one dtype):

* ``state`` ``(S,)``: the agent's own state (quadrotor: ``[p, R row-major, v, w]``, 18 numbers);
* ``goal`` ``(d,)``: its goal position;
* ``neighbours`` ``(K, S)``: the states its neighbours broadcast (any K >= 0). The policy reads those within the
  communication radius (strictly closer than ``comm_radius``, as in the simulator); farther ones are ignored.
  At most ``max_neighbours`` of them are used, the nearest (documented limit; the swarm evaluation has none, so
  beyond it the two differ: tested);
* ``hits`` ``(H, d)``: its LiDAR hit points (any H >= 0; at most ``max_hits``, the nearest, are used; the
  simulator keeps ``lidar_max_hits`` per agent, 16 by default).

Output: the body control ``u`` (quadrotor: torque and thrust, through the attitude loop of the checkpoint's command
interface), and ``info`` with ``"command"`` (the policy's command, e.g. the desired acceleration) and
``"num_neighbours"``, ``"num_hits"`` (how many were used).

How: the network has one message-passing layer, so an agent's output reads only its own incoming edges (its
neighbours, its goal, its hits). The call builds the graph of the agent and its in-range neighbours alone and
keeps the agent's edges (:meth:`egcbf.graph.SwarmGraph.with_receivers`): the same computation as the swarm-level
:class:`egcbf.algo.learner.LearnedController` for that agent (``tests/egcbf/test_deploy.py``: every agent of
random scenes within 1e-9 in float64). Run-time filters, export (TorchScript, ONNX) and fixed-shape inputs are the
issue's next parts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .algo.interface import make_interface
from .algo.learner import policy_command
from .env import EnvConfig, SwarmState
from .env.lidar import LidarScan
from .env.obstacles import Obstacles
from .graph import build_graph
from .nn import ModelConfig, PolicyNet
from .robots import Robot

__all__ = ["AgentController"]


@dataclass
class AgentController:
    """A learned policy as one agent's controller (module doc). ``env_config`` carries the sensing settings the
    policy was trained with (communication radius, LiDAR range)."""

    policy: PolicyNet
    model_config: ModelConfig
    env_config: EnvConfig
    max_neighbours: int = 64
    max_hits: int = 16

    def __post_init__(self) -> None:
        for name in ("max_neighbours", "max_hits"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"AgentController.{name} must be an integer >= 0, got {v!r}")

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
        from .checkpoint import load_controller

        learned, train_cfg = load_controller(path, device=device, dtype=dtype)
        env = EnvConfig.for_robot(train_cfg.robot, num_agents=1, **dict(train_cfg.env_overrides))
        hits = env.lidar_max_hits if max_hits is None else max_hits
        return cls(learned.policy, learned.model_config, env, max_neighbours=max_neighbours, max_hits=hits)

    @property
    def robot(self) -> Robot:
        return self.env_config.make_robot()

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
        for name, t in (("state", state), ("goal", goal), ("neighbours", neighbours), ("hits", hits)):
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} holds NaN or inf")

    @torch.no_grad()
    def __call__(self, state: Tensor, goal: Tensor, neighbours: Tensor, hits: Tensor) -> tuple[Tensor, dict]:
        """The agent's body control ``(control_dim,)`` and ``info`` (module doc)."""
        self._check(state, goal, neighbours, hits)
        robot = self.robot
        p = next(self.policy.parameters())
        state, goal, neighbours, hits = (t.to(device=p.device, dtype=p.dtype) for t in (state, goal, neighbours, hits))
        pos = robot.positions(state)
        # the neighbours in range (strict, as the simulator's edges), the nearest max_neighbours of them
        dist = torch.linalg.vector_norm(robot.positions(neighbours) - pos, dim=-1)
        order = torch.argsort(dist)
        order = order[dist[order] < self.env_config.comm_radius][: self.max_neighbours]
        near = neighbours[order]
        kept_hits = hits[torch.argsort(torch.linalg.vector_norm(hits - pos, dim=-1))][: self.max_hits]
        n = 1 + near.shape[0]
        x = torch.cat((state[None], near))[None]  # (1, n, S): the agent is row 0
        # the neighbours' goals, obstacles and hits do not reach the agent's output: placeholders
        goals = torch.cat((goal[None], robot.positions(near)))[None]
        d = robot.dim
        obstacles = Obstacles(x.new_zeros(1, 0, d), x.new_zeros(1, 0))
        swarm = SwarmState(x, goals, obstacles, robot=robot)
        h = kept_hits.shape[0]
        points = x.new_zeros(1, n, max(h, 1), d) + robot.positions(x)[:, :, None]
        valid = torch.zeros(1, n, max(h, 1), dtype=torch.bool, device=x.device)
        points[0, 0, :h] = kept_hits
        valid[0, 0, :h] = True
        distance = torch.where(valid, torch.linalg.vector_norm(points - robot.positions(x)[:, :, None], dim=-1),
                               torch.full_like(valid, float("inf"), dtype=x.dtype))  # fmt: skip
        lidar = LidarScan(points, valid, distance)
        keep = torch.zeros(n, dtype=torch.bool, device=x.device)
        keep[0] = True
        graph = build_graph(swarm, self.env_config, lidar=lidar).with_receivers(keep)
        itf = make_interface(self.model_config.interface, robot)
        command, _ = policy_command(self.policy, self.model_config, itf, graph, x, goals)
        u = itf.apply(x, command)  # as egcbf.algo.learner.act: the command through the robot's inner loop
        return u[0, 0], {"command": command[0, 0], "num_neighbours": int(near.shape[0]), "num_hits": int(h)}
