"""The cell-list neighbour search equals the dense brute-force reference."""

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from egcbf.geometry import neighbors
from egcbf.geometry.neighbors import brute_force_neighbors, radius_neighbors, radius_search


@st.composite
def point_sets(draw):
    m = draw(st.integers(0, 60))
    d = draw(st.sampled_from([1, 2, 3]))
    seed = draw(st.integers(0, 2**31 - 1))
    gen = torch.Generator().manual_seed(seed)
    extent = draw(st.floats(0.1, 5.0))
    pos = torch.rand(m, d, generator=gen, dtype=torch.float64) * extent
    if m and draw(st.booleans()):  # duplicated points and points on a lattice (ties with the cell boundaries)
        pos = torch.round(pos * 4) / 4
    nb = draw(st.integers(1, 4))
    batch = torch.randint(0, nb, (m,), generator=gen) if draw(st.booleans()) else None
    radius = draw(st.floats(0.05, 2.0))
    return pos, radius, batch


@given(data=point_sets(), loop=st.booleans(), k=st.sampled_from([1, 2, 3]), chunk=st.sampled_from([1, 7, 2**21]))
def test_equals_brute_force(data, loop, k, chunk):
    pos, radius, batch = data
    got = radius_neighbors(pos, radius, batch, loop=loop, cells_per_radius=k, max_candidates=chunk)
    ref = brute_force_neighbors(pos, radius, batch, loop=loop)
    assert got.dtype == torch.long and got.shape[0] == 2
    assert torch.equal(got, ref)


@given(data=point_sets())
def test_unsorted_same_set_and_symmetric(data):
    pos, radius, batch = data
    got = radius_neighbors(pos, radius, batch, sort=False)
    ref = brute_force_neighbors(pos, radius, batch)
    m = max(pos.shape[0], 1)
    assert sorted((got[1] * m + got[0]).tolist()) == sorted((ref[1] * m + ref[0]).tolist())
    assert sorted((got[0] * m + got[1]).tolist()) == sorted((got[1] * m + got[0]).tolist())


@given(a=point_sets(), b=point_sets(), k=st.sampled_from([1, 2]))
def test_bipartite_search_equals_brute_force(a, b, k):
    x, radius, _ = a
    y = b[0]
    if x.shape[1] != y.shape[1]:
        y = torch.rand(y.shape[0], x.shape[1], dtype=torch.float64)
    gen = torch.Generator().manual_seed(x.shape[0] * 7 + y.shape[0])
    bx = torch.randint(0, 2, (x.shape[0],), generator=gen)
    by = torch.randint(0, 2, (y.shape[0],), generator=gen)
    got = radius_search(x, y, radius, bx, by, cells_per_radius=k)
    adj = ((x[:, None] - y[None]).square().sum(-1) < radius**2) & (bx[:, None] == by[None])
    i, j = adj.nonzero(as_tuple=True)
    assert torch.equal(got, torch.stack((j, i)))


@given(data=point_sets(), search=st.sampled_from(["k-d tree", "cell list"]))
def test_radius_pairs_hold_every_pair_once(data, search):
    """``radius_pairs`` (the k-d tree on the CPU, or the cell list) returns every unordered pair of one batch id
    closer than the reach, each once, and perhaps pairs at the reach up to rounding; nothing farther."""
    pos, radius, batch = data
    m = pos.shape[0]
    batch = torch.zeros(m, dtype=torch.long) if batch is None else batch
    pairs = neighbors._kd_tree_pairs if search == "k-d tree" else neighbors._cell_list_pairs
    u, v = pairs(pos, batch, radius) if m >= 2 else neighbors.radius_pairs(pos, batch, radius)
    got = sorted(zip(torch.minimum(u, v).tolist(), torch.maximum(u, v).tolist()))
    assert len(got) == len(set(got)) and all(a != b and batch[a] == batch[b] for a, b in got)
    d2 = (pos[:, None] - pos[None]).square().sum(-1)
    same = batch[:, None] == batch[None]
    want = {(a, b) for a, b in (torch.triu(same & (d2 < radius**2), 1)).nonzero().tolist()}
    near = {(a, b) for a, b in (torch.triu(same & (d2 <= radius**2 * (1 + 1e-9)), 1)).nonzero().tolist()}
    assert want <= set(got) <= near


def test_sparse_occupancy_uses_binary_search_and_agrees():
    """Two far-apart clusters: the grid is too large for a cell table, the searchsorted path must agree."""
    gen = torch.Generator().manual_seed(1)
    pos = torch.cat((torch.rand(40, 3, generator=gen), 1e4 + torch.rand(40, 3, generator=gen))).double()
    assert (1e4 / 0.3) ** 3 > neighbors._TABLE_FACTOR * 80 + 2**16
    assert torch.equal(radius_neighbors(pos, 0.3), brute_force_neighbors(pos, 0.3))


def test_float32_and_exact_boundary_is_excluded():
    pos = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.5, 0.0]], dtype=torch.float32)
    e = radius_neighbors(pos, 1.0)  # distance exactly 1 is not < 1
    assert {tuple(c) for c in e.t().tolist()} == {(2, 0), (0, 2)}


def test_large_sparse_set_is_linear_not_dense():
    gen = torch.Generator().manual_seed(0)
    n = 20000  # a dense 20000^2 float64 distance matrix would need 3.2 GB
    pos = torch.rand(n, 3, generator=gen, dtype=torch.float64) * n ** (1 / 3)
    e = radius_neighbors(pos, 1.0, max_candidates=2**16)
    d = (pos[e[0]] - pos[e[1]]).norm(dim=-1)
    assert (d < 1.0).all() and (e[0] != e[1]).all()
    # expected number of neighbours at density 1: 4/3 pi (minus boundary effects)
    assert 2.5 * n < e.shape[1] < 4.3 * n


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"radius": 0.0}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"radius": 1.0, "cells_per_radius": 0}, "cells_per_radius"),
        ({"radius": 1.0, "batch": torch.zeros(2, dtype=torch.long)}, "batch"),
        ({"radius": 1.0, "batch": torch.zeros(3)}, "integer"),
    ],
)
def test_bad_inputs(kwargs, match):
    with pytest.raises(ValueError, match=match):
        radius_neighbors(torch.zeros(3, 3), **kwargs)


def test_non_finite_positions_raise():
    with pytest.raises(ValueError, match="NaN"):
        radius_neighbors(torch.tensor([[0.0, 0.0, float("nan")]]), 1.0)
    with pytest.raises(ValueError, match=r"\(num_points, dim\)"):
        radius_neighbors(torch.zeros(3), 1.0)
