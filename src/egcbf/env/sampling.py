"""Vectorized rejection sampling of well-separated points (agents' starts and goals).

GCBF+ convention: points uniform in ``[0, l]^3``, pairwise distance ``> min_separation`` (4 r), and outside every
obstacle inflated by ``obstacle_margin`` (4 r). GCBF+ places points one at a time; here every still-unplaced
point of every set is proposed at once per round: each unplaced slot draws one or more uniform candidates (more
when few slots are left, so that the last points of a crowded arena do not take hundreds of rounds), takes the
first one that is clear of the obstacles and of all placed points (a uniform draw from the free region, as in
sequential placement), and the slot's choice is kept unless it conflicts with the choice of a lower-indexed slot
of the same round (so the accepted set is conflict-free). Conflicts are found with the sparse cell-list search,
never with a dense ``N x N`` matrix.
Rounds are bounded; an impossible request raises ``ValueError`` (immediately if even the densest sphere packing
cannot hold the points, otherwise after ``max_rounds`` rounds).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..neighbors import radius_neighbors
from .obstacles import Obstacles

__all__ = ["packing_feasible", "sample_separated_points"]

_DENSEST_PACKING = math.pi / (3 * math.sqrt(2))  # 0.7405, Kepler


def packing_feasible(num_points: int, area_size: float, min_separation: float) -> bool:
    """Whether ``num_points`` points pairwise farther apart than ``min_separation`` can fit in ``[0, l]^3`` by the
    densest-packing bound (a necessary condition, checked before any sampling: points separated by ``sep`` have
    disjoint balls of radius ``sep / 2`` inside ``[-sep/2, l + sep/2]^3``)."""
    sep, l = float(min_separation), float(area_size)
    return num_points * (4 / 3) * math.pi * (sep / 2) ** 3 <= _DENSEST_PACKING * (l + sep) ** 3


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
) -> Tensor:
    """Sample ``(num_envs, num_sets, num_points, 3)`` points; each set of each environment is separated.

    Sets are independent (e.g. set 0 = start positions, set 1 = goals: a start may coincide with another agent's
    goal, as in GCBF+). Runs on the CPU with ``generator`` (reproducible); move the result with ``.to``.

    Raises:
        ValueError: if the points cannot be placed (message names N, l and the separation).
    """
    b, s, n = int(num_envs), int(num_sets), int(num_points)
    sep, l = float(min_separation), float(area_size)

    def fail(reason: str) -> ValueError:
        return ValueError(
            f"cannot place N={n} agents (and goals) in the area [0, {l:g}]^3 with pairwise separation > "
            f"{sep:g} and obstacle clearance {obstacle_margin:g}: {reason}. Use a larger area_size, fewer agents "
            "or obstacles, or a smaller agent_radius."
        )

    if not packing_feasible(n, l, sep):
        raise fail("even the densest sphere packing cannot hold them")
    obstacles = obstacles.to(dtype=dtype, device="cpu")
    total = b * s * n
    pos = torch.zeros(total, 3, dtype=dtype)
    placed = torch.zeros(total, dtype=torch.bool)
    slot_ids = torch.arange(total)
    group = slot_ids // n  # env * S + set: points of different groups never conflict
    env = slot_ids // (s * n)
    pad = sep * (1 + 1e-9) + 1e-12  # search radius; the exact test below is distance <= sep
    for _ in range(max_rounds):
        todo = slot_ids[~placed]
        u = todo.shape[0]
        if u == 0:
            return pos.view(b, s, n, 3)
        # candidates per unplaced slot: 1 while most are unplaced, up to 64 for the last few (bounded work)
        per = int(min(64, max(1, -(-total // u))))
        cand_slot = todo.repeat_interleave(per)
        cand = torch.rand(u * per, 3, generator=generator, dtype=dtype) * l
        pi, _ = obstacles.near_pairs_flat(cand, env[cand_slot], obstacle_margin)
        clear = torch.ones(u * per, dtype=torch.bool)
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
        return pos.view(b, s, n, 3)
    missing = int((~placed).sum())
    raise fail(f"{missing} of {b * s * n} points still unplaced after {max_rounds} rounds of rejection sampling")
