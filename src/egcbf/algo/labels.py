"""Finite-horizon safe / unsafe labels of rollouts (GCBF+'s approximation of the control-invariant set).

For a trajectory of ``L`` states with per-agent unsafe masks ``u_t`` (agent–agent distance ``< 2.5 r`` or inside
an obstacle inflated by ``1.5 r``, :class:`egcbf.env.StepInfo`):

* unsafe at ``t``: ``u_t``;
* safe at ``t``: no unsafe state in ``[t, t + T]`` (the policy that produced the rollout kept the agent safe for
  ``T`` more steps);
* otherwise unlabelled (it becomes unsafe within ``T`` steps: neither a safe nor an unsafe example).

Windows cut by the end of the rollout count what they see (GCBF+ does the same): a state in the last ``T`` steps
is safe if no unsafe state follows it *within the rollout*. ``truncated_safe=False`` leaves such states
unlabelled instead (conservative, at the price of fewer labels for short rollouts).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["finite_horizon_labels"]


def finite_horizon_labels(unsafe: Tensor, horizon: int, truncated_safe: bool = True) -> tuple[Tensor, Tensor]:
    """Safe and unsafe masks from per-step unsafe masks.

    Args:
        unsafe: ``(L, *batch)`` bool, time first (e.g. ``(L, B, N)``).
        horizon: ``T >= 0`` steps of look-ahead (``T = 0``: safe = not unsafe).
        truncated_safe: label windows cut by the rollout end as safe when no unsafe state is seen (GCBF+).

    Returns:
        ``(safe, unsafe)``, both ``(L, *batch)`` bool and disjoint.
    """
    if unsafe.dtype != torch.bool or unsafe.dim() < 1:
        raise ValueError(f"unsafe must be a bool tensor (L, ...), got {unsafe.dtype} {tuple(unsafe.shape)}")
    if int(horizon) != horizon or horizon < 0:
        raise ValueError(f"horizon must be an integer >= 0, got {horizon!r}")
    length = unsafe.shape[0]
    # prefix counts: c[k] = number of unsafe states in [0, k)
    c = torch.cat((torch.zeros_like(unsafe[:1], dtype=torch.long), unsafe.long().cumsum(0)))
    t = torch.arange(length, device=unsafe.device)
    end = torch.clamp(t + horizon + 1, max=length)  # window [t, end)
    shape = (length,) + (1,) * (unsafe.dim() - 1)
    count = c[end] - c[t]
    safe = count == 0
    if not truncated_safe:
        safe &= (t + horizon < length).view(shape)
    return safe, unsafe.clone()
