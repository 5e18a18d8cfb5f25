"""The certificate's rates: counts over a recorded rollout, pooling, and exact binomial (Clopper-Pearson) bounds.

Sampled states are the agent-states ``x_t`` at every ``stride``-th step ``t < T`` (the last state has no successor).
With ``W`` the look-ahead window (steps) and ``c_t`` the collision mask, for each barrier ``h``:

* containment: among sampled states in collision, those with ``h >= 0`` (``unsafe_claimed`` of ``unsafe``);
* miss rate: among sampled states not in collision from which the agent collides within ``1 .. W`` steps, those with
  ``h >= 0`` (``missed`` of ``preceding``);
* false-safe rate: among sampled states with ``h >= 0`` whose next ``W`` steps are known (the agent collides within
  them, or ``t + W <= T``), those in collision or preceding one (``false_safe`` of ``claims_known``);
* condition violation: among sampled states with ``h >= 0``, those where ``h(x_{t+1}) - h(x_t) < -dt kappa(h(x_t))``
  under the commands every agent applied (``violated`` of ``claims``); with a run-time filter also the states whose
  filter QP needed slack or braked (``filter_bad`` of ``states``) and the union of both (``violated_or_bad``);
* invariance: agent-episodes that start in ``{h >= 0}`` (``starts``), those that leave it at a later step
  (``breaches``), and of those the ones in collision at or after they left (``breaches_collided``);
* conservativeness: among sampled states with ``h < 0`` and ``t + W <= T``, those with no collision in
  ``t .. t + W`` (``cautious`` of ``negatives_known``).

States along one trajectory are correlated; the bounds treat the sampled states as independent draws (thinned by
``stride``), and each count of failures is given with the number of distinct agent-episodes it comes from
(``*_agents``) so that a reader can judge the clustering. ``histogram`` counts sampled states by time to collision
(0: in collision; ``1 .. W``; ``W + 1``: none within ``W``, known) and ``h`` bin (:data:`H_BINS`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import torch
from torch import Tensor

from .rollout import Trajectory

__all__ = ["H_BINS", "RATES", "bin_centers", "clopper_pearson", "count_rates", "pool_counts", "rate"]

#: ``(low, high, width)`` of the histogram's ``h`` bins; values outside go to the first or last bin
H_BINS = (-1.0, 2.0, 0.02)

#: the reported rates: name -> (failures key, trials key, agent-episodes key or None, two-sided bound?)
RATES = {
    "containment": ("unsafe_claimed", "unsafe", "unsafe_claimed_agents", False),
    "miss": ("missed", "preceding", "missed_agents", False),
    "false_safe": ("false_safe", "claims_known", None, False),
    "violation": ("violated", "claims", "violated_agents", False),
    "filter_bad": ("filter_bad", "filter_states", None, False),
    "violation_or_bad": ("violated_or_bad", "claims", None, False),
    "breach": ("breaches", "starts", None, False),
    "breach_collided": ("breaches_collided", "breaches", None, False),
    "cautious": ("cautious", "negatives_known", None, True),
}


def _num_bins() -> int:
    lo, hi, w = H_BINS
    return round((hi - lo) / w)


def bin_centers() -> list[float]:
    """The ``h`` value at the centre of each histogram bin."""
    lo, _, w = H_BINS
    return [lo + (k + 0.5) * w for k in range(_num_bins())]


def _agents(mask: Tensor) -> int:
    """How many agent-episodes (the last two dims of ``(S, B, N)``) have any entry of ``mask``."""
    return int(mask.any(0).sum())


def count_rates(traj: Trajectory, name: str, kappa, *, window: int = 32, stride: int = 4) -> dict:
    """The counts of the module doc for barrier ``name`` of ``traj``; ``kappa`` its class-K function (on tensors)."""
    if window < 1 or stride < 1:
        raise ValueError(f"count_rates: window and stride must be >= 1, got {window}, {stride}")
    h = traj.h[name]
    coll = traj.collision
    steps = coll.shape[0] - 1  # T
    big = steps + window + 10
    # next collision at or after t, as a step index (big: none)
    nxt = torch.full_like(coll, big, dtype=torch.long)
    run = torch.full(coll.shape[1:], big, dtype=torch.long)
    for t in range(steps, -1, -1):
        run = torch.where(coll[t], torch.full_like(run, t), run)
        nxt[t] = run
    ts = torch.arange(0, steps, stride)
    hs, cs = h[ts], coll[ts]
    ttc = nxt[ts] - ts.view(-1, 1, 1)  # 0: in collision now
    known = (ttc <= window) | ((ts + window) <= steps).view(-1, 1, 1)
    claim = hs >= 0
    preceding = ~cs & (ttc <= window)
    h_next = h[ts + 1]
    finite = torch.isfinite(hs)
    violated = claim & finite & (h_next - hs < -traj.dt * kappa(torch.where(finite, hs, 0.0)))
    out = {
        "states": int(ts.numel() * hs[0].numel()),
        "unsafe": int(cs.sum()),
        "unsafe_claimed": int((cs & claim).sum()),
        "unsafe_claimed_agents": _agents(cs & claim),
        "preceding": int(preceding.sum()),
        "missed": int((preceding & claim).sum()),
        "missed_agents": _agents(preceding & claim),
        "claims_known": int((claim & known).sum()),
        "false_safe": int((claim & known & (ttc <= window)).sum()),
        "claims": int(claim.sum()),
        "violated": int(violated.sum()),
        "violated_agents": _agents(violated),
    }
    if traj.filter_bad is not None:
        bad = traj.filter_bad[ts]
        out["filter_states"] = int(bad.numel())
        out["filter_bad"] = int(bad.sum())
        out["violated_or_bad"] = int((claim & (violated | bad)).sum())
    else:
        out["filter_states"] = 0
        out["filter_bad"] = 0
        out["violated_or_bad"] = out["violated"]
    neg_known = ~claim & ((ts + window) <= steps).view(-1, 1, 1)
    out["negatives_known"] = int(neg_known.sum())
    out["cautious"] = int((neg_known & (ttc > window)).sum())
    # invariance, over every step of each agent-episode
    start = h[0] >= 0
    below = h[1:] < 0
    left = start & below.any(0)
    first = torch.where(below.any(0), below.double().argmax(0) + 1, torch.full_like(start, big, dtype=torch.long))
    last_coll = torch.where(coll.any(0), steps - coll.flip(0).double().argmax(0), torch.full_like(first, -1))
    out["starts"] = int(start.sum())
    out["breaches"] = int(left.sum())
    out["breaches_collided"] = int((left & (last_coll >= first)).sum())
    # histogram: time to collision (0 .. window + 1) x h bin, sparse
    lo, _, w = H_BINS
    bins = ((hs.clamp(lo, 1e9) - lo) / w).floor().clamp(0, _num_bins() - 1).long()
    ttc_bin = ttc.clamp(max=window + 1)
    keep = known
    keys = (ttc_bin[keep] * _num_bins() + bins[keep]).flatten()
    uniq, counts = torch.unique(keys, return_counts=True)
    out["histogram"] = {f"{int(k) // _num_bins()}:{int(k) % _num_bins()}": int(c) for k, c in zip(uniq, counts)}
    return out


def pool_counts(counts: Iterable[Mapping]) -> dict:
    """The sum of several :func:`count_rates` results (histograms added bin by bin)."""
    total: dict = {}
    for c in counts:
        for k, v in c.items():
            if k == "histogram":
                hist = total.setdefault("histogram", {})
                for b, n in v.items():
                    hist[b] = hist.get(b, 0) + n
            else:
                total[k] = total.get(k, 0) + v
    return total


def clopper_pearson(k: int, n: int, two_sided: bool = False, level: float = 0.95) -> tuple[float, float]:
    """The exact binomial interval of ``k`` successes in ``n`` trials: ``(0, upper)`` one-sided at ``level`` (the
    ``level`` quantile of ``Beta(k + 1, n - k)``), or two-sided ``(lower, upper)``; ``n = 0``: ``(0, 1)``."""
    from scipy.stats import beta

    if not (0 <= k <= n):
        raise ValueError(f"clopper_pearson needs 0 <= k <= n, got k = {k}, n = {n}")
    if n == 0:
        return 0.0, 1.0
    a = (1 - level) / 2 if two_sided else 1 - level
    upper = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    lower = 0.0 if (k == 0 or not two_sided) else float(beta.ppf(a, k, n - k + 1))
    return lower, upper


def rate(counts: Mapping, name: str) -> dict:
    """One rate of :data:`RATES` from ``counts``: ``{"k", "n", "rate", "lower", "upper", "agents"}`` (``rate``
    NaN when ``n = 0``)."""
    fail, trials, agents, two = RATES[name]
    k, n = int(counts.get(fail, 0)), int(counts.get(trials, 0))
    lower, upper = clopper_pearson(k, n, two_sided=two)
    return {"k": k, "n": n, "rate": k / n if n else math.nan, "lower": lower, "upper": upper,
            "agents": None if agents is None else int(counts.get(agents, 0))}  # fmt: skip
