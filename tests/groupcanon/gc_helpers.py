"""Shared pieces of the groupcanon test suite: the groups under test, typed field layouts, graph-input strategies.

(Named ``gc_helpers`` rather than ``helpers`` so that it cannot collide with another test directory's module
under pytest's default ``prepend`` import mode.)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from hypothesis import strategies as st

from groupcanon import FieldType
from groupcanon import groups as gg
from groupcanon.features import Point, Scalar, Vector
from groupcanon.testing import strategies as gst

F64, F32 = torch.float64, torch.float32

#: Stated tolerances. float64: algebra exact to rounding, errors observed ~1e-14 (translations ~10);
#: float32: 1e-4 (scaled by the magnitude of the numbers compared where translations ~10 are involved).
TOL = {F64: 1e-10, F32: 1e-4}
#: Acceptance bound for wrapped graph layers in float64 (observed errors ~1e-14).
LAYER_TOL_F64 = 1e-9

# Theseus-style near-singular angles, plus their negatives where the principal branch matters.
NEAR_SINGULAR_ANGLES = (1e-5, 3e-3, math.pi - 1e-7, math.pi - 1e-11, 2 * math.pi - 1e-11)


def all_groups() -> list[gg.Group]:
    return [
        gg.SO2(),
        gg.SE2(),
        gg.SE2xR(),
        gg.SO3(),
        gg.SE3(),
        gg.Trivial(),
        gg.Cyclic(1),
        gg.Cyclic(5),
        gg.Cyclic(6),
        gg.CyclicSE2(4),
        gg.CyclicSE2xR(4),
        gg.Translation(2),
        gg.Product(gg.SE2(), gg.Translation(1)),
        gg.Product(gg.SO2(), gg.SO3()),
    ]


def group_id(G) -> str:
    return repr(G).replace("translation_scale=10", "").replace("()", "").replace(", )", ")").replace("(,", "(")


def in_out_types(G: gg.Group) -> tuple[FieldType, FieldType]:
    """Input/output layouts with invariant, rotated and (for groups with translations) translated channels."""
    d = G.space_dim
    t_in = FieldType(G, {"s": Scalar(2), "v": Vector(d), "p": Point(d)})
    t_out = FieldType(G, {"s": Scalar(3), "v": Vector(d, n=2), "p": Point(d)})
    return t_in, t_out


class GraphInput(NamedTuple):
    num_nodes: int
    edge_index: torch.Tensor
    x: torch.Tensor
    frames: torch.Tensor
    g: torch.Tensor  # (k, *element_shape): the global transforms to test with
    pos: torch.Tensor | None
    edge_attr: torch.Tensor | None


@st.composite
def graph_inputs(
    draw,
    G: gg.Group,
    t_in: FieldType,
    *,
    dtype: torch.dtype = F64,
    min_nodes: int = 1,
    max_nodes: int = 16,
    max_degree: int = 6,
    min_edges: int = 0,
    pos: bool = False,
    edge_type: FieldType | None = None,
    edge_dim: int = 0,
    n_g: int = 3,
) -> GraphInput:
    """A random graph with features, per-node frames, optional positions / edge attributes and global elements."""
    graph = draw(gst.graphs(min_nodes, max_nodes, max_degree=max_degree, min_edges=min_edges))
    n, e = graph.num_nodes, graph.edge_index.shape[1]
    x = draw(gst.features(t_in, batch=(n,), dtype=dtype))
    frames = draw(gst.elements(G, batch=(n,), dtype=dtype))
    g = draw(gst.elements(G, batch=(n_g,), dtype=dtype))
    p = draw(gst.features(FieldType(G, [Point(G.space_dim)]), batch=(n,), dtype=dtype, scale=3.0)) if pos else None
    if edge_type is not None:
        edge_attr = draw(gst.features(edge_type, batch=(e,), dtype=dtype))
    elif edge_dim:
        edge_attr = draw(gst.features(FieldType(G, [Scalar(edge_dim)]), batch=(e,), dtype=dtype))
    else:
        edge_attr = None
    return GraphInput(n, graph.edge_index, x, frames, g, p, edge_attr)


def fixed_graph(n: int = 12, seed: int = 0, degree: int = 3) -> torch.Tensor:
    """A deterministic graph in which every node receives from ``degree`` distinct other nodes."""
    gen = torch.Generator().manual_seed(seed)
    src, dst = [], []
    for v in range(n):
        cand = torch.randperm(n, generator=gen)
        cand = cand[cand != v][:degree]
        src.append(cand)
        dst.append(torch.full((cand.numel(),), v, dtype=torch.long))
    return torch.stack((torch.cat(src), torch.cat(dst)))
