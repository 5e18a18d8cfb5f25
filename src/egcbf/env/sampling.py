"""Vectorized rejection sampling of well-separated points (agents' starts and goals).

GCBF+ convention: points uniform in ``[0, l]^d`` (``d = 3`` for the quadrotor, ``d = 2`` for a planar swarm; the
argument ``dim``), pairwise distance ``> min_separation`` (4 r), and outside every
obstacle inflated by ``obstacle_margin`` (4 r). GCBF+ places points one at a time; here every still-unplaced
point of every set is proposed at once per round: each unplaced slot draws one or more uniform candidates (more
when few slots are left, so that the last points of a crowded arena do not take hundreds of rounds), takes the
first one that is clear of the obstacles and of all placed points (a uniform draw from the free region, as in
sequential placement), and the slot's choice is kept unless it conflicts with the choice of a lower-indexed slot
of the same round (so the accepted set is conflict-free). Conflicts are found with the sparse cell-list search,
never with a dense ``N x N`` matrix.
Rounds are bounded; an impossible request raises ``ValueError`` (immediately if even the densest packing of
balls (``d = 3``) or discs (``d = 2``) cannot hold the points, see :func:`packing_feasible`, otherwise after
``max_rounds`` rounds).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..geometry.neighbors import radius_neighbors
from .obstacles import Obstacles

__all__ = ["packing_feasible", "sample_separated_points"]

_DENSEST_PACKING = math.pi / (3 * math.sqrt(2))  # 0.7405, Kepler (balls in 3-D; proved by Hales)
_DENSEST_DISC_PACKING = math.pi / (2 * math.sqrt(3))  # 0.9069, hexagonal (discs in 2-D; Thue, Fejes Toth)


def _check_dim(dim: int) -> int:
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 (planar) or 3 (spatial), got {dim!r}")
    return int(dim)


def packing_feasible(
    num_points: int, area_size: float, min_separation: float, dim: int = 3, extents: tuple[float, ...] | None = None
) -> bool:
    """Whether ``num_points`` points pairwise farther apart than ``min_separation`` can fit in ``[0, l]^dim`` (or in
    a box of sides ``extents``) by the densest-packing bound (a necessary condition, checked before any sampling).

    Points separated by ``sep`` have disjoint balls (``dim = 3``) or discs (``dim = 2``) of radius ``sep / 2``
    inside the cube/square ``[-sep/2, l + sep/2]^dim`` of side ``l + sep``. Translating that finite packing by the
    lattice ``(l + sep) Z^dim`` gives a periodic packing of all of space with the same density, so its density is
    at most the densest packing density: ``pi / (3 sqrt 2)`` for balls (Kepler's conjecture, Hales) and
    ``pi / (2 sqrt 3)`` for discs (Thue, Fejes Toth). The bound compares the summed *volume*
    ``N (4/3) pi (sep/2)^3`` with ``0.7405 (l + sep)^3`` in 3-D, and the summed *area* ``N pi (sep/2)^2`` with
    ``0.9069 (l + sep)^2`` in 2-D. A box of sides ``e_i`` tiles space the same way, with ``prod_i (e_i + sep)`` in
    place of ``(l + sep)^dim``.
    """
    sep, l = float(min_separation), float(area_size)
    dim = _check_dim(dim)
    cell = (l + sep) ** dim if extents is None else math.prod(float(e) + sep for e in extents)
    if dim == 2:
        return num_points * math.pi * (sep / 2) ** 2 <= _DENSEST_DISC_PACKING * cell
    return num_points * (4 / 3) * math.pi * (sep / 2) ** 3 <= _DENSEST_PACKING * cell


def sample_separated_points(
    num_envs: int,
    num_sets: int,
    num_points: int,
    area_size: float,
    min_separation: float,
    obstacles: Obstacles,
    obstacle_margin: float,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    max_rounds: int = 200,
    dim: int = 3,
    box: tuple[tuple[float, float], ...] | None = None,
    anchors: Tensor | None = None,
    max_offset: float | None = None,
) -> Tensor:
    """Sample ``(num_envs, num_sets, num_points, dim)`` points in ``[0, l]^dim`` (world frame), or in ``box`` (``dim``
    pairs ``(low, high)``, metres) if given; each set of each environment is separated.

    ``dim`` is 3 (the default; the quadrotor) or 2 (a planar swarm); ``obstacles`` must be ``dim``-dimensional
    (spheres or discs, centres ``(num_envs, K, dim)``). With ``dim = 3`` the generator is consumed exactly as it
    always was (the same seed gives the same points).

    Sets are independent (e.g. set 0 = start positions, set 1 = goals: a start may coincide with another agent's
    goal, as in GCBF+). Runs on the CPU with ``generator`` (reproducible); move the result with ``.to``.

    ``anchors`` ``(num_envs, num_sets, num_points, dim)`` with ``max_offset`` (m): each point within ``max_offset`` of
    its anchor (GCBF+'s goals within ``max_travel`` of their starts): its candidates are the anchor plus a uniform
    offset in ``[-max_offset, max_offset]^dim``, kept if inside the region and within the distance.

    Raises:
        ValueError: if the points cannot be placed (message names N, l and the separation).
    """
    b, s, n = int(num_envs), int(num_sets), int(num_points)
    sep, l = float(min_separation), float(area_size)
    dim = _check_dim(dim)
    extents = None
    if box is not None:
        if len(box) != dim or any(len(b) != 2 or not float(b[0]) < float(b[1]) for b in box):
            raise ValueError(f"box must be {dim} pairs (low, high) with low < high, got {box!r}")
        low = torch.tensor([float(b[0]) for b in box], dtype=dtype)
        extents = tuple(float(b[1]) - float(b[0]) for b in box)
        width = torch.tensor(extents, dtype=dtype)
    if obstacles.dim != dim:
        raise ValueError(
            f"obstacles must be {dim}-D (centers (B, K, {dim})) to sample {dim}-D points, got centers "
            f"{tuple(obstacles.centers.shape)}"
        )

    region = f"[0, {l:g}]^{dim}" if box is None else " x ".join(f"[{b[0]:g}, {b[1]:g}]" for b in box)

    def fail(reason: str) -> ValueError:
        return ValueError(
            f"cannot place N={n} agents (and goals) in the area {region} with pairwise separation > "
            f"{sep:g} and obstacle clearance {obstacle_margin:g}: {reason}. Use a larger area_size, fewer agents "
            "or obstacles, or a smaller agent_radius."
        )

    if (anchors is None) != (max_offset is None):
        raise ValueError("anchors and max_offset go together: pass both or neither")
    if anchors is not None:
        if tuple(anchors.shape) != (b, s, n, dim):
            raise ValueError(f"anchors must be {(b, s, n, dim)}, got {tuple(anchors.shape)}")
        if not float(max_offset) > 0:
            raise ValueError(f"max_offset must be > 0, got {max_offset!r}")
        anchors = anchors.to(dtype=dtype, device="cpu").reshape(b * s * n, dim)
    if not packing_feasible(n, l, sep, dim, extents):
        raise fail(f"even the densest {'sphere' if dim == 3 else 'disc'} packing cannot hold them")
    obstacles = obstacles.to(dtype=dtype, device="cpu")
    total = b * s * n
    pos = torch.zeros(total, dim, dtype=dtype)
    placed = torch.zeros(total, dtype=torch.bool)
    slot_ids = torch.arange(total)
    group = slot_ids // n  # env * S + set: points of different groups never conflict
    env = slot_ids // (s * n)
    pad = sep * (1 + 1e-9) + 1e-12  # search radius; the exact test below is distance <= sep
    for _ in range(max_rounds):
        todo = slot_ids[~placed]
        u = todo.shape[0]
        if u == 0:
            return pos.view(b, s, n, dim)
        # candidates per unplaced slot: 1 while most are unplaced, up to 64 for the last few (bounded work)
        per = int(min(64, max(1, -(-total // u))))
        cand_slot = todo.repeat_interleave(per)
        cand = torch.rand(u * per, dim, generator=generator, dtype=dtype)
        if anchors is not None:  # around each slot's anchor, inside the region and within the distance
            cand = anchors[cand_slot] + (2 * cand - 1) * float(max_offset)
            lo_r = torch.zeros(dim, dtype=dtype) if box is None else low
            hi_r = torch.full((dim,), l, dtype=dtype) if box is None else low + width
            inside = ((cand >= lo_r) & (cand <= hi_r)).all(-1)
            inside &= (cand - anchors[cand_slot]).norm(dim=-1) <= float(max_offset)
        else:
            cand = cand * l if box is None else low + cand * width
            inside = torch.ones(u * per, dtype=torch.bool)
        pi, _ = obstacles.near_pairs_flat(cand, env[cand_slot], obstacle_margin)
        clear = inside.clone()
        clear[pi] = False
        cand, cand_slot = cand[clear], cand_slot[clear]
        c = cand.shape[0]
        if c == 0:
            continue
        # conflicts among placed points and clear candidates (sparse search over both sets)
        old = slot_ids[placed]
        pts = torch.cat((pos[old], cand))
        owner = torch.cat((old, cand_slot))
        is_cand = torch.cat((torch.zeros(old.shape[0], dtype=torch.bool), torch.ones(c, dtype=torch.bool)))
        src, dst = radius_neighbors(pts, pad, group[owner], sort=False)
        close = (pts[src] - pts[dst]).norm(dim=-1) <= sep
        src, dst = src[close], dst[close]
        # a candidate is good if no placed point is within sep; each slot takes its first good candidate
        bad = torch.zeros(pts.shape[0], dtype=torch.bool)
        bad[dst[~is_cand[src]]] = True
        good = is_cand & ~bad
        rows = torch.arange(pts.shape[0])
        first = torch.full((total,), pts.shape[0], dtype=torch.long)
        first = first.scatter_reduce(0, owner[good], rows[good], reduce="amin")
        chosen = torch.zeros(pts.shape[0], dtype=torch.bool)
        chosen[first[first < pts.shape[0]]] = True
        # chosen candidates of different slots that conflict: the higher slot index waits for the next round
        clash = chosen[src] & chosen[dst] & (owner[src] < owner[dst])
        chosen[dst[clash]] = False
        new_rows = rows[chosen]
        pos[owner[new_rows]] = pts[new_rows]
        placed[owner[new_rows]] = True
    if bool(placed.all()):
        return pos.view(b, s, n, dim)
    missing = int((~placed).sum())
    raise fail(f"{missing} of {b * s * n} points still unplaced after {max_rounds} rounds of rejection sampling")
