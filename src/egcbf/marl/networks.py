"""The per-agent actor and critic of the MARL baselines, over each agent's own observation.

Input: the observation dictionary of :func:`egcbf.env.observations.agent_observations` (``(B, N, ...)`` tensors,
world frame). Features, all translation-invariant (positions only as offsets, in communication radii):

* the agent's own ``Robot.agent_features(x)`` (quadrotor: velocity, attitude, body rates), its goal offset
  ``g - p`` (rescaled to norm <= 1) and the goal distance (clipped at 1);
* each neighbour row: its offset ``p_j - p_i`` and its ``agent_features``; each LiDAR hit: ``h - p``.

Neighbour and hit rows are encoded by one MLP each and pooled (masked mean and max: the output does not depend on
the rows' order or on masked rows); the pools and the own features go through a head MLP. All agents share the
parameters (IPPO).

The actor acts on a *command interface* (:mod:`egcbf.algo.interface`), the one the learned CBF methods use: for the
quadrotor a normalized world acceleration tracked by the attitude loop (``"accel"``), for the other robots their
normalized raw control (``"control"``). Its mean command is the interface's nominal command plus a bounded residual,
``loc = n(x, g) + residual_scale * w * tanh(head)`` (``w`` the half-widths of the interface's command box), so that
a new actor starts as the nominal controller; its standard deviations ``exp(log_std) * w`` are state-independent.
:meth:`MarlActor.to_control` turns a command into the robot's body control (clipped to the command's bounds, then
the interface's ``apply``): what the environment steps with.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn

from ..algo.interface import CommandInterface
from ..robots import Robot

__all__ = ["MarlActor", "MarlCritic", "MarlNetConfig", "observation_features"]


@dataclass(frozen=True)
class MarlNetConfig:
    """Sizes of the actor and critic: ``hidden`` units per layer; the residual's scale (in box half-widths); the
    initial log standard deviation (in box half-widths)."""

    hidden: int = 64
    residual_scale: float = 1.0
    initial_log_std: float = -1.5

    def to_dict(self) -> dict:
        return asdict(self)


def observation_features(robot: Robot, comm_radius: float, obs: dict[str, Tensor]) -> tuple[Tensor, ...]:
    """``own (B, N, F)``, ``neighbours (B, N, K, d + A)``, ``neighbour_mask (B, N, K)``, ``hits (B, N, H, d)``,
    ``hit_mask (B, N, H)`` (module doc; ``A`` = the width of ``agent_features``)."""
    x, goal = obs["state"], obs["goal"]
    p = robot.positions(x)
    scale = 1.0 / float(comm_radius)
    offset = (goal.to(p.dtype) - p) * scale
    dist = torch.linalg.vector_norm(offset, dim=-1, keepdim=True)
    own = torch.cat((robot.agent_features(x), offset / dist.clamp_min(1.0), dist.clamp(max=1.0)), -1)
    nbr = obs["neighbours"]
    nbr_feat = torch.cat(((robot.positions(nbr) - p[..., None, :]) * scale, robot.agent_features(nbr)), -1)
    hits = (obs["hits"].to(p.dtype) - p[..., None, :]) * scale
    return own, nbr_feat, obs["neighbour_mask"], hits, obs["hit_mask"]


def _mlp(width_in: int, hidden: int, width_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(width_in, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                         nn.Linear(hidden, width_out))  # fmt: skip


def _pool(rows: Tensor, mask: Tensor) -> Tensor:
    """Masked mean and max over the row axis ``-2`` of ``rows`` ``(..., R, C)``: ``(..., 2 C)`` (zeros without
    a valid row)."""
    m = mask[..., None].to(rows.dtype)
    count = m.sum(-2)
    mean = (rows * m).sum(-2) / count.clamp_min(1.0)
    low = torch.finfo(rows.dtype).min
    peak = torch.where(mask[..., None], rows, torch.full((), low, dtype=rows.dtype, device=rows.device)).amax(-2)
    peak = torch.where(count > 0, peak, torch.zeros((), dtype=rows.dtype, device=rows.device))
    return torch.cat((mean, peak), -1)


class _Trunk(nn.Module):
    """Own features, pooled neighbour and hit encodings, and a head with ``width_out`` outputs per agent."""

    def __init__(self, robot: Robot, comm_radius: float, hidden: int, width_out: int):
        super().__init__()
        self.robot, self.comm_radius = robot, float(comm_radius)
        a = robot.agent_features(torch.zeros(1, robot.state_dim)).shape[-1]
        d = robot.dim
        self.neighbour_encoder = _mlp(d + a, hidden, hidden)
        self.hit_encoder = _mlp(d, hidden, hidden)
        self.head = _mlp(a + d + 1 + 4 * hidden, hidden, width_out)

    def forward(self, obs: dict[str, Tensor]) -> Tensor:
        own, nbr, nbr_mask, hits, hit_mask = observation_features(self.robot, self.comm_radius, obs)
        dtype = self.head[0].weight.dtype
        pooled_n = _pool(self.neighbour_encoder(nbr.to(dtype)), nbr_mask)
        pooled_h = _pool(self.hit_encoder(hits.to(dtype)), hit_mask)
        return self.head(torch.cat((own.to(dtype), pooled_n, pooled_h), -1))


_KEYS = ("state", "goal", "neighbours", "neighbour_mask", "hits", "hit_mask")


class MarlActor(nn.Module):
    """``forward(state, goal, neighbours, neighbour_mask, hits, hit_mask) -> (loc, scale)``, each
    ``(B, N, interface.dim)``: the normal distribution of the normalized command of ``interface`` (module doc).
    :meth:`to_control` maps commands to body controls ``(B, N, control_dim)``; :meth:`command` is the deterministic
    body control (the mean command, clipped, applied)."""

    observation_keys = _KEYS

    def __init__(self, robot: Robot, comm_radius: float, interface: CommandInterface,
                 config: MarlNetConfig | None = None):  # fmt: skip
        super().__init__()
        self.config = config or MarlNetConfig()
        self.robot, self.interface = robot, interface
        k = interface.dim
        self.trunk = _Trunk(robot, comm_radius, self.config.hidden, k)
        nn.init.zeros_(self.trunk.head[-1].weight)  # a new actor's mean is the nominal command
        nn.init.zeros_(self.trunk.head[-1].bias)
        self.log_std = nn.Parameter(torch.full((k,), float(self.config.initial_log_std)))
        lo, hi = interface.bounds(torch.zeros(()))
        self.register_buffer("box_half_width", (hi - lo) / 2)

    def forward(self, state, goal, neighbours, neighbour_mask, hits, hit_mask) -> tuple[Tensor, Tensor]:
        obs = dict(zip(_KEYS, (state, goal, neighbours, neighbour_mask, hits, hit_mask)))
        residual = torch.tanh(self.trunk(obs))
        nominal = self.interface.nominal(state, goal.to(state.dtype)).to(residual.dtype)
        w = self.box_half_width.to(residual.dtype)
        loc = nominal + self.config.residual_scale * w * residual
        scale = (self.log_std.exp() * w).expand_as(loc)
        return loc, scale

    def to_control(self, state: Tensor, command: Tensor) -> Tensor:
        """The body control ``(B, N, control_dim)`` of the normalized commands ``command`` ``(B, N, k)`` at the
        states ``state``: clipped to the bounds at ``state``, applied by the interface, clipped to the actuator
        box."""
        c = self.interface.clip(state, command.to(state.dtype))
        return self.robot.clip_control(self.interface.apply(state, c))

    def command(self, obs: dict[str, Tensor]) -> Tensor:
        """The deterministic body control ``(B, N, control_dim)`` of observations ``obs``: :meth:`to_control` of
        the mean command."""
        loc, _ = self(*(obs[k] for k in _KEYS))
        return self.to_control(obs["state"], loc).to(loc.dtype)


class MarlCritic(nn.Module):
    """``forward(state, goal, neighbours, neighbour_mask, hits, hit_mask) -> value (B, N, 1)``: each agent's value
    from its own observation (IPPO's decentralized critic)."""

    def __init__(self, robot: Robot, comm_radius: float, config: MarlNetConfig | None = None):
        super().__init__()
        self.config = config or MarlNetConfig()
        self.trunk = _Trunk(robot, comm_radius, self.config.hidden, 1)

    def forward(self, state, goal, neighbours, neighbour_mask, hits, hit_mask) -> Tensor:
        return self.trunk(dict(zip(_KEYS, (state, goal, neighbours, neighbour_mask, hits, hit_mask))))
