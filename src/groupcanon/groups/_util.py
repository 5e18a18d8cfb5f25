"""Small batched helpers shared by the built-in groups (planar complex numbers, sampling)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..group import default_dtype

# Angles where planar-rotation numerics are delicate (theseus' choice plus the exact half and full turns).
SPECIAL_ANGLES = (0.0, 1e-5, 3e-3, math.pi - 1e-7, math.pi - 1e-11, math.pi, 2 * math.pi - 1e-11, -1e-11)


def complex_mul(a: Tensor, b: Tensor) -> Tensor:
    """Product of unit complex numbers stored as ``(..., 2) = (cos, sin)``; batch dims broadcast."""
    ac, as_ = a[..., 0], a[..., 1]
    bc, bs = b[..., 0], b[..., 1]
    return torch.stack((ac * bc - as_ * bs, as_ * bc + ac * bs), dim=-1)


def complex_conj(a: Tensor) -> Tensor:
    return torch.stack((a[..., 0], -a[..., 1]), dim=-1)


def rotate2d(cs: Tensor, v: Tensor) -> Tensor:
    """Rotate planar vectors ``v`` ``(..., 2)`` by ``cs = (cos, sin)`` ``(..., 2)``."""
    c, s = cs[..., 0], cs[..., 1]
    x, y = v[..., 0], v[..., 1]
    return torch.stack((c * x - s * y, s * x + c * y), dim=-1)


def rotmat2d(cs: Tensor) -> Tensor:
    c, s = cs[..., 0], cs[..., 1]
    return torch.stack((torch.stack((c, -s), -1), torch.stack((s, c), -1)), -2)


def angle_to_cs(theta: Tensor) -> Tensor:
    return torch.stack((torch.cos(theta), torch.sin(theta)), dim=-1)


def uniform_angle(batch, generator, dtype, device) -> Tensor:
    """Haar-uniform angles in [0, 2 pi), shape ``batch``."""
    u = torch.rand(tuple(batch), generator=generator, dtype=default_dtype(dtype), device=device)  # batch may be ()
    return 2 * math.pi * u


def special_angle_tensor(dtype, device) -> Tensor:
    # Build in float64 so that pi - 1e-11 is not rounded to pi before the cast.
    return torch.tensor(SPECIAL_ANGLES, dtype=torch.float64, device=device).to(default_dtype(dtype))


def special_cs(dtype, device) -> Tensor:
    theta = torch.tensor(SPECIAL_ANGLES, dtype=torch.float64, device=device)
    return angle_to_cs(theta).to(default_dtype(dtype))


def gaussian(batch, dim, scale, generator, dtype, device) -> Tensor:
    return scale * torch.randn(*batch, dim, generator=generator, dtype=default_dtype(dtype), device=device)


def identity_cs(batch, dtype, device) -> Tensor:
    out = torch.zeros(*batch, 2, dtype=default_dtype(dtype), device=device)
    out[..., 0] = 1
    return out
