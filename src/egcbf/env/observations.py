"""Each agent's own fixed-shape, masked observation of a swarm state: what a robot senses and hears.

The layout is the one :mod:`egcbf.deploy` (``AgentPolicy``) and the ONNX export take, batched over ``B``
environments of ``N`` agents (world frame, SI units):

========================  ====================  ==============================================================
key                       shape                 contents
========================  ====================  ==============================================================
``state``                 ``(B, N, S)``         the agent's own state (quadrotor ``[p, R row-major, v, w]``)
``goal``                  ``(B, N, d)``         its goal position
``neighbours``            ``(B, N, K, S)``      the states of its neighbours within ``comm_radius`` (strict),
                                                nearest first; rows past the last neighbour hold zeros
``neighbour_mask``        ``(B, N, K)`` bool    which neighbour rows hold a neighbour
``hits``                  ``(B, N, H, d)``      its LiDAR hit points, nearest first; invalid rows hold zeros
``hit_mask``              ``(B, N, H)`` bool    which hit rows hold a hit
========================  ====================  ==============================================================

``K = max_neighbours`` is fixed by the caller; an agent with more neighbours in range keeps the ``K`` nearest (the
deployed controller's rule). ``H = EnvConfig.lidar_max_hits``: the simulator's scan already keeps that many, the
nearest. Equal distances (a set of measure zero) come in no promised order.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry.neighbors import radius_neighbors
from .config import EnvConfig
from .lidar import LidarScan

__all__ = ["OBSERVATION_KEYS", "NeighbourList", "ObservationLayout", "agent_observations"]

#: the keys of an observation, in the order of the table above
OBSERVATION_KEYS = ("state", "goal", "neighbours", "neighbour_mask", "hits", "hit_mask")


@dataclass(frozen=True)
class ObservationLayout:
    """The per-agent shapes of an observation: ``state_dim`` ``S``, ``dim`` ``d``, ``max_neighbours`` ``K``,
    ``max_hits`` ``H``."""

    state_dim: int
    dim: int
    max_neighbours: int
    max_hits: int

    def __post_init__(self) -> None:
        k = self.max_neighbours
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"max_neighbours must be an integer >= 1 (an agent that hears no neighbour cannot "
                             f"avoid them), got {k!r}")  # fmt: skip

    @classmethod
    def of(cls, config: EnvConfig, max_neighbours: int) -> ObservationLayout:
        """The layout of ``config``'s robot and LiDAR with ``max_neighbours`` neighbour rows."""
        robot = config.make_robot()
        return cls(robot.state_dim, robot.dim, max_neighbours, config.lidar_max_hits)

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """``key -> per-agent shape`` (without the ``(B, N)`` batch), in :data:`OBSERVATION_KEYS` order."""
        s, d, k, h = self.state_dim, self.dim, self.max_neighbours, self.max_hits
        return {"state": (s,), "goal": (d,), "neighbours": (k, s), "neighbour_mask": (k,), "hits": (h, d),
                "hit_mask": (h,)}  # fmt: skip

    def is_mask(self, key: str) -> bool:
        return key.endswith("_mask")


