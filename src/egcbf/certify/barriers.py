"""The barriers a certificate checks: a checkpoint's learned graph CBF and the ``dcbf`` filter's hand-crafted one.

A barrier maps a swarm state to one value per agent, ``h`` ``(B, N)`` float64: ``h_i >= 0`` claims that agent ``i`` is
safe. Each declares its class-K function ``kappa`` (1/s times the unit of ``h``), so that the discrete decrease
condition a certificate checks is ``h(x_{t+1}) - h(x_t) >= -dt kappa(h(x_t))``.

* :class:`LearnedBarrier`: ``h_i`` the graph CBF's output (``CBFNet``: ``tanh`` of the head's value, the quantity
  training constrains with ``hdot + alpha h >= 0``), from the agent's own graph as the environment builds it;
  ``kappa(h) = alpha h`` with the checkpoint's training ``alpha``.
* :class:`BrakingBarrier`: the minimum over an agent's pair and obstacle barriers of the ``dcbf`` filter
  (Wang, Ames & Egerstedt's braking-distance barrier ``sqrt(2 A_sum (d - D)) + d'`` with the filter's margin,
  deceleration and culling radius, :data:`egcbf.control.filters.DCBF_FILTER_BARRIER`), read at the current state
  (no look-ahead); inside the safety distance (``d < D``, where that barrier is undefined) ``h = d - D < 0``;
  ``kappa(h) = gamma h^3``, the filter's class-K function. An agent with no pair or obstacle within range has
  ``h = +inf`` (nothing threatens it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import Tensor

from ..env import EnvConfig, SwarmState
from ..env.graph import build_graph
from ..nn.models import CBFNet
from ..robots.quadrotor.barriers import BarrierConfig, agent_pairs

__all__ = ["BrakingBarrier", "LearnedBarrier"]


class LearnedBarrier:
    """A checkpoint's graph CBF ``h_i`` (module doc); ``alpha``: its class-K gain (1/s)."""

    kind = "learned"

    def __init__(self, cbf: CBFNet, alpha: float):
        if not alpha > 0:
            raise ValueError(f"LearnedBarrier: alpha must be > 0, got {alpha!r}")
        self.cbf, self.alpha = cbf, float(alpha)

    @torch.no_grad()
    def values(self, state: SwarmState, config: EnvConfig) -> Tensor:
        """``(B, N)`` float64 on the CPU: every agent's ``h``."""
        p = next(self.cbf.parameters())
        s = state if state.x.dtype == p.dtype and state.x.device == p.device else state.to(p.device, dtype=p.dtype)
        h = self.cbf(build_graph(s, config))
        return h.to(torch.float64).cpu().view(state.x.shape[:2])

    def kappa(self, h: Tensor) -> Tensor:
        return self.alpha * h


class BrakingBarrier:
    """The ``dcbf`` filter's braking-distance barrier per agent (module doc); ``barrier`` its settings (the
    culling radius defaults to the environment's communication radius, as in the filter)."""

    kind = "handcrafted"

    def __init__(self, barrier: BarrierConfig):
        if barrier.kind != "wang":
            raise ValueError(f"BrakingBarrier reads the braking-distance barrier (kind 'wang'), got {barrier.kind!r}")
        self.barrier = barrier

    @staticmethod
    def _pieces(dp: np.ndarray, dv: np.ndarray, distance: np.ndarray, brake_sum: float) -> np.ndarray:
        d = np.sqrt((dp * dp).sum(-1))
        ddot = (dp * dv).sum(-1) / np.maximum(d, 1e-12)
        gap = d - distance
        return np.where(gap >= 0, np.sqrt(2.0 * brake_sum * np.maximum(gap, 0.0)) + ddot, gap)

    def values(self, state: SwarmState, config: EnvConfig) -> Tensor:
        """``(B, N)`` float64 on the CPU: every agent's ``h`` (``+inf``: nothing within range)."""
        cfg = self.barrier
        if cfg.cull_radius is None:
            cfg = dataclasses.replace(cfg, cull_radius=config.comm_radius)
        b, n = state.x.shape[:2]
        x = state.x.detach().to(torch.float64).cpu().numpy().reshape(b * n, -1)
        pos, vel = x[:, 0:3], x[:, 12:15]
        h = np.full(b * n, np.inf)
        pairs = agent_pairs(pos, cfg, np.repeat(np.arange(b), n))
        if pairs.shape[1]:
            i, j = pairs
            hp = self._pieces(pos[i] - pos[j], vel[i] - vel[j], np.full(i.shape, cfg.safe_distance),
                              2.0 * cfg.brake_accel)  # fmt: skip
            np.minimum.at(h, i, hp)
            np.minimum.at(h, j, hp)
        obs = state.obstacles
        if obs.centers is not None and obs.centers.shape[1]:
            if obs.boxes is not None:
                raise ValueError("BrakingBarrier reads sphere obstacles; this scene has rectangles")
            centers = obs.centers.detach().to(torch.float64).cpu().numpy()  # (B, K, 3)
            radii = obs.radii.detach().to(torch.float64).cpu().numpy()  # (B, K)
            p3 = pos.reshape(b, n, 1, 3)
            dp = p3 - centers[:, None]  # (B, N, K, 3)
            surface = np.sqrt((dp * dp).sum(-1)) - radii[:, None] - cfg.agent_radius
            cull = cfg.obstacle_cull if cfg.obstacle_cull is not None else cfg.cull_radius
            dvo = np.broadcast_to(vel.reshape(b, n, 1, 3), dp.shape)
            ho = self._pieces(dp, dvo, radii[:, None] + cfg.agent_radius + cfg.margin, cfg.brake_accel)
            ho = np.where(surface < cull, ho, np.inf).min(-1).reshape(-1)
            h = np.minimum(h, ho)
        return torch.from_numpy(h).view(b, n)

    def kappa(self, h: Tensor) -> Tensor:
        return self.barrier.gamma * h**3
