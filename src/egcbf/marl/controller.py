"""A trained MARL actor as a swarm controller: ``u, info = controller(state, env_config)``, as every controller of
:mod:`egcbf.control.controllers` (what ``egcbf eval`` and ``egcbf reproduce`` run).

Each agent's command is the actor's deterministic command (its mean, clipped to the box) on its own observation
(:func:`egcbf.env.observations.agent_observations`: its state and goal, its ``K`` nearest neighbours' states, its
LiDAR hits), so the controller is as decentralized as the actor. It reads the true state (``reads_sensing =
False``): the fault models' perceived states and messages are not passed to it.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from ..env.observations import NeighbourList, agent_observations
from .checkpoint import MarlTrainConfig, load_actor
from .networks import MarlActor

__all__ = ["MarlController", "load_marl_controller"]


class MarlController:
    """The actor ``actor`` (trained with ``config``) as a swarm controller (module doc)."""

    reads_sensing = False

    def __init__(self, actor: MarlActor, config: MarlTrainConfig):
        self.actor, self.config = actor, config
        self._neighbours: NeighbourList | None = None

    @torch.no_grad()
    def __call__(self, state, env_config) -> tuple[Tensor, dict]:
        radius = float(env_config.comm_radius)
        if self._neighbours is None or self._neighbours.radius != radius:
            self._neighbours = NeighbourList(radius, self.config.task.neighbour_skin * radius)
        scan = env_config.scan(state.positions, state.robot.heading(state.x), state.obstacles)
        p = next(self.actor.parameters())
        obs = agent_observations(state.x, state.goals, state.positions, scan, radius,
                                 self.config.task.max_neighbours, self._neighbours)  # fmt: skip
        obs = {k: v.to(device=p.device, dtype=p.dtype) if v.is_floating_point() else v.to(p.device)
               for k, v in obs.items()}  # fmt: skip
        u = self.actor.command(obs)
        return u.to(dtype=state.x.dtype, device=state.x.device), {}


def load_marl_controller(path: str | Path, *, device="cpu", dtype=torch.float32) -> MarlController:
    """The controller of the MARL checkpoint ``path``."""
    actor, config = load_actor(path, device=device, dtype=dtype)
    return MarlController(actor, config)
