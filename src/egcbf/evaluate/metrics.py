"""Evaluation metrics of the paper's Table I (definitions in ``docs/metrics.md``).

Per agent ``i`` of an episode of ``T`` steps with collision mask ``c_i(t)`` and reached mask ``r_i(t)``
(``t = 1..T``, the states after each step; the initial state is collision-free by construction):

* safe_i    = 1 if ``c_i(t)`` is false at every step;
* reached_i = 1 if ``r_i(t)`` is true at some step;
* success_i = safe_i and reached_i;
* events_i  = number of collision *events*: rising edges of ``c_i`` (``c_i(t) and not c_i(t-1)``, with
  ``c_i(0) = False``), so an agent that stays in contact for 20 steps counts one collision;
* reward_i  = ``-sum_t ||u_i(t) - u_ref,i(t)||^2`` (the applied control against the reference/nominal control);
* steps_i   = number of steps in collision (reported as ``collision_steps``, the other reading of "cost").

Episode values average over its agents; the reported rates, cost and reward average over agents and episodes;
``cost_min`` / ``cost_max`` are the extremes of the per-episode cost over the episodes (the table's "(min/max)").
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["EpisodeStats", "summarize"]

_EPISODE_KEYS = ("safe_rate", "reach_rate", "success_rate", "cost", "reward")  # collision_steps is optional


class EpisodeStats:
    """Accumulates the metrics of ``B`` simultaneous episodes of ``N`` agents, one :meth:`update` per step.

    ``stats = EpisodeStats(B, N)``; every step ``stats.update(info, u=u, u_ref=u_nom)``; at the end
    ``stats.result()`` (a dict row) or ``stats.per_episode()`` (``(B,)`` tensors, to pool several batches with
    :func:`summarize`).

    ``counted`` (``(B, N)`` bool, ``None``: every agent): the agents the episode values average over (non-cooperative
    agents under :mod:`egcbf.faults` are not counted; collisions with them are); every episode must count the same
    number of agents, so that pooled means stay means over agents.
    """

    def __init__(
        self,
        num_envs: int,
        num_agents: int,
        device: torch.device | str | None = None,
        counted: Tensor | None = None,
    ):
        if int(num_envs) != num_envs or num_envs < 1 or int(num_agents) != num_agents or num_agents < 1:
            raise ValueError(f"EpisodeStats needs num_envs, num_agents >= 1, got {num_envs!r}, {num_agents!r}")
        self.num_envs, self.num_agents = int(num_envs), int(num_agents)
        shape = (self.num_envs, self.num_agents)
        if counted is not None:
            if tuple(counted.shape) != shape or counted.dtype != torch.bool:
                raise ValueError(
                    f"counted must be a bool tensor of shape {shape}, got {counted.dtype} {tuple(counted.shape)}"
                )
            per_env = counted.sum(1)
            if bool((per_env == 0).any()) or bool((per_env != per_env[0]).any()):
                raise ValueError(
                    f"counted must keep the same number (>= 1) of agents in every episode, got {per_env.tolist()}"
                )
            counted = counted.to(device)
        self.counted = counted
        self.ever_collided = torch.zeros(shape, dtype=torch.bool, device=device)
        self.ever_reached = torch.zeros(shape, dtype=torch.bool, device=device)
        self.prev_collision = torch.zeros(shape, dtype=torch.bool, device=device)
        self.collision_events = torch.zeros(shape, dtype=torch.long, device=device)
        self.collision_steps = torch.zeros(shape, dtype=torch.long, device=device)
        self.reward = torch.zeros(shape, dtype=torch.float64, device=device)
        self.steps = 0

    def update(self, info, u: Tensor | None = None, u_ref: Tensor | None = None) -> None:
        """Add one step: ``info`` has ``collision`` and ``reached`` ``(B, N)`` bool (a ``StepInfo`` or a dict);
        ``u`` and ``u_ref`` ``(B, N, nu)`` (both or neither) add ``-||u - u_ref||^2`` to each agent's reward."""
        coll = info["collision"] if isinstance(info, dict) else info.collision
        reach = info["reached"] if isinstance(info, dict) else info.reached
        shape = (self.num_envs, self.num_agents)
        for name, m in (("collision", coll), ("reached", reach)):
            if tuple(m.shape) != shape or m.dtype != torch.bool:
                raise ValueError(f"info.{name} must be a bool tensor of shape {shape}, got {m.dtype} {tuple(m.shape)}")
        coll = coll.to(self.ever_collided.device)
        self.collision_events += (coll & ~self.prev_collision).long()
        self.collision_steps += coll.long()
        self.prev_collision = coll.clone()
        self.ever_collided |= coll
        self.ever_reached |= reach.to(self.ever_reached.device)
        if (u is None) != (u_ref is None):
            raise ValueError("pass both u and u_ref (or neither) to accumulate the reward")
        if u is not None:
            if u.shape != u_ref.shape or tuple(u.shape[:2]) != shape:
                raise ValueError(
                    f"u and u_ref must both be (B, N, nu) with (B, N) = {shape}, got "
                    f"{tuple(u.shape)} and {tuple(u_ref.shape)}"
                )
            d = (u.detach().double() - u_ref.detach().double()).square().sum(-1)
            self.reward -= d.to(self.reward.device)
        self.steps += 1

    def per_episode(self) -> dict[str, Tensor]:
        """``(B,)`` float64 tensors: ``safe_rate``, ``reach_rate``, ``success_rate``, ``cost``, ``reward``,
        ``collision_steps`` (agent averages of each episode)."""
        safe = ~self.ever_collided
        if self.counted is None:

            def mean(v: Tensor) -> Tensor:
                return v.double().mean(1)
        else:
            w = self.counted.double()

            def mean(v: Tensor) -> Tensor:
                return (v.double() * w).sum(1) / w.sum(1)

        return {
            "safe_rate": mean(safe),
            "reach_rate": mean(self.ever_reached),
            "success_rate": mean(safe & self.ever_reached),
            "cost": mean(self.collision_events),
            "reward": mean(self.reward),
            "collision_steps": mean(self.collision_steps),
        }

    def result(self) -> dict[str, float | int]:
        """The table row: ``num_agents, safe_rate, reach_rate, success_rate, cost, cost_min, cost_max, reward``
        (rates are fractions in ``[0, 1]``), plus ``collision_steps``, ``num_episodes`` and ``steps``."""
        row = summarize(self.per_episode(), self.num_agents)
        row["steps"] = self.steps
        return row


def summarize(per_episode: dict[str, Tensor], num_agents: int) -> dict[str, float | int]:
    """Pool per-episode values (``(E,)`` tensors, e.g. concatenated from several :class:`EpisodeStats`) into a
    row. Every episode has ``num_agents`` agents, so the mean over episodes is the mean over all agents."""
    missing = [k for k in _EPISODE_KEYS if k not in per_episode]
    if missing:
        raise KeyError(f"per_episode lacks {missing}")
    e = per_episode["cost"].numel()
    if e == 0:
        raise ValueError("summarize needs at least one episode")
    cost = per_episode["cost"].double()
    row = {
        "num_agents": int(num_agents),
        "safe_rate": float(per_episode["safe_rate"].double().mean()),
        "reach_rate": float(per_episode["reach_rate"].double().mean()),
        "success_rate": float(per_episode["success_rate"].double().mean()),
        "cost": float(cost.mean()),
        "cost_min": float(cost.min()),
        "cost_max": float(cost.max()),
        "reward": float(per_episode["reward"].double().mean()),
        "num_episodes": int(e),
    }
    if "collision_steps" in per_episode:
        row["collision_steps"] = float(per_episode["collision_steps"].double().mean())
    return row
