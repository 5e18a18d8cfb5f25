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

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..geometry.neighbors import radius_pairs
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
    """Each agent's neighbours closer than ``radius``, kept between steps as a Verlet list: one search for the pairs
    closer than ``radius + skin`` around *anchor* points serves every later query until some agent is more than
    ``skin / 2`` from its anchor (then no pair now closer than ``radius`` can have been missed: each end is at most
    ``skin / 2`` from its anchor; the search's radius is inflated by a relative ``1e-5`` so that rounding cannot miss
    one either). While the agents move steadily (their last two steps differ by at most a quarter of the longest
    one) the anchors lead them: each agent's last step carried forward by as many steps as puts the fastest
    ``0.9 skin / 2`` from its anchor, so that an agent in steady motion passes its anchor halfway through the list's
    life and a search serves about twice as many steps as one anchored at the positions (a speed choice only: any
    anchors within ``skin / 2`` give the same answers). The candidates are stored as unordered
    pairs; a query (:meth:`nearest`) measures each pair once, keeps those closer than ``radius`` and ranks every
    agent's neighbours with one sort; its result is what a fresh search returns. The search is
    :func:`~egcbf.geometry.neighbors.radius_pairs` (a k-d tree on the CPU, the cell list on other devices).
    ``skin = 0`` searches anew every time; ``searches`` counts the searches."""

    #: how far inside ``skin / 2`` a fresh search's leading anchors are placed (the fastest agent's share)
    LEAD = 0.9

    def __init__(self, radius: float, skin: float = 0.0):
        if not radius > 0 or not skin >= 0:
            raise ValueError(f"NeighbourList needs radius > 0 and skin >= 0, got {radius!r}, {skin!r}")
        self.radius, self.skin = float(radius), float(skin)
        self._anchor: Tensor | None = None
        self._last: tuple[Tensor, ...] = ()  # the positions of the last two queries (the agents' last steps)
        self._pairs: tuple[Tensor, Tensor] | None = None
        self._packed: tuple[Tensor, Tensor] | None = None  # the pairs' high key bits, both ways (_rank_packed)
        self._close: tuple[Tensor, Tensor, Tensor, Tensor] | None = None
        self.searches = 0

    def _lead(self, positions: Tensor) -> Tensor:
        """Anchors for a search at ``positions`` (class doc): ``positions + h * (positions - last)`` with the one
        ``h >= 0`` that puts the fastest agent ``LEAD * skin / 2`` from its anchor, when the last two steps agree;
        the positions themselves otherwise (no last steps, no motion, or a turn)."""
        if len(self._last) < 2 or any(q.shape != positions.shape or q.device != positions.device for q in self._last):
            return positions.clone()
        step = positions - self._last[-1]
        turn = step - (self._last[-1] - self._last[-2])
        fastest = float(step.square().sum(-1).max()) if positions.shape[0] else 0.0
        if not 0 < fastest < math.inf or not float(turn.square().sum(-1).max()) <= fastest / 16:
            return positions.clone()
        anchor = positions + step * (self.LEAD * self.skin / 2 / math.sqrt(fastest))
        if not bool((positions - anchor).square().sum(-1).max() <= (self.skin / 2) ** 2):  # rounding: never
            return positions.clone()
        return anchor

    def _candidates(self, positions: Tensor, batch: Tensor) -> tuple[Tensor, Tensor]:
        """``u, v`` ``(E,)``: every unordered pair of ``positions`` ``(M, d)`` of one ``batch`` id that was closer
        than ``radius + skin`` at the last search's anchors, once each; searched anew when stale (class doc)."""
        anchor = self._anchor
        stale = anchor is None or anchor.shape != positions.shape or anchor.device != positions.device
        if not stale and self.skin > 0 and positions.shape[0] > 0:
            moved = (positions - anchor).square().sum(-1).max()
            stale = bool(moved > (self.skin / 2) ** 2)
        if stale or self.skin == 0:
            anchor = self._lead(positions) if self.skin > 0 else positions.clone()
            self._pairs = radius_pairs(anchor, batch, (self.radius + self.skin) * (1 + 1e-5))
            self._anchor, self._packed = anchor, None
            self.searches += 1
        self._last = (*self._last[-1:], positions.clone())
        return self._pairs

    def nearest(self, positions: Tensor, batch: Tensor, k: int) -> tuple[Tensor, Tensor]:
        """``index, mask`` ``(M, k)``: for each of ``positions`` ``(M, d)`` (agents of environments ``batch``
        ``(M,)``) its ``k`` nearest other agents of its environment closer than ``radius`` (strictly), nearest
        first (equal distances, a set of measure zero, in no promised order); ``mask`` marks the slots that hold
        one, the others hold index ``M``."""
        p = positions.detach()
        u, v = self._candidates(p, batch)
        d2 = _pair_distances2(p, u, v)
        close = (d2 < self.radius**2).nonzero().squeeze(1)
        d2 = d2.index_select(0, close)
        self._close = (u, v, close, d2)
        m, k = positions.shape[0], int(k)
        if _packs(d2, m):
            if self._packed is None:
                self._packed = _pack_pairs(u, v, m)
            return _rank_packed(self._packed, close, d2, m, k)
        return _rank_neighbours(u.index_select(0, close), v.index_select(0, close), d2, m, k)

    def pairs_within(self, distance: float) -> tuple[Tensor, Tensor]:
        """``u, v``: the unordered pairs of the last :meth:`nearest`'s positions closer than ``distance <= radius``,
        with perhaps a few farther by a relative ``1e-4`` (a superset for a caller that tests the distance again)."""
        if self._close is None:
            raise RuntimeError("NeighbourList.pairs_within before nearest")
        if not distance <= self.radius:
            raise ValueError(f"pairs_within needs distance <= radius = {self.radius:g}, got {distance!r}")
        u, v, close, d2 = self._close
        keep = close.index_select(0, (d2 < float(distance) ** 2 * (1 + 1e-4)).nonzero().squeeze(1))
        return u.index_select(0, keep), v.index_select(0, keep)

    def reset(self) -> None:
        """Forget the stored search (a new episode)."""
        self._anchor = self._pairs = self._packed = self._close = None
        self._last = ()


