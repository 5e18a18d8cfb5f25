"""Hypothesis strategies for group elements, typed features and graphs.

Tensors are generated from a drawn seed with ``torch.Generator`` (fast, and shrinkable through the seed); group
elements mix in the group's ``special_elements`` (angles near 0, pi, 2 pi) so near-singular cases are always
tried.

    from hypothesis import given
    from groupcanon.testing import strategies as gst

    @given(g=gst.elements(G, batch=(16,)), x=gst.features(ftype, batch=(16,)))
    def test_roundtrip(g, x): ...
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from hypothesis import strategies as st

from ..field_type import FieldType
from ..group import Group, default_dtype

__all__ = ["Graph", "elements", "features", "graphs", "seeds"]


def seeds() -> st.SearchStrategy[int]:
    return st.integers(min_value=0, max_value=2**63 - 1)


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def elements(
    group: Group,
    batch: tuple[int, ...] = (),
    *,
    dtype: torch.dtype = torch.float64,
    device=None,
    special: bool = True,
) -> st.SearchStrategy[torch.Tensor]:
    """Elements of shape ``(*batch, *group.element_shape)``: Haar-random, or (if ``special``) batches in which
    each entry is, with some probability, one of the group's near-singular ``special_elements``."""
    dtype = default_dtype(dtype)

    def random(seed: int) -> torch.Tensor:
        return group.sample(*batch, generator=_generator(seed), dtype=dtype).to(device)

    base = seeds().map(random)
    if not special:
        return base

    def mixed(seed: int) -> torch.Tensor:
        gen = _generator(seed)
        sp = group.special_elements(dtype=dtype)
        rand = group.sample(*batch, generator=gen, dtype=dtype)
        if not batch:
            pick = int(torch.randint(0, sp.shape[0], (), generator=gen))
            return sp[pick].to(device)
        flat = rand.reshape(math.prod(batch), *group.element_shape)  # not -1: Trivial elements are empty
        use = torch.rand(flat.shape[0], generator=gen) < 0.5
        idx = torch.randint(0, sp.shape[0], (flat.shape[0],), generator=gen)
        flat = torch.where(use.view(-1, *([1] * len(group.element_shape))), sp[idx], flat)
        return flat.reshape(rand.shape).to(device)

    return st.one_of(base, seeds().map(mixed))


def features(
    field_type: FieldType,
    batch: tuple[int, ...] = (8,),
    *,
    dtype: torch.dtype = torch.float64,
    device=None,
    scale: float = 1.0,
) -> st.SearchStrategy[torch.Tensor]:
    """Gaussian feature tensors ``(*batch, field_type.dim)`` with standard deviation ``scale``."""
    dtype = default_dtype(dtype)

    def make(seed: int) -> torch.Tensor:
        return (scale * torch.randn(*batch, field_type.dim, generator=_generator(seed), dtype=dtype)).to(device)

    return seeds().map(make)


class Graph(NamedTuple):
    """A random directed graph: ``edge_index`` ``(2, E)`` (source, target), no duplicate edges."""

    num_nodes: int
    edge_index: torch.Tensor


def graphs(
    min_nodes: int = 1,
    max_nodes: int = 24,
    *,
    max_degree: int = 8,
    self_loops: bool = False,
    min_edges: int = 0,
) -> st.SearchStrategy[Graph]:
    """Random directed graphs with ``min_nodes..max_nodes`` nodes and in-degree at most ``max_degree``.

    Isolated nodes (no incoming edge) occur naturally and are part of the contract being tested.
    ``min_edges``: at least this many edges where ``max_degree`` and the node count allow it (the in-degree bound
    always holds).
    """

    @st.composite
    def build(draw) -> Graph:
        n = draw(st.integers(min_value=min_nodes, max_value=max_nodes))
        seed = draw(seeds())
        gen = _generator(seed)
        # a lower bound on the in-degree gives min_edges without ever exceeding max_degree
        lo = min(max_degree, -(-min_edges // n)) if n else 0
        deg = torch.randint(lo, max_degree + 1, (n,), generator=gen)
        src, dst = [], []
        for v in range(n):
            cand = torch.randperm(n, generator=gen)
            if not self_loops:
                cand = cand[cand != v]
            k = min(int(deg[v]), cand.numel())
            src.append(cand[:k])
            dst.append(torch.full((k,), v, dtype=torch.long))
        edge_index = torch.stack((torch.cat(src), torch.cat(dst))) if n else torch.zeros(2, 0, dtype=torch.long)
        return Graph(n, edge_index.long())

    return build()
