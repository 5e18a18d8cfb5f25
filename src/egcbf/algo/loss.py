"""The loss of the paper (Learning Safe Distributed Policy), in GCBF+'s discretization.

Per agent ``i`` of every graph in the minibatch, with ``h_i`` the learned CBF, ``u_i`` the policy's (normalized)
control and ``u_ref,i`` the reference (``u_QP`` for GCBF+ / EGCBF+, ``u_nom`` for GCBF / EGCBF)::

    L = eta_unsafe * mean_{i unsafe} relu(gamma + h_i)
      + eta_safe   * mean_{i safe}   relu(gamma - h_i)
      + eta_d      * mean_{all i}    relu(gamma - hdot_i - alpha h_i)
      + eta_c      * mean_{all i}    ||u_i - u_ref,i||^2        (or ||.|| with control="norm", the paper's form)

``hdot_i = (h_i(x') - h_i(x)) / dt`` with ``x'`` one dynamics step with the policy's control, the graph refreshed
with the same topology (GCBF+). For unlabelled agents (neither safe nor unsafe) the derivative term only trains
the policy: ``h`` and ``h(x')`` come from the CBF with its parameters frozen (``h_frozen``, ``h_next_frozen``), as
GCBF+ does (it freezes ``h(x')`` and the finite difference; we also freeze the ``alpha h`` term, so that an
unlabelled state never pushes the CBF itself). Means over empty label sets are 0.

Choices against the paper (docs/learning.md): means rather than sums (sizes of minibatches and label sets then do
not rescale the weights; GCBF+); the squared control error by default (smooth at 0; GCBF+), the paper's norm with
``control="norm"``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["cbf_loss"]


def _masked_mean(v: Tensor, mask: Tensor) -> Tensor:
    m = mask.to(v.dtype)
    return (v * m).sum() / m.sum().clamp_min(1.0)


def cbf_loss(
    h: Tensor,
    h_next: Tensor,
    safe: Tensor,
    unsafe: Tensor,
    u: Tensor,
    u_ref: Tensor,
    dt: float,
    *,
    gamma: float = 0.02,
    alpha: float = 1.0,
    eta_d: float = 0.2,
    eta_c: float = 1.0,
    eta_safe: float = 1.0,
    eta_unsafe: float = 1.0,
    control: str = "squared",
    h_frozen: Tensor | None = None,
    h_next_frozen: Tensor | None = None,
    hdot_labelled: Tensor | None = None,
) -> dict[str, Tensor]:
    """The loss terms and diagnostics (module doc).

    Args:
        h, h_next: ``(M,)`` CBF values at ``x`` and at the next state (with gradients).
        safe, unsafe: ``(M,)`` bool labels.
        u, u_ref: ``(M, k)`` the policy's and the reference's normalized commands (``k`` the command interface's
            width: 3 for the acceleration interface, 4 for torque and thrust; ``u_ref`` is not differentiated).
        dt: the control period of the finite difference.
        h_frozen, h_next_frozen: the same values from the CBF with frozen parameters (gradient to the action only),
            used for unlabelled agents; ``None``: use ``h`` and ``h_next`` everywhere.
        hdot_labelled: ``(M,)`` bool, the agents whose derivative term trains the CBF too (default: the labelled
            ones, ``safe | unsafe``); the others use the frozen values.

    Returns:
        dict with ``total`` and the weighted-sum parts ``unsafe``, ``safe``, ``hdot``, ``control`` (unweighted), and
        the accuracies ``acc_unsafe`` (h < 0 on unsafe), ``acc_safe`` (h > 0 on safe), ``acc_hdot``
        (hdot + alpha h > 0), all 0-dim tensors.
    """
    if control not in ("squared", "norm"):
        raise ValueError(f"control must be 'squared' or 'norm', got {control!r}")
    safe, unsafe = safe.bool(), unsafe.bool()
    l_unsafe = _masked_mean(torch.relu(gamma + h), unsafe)
    l_safe = _masked_mean(torch.relu(gamma - h), safe)
    hdot = (h_next - h) / dt
    v = torch.relu(gamma - hdot - alpha * h)
    condition = hdot + alpha * h  # the one-step CBF condition's left side, per agent (for the accuracy)
    if h_next_frozen is not None:
        hf = h.detach() if h_frozen is None else h_frozen
        cond_frozen = (h_next_frozen - hf) / dt + alpha * hf.detach()
        v_frozen = torch.relu(gamma - cond_frozen)
        own = safe | unsafe if hdot_labelled is None else hdot_labelled.bool()
        v = torch.where(own, v, v_frozen)
        # the other agents' h_next is read on a graph without their neighbours: their condition is the frozen one
        condition = torch.where(own, condition, cond_frozen)
    l_hdot = v.mean()
    err = (u - u_ref.detach()).square().sum(-1)
    l_control = (err if control == "squared" else err.clamp_min(1e-12).sqrt()).mean()
    total = eta_unsafe * l_unsafe + eta_safe * l_safe + eta_d * l_hdot + eta_c * l_control
    with torch.no_grad():
        acc_unsafe = _masked_mean((h < 0).to(h.dtype), unsafe)
        acc_safe = _masked_mean((h > 0).to(h.dtype), safe)
        acc_hdot = (condition > 0).to(h.dtype).mean()
    return {
        "total": total,
        "unsafe": l_unsafe,
        "safe": l_safe,
        "hdot": l_hdot,
        "control": l_control,
        "acc_unsafe": acc_unsafe,
        "acc_safe": acc_safe,
        "acc_hdot": acc_hdot,
    }
