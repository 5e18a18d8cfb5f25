"""docs/groupcanon.md's statement about e3nn, checked against e3nn's own matrices where e3nn is installed: its
``1o`` irreps are plain ``(x, y, z)`` vectors (``D_from_matrix(R) == R``), the order of ``Vector(3)``."""

import pytest
import torch

from groupcanon import FieldType
from groupcanon import groups as gg
from groupcanon.features import Vector

o3 = pytest.importorskip("e3nn.o3")


def test_e3nn_1o_is_our_vector_without_permutation():
    group = gg.SO3()
    g = group.sample(8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    R = group.rotation(g)
    D = o3.Irreps("1o").D_from_matrix(R)
    assert torch.allclose(D, R, atol=1e-12)
    v = torch.randn(8, 3, dtype=torch.float64)
    ours = FieldType(group, [Vector(3)]).act(g, v)
    assert torch.allclose(ours, torch.einsum("bij,bj->bi", D, v), atol=1e-12)
