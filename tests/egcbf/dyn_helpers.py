"""Random quadrotor states and controls for the dynamics and nominal-controller tests."""

from __future__ import annotations

import torch

from egcbf.robots.quadrotor.dynamics import DEFAULT_PARAMS, state_from_parts
from egcbf.robots.quadrotor.so3 import so3_exp

F64, F32 = torch.float64, torch.float32


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def random_states(seed: int, batch=(8,), dtype=F64, pos=4.0, vel=2.0, rate=10.0) -> torch.Tensor:
    """States with uniform attitudes, positions in [0, pos]^3, Gaussian velocities and body rates."""
    g = gen(seed)
    p = torch.rand(*batch, 3, generator=g, dtype=F64) * pos
    axis = torch.randn(*batch, 3, generator=g, dtype=F64)
    angle = torch.rand(*batch, 1, generator=g, dtype=F64) * torch.pi
    r = so3_exp(axis / axis.norm(dim=-1, keepdim=True) * angle)
    v = torch.randn(*batch, 3, generator=g, dtype=F64) * vel
    w = torch.randn(*batch, 3, generator=g, dtype=F64) * rate
    return state_from_parts(p, r, v, w).to(dtype)


def random_controls(seed: int, batch=(8,), dtype=F64, params=DEFAULT_PARAMS) -> torch.Tensor:
    """Controls uniform in the actuator box."""
    g = gen(seed + 1)
    tmax = torch.tensor(params.max_torque, dtype=F64)
    tau = (2 * torch.rand(*batch, 3, generator=g, dtype=F64) - 1) * tmax
    f = torch.rand(*batch, 1, generator=g, dtype=F64) * params.max_thrust
    return torch.cat((tau, f), dim=-1).to(dtype)


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Max abs error divided by max(1, max |b|)."""
    return float((a - b).abs().max() / b.abs().max().clamp_min(1.0))


def moving_scene(cfg, seed: int):
    """A reset swarm state (``egcbf.env.SwarmState``, float64) with random attitudes, velocities and body rates, so
    that every graph feature is non-trivial."""
    from egcbf.env import SwarmEnv, SwarmState

    s = SwarmEnv(cfg, dtype=F64).reset(seed)
    g = gen(seed + 1)
    b, n = cfg.num_envs, cfg.num_agents
    rot = so3_exp(torch.randn(b, n, 3, generator=g, dtype=F64))
    v = torch.randn(b, n, 3, generator=g, dtype=F64)
    w = torch.randn(b, n, 3, generator=g, dtype=F64)
    return SwarmState(state_from_parts(s.positions, rot, v, w), s.goals, s.obstacles)
