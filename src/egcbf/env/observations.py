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
nearest. Equal distances (a set of measure zero) keep the neighbour search's order.
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
    """The pairs of agents closer than ``radius``, kept between steps as a Verlet list: one cell-list search of
    radius ``radius + skin`` serves every later query until some agent has moved more than ``skin / 2`` since that
    search (then no pair now closer than ``radius`` can have been missed: each end moved at most ``skin / 2``).
    Each query only filters the stored candidates by their current distance, so its result is the set a fresh
    search returns. ``skin = 0`` searches anew every time."""

    def __init__(self, radius: float, skin: float = 0.0):
        if not radius > 0 or not skin >= 0:
            raise ValueError(f"NeighbourList needs radius > 0 and skin >= 0, got {radius!r}, {skin!r}")
        self.radius, self.skin = float(radius), float(skin)
        self._anchor: Tensor | None = None
        self._pairs: Tensor | None = None
        self.searches = 0

    def pairs(self, positions: Tensor, batch: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``src, dst, d2, near``: candidate ordered pairs ``src -> dst`` of ``positions`` ``(M, d)`` (same
        ``batch`` id, ``j != i``, both directions), their squared distances, and ``near = d2 < radius^2``: the
        pairs within ``radius`` are exactly those marked ``near`` (the others are candidates of the skin)."""
        anchor = self._anchor
        stale = anchor is None or anchor.shape != positions.shape or anchor.device != positions.device
        if not stale and self.skin > 0:
            moved = (positions.detach() - anchor).square().sum(-1).max()
            stale = bool(moved > (self.skin / 2) ** 2)
        if stale or self.skin == 0:
            self._pairs = radius_neighbors(positions.detach(), self.radius + self.skin, batch, sort=False,
                                           cells_per_radius=2)  # fmt: skip
            self._anchor = positions.detach().clone()
            self.searches += 1
        src, dst = self._pairs
        d2 = (positions.index_select(0, src) - positions.index_select(0, dst)).square().sum(-1)
        return src, dst, d2, d2 < self.radius**2

    def reset(self) -> None:
        """Forget the stored search (a new episode)."""
        self._anchor = self._pairs = None


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
    src, dst, dist, near = neighbours.pairs(flat, batch)
    within = near.nonzero().squeeze(1)
    src, dst, dist = src.index_select(0, within), dst.index_select(0, within), dist.index_select(0, within)
    # one sort by (receiver, squared distance): the receiver's index is the integer part of the key
    key = dst.to(torch.float64) * (2 * float(comm_radius) ** 2 + 1) + dist.to(torch.float64)
    order = torch.argsort(key, stable=True)
    src, dst = src.index_select(0, order), dst.index_select(0, order)
    counts = torch.bincount(dst, minlength=b * n)
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(dst.shape[0], device=x.device) - first.index_select(0, dst)
    kept = (rank < k).nonzero().squeeze(1)
    src, dst, rank = src.index_select(0, kept), dst.index_select(0, kept), rank.index_select(0, kept)
    rows = torch.zeros(b * n, k, s, dtype=x.dtype, device=x.device)
    mask = torch.zeros(b * n, k, dtype=torch.bool, device=x.device)
    rows[dst, rank] = x.reshape(b * n, s).index_select(0, src)
    mask[dst, rank] = True
    hits = torch.where(scan.valid[..., None], scan.points.to(x.dtype), torch.zeros((), dtype=x.dtype, device=x.device))
    return {
        "state": x,
        "goal": goals.to(x.dtype),
        "neighbours": rows.reshape(b, n, k, s),
        "neighbour_mask": mask.reshape(b, n, k),
        "hits": hits,
        "hit_mask": scan.valid,
    }
