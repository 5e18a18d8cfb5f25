"""docs/groupcanon.md's and docs/escnn.md's statements about e3nn, checked against e3nn's own matrices where e3nn is
installed: its ``1o`` irreps are plain ``(x, y, z)`` vectors (``D_from_matrix(R) == R``), the order of
``Vector(3)``; and its degree-``l`` irreps are the real spherical harmonics of docs/escnn.md (escnn's basis) read on
the axes ``(z, x, y)``: ``D^l(R) = S_l(Pi) S_l(R) S_l(Pi)^T`` (``tests/groupcanon/real_harmonics.py``)."""

import numpy as np
import pytest
import torch
from real_harmonics import E3NN_AXES, harmonic_matrix

from groupcanon import FieldType
from groupcanon import groups as gg
from groupcanon.features import Vector

o3 = pytest.importorskip("e3nn.o3")


@pytest.fixture
def float64_default():
    """e3nn builds its generators in torch's default dtype: float64 for a tight comparison."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def _rotations(n: int, seed: int = 0):
    group = gg.SO3()
    g = group.sample(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return group, g, group.rotation(g)


def test_e3nn_1o_is_our_vector_without_permutation(float64_default):
    group, g, R = _rotations(8)
    D = o3.Irreps("1o").D_from_matrix(R)
    assert torch.allclose(D, R, atol=1e-12)
    v = torch.randn(8, 3, dtype=torch.float64)
    ours = FieldType(group, [Vector(3)]).act(g, v)
    assert torch.allclose(ours, torch.einsum("bij,bj->bi", D, v), atol=1e-12)


@pytest.mark.parametrize("l", [0, 1, 2, 3, 4, 5])
def test_e3nn_degree_l_is_the_stated_harmonics_on_permuted_axes(float64_default, l):
    _, _, R = _rotations(6, seed=l)
    axes = harmonic_matrix(l, E3NN_AXES)
    for rotation in R.numpy():
        D = o3.Irrep(l, (-1) ** l).D_from_matrix(torch.from_numpy(rotation)).numpy()
        np.testing.assert_allclose(D, axes @ harmonic_matrix(l, rotation) @ axes.T, atol=1e-11, rtol=0)
        if l >= 1:  # the permutation is not a no-op: without it the bases differ
            assert np.abs(D - harmonic_matrix(l, rotation)).max() > 0.1