class NeighbourList:
    """Each agent's neighbours closer than ``radius``, kept between steps as a Verlet list: one cell-list search of
    radius ``radius + skin`` serves every later query until some agent has moved more than ``skin / 2`` since that
    search (then no pair now closer than ``radius`` can have been missed: each end moved at most ``skin / 2``).
    The search's candidates are stored as a padded table, one row of candidate indices per agent, so that a query
    only measures each agent's candidates and keeps the nearest (:meth:`nearest`); its result is what a fresh search
    returns. ``skin = 0`` searches anew every time; ``searches`` counts the searches."""

    def __init__(self, radius: float, skin: float = 0.0):
        if not radius > 0 or not skin >= 0:
            raise ValueError(f"NeighbourList needs radius > 0 and skin >= 0, got {radius!r}, {skin!r}")
        self.radius, self.skin = float(radius), float(skin)
        self._anchor: Tensor | None = None
        self._table: Tensor | None = None
        self.searches = 0

    def _candidates(self, positions: Tensor, batch: Tensor) -> Tensor:
        """The candidate table ``(M, C)`` of ``positions`` ``(M, d)``: row ``i`` lists the agents (same ``batch``
        id, not ``i``) that were within ``radius + skin`` of ``i`` at the last search, padded with ``M`` (no
        agent); searched anew when stale (class doc)."""
        anchor = self._anchor
        stale = anchor is None or anchor.shape != positions.shape or anchor.device != positions.device
        if not stale and self.skin > 0:
            moved = (positions.detach() - anchor).square().sum(-1).max()
            stale = bool(moved > (self.skin / 2) ** 2)
        if stale or self.skin == 0:
            m = positions.shape[0]
            src, dst = radius_neighbors(positions.detach(), self.radius + self.skin, batch, sort=False,
                                        cells_per_radius=2)  # fmt: skip
            order = torch.argsort(dst, stable=True)
            src, dst = src.index_select(0, order), dst.index_select(0, order)
            counts = torch.bincount(dst, minlength=m)
            first = torch.cumsum(counts, 0) - counts
            rank = torch.arange(dst.shape[0], device=dst.device) - first.index_select(0, dst)
            width = int(counts.max()) if m > 0 and dst.numel() > 0 else 0
            table = torch.full((m, width), m, dtype=torch.long, device=positions.device)
            table[dst, rank] = src
            self._table, self._anchor = table, positions.detach().clone()
            self.searches += 1
        return self._table

    def nearest(self, positions: Tensor, batch: Tensor, k: int) -> tuple[Tensor, Tensor]:
        """``index, mask`` ``(M, k)``: for each of ``positions`` ``(M, d)`` (agents of environments ``batch``
        ``(M,)``) its ``k`` nearest other agents of its environment closer than ``radius`` (strictly), nearest
        first (equal distances, a set of measure zero, in no promised order); ``mask`` marks the slots that hold
        one, the others hold index ``M``."""
        m, d = positions.shape
        table = self._candidates(positions, batch)
        width = table.shape[1]
        padded = torch.cat((positions, torch.full((1, d), torch.inf, dtype=positions.dtype,
                                                  device=positions.device)))  # fmt: skip
        d2 = (padded.index_select(0, table.reshape(-1)).reshape(m, width, d) - positions[:, None, :]).square().sum(-1)
        if width > k:
            d2, slot = torch.topk(d2, k, dim=1, largest=False, sorted=True)
        else:
            d2, slot = torch.sort(d2, dim=1, stable=True)
        index = table.gather(1, slot)
        if width < k:
            index = torch.cat((index, index.new_full((m, k - width), m)), 1)
            d2 = torch.cat((d2, d2.new_full((m, k - width), torch.inf)), 1)
        mask = d2 < self.radius**2
        return torch.where(mask, index, index.new_full((), m)), mask

    def reset(self) -> None:
        """Forget the stored search (a new episode)."""
        self._anchor = self._table = None


def agent_observations(
    x: Tensor,
    goals: Tensor,
    positions: Tensor,
    scan: LidarScan,
    comm_radius: float,
    max_neighbours: int,
    neighbours: NeighbourList | None = None,
) -> dict[str, Tensor]:
    """The observations (module doc) of agents with states ``x`` ``(B, N, S)``, goals ``(B, N, d)``, positions
    ``(B, N, d)`` (the robot's positions of ``x``) and LiDAR ``scan``: sparse radius search (``neighbours``, a
    :class:`NeighbourList` of radius ``comm_radius`` kept between calls, or a fresh search), no ``N x N`` matrix."""
    b, n, s = x.shape
    d = positions.shape[-1]
    k = int(max_neighbours)
    flat = positions.reshape(b * n, d)
    batch = torch.arange(b, device=x.device).repeat_interleave(n)
    if neighbours is None:
        neighbours = NeighbourList(comm_radius)
    elif neighbours.radius != float(comm_radius):
        raise ValueError(f"the NeighbourList's radius {neighbours.radius:g} is not comm_radius {comm_radius:g}")
    index, mask = neighbours.nearest(flat, batch, k)
    padded = torch.cat((x.reshape(b * n, s), torch.zeros(1, s, dtype=x.dtype, device=x.device)))
    rows = padded.index_select(0, index.reshape(-1)).reshape(b * n, k, s)
    hits = torch.where(scan.valid[..., None], scan.points.to(x.dtype), torch.zeros((), dtype=x.dtype, device=x.device))
    return {
        "state": x,
        "goal": goals.to(x.dtype),
        "neighbours": rows.reshape(b, n, k, s),
        "neighbour_mask": mask.reshape(b, n, k),
        "hits": hits,
        "hit_mask": scan.valid,
    }
