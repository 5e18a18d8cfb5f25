"""LiDAR against round obstacles (3-D: spheres, 2-D: discs), analytic and vectorized over environments, agents,
rays and obstacles. The dimension ``d`` is read from the positions ``(B, N, d)``; the obstacles must match.

3-D ray pattern (GCBF+'s 3-D LiDAR): ``n_rays`` azimuths ``phi in linspace(-pi, pi - 2 pi / n_rays, n_rays)`` times
``n_rays // 2`` elevations ``theta in linspace(-pi/2 + 2 pi / n_rays, pi/2 - 2 pi / n_rays, n_rays // 2)``, plus
one ray straight up and one straight down; every ray has length ``max_range``. Only the ``max_hits`` closest hits
are kept per agent (GCBF+ keeps 16).

2-D ray pattern: the same ``n_rays`` azimuths ``phi in linspace(-pi, pi - 2 pi / n_rays, n_rays)`` and nothing
else (no elevations, no up/down rays), each of length ``max_range``, in the agent's heading frame: azimuth 0 is
the agent's heading, positive azimuths turn counter-clockwise. The same ``max_hits`` selection and conventions
apply. A world transform ``g = (R(a), t)`` of SE(2) (``groupcanon.groups.SE2``, element ``(cos a, sin a, tx,
ty)``) moves agents, headings and discs together, so ``hits(g . scene) = g . hits(scene)`` (the argument below,
with ``R_z`` replaced by the planar rotation ``R`` and the heading frame ``groupcanon.frames.planar_frame``).

Equivariance (3-D). The pattern is defined in each agent's *yaw frame*: the directions are rotated about the world z
axis by the agent's yaw (the heading of its body x axis projected on the horizontal plane, exactly the rotation
part of its SE2xR frame ``groupcanon.frames.se2xr_frame(R[:, 0], p)``). A world transform ``g = (R_z(a), t)``
moves agents, obstacles and the yaw frames together, so every ray meets the same obstacle at the same distance
and the hit points move as points: ``hits(g . scene) = g . hits(scene)`` exactly (up to rounding). Rays fixed in
the world frame would break this for every rotation that does not map the discrete azimuth grid onto itself.
Pitch and roll are ignored (the pattern stays level), as gravity fixes the vertical.

Conventions: a ray from an agent inside an obstacle reports a hit at distance 0 (the agent's own position);
a ray that hits nothing within ``max_range`` is invalid. Invalid slots hold the agent's position and
``valid = False``; ``distance`` is ``inf`` there. The arena boundary is not sensed (as in GCBF+).

Cost: rays are only traced for the agent–obstacle pairs within ``max_range + radius`` (found with
:meth:`Obstacles.near_pairs`: dense for a few obstacles, cell list for many), so the work is linear in the number
of agents and obstacles at fixed densities. Of each sphere pair's rays only those within the sphere's angular
window (its angular radius around the direction to its centre, widened far past rounding) are tested, on the values
of the one ``(P, d) x (d, Rr)`` product, so the hits are the every-ray test's; without autograd the closest hits
are kept by two sorts of packed integer keys and the points formed for the valid slots alone.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from groupcanon.frames import planar_frame

from ..geometry.rectangles import ray_distances
from .obstacles import Obstacles

__all__ = ["LidarScan", "RayFaults", "lidar_scan", "ray_directions"]

#: ``(agent, ray, distance) -> (measured distance, arrived)``, each ``(R,)``: a sensor's faults on the returns of
#: single rays (:func:`lidar_scan`'s ``ray_faults``)
RayFaults = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


@dataclass
class LidarScan:
    """The kept hits of every agent, sorted by distance: ``points`` ``(B, N, H, d)`` (world frame; the agent's
    position in invalid slots), ``valid`` ``(B, N, H)`` bool, ``distance`` ``(B, N, H)`` (``inf`` where invalid)."""

    points: Tensor
    valid: Tensor
    distance: Tensor


def ray_directions(n_rays: int, *, dim: int = 3, dtype: torch.dtype | None = None, device=None) -> Tensor:
    """Unit ray directions in the agent's frame (yaw frame in 3-D, heading frame in 2-D).

    ``dim = 3``: ``(n_rays * (n_rays // 2) + 2, 3)``, the elevation x azimuth grid (elevation-major), then up,
    then down. ``dim = 2``: ``(n_rays, 2)``, ``(cos phi, sin phi)`` for the azimuths ``phi`` (see module doc).
    """
    if int(n_rays) != n_rays or n_rays < 2:
        raise ValueError(f"n_rays must be an integer >= 2, got {n_rays!r}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    n = int(n_rays)
    dtype = dtype or torch.get_default_dtype()
    step = 2 * math.pi / n
    if dim == 2:
        phi = torch.linspace(-math.pi, math.pi - step, n, dtype=torch.float64)
        return torch.stack((torch.cos(phi), torch.sin(phi)), dim=-1).to(dtype=dtype, device=device)
    theta = torch.linspace(-math.pi / 2 + step, math.pi / 2 - step, n // 2, dtype=torch.float64)
    phi = torch.linspace(-math.pi, math.pi - step, n, dtype=torch.float64)
    ct, st = torch.cos(theta)[:, None], torch.sin(theta)[:, None]
    grid = torch.stack((ct * torch.cos(phi)[None], ct * torch.sin(phi)[None], st.expand(-1, n)), dim=-1).reshape(-1, 3)
    updown = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    return torch.cat((grid, updown)).to(dtype=dtype, device=device)


def _yaw_rotate(cs: Tensor, d: Tensor) -> Tensor:
    """Rotate ``d`` ``(..., 3)`` about z (or ``(..., 2)`` in the plane) by the yaw ``cs = (cos, sin)`` ``(..., 2)``."""
    c, s = cs[..., 0:1], cs[..., 1:2]
    x, y = d[..., 0:1], d[..., 1:2]
    xy = torch.cat((c * x - s * y, s * x + c * y), dim=-1)
    if d.shape[-1] == 2:
        return xy
    return torch.cat((xy, d[..., 2:3].expand(*xy.shape[:-1], 1)), dim=-1)


def _sort_by(major: Tensor, minor: Tensor, major_bound: int | None = None) -> Tensor:
    """Permutation sorting by ``(major, minor)``; ties keep their input order.

    ``major``: integers, in ``[0, major_bound)`` when ``major_bound`` is given. Two stable sorts (by ``minor``, then
    by ``major``); on the CPU, for a float32 ``minor`` without NaN and ``major_bound <= 2**31``, one stable sort of
    the packed ``int64`` key ``(major, minor's IEEE bits as an ordered integer)`` instead: the same permutation.
    """
    if (
        major_bound is not None
        and major_bound <= 2**31
        and minor.dtype == torch.float32
        and minor.device.type == "cpu"
        and not bool(torch.isnan(minor).any())
    ):
        bits = (minor + 0.0).view(torch.int32).to(torch.int64)  # + 0.0: -0.0 becomes 0.0, which it equals
        order = bits ^ ((bits >> 31) & 0x7FFFFFFF)  # negative floats' magnitude bits flipped: ordered as the floats
        return torch.sort((major << 32) + order, stable=True).indices
    p = torch.sort(minor, stable=True).indices
    return p[torch.sort(major[p], stable=True).indices]


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
    """Cast the LiDAR of every agent.

    Args:
        positions: ``(B, N, d)`` agent positions (world frame), ``d = 3`` (spheres, 3-D pattern) or ``d = 2``
            (discs, 2-D pattern).
        headings: ``(B, N, >=2)`` heading vectors (world frame) whose first two components set the yaw of the
            ray pattern (they are normalized; only their direction matters). 3-D: e.g. the body x axis
            ``R[..., :, 0]`` (its horizontal part), or ``(cos yaw, sin yaw)``. 2-D: the heading ``(B, N, 2)``, a
            unit vector ``(cos theta, sin theta)`` or any nonzero vector along it.
        obstacles: ``K`` obstacles per environment of the same dimension (centres ``(B, K, d)``).
        n_rays, max_range, max_hits: the pattern (see module doc), the ray length, the hits kept per agent.
        ray_faults: what the sensor does to each ray's return before the closest ``max_hits`` are kept (a faulty
            sensor, :meth:`egcbf.faults.Sensing.scan`): called with ``agent`` ``(R,)`` (flat rows ``b * N + i``),
            ``ray`` ``(R,)`` (indices into :func:`ray_directions`) and ``distance`` ``(R,)`` of every ray that
            hits, it returns the measured distances ``(R,)`` and which returns arrive ``(R,)`` bool.

    Returns:
        :class:`LidarScan` with ``H = max_hits`` slots per agent, closest first, points ``(B, N, H, d)``.
        Differentiable with respect to positions and obstacles (where the hit set does not change).
    """
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
    h = int(max_hits)
    grad = positions.requires_grad or headings.requires_grad or obstacles.centers.requires_grad
    grad = grad or obstacles.radii.requires_grad or (obstacles.boxes is not None and obstacles.boxes.requires_grad)
    if (obstacles.num_obstacles == 0 or b * n == 0) and not grad:
        # nothing to hit: every slot invalid, holding the agent's position (what the scan below gives)
        invalid = torch.zeros(b, n, h, dtype=torch.bool, device=device)
        distance = torch.full((b, n, h), math.inf, dtype=dtype, device=device)
        return LidarScan(points=_repeat_rows(positions, h), valid=invalid, distance=distance)
    dirs = ray_directions(n_rays, dim=dim, dtype=dtype, device=device)  # (Rr, d)
    n_dirs = dirs.shape[0]
    m = b * n
    best = torch.full((m, h), math.inf, dtype=dtype, device=device)
    idx = torch.zeros(m, h, dtype=torch.long, device=device)
    hit_agent = hit_rank = hit_t = hit_ray = None  # the kept hits, one entry per valid slot (for the points)

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
        elif bi.numel() > 0 and grad:
            # ray x sphere (disc) in the agent's yaw frame: one (P, d) x (d, Rr) product gives every d . (p - c);
            # with autograd every ray of every pair is tested, as the gradients have always been formed
            cs = planar_frame(headings[bi, ni])  # (P, 2)
            oc = _yaw_rotate(cs * cs.new_tensor([1.0, -1.0]), positions[bi, ni] - centers[bi, ki])  # (P, d)
            proj = oc @ dirs.T  # (P, Rr)
            c0 = oc.square().sum(-1) - radii[bi, ki].square()  # (P,); <= 0: the agent is inside
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
        elif bi.numel() > 0:
            # ray x sphere (disc) in the agent's yaw frame: one (P, d) x (d, Rr) product gives every d . (p - c)
            pa = bi * n + ni  # (P,) flat agents
            ck = bi * obstacles.num_obstacles + ki  # (P,) flat obstacles
            cs = planar_frame(headings.reshape(m, -1).index_select(0, pa))  # (P, 2)
            offset = positions.reshape(m, dim).index_select(0, pa) - centers.reshape(-1, dim).index_select(0, ck)
            oc = _yaw_rotate(cs * cs.new_tensor([1.0, -1.0]), offset)  # (P, d)
            proj = torch.mm(oc, dirs.T, out=_scratch(oc.shape[0] * n_dirs, dtype, device).view(-1, n_dirs))
            c0 = oc.square().sum(-1) - radii.reshape(-1).index_select(0, ck).square()  # (P,); <= 0: inside
            # outside: the ray hits iff the line meets the sphere ahead (disc = proj^2 - c0 >= 0, that is proj^2 >=
            # c0, and proj < 0); inside: every ray, at distance 0. A threshold a little above -sqrt(c0) keeps a
            # superset of the hits; the exact test and disc are then formed on those alone. Only the rays within
            # the sphere's angular window (widened far past rounding) can pass the threshold: those are the
            # candidates, read from the product (so every value is the dense product's).
            inside = c0 <= 0
            slack = 1 - 8 * torch.finfo(dtype).eps
            below = torch.where(inside, torch.inf, -torch.sqrt(c0.clamp(min=0.0)) * slack)
            pc, flat = _window_rays(oc.detach(), below.detach(), n_rays, dim)
            near = proj.view(-1).index_select(0, flat)
            disc = near.square() - c0.index_select(0, pc)
            inner = inside.index_select(0, pc)
            t = torch.where(inner, torch.zeros_like(near), -near - torch.sqrt(torch.clamp(disc, min=0.0)))
            hit = (near < below.index_select(0, pc)) & (inner | ((disc >= 0) & (near < 0))) & (t <= max_range)
            keep = hit.nonzero().squeeze(1)
            pc, flat, t = pc.index_select(0, keep), flat.index_select(0, keep), t.index_select(0, keep)
            agent, ri = pa.index_select(0, pc), flat - pc * n_dirs
        if bi.numel() > 0 and ray_faults is None and not grad and _packs_hits(t, m, n_dirs):
            hit_agent, hit_rank, hit_t, hit_ray = _closest_hits_packed(agent, ri, t, m, n_dirs, h)
        elif bi.numel() > 0:
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
            hit_agent, hit_rank, hit_t, hit_ray = agent[keep], rank[keep], t[keep], ri[keep]
        if hit_agent is not None and not grad:
            best.index_put_((hit_agent, hit_rank), hit_t)
            idx.index_put_((hit_agent, hit_rank), hit_ray)
        elif hit_agent is not None:
            best = best.index_put((hit_agent, hit_rank), hit_t)
            idx = idx.index_put((hit_agent, hit_rank), hit_ray)

    best, idx = best.view(b, n, h), idx.view(b, n, h)
    valid = torch.isfinite(best)
    if hit_agent is None or not hit_agent.numel():
        if not (positions.requires_grad or headings.requires_grad):
            # no ray hit (no obstacle in range): every slot holds the agent's position, as p + d * 0 below would
            return LidarScan(points=_repeat_rows(positions, h), valid=valid, distance=best)
    elif not grad:
        # the points of the valid slots alone (each as p + d * t below forms it); the others hold the position
        cs = planar_frame(headings).reshape(m, 2).index_select(0, hit_agent)  # (Q, 2)
        d = _yaw_rotate(cs, dirs.index_select(0, hit_ray))  # (Q, d)
        at = hit_agent * h + hit_rank
        points = _repeat_rows(positions, h).view(m * h, dim)
        points.index_copy_(0, at, positions.reshape(m, dim).index_select(0, hit_agent) + d * hit_t[:, None])
        return LidarScan(points=points.view(b, n, h, dim), valid=valid, distance=best)
    cs = planar_frame(headings)  # (B, N, 2)
    d = _yaw_rotate(cs[:, :, None, :], dirs[idx])  # (B, N, H, d)
    step = torch.where(valid, best, torch.zeros_like(best))
    points = positions[:, :, None, :] + d * step[..., None]
    return LidarScan(points=points, valid=valid, distance=best)


_SCRATCH = threading.local()
#: the largest buffer (elements) :func:`_scratch` keeps; a larger product is allocated afresh
_SCRATCH_MAX = 2**24


def _scratch(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """A flat buffer of ``size`` elements for a scan's ``(P, Rr)`` product, which is only read inside that scan: on
    the CPU, up to ``_SCRATCH_MAX`` elements, this thread's own buffer kept between scans (a fresh one would be new
    memory, page faults and all, every step); otherwise a new tensor."""
    if device.type != "cpu" or size > _SCRATCH_MAX:
        return torch.empty(size, dtype=dtype, device=device)
    cache = getattr(_SCRATCH, "buffers", None)
    if cache is None:
        cache = _SCRATCH.buffers = {}
    buf = cache.get(dtype)
    if buf is None or buf.numel() < size:
        buf = cache[dtype] = torch.empty(min(max(size, 2 * (0 if buf is None else buf.numel())), _SCRATCH_MAX),
                                         dtype=dtype)  # fmt: skip
    return buf[:size]


def _repeat_rows(positions: Tensor, h: int) -> Tensor:
    """``(B, N, h, d)``: each agent's position in each of its ``h`` slots, a new tensor (a contiguous copy: faster
    than cloning the expanded view, which keeps its layout)."""
    b, n, d = positions.shape
    return positions[:, :, None, :].expand(b, n, h, d).clone(memory_format=torch.contiguous_format)


def _window_rays(oc: Tensor, below: Tensor, n_rays: int, dim: int) -> tuple[Tensor, Tensor]:
    """``pair, flat`` ``(C,)``: for each agent-sphere pair (``oc`` ``(P, d)``, the agent's offset from the centre in
    its yaw frame; ``below`` ``(P,)``, :func:`lidar_scan`'s threshold, ``inf`` inside) the rays of
    :func:`ray_directions` that may have ``d . oc < below``, as flat indices ``pair * Rr + ray`` into the ``(P, Rr)``
    product: those within the angle ``acos(-below / |oc|)`` of the direction to the centre (the sphere's angular
    radius), widened by ``1e-5`` in its cosine and by ``0.01`` rad (far past the rounding of the product, of the
    float directions and of this function), found as a band of elevations and, in it, a band of azimuths (all of
    them around a pole), plus up and down when they are within the angle; every ray from inside. Grouped by pair,
    in no other promised order."""
    device, dt = oc.device, oc.dtype
    n = int(n_rays)
    n_dirs = n * (n // 2) + 2 if dim == 3 else n
    step = 2 * math.pi / n
    w = (-oc).t().contiguous()  # toward the centre, one row per coordinate
    flat_dist = torch.hypot(w[0], w[1])
    dist = flat_dist if dim == 2 else torch.hypot(flat_dist, w[2])
    cos = -below / dist.clamp(min=torch.finfo(dt).tiny)
    alpha = torch.acos((cos - 1e-5).clamp(-1.0, 1.0)) + 0.01  # inside (below = inf): cos = -inf, alpha > pi
    phi = torch.atan2(w[1], w[0])
    pairs = torch.arange(oc.shape[0], device=device)
    if dim == 3:
        theta_c = torch.atan2(w[2], flat_dist)
        theta = torch.linspace(-math.pi / 2 + step, math.pi / 2 - step, n // 2, dtype=torch.float64).to(dt)
        lo = torch.searchsorted(theta.to(device), theta_c - alpha)
        rows = (torch.searchsorted(theta.to(device), theta_c + alpha, right=True) - lo).clamp(min=0)
        ratio = (torch.sin(alpha) / torch.cos(theta_c).clamp(min=torch.finfo(dt).tiny)).clamp(max=1.0)
        half = torch.where(theta_c.abs() + alpha >= math.pi / 2, math.pi, torch.asin(ratio))  # a pole: all
        up = (math.pi / 2 - theta_c <= alpha).nonzero().squeeze(1)
        down = (theta_c + math.pi / 2 <= alpha).nonzero().squeeze(1)
        rp = torch.repeat_interleave(pairs, rows)  # one entry per (pair, elevation row)
        row = lo.index_select(0, rp) + torch.arange(rp.shape[0], device=device)
        row = row - (torch.cumsum(rows, 0) - rows).index_select(0, rp)
    else:
        half, rp, row = alpha, pairs, torch.zeros_like(pairs)
    first = torch.ceil((phi - half + math.pi) / step).long()
    cols = torch.floor((phi + half + math.pi) / step).long() - first + 1
    whole = (half >= math.pi) | (cols >= n)
    first = torch.where(whole, 0, first % n).index_select(0, rp)
    cols = torch.where(whole, n, cols.clamp(min=0)).index_select(0, rp)
    # each (pair, row) band of azimuths as one or two runs of flat indices (two where it wraps past azimuth n - 1)
    base = rp * n_dirs + row * n
    head = torch.minimum(cols, n - first)
    starts, lens, owner = [base + first, base], [head, cols - head], [rp, rp]
    if dim == 3:
        for extra, ray in ((up, n * (n // 2)), (down, n * (n // 2) + 1)):
            starts.append(extra * n_dirs + ray)
            lens.append(torch.ones_like(extra))
            owner.append(extra)
    starts, lens, owner = torch.cat(starts), torch.cat(lens), torch.cat(owner)
    total = int(lens.sum())
    flat = torch.repeat_interleave(starts - (torch.cumsum(lens, 0) - lens), lens, output_size=total)
    flat = flat + torch.arange(total, device=device)
    return torch.repeat_interleave(owner, lens, output_size=total), flat


def _packs_hits(t: Tensor, m: int, n_dirs: int) -> bool:
    """Whether :func:`_closest_hits_packed` takes these hits: float32 distances without autograd on the CPU, their
    keys within 63 bits."""
    fits = (m - 1).bit_length() + 32 + (n_dirs - 1).bit_length() <= 63
    return t.dtype == torch.float32 and t.device.type == "cpu" and not t.requires_grad and fits


def _closest_hits_packed(agent: Tensor, ray: Tensor, t: Tensor, m: int, n_dirs: int, h: int):
    """``agent, rank, t, ray`` of the kept hits: the closest obstacle of each ``(agent, ray)``, then each agent's
    ``h`` closest rays, ``rank`` their order; what the two stable sorts of :func:`lidar_scan` keep, by two sorts of
    packed ``int64`` keys whose values carry every field (``(agent, ray, t)``, then ``(agent, t, ray)``, ``t`` as its
    ordered IEEE bits: ties in ``t`` then go by ray, as the stable sorts leave them)."""
    rbits = max((n_dirs - 1).bit_length(), 1)
    bits = (t + 0.0).view(torch.int32).to(torch.int64)  # + 0.0: -0.0 becomes 0.0, which it equals
    order = (bits ^ ((bits >> 31) & 0x7FFFFFFF)) + 2**31  # ordered as the floats, in [0, 2**32)
    key = _sorted(((agent << (rbits + 32)) | (ray << 32)) | order)
    pair = key >> 32  # (agent, ray)
    first = torch.ones_like(pair, dtype=torch.bool)
    torch.ne(pair[1:], pair[:-1], out=first[1:])
    key = key.index_select(0, first.nonzero().squeeze(1))
    ray = (key >> 32) & ((1 << rbits) - 1)
    key = _sorted(((key >> (rbits + 32)) << (rbits + 32)) | ((key & 0xFFFFFFFF) << rbits) | ray)
    agent = key >> (32 + rbits)
    rank = torch.arange(agent.shape[0]) - torch.searchsorted(agent, agent)  # place in its agent's run
    keep = (rank < h).nonzero().squeeze(1)
    key, agent, rank = key.index_select(0, keep), agent.index_select(0, keep), rank.index_select(0, keep)
    order = ((key >> rbits) & 0xFFFFFFFF) - 2**31
    t = (order ^ ((order >> 31) & 0x7FFFFFFF)).to(torch.int32).view(torch.float32)
    return agent, rank, t, key & ((1 << rbits) - 1)


def _sorted(key: Tensor) -> Tensor:
    """``key`` (a CPU ``int64`` tensor of the caller's own) sorted in place by NumPy's sort."""
    key.numpy().sort()
    return key
