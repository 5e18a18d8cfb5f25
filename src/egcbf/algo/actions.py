"""Body controls in units of the actuator box (the torque interface's command, :mod:`egcbf.algo.interface`).

The body-frame control ``u = (tau (3), F3)`` mixes units (N m, N) and scales (``|tau| <= 1e-2``, ``F3 <= 0.59``).
Learning, the QP and the loss all work with the *normalized* control ``u~ = u / u_max`` with
``u_max = (max_torque (3), max_thrust)``, so every component lives in ``[-1, 1]`` (thrust in ``[0, 1]``) and
``||u~ - u~_ref||^2`` weighs torque and thrust alike. The scaling is a per-channel constant, so it commutes with the
(trivial) group action on the body-frame control.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..robots.quadrotor.dynamics import DEFAULT_PARAMS, QuadrotorParams

__all__ = ["control_bounds", "control_scale", "normalize", "unnormalize"]


def control_scale(params: QuadrotorParams = DEFAULT_PARAMS, like: Tensor | None = None) -> Tensor:
    """``u_max = (max_torque (3), max_thrust)`` as a ``(4,)`` tensor (dtype/device of ``like``)."""
    kw = {} if like is None else {"dtype": like.dtype, "device": like.device}
    return torch.tensor((*params.max_torque, params.max_thrust), **kw)


def control_bounds(like: Tensor) -> tuple[Tensor, Tensor]:
    """Bounds of the normalized control: ``lo = (-1, -1, -1, 0)``, ``hi = (1, 1, 1, 1)``."""
    lo = torch.tensor((-1.0, -1.0, -1.0, 0.0), dtype=like.dtype, device=like.device)
    return lo, torch.ones(4, dtype=like.dtype, device=like.device)


def normalize(u: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """``u / u_max``."""
    return u / control_scale(params, u)


def unnormalize(u_norm: Tensor, params: QuadrotorParams = DEFAULT_PARAMS) -> Tensor:
    """``u~ * u_max``."""
    return u_norm * control_scale(params, u_norm)
