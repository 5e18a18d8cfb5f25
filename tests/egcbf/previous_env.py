"""The previous implementations of the LiDAR scan and of the observations' neighbour rows, kept verbatim (the
release before the angular-window LiDAR and the leading Verlet anchors): the tests compare the current code's
outputs with theirs, bit for bit, on random scenes (tests/egcbf/test_lidar.py, test_observations.py)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from egcbf.env.lidar import LidarScan, RayFaults, _sort_by, _yaw_rotate, ray_directions
from egcbf.env.obstacles import Obstacles
from egcbf.geometry.neighbors import radius_pairs
from egcbf.geometry.rectangles import ray_distances
from groupcanon.frames import planar_frame

__all__ = ["NeighbourList", "agent_observations", "lidar_scan"]


def lidar_scan(
    positions: Tensor,
    headings: Tensor,
    obstacles: Obstacles,
    *,
    n_rays: int = 32,
    max_range: float = 1.0,
    max_hits: int = 16,
    ray_faults: RayFaults | None = None,
) -> LidarScan:
    """The previous ``lidar_scan`` (every ray of every agent-obstacle pair tested)."""
    if positions.dim() != 3 or positions.shape[-1] not in (2, 3):
        raise ValueError(f"positions must be (B, N, d) with d = 3 or d = 2, got {tuple(positions.shape)}")
    if headings.shape[:2] != positions.shape[:2] or headings.shape[-1] < 2:
        raise ValueError(f"headings must be (B, N, >=2) matching positions, got {tuple(headings.shape)}")
    if obstacles.dim != positions.shape[-1]:
        raise ValueError(
            f"obstacles must have the positions' dimension: centers (B, K, {positions.shape[-1]}), got "
            f"{tuple(obstacles.centers.shape)}"
        )
    if obstacles.num_envs != positions.shape[0]:
        raise ValueError(f"obstacles are for {obstacles.num_envs} environments, positions for {positions.shape[0]}")
    if not (max_range > 0):
        raise ValueError(f"max_range must be > 0, got {max_range!r}")
    if int(max_hits) != max_hits or max_hits < 1:
        raise ValueError(f"max_hits must be a positive integer, got {max_hits!r}")
    b, n, dim = positions.shape
    dtype, device = positions.dtype, positions.device
    dirs = ray_directions(n_rays, dim=dim, dtype=dtype, device=device)  # (Rr, d)
    n_dirs = dirs.shape[0]
    h = int(max_hits)
    m = b * n
    best = torch.full((m, h), math.inf, dtype=dtype, device=device)
    idx = torch.zeros(m, h, dtype=torch.long, device=device)

    if obstacles.num_obstacles > 0 and m > 0:
        centers = obstacles.centers.to(dtype)
        radii = obstacles.radii.to(dtype)
        # agent-obstacle pairs whose ray segments can reach the sphere (sparse: linear in N and K)
        bi, ni, ki = obstacles.near_pairs(positions.detach(), max_range)
        if bi.numel() > 0 and obstacles.is_rectangles:
            # ray x rectangle (slab method in the rectangle's axes), the rays turned into the world by the heading
            cs = planar_frame(headings[bi, ni])  # (P, 2)
            world = _yaw_rotate(cs[:, None, :], dirs[None].expand(cs.shape[0], -1, -1))  # (P, Rr, 2)
            box = obstacles.boxes.to(dtype)[bi, ki]
            t_all = ray_distances(positions[bi, ni], world, centers[bi, ki], box[:, :2], box[:, 2:])
            pi, ri = torch.isfinite(t_all).nonzero(as_tuple=True)
            t = t_all[pi, ri]
            keep = t <= max_range
            agent, ri, t = (bi * n + ni)[pi[keep]], ri[keep], t[keep]
        elif bi.numel() > 0:
            # ray x sphere (disc) in the agent's yaw frame: one (P, d) x (d, Rr) product gives every d . (p - c)
            cs = planar_frame(headings[bi, ni])  # (P, 2)
            oc = _yaw_rotate(cs * cs.new_tensor([1.0, -1.0]), positions[bi, ni] - centers[bi, ki])  # (P, d)
            proj = oc @ dirs.T  # (P, Rr)
            c0 = oc.square().sum(-1) - radii[bi, ki].square()  # (P,); <= 0: the agent is inside
            # outside: the ray hits iff the line meets the sphere ahead (disc = proj^2 - c0 >= 0, that is proj^2 >=
            # c0, and proj < 0); inside: every ray, at distance 0. A threshold a little above -sqrt(c0) keeps a
            # superset of the hits; the exact test and disc are then formed on those alone.
            inside = c0 <= 0
            slack = 1 - 8 * torch.finfo(dtype).eps
            below = torch.where(inside, torch.inf, -torch.sqrt(c0.clamp(min=0.0)) * slack)
            flat = (proj < below[:, None]).view(-1).nonzero().squeeze(1)  # row-major, as a 2-D nonzero
            near = proj.view(-1).index_select(0, flat)
            disc = near.square() - c0.index_select(0, flat // n_dirs)
            inner = inside.index_select(0, flat // n_dirs)
            hit = (inner | ((disc >= 0) & (near < 0))).nonzero().squeeze(1)
            flat, near, disc, inner = (v.index_select(0, hit) for v in (flat, near, disc, inner))
            pi, ri = flat // n_dirs, flat % n_dirs
            t = torch.where(inner, torch.zeros_like(near), -near - torch.sqrt(torch.clamp(disc, min=0.0)))
            keep = t <= max_range
            agent, ri, t = (bi * n + ni)[pi[keep]], ri[keep], t[keep]
        if bi.numel() > 0:
            # closest obstacle per (agent, ray): sort by t, then (stably) by (agent, ray), keep the first of each
            perm = _sort_by(agent * n_dirs + ri, t, m * n_dirs)
            key = (agent * n_dirs + ri)[perm]
            first = torch.ones_like(key, dtype=torch.bool)
            first[1:] = key[1:] != key[:-1]
            perm = perm[first]
            agent, ri, t = agent[perm], ri[perm], t[perm]
            if ray_faults is not None:
                t, arrived = ray_faults(agent, ri, t)
                agent, ri, t = agent[arrived], ri[arrived], t[arrived]
            # the max_hits closest rays per agent: sort by (agent, t), rank within the agent's run
            perm = _sort_by(agent, t, m)
            agent, ri, t = agent[perm], ri[perm], t[perm]
            pos_in = torch.arange(agent.shape[0], device=device)
            start = torch.ones_like(agent, dtype=torch.bool)
            start[1:] = agent[1:] != agent[:-1]
            rank = pos_in - torch.cummax(torch.where(start, pos_in, torch.zeros_like(pos_in)), 0).values
            keep = rank < h
            best = best.index_put((agent[keep], rank[keep]), t[keep])
            idx = idx.index_put((agent[keep], rank[keep]), ri[keep])

    best, idx = best.view(b, n, h), idx.view(b, n, h)
    valid = torch.isfinite(best)
    if not (positions.requires_grad or headings.requires_grad) and not bool(valid.any()):
        # no ray hit (no obstacle in range): every slot holds the agent's position, as p + d * 0 below would
        return LidarScan(points=positions[:, :, None, :].expand(b, n, h, dim).clone(), valid=valid, distance=best)
    cs = planar_frame(headings)  # (B, N, 2)
    d = _yaw_rotate(cs[:, :, None, :], dirs[idx])  # (B, N, H, d)
    step = torch.where(valid, best, torch.zeros_like(best))
    points = positions[:, :, None, :] + d * step[..., None]
    return LidarScan(points=points, valid=valid, distance=best)


class NeighbourList:
    """Each agent's neighbours closer than ``radius``, kept between steps as a Verlet list: one search for the pairs
    closer than ``radius + skin`` serves every later query until some agent has moved more than ``skin / 2`` since
    that search (then no pair now closer than ``radius`` can have been missed: each end moved at most ``skin / 2``;
    the search's radius is inflated by a relative ``1e-5`` so that rounding cannot miss one either). The candidates
    are stored as unordered pairs; a query (:meth:`nearest`) measures each pair once, keeps those closer than
    ``radius`` and ranks every agent's neighbours with one sort; its result is what a fresh search returns. The
    search is :func:`~egcbf.geometry.neighbors.radius_pairs` (a k-d tree on the CPU, the cell list on other
    devices). ``skin = 0`` searches anew every time;
    ``searches`` counts the searches."""

    def __init__(self, radius: float, skin: float = 0.0):
        if not radius > 0 or not skin >= 0:
            raise ValueError(f"NeighbourList needs radius > 0 and skin >= 0, got {radius!r}, {skin!r}")
        self.radius, self.skin = float(radius), float(skin)
        self._anchor: Tensor | None = None
        self._pairs: tuple[Tensor, Tensor] | None = None
        self._close: tuple[Tensor, Tensor, Tensor] | None = None
        self.searches = 0

    def _candidates(self, positions: Tensor, batch: Tensor) -> tuple[Tensor, Tensor]:
        """``u, v`` ``(E,)``: every unordered pair of ``positions`` ``(M, d)`` of one ``batch`` id that was closer
        than ``radius + skin`` at the last search, once each; searched anew when stale (class doc)."""
        anchor = self._anchor
        stale = anchor is None or anchor.shape != positions.shape or anchor.device != positions.device
        if not stale and self.skin > 0 and positions.shape[0] > 0:
            moved = (positions.detach() - anchor).square().sum(-1).max()
            stale = bool(moved > (self.skin / 2) ** 2)
        if stale or self.skin == 0:
            self._pairs = radius_pairs(positions.detach(), batch, (self.radius + self.skin) * (1 + 1e-5))
            self._anchor = positions.detach().clone()
            self.searches += 1
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
        u, v, d2 = u.index_select(0, close), v.index_select(0, close), d2.index_select(0, close)
        self._close = (u, v, d2)
        return _rank_neighbours(u, v, d2, positions.shape[0], int(k))

    def pairs_within(self, distance: float) -> tuple[Tensor, Tensor]:
        """``u, v``: the unordered pairs of the last :meth:`nearest`'s positions closer than ``distance <= radius``,
        with perhaps a few farther by a relative ``1e-4`` (a superset for a caller that tests the distance again)."""
        if self._close is None:
            raise RuntimeError("NeighbourList.pairs_within before nearest")
        if not distance <= self.radius:
            raise ValueError(f"pairs_within needs distance <= radius = {self.radius:g}, got {distance!r}")
        u, v, d2 = self._close
        keep = (d2 < float(distance) ** 2 * (1 + 1e-4)).nonzero().squeeze(1)
        return u.index_select(0, keep), v.index_select(0, keep)

    def reset(self) -> None:
        """Forget the stored search (a new episode)."""
        self._anchor = self._pairs = self._close = None


def _pair_distances2(positions: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """``(E,)``: ``|p_v - p_u|^2`` of the pairs ``u, v`` of ``positions`` ``(M, d)``, summed over the coordinates in
    order (what ``(p_v - p_u).square().sum(-1)`` gives), one coordinate column at a time."""
    d2 = None
    for column in positions.t():
        diff = column.index_select(0, v) - column.index_select(0, u)
        d2 = diff.square() if d2 is None else d2.add_(diff.square())
    return d2


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


def _sort_values(key: Tensor) -> Tensor:
    """``key`` ``(E,)`` int64 sorted ascending: NumPy's sort on the CPU (the faster integer sort there), torch's
    elsewhere."""
    if key.device.type == "cpu":
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
    hits = torch.where(scan.valid[..., None], scan.points.to(x.dtype), torch.zeros((), dtype=x.dtype, device=x.device))
    return {
        "state": x,
        "goal": goals.to(x.dtype),
        "neighbours": rows.reshape(b, n, k, s),
        "neighbour_mask": mask.reshape(b, n, k),
        "hits": hits,
        "hit_mask": scan.valid,
    }
