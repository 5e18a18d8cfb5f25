"""Counter-based random draws: every random number of a fault is a pure function of its *address*.

A draw's address is a tuple of integers, e.g. ``(episode seed, stream, step, receiver, sender)``; the number is a
hash of it (SplitMix64's finalizer, chained). So a fault's draws do not depend on how episodes are batched, on the
order of a graph's edges, or on how many other draws were made, and a rotated copy of a scene can be given the same
draws rotated (the equivariance tests of :mod:`egcbf.faults`). Plain torch on int64 (wrapping arithmetic), on any
device.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["normal", "uniform"]

_M1 = 0xBF58476D1CE4E5B9 - (1 << 64)  # SplitMix64's constants as signed int64
_M2 = 0x94D049BB133111EB - (1 << 64)
_GOLDEN = 0x9E3779B97F4A7C15 - (1 << 64)


def _shr(x: Tensor, k: int) -> Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic)."""
    return (x >> k) & ((1 << (64 - k)) - 1)


def _mix(x: Tensor) -> Tensor:
    x = x + _GOLDEN
    x = (x ^ _shr(x, 30)) * _M1
    x = (x ^ _shr(x, 27)) * _M2
    return x ^ _shr(x, 31)


def _hash(address: tuple) -> Tensor:
    tensors = [a if isinstance(a, Tensor) else torch.as_tensor(int(a)) for a in address]
    device = next((a.device for a in tensors if a.dim() > 0), tensors[0].device)
    h = torch.zeros((), dtype=torch.int64, device=device)
    for a in tensors:
        h = _mix(h ^ a.to(device=device, dtype=torch.int64))
    return h


def uniform(*address, dtype: torch.dtype = torch.float64) -> Tensor:
    """Uniform numbers in ``[0, 1)`` (53 bits), one per element of the broadcast address tensors."""
    return (_shr(_hash(address), 11).to(torch.float64) * 2.0**-53).to(dtype)


def normal(*address, dtype: torch.dtype = torch.float64) -> Tensor:
    """Standard normal numbers (Box-Muller on two uniforms of the address), one per element of the broadcast
    address."""
    u1 = uniform(*address, 0)
    u2 = uniform(*address, 1)
    r = torch.sqrt(-2.0 * torch.log1p(-u1))  # 1 - u1 in (0, 1]: finite
    return (r * torch.cos(2.0 * math.pi * u2)).to(dtype)
