"""The O(2) group (2 x 2 orthogonal matrices, escnn's (flip, theta) convention): axioms, actions, parts."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given

from groupcanon import FieldType
from groupcanon.features import Point, Rotation, SO2Irrep, Vector
from groupcanon.groups import O2
from groupcanon.testing import check_action_laws, check_group_axioms
from groupcanon.testing import strategies as gst

G = O2()
TOL = {torch.float64: 1e-10, torch.float32: 1e-4}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_group_axioms(dtype):
    check_group_axioms(G, dtype=dtype, atol=TOL[dtype])


@given(a=gst.elements(G, batch=(16,)), b=gst.elements(G, batch=(16,)), c=gst.elements(G, batch=(16,)))
def test_group_axioms_hypothesis(a, b, c):
    check_group_axioms(G, elements=(a, b, c))


@pytest.mark.parametrize("feature", [Vector(2), Point(2, n=3), Rotation()], ids=repr)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_action_laws(feature, dtype):
    check_action_laws(G, FieldType(G, [feature]), dtype=dtype, atol=TOL[dtype])


def test_layout_and_parts():
    theta = torch.tensor([0.0, 0.3, -2.0, math.pi - 1e-11], dtype=torch.float64)
    flip = torch.tensor([False, True, True, False])
    g = G.element(theta, flip)
    assert g.shape == (4, 2, 2)
    torch.testing.assert_close(G.angle(g), theta, atol=1e-12, rtol=0)
    assert torch.equal(G.flip(g), flip)
    # R(theta) M^f: reflect across the x axis first, then rotate
    m = torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64))
    r = G.element(theta, False)
    torch.testing.assert_close(g, torch.where(flip[:, None, None], r @ m, r), atol=0, rtol=0)
    torch.testing.assert_close(g @ g.transpose(-1, -2), torch.eye(2, dtype=torch.float64).expand(4, 2, 2))
    torch.testing.assert_close(torch.linalg.det(g), 1.0 - 2.0 * flip.double())


def test_sample_is_haar_like():
    g = G.sample(20000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert abs(G.flip(g).double().mean().item() - 0.5) < 0.02
    assert abs(torch.cos(G.angle(g)).mean().item()) < 0.03
    assert G.special_elements().shape[1:] == (2, 2)
    assert G.flip(G.special_elements()).any() and not G.flip(G.special_elements()).all()


def test_no_so2_part():
    with pytest.raises(ValueError, match="SO\\(2\\) part"):
        FieldType(G, [SO2Irrep(1)])