def _pair_distances2(positions: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """``(E,)``: ``|p_v - p_u|^2`` of the pairs ``u, v`` of ``positions`` ``(M, d)``, summed over the coordinates in
    order (what ``(p_v - p_u).square().sum(-1)`` gives), one coordinate column at a time."""
    d2 = None
    for column in positions.t().contiguous():
        diff = column.index_select(0, v) - column.index_select(0, u)
        d2 = diff.square() if d2 is None else d2.add_(diff.square())
    return d2


def _packs(d2: Tensor, m: int) -> bool:
    """Whether :func:`_rank_neighbours` ranks ``m`` agents' pairs with the one packed ``int64`` key (float32
    distances and ``m <= 2**16``)."""
    return d2.dtype == torch.float32 and 2 * max((m - 1).bit_length(), 1) + 31 <= 63


def _pack_pairs(u: Tensor, v: Tensor, m: int) -> tuple[Tensor, Tensor]:
    """The agent and partner bits of :func:`_rank_neighbours`'s packed key for the pairs ``u, v``, both ways:
    ``(u << shift) | v`` and ``(v << shift) | u`` (computed once per search, their distances ORed in per query)."""
    bits = max((m - 1).bit_length(), 1)
    shift = 31 + bits
    return (u << shift) | v, (v << shift) | u


def _rank_packed(packed: tuple[Tensor, Tensor], close: Tensor, d2: Tensor, m: int, k: int) -> tuple[Tensor, Tensor]:
    """:func:`_rank_neighbours` of the pairs ``close`` (indices into the pairs of ``packed``, :func:`_pack_pairs`)
    with squared distances ``d2``, by its packed key (:func:`_packs`): the same sorted keys, so the same answer.
    Each agent's run of the sorted keys is found by a binary search for its first possible key."""
    bits = max((m - 1).bit_length(), 1)
    shift = 31 + bits
    slot = torch.arange(k, device=d2.device)
    if close.shape[0] == 0:
        none = torch.zeros(m, k, dtype=torch.bool, device=d2.device)
        return torch.full((m, k), m, dtype=torch.long, device=d2.device), none
    e = close.shape[0]
    dist = d2.view(torch.int32).to(torch.int64).bitwise_left_shift_(bits)
    key = torch.empty(2 * e, dtype=torch.int64, device=d2.device)
    torch.index_select(packed[0], 0, close, out=key[:e]).bitwise_or_(dist)
    torch.index_select(packed[1], 0, close, out=key[e:]).bitwise_or_(dist)
    key = _sort_values(key, in_place=True)
    starts = torch.searchsorted(key, torch.arange(m, device=d2.device) << shift)  # (agent m << shift may overflow)
    counts = torch.diff(starts, append=starts.new_full((1,), key.shape[0]))
    mask = slot < counts[:, None]
    at = (starts[:, None] + slot).clamp_(max=key.shape[0] - 1).view(-1)
    partner = key.index_select(0, at) & ((1 << bits) - 1)
    return torch.where(mask, partner.view(m, k), m), mask


def _rank_neighbours(u: Tensor, v: Tensor, d2: Tensor, m: int, k: int) -> tuple[Tensor, Tensor]:
    """``index, mask`` ``(m, k)``: each of ``m`` agents' ``k`` nearest partners among the unordered pairs ``u, v``
    ``(E,)`` with squared distances ``d2`` ``(E,)``, nearest first; ``mask`` marks the slots that hold one, the
    others hold index ``m``.

    Both directions of every pair are sorted by (agent, distance): for float32 distances and ``m <= 2**16`` as one
    ``int64`` key ``(agent, the distance's IEEE bits, partner)`` (non-negative floats order as their bits; ties then
    by partner), otherwise by two stable sorts (ties in input order). Each agent's run of the sorted pairs starts
    after those of the agents before it, so its first ``k`` are gathered from there, as many as it has."""
    counts = torch.bincount(u, minlength=m) + torch.bincount(v, minlength=m)
    slot = torch.arange(k, device=u.device)
    mask = slot < counts[:, None]
    if u.shape[0] == 0:
        return torch.full((m, k), m, dtype=torch.long, device=u.device), mask
    at = ((torch.cumsum(counts, 0) - counts)[:, None] + slot).clamp_(max=2 * u.shape[0] - 1).view(-1)
    bits = max((m - 1).bit_length(), 1)
    if d2.dtype == torch.float32 and 2 * bits + 31 <= 63:
        dist = d2.view(torch.int32).to(torch.int64) << bits
        shift = 31 + bits
        key = _sort_values(torch.cat(((u << shift) | dist | v, (v << shift) | dist | u)))
        partner = key.index_select(0, at) & ((1 << bits) - 1)
    else:
        agent, partner = torch.cat((u, v)), torch.cat((v, u))
        order = torch.sort(torch.cat((d2, d2)), stable=True).indices
        order = order.index_select(0, torch.sort(agent.index_select(0, order), stable=True).indices)
        partner = partner.index_select(0, order.index_select(0, at))
    return torch.where(mask, partner.view(m, k), m), mask


def _sort_values(key: Tensor, in_place: bool = False) -> Tensor:
    """``key`` ``(E,)`` int64 sorted ascending: NumPy's sort on the CPU (the faster integer sort there; ``in_place``:
    sorting ``key`` itself, a contiguous tensor of the caller's own), torch's elsewhere."""
    if key.device.type == "cpu":
        if in_place:
            key.numpy().sort()
            return key
        return torch.from_numpy(np.sort(key.numpy()))
    return torch.sort(key).values


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
    if scan.valid.device.type == "cpu" and not bool(scan.valid.any()):  # no hit (no obstacle in range): zeros
        hits = torch.zeros(scan.points.shape, dtype=x.dtype, device=x.device)
    else:
        zero = torch.zeros((), dtype=x.dtype, device=x.device)
        hits = torch.where(scan.valid[..., None], scan.points.to(x.dtype), zero)
    return {
        "state": x,
        "goal": goals.to(x.dtype),
        "neighbours": rows.reshape(b, n, k, s),
        "neighbour_mask": mask.reshape(b, n, k),
        "hits": hits,
        "hit_mask": scan.valid,
    }
