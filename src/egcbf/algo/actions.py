"""Controls in units of the actuator box, and how the policy's residual becomes a control.

The body-frame control ``u = (tau (3), F3)`` mixes units (N m, N) and scales (``|tau| <= 1e-2``, ``F3 <= 0.59``).
Learning, the QP and the loss all work with the *normalized* control ``u~ = u / u_max`` with
``u_max = (max_torque (3), max_thrust)``, so every component lives in ``[-1, 1]`` (thrust in ``[0, 1]``) and
``||u~ - u~_ref||^2`` weighs torque and thrust alike. The scaling is a per-channel constant, so it commutes with the
(trivial) group action on the body-frame control.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..dynamics.quadrotor import DEFAULT_PARAMS, QuadrotorParams

__all__ = ["control_bounds", "control_scale", "normalize", "policy_control", "unnormalize"]


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


def policy_control(
    residual: Tensor,
    u_nom: Tensor,
    action_scale: float | Sequence[float],
    params: QuadrotorParams = DEFAULT_PARAMS,
):
    """The applied normalized control ``clip(u~_nom + action_scale * residual)`` (GCBF+: ``clip(2 pi + u_ref)``).

    ``residual`` ``(..., 4)`` is the policy output in ``[-1, 1]^4``; ``u_nom`` the nominal control in physical
    units; ``action_scale`` one number or four (per channel: ``ModelConfig.action_scales``). Returns the
    normalized control (multiply by :func:`control_scale` for physical units). The clip is a ``clamp`` (its
    gradient is zero where the box is active, as for the applied control).
    """
    lo, hi = control_bounds(residual)
    if not isinstance(action_scale, (int, float)):
        action_scale = torch.as_tensor(action_scale, dtype=residual.dtype, device=residual.device)
    u = normalize(u_nom, params).to(residual.dtype) + action_scale * residual
    return torch.maximum(torch.minimum(u, hi), lo)
