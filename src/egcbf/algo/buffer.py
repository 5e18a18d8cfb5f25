"""Replay buffers (GCBF+): recent trajectories, and a separate buffer of unsafe graphs that is oversampled.

A sample is one time step of one environment: the agents' states, goals, obstacles, the LiDAR hits seen there
(kept so the graph can be rebuilt without re-casting rays) and the safe/unsafe labels. :class:`Samples` holds
any batch of them with leading dimensions ``(*lead, ...)``; a batch with one leading dimension ``S`` turns into a
``SwarmState`` of ``S`` environments and its graph (:meth:`Samples.graph`).

* :class:`TrajectoryBuffer`: the last ``capacity`` trajectories of ``L`` steps (a ring); ``sample(k)`` draws ``k``
  distinct trajectories (all of them if fewer are stored).
* :class:`UnsafeBuffer`: the last ``capacity`` samples in which some agent is unsafe (a ring); ``sample(k)``
  draws ``k`` of them *with replacement*, so a few rare unsafe graphs are seen many times per update. An empty
  buffer (no unsafe state seen yet, the normal situation with a good policy) returns ``None`` instead of
  failing: a crash GCBF+ users hit.

Both are plain tensors (no Python objects per sample) and serialize to a flat ``dict[str, Tensor]``
(:meth:`state_dict` / :meth:`load_state_dict`) for checkpoints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..env import EnvConfig, LidarScan, Obstacles, SwarmState
from ..env.graph import SwarmGraph, build_graph
from ..robots import Robot

__all__ = ["Samples", "TrajectoryBuffer", "UnsafeBuffer"]


@dataclass
class Samples:
    """A batch of time steps, leading dimensions ``lead`` (e.g. ``(S,)`` or ``(L, B)``).

    Attributes:
        x: ``(*lead, N, S)`` agent states; goals ``(*lead, N, d)``.
        centers: ``(*lead, K, d)``, radii ``(*lead, K)`` and boxes ``(*lead, K, 4)`` (rectangles) or ``(*lead, K, 0)``
            (round): the obstacles (:meth:`egcbf.env.Obstacles.unpack`).
        hit_points: ``(*lead, N, H, d)`` LiDAR hits (world frame) and hit_valid ``(*lead, N, H)``.
        safe, unsafe: ``(*lead, N)`` bool labels (:func:`egcbf.algo.labels.finite_horizon_labels`).
    """

    x: Tensor
    goals: Tensor
    centers: Tensor
    radii: Tensor
    boxes: Tensor
    hit_points: Tensor
    hit_valid: Tensor
    safe: Tensor
    unsafe: Tensor

    def map(self, fn) -> Samples:
        return Samples(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, idx) -> Samples:
        return self.map(lambda t: t[idx])

    def flatten(self, ndims: int = 2) -> Samples:
        """Merge the first ``ndims`` leading dimensions into one."""
        return self.map(lambda t: t.reshape(math.prod(t.shape[:ndims]), *t.shape[ndims:]))  # -1: not for 0 elements

    @staticmethod
    def cat(items: list[Samples]) -> Samples:
        items = [s for s in items if s is not None and len(s) > 0]
        return Samples(**{f.name: torch.cat([getattr(s, f.name) for s in items]) for f in fields(Samples)})

    def to(self, *args, **kwargs) -> Samples:
        return self.map(lambda t: t.to(*args, **kwargs) if t.is_floating_point() else t.to(device=t.device))

    @property
    def num_agents(self) -> int:
        return self.x.shape[-2]

    def state(self, robot: Robot | None = None) -> SwarmState:
        """The ``SwarmState`` of ``S`` environments of ``robot`` (``None``: the quadrotor; needs exactly one
        leading dimension)."""
        if self.x.dim() != 3:
            raise ValueError(f"state() needs samples with one leading dimension, got x {tuple(self.x.shape)}")
        return SwarmState(self.x, self.goals, Obstacles.unpack(self.centers, self.radii, self.boxes), robot=robot)

    def lidar(self, robot: Robot | None = None) -> LidarScan:
        p = self.x[..., 0:3] if robot is None else robot.positions(self.x)
        d = (self.hit_points - p[..., None, :]).norm(dim=-1)
        return LidarScan(self.hit_points, self.hit_valid, torch.where(self.hit_valid, d, torch.full_like(d, torch.inf)))

    def graph(self, env_config: EnvConfig) -> SwarmGraph:
        """The swarm graph of these samples (with the stored LiDAR hits)."""
        robot = env_config.make_robot()
        return build_graph(self.state(robot), env_config, lidar=self.lidar(robot))


def _empty_like(s: Samples, capacity: int) -> Samples:
    return s.map(lambda t: torch.zeros((capacity, *t.shape[1:]), dtype=t.dtype, device=t.device))


class _Ring:
    """A ring of ``capacity`` samples along dimension 0 (storage allocated at the first append)."""

    def __init__(self, capacity: int, prefix: str):
        if int(capacity) != capacity or capacity < 1:
            raise ValueError(f"buffer capacity must be an integer >= 1, got {capacity!r}")
        self.capacity = int(capacity)
        self.prefix = prefix
        self.data: Samples | None = None
        self.size = 0
        self.ptr = 0

    def __len__(self) -> int:
        return self.size

    def _append(self, items: Samples) -> None:
        k = len(items)
        if k == 0:
            return
        if self.data is None:
            self.data = _empty_like(items, self.capacity)
        if k > self.capacity:  # only the most recent ones fit
            items = items[k - self.capacity :]
            k = self.capacity
        idx = (self.ptr + torch.arange(k)) % self.capacity
        for f in fields(Samples):
            getattr(self.data, f.name)[idx.to(getattr(self.data, f.name).device)] = getattr(items, f.name)
        self.ptr = (self.ptr + k) % self.capacity
        self.size = min(self.size + k, self.capacity)

    def state_dict(self) -> dict[str, Tensor]:
        out = {f"{self.prefix}.meta": torch.tensor([self.size, self.ptr, self.capacity], dtype=torch.long)}
        if self.data is not None:
            for f in fields(Samples):
                out[f"{self.prefix}.{f.name}"] = getattr(self.data, f.name)[: self.capacity].contiguous()
        return out

    def load_state_dict(self, sd: dict[str, Tensor]) -> None:
        size, ptr, cap = (int(v) for v in sd[f"{self.prefix}.meta"])
        if cap != self.capacity:
            raise ValueError(f"checkpointed buffer {self.prefix!r} has capacity {cap}, this one {self.capacity}")
        self.size, self.ptr = size, ptr
        if f"{self.prefix}.x" in sd:
            stored = {f.name: sd.get(f"{self.prefix}.{f.name}") for f in fields(Samples)}
            if stored["boxes"] is None:  # written before rectangle obstacles: round ones
                stored["boxes"] = stored["centers"].new_zeros(*stored["centers"].shape[:-1], 0)
            self.data = Samples(**{k: v.clone() for k, v in stored.items()})
        else:
            self.data = None


class TrajectoryBuffer(_Ring):
    """The last ``capacity`` trajectories; ``append`` takes samples ``(B, L, ...)`` (one row per trajectory)."""

    def __init__(self, capacity: int):
        super().__init__(capacity, "traj")

    def append(self, trajectories: Samples) -> None:
        self._append(trajectories)

    def sample(self, k: int, generator: torch.Generator) -> Samples | None:
        """``min(k, len)`` distinct trajectories ``(k, L, ...)`` chosen uniformly; ``None`` if empty or ``k = 0``."""
        if self.size == 0 or k <= 0:
            return None
        idx = torch.randperm(self.size, generator=generator)[: min(k, self.size)]
        return self.data[idx.to(self.data.x.device)]


class UnsafeBuffer(_Ring):
    """The last ``capacity`` samples with an unsafe agent; ``add`` filters a batch ``(S, ...)`` for them."""

    def __init__(self, capacity: int):
        super().__init__(capacity, "unsafe")

    def add(self, samples: Samples) -> int:
        """Append the samples of ``samples`` ``(S, ...)`` in which some agent is unsafe; returns how many."""
        keep = samples.unsafe.any(-1)
        n = int(keep.sum())
        if n:
            self._append(samples[keep])
        return n

    def sample(self, k: int, generator: torch.Generator) -> Samples | None:
        """``k`` samples drawn with replacement (oversampling); ``None`` if the buffer is empty or ``k = 0``."""
        if self.size == 0 or k <= 0:
            return None
        idx = torch.randint(self.size, (k,), generator=generator)
        return self.data[idx.to(self.data.x.device)]
