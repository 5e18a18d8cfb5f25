"""Closed-loop rollouts that record what a certificate needs: every agent's barrier values, collisions and QP status.

:func:`roll_out` runs a controller on a batch of episodes exactly as :func:`egcbf.evaluate.episodes.run_episodes` does
(the same seeds, resets and steps, no faults) and keeps, per step ``t = 0 .. T`` and agent, each barrier's value at the
state ``x_t``, whether ``x_t`` is in collision (``x_0`` never is), and for ``t < T`` whether the controller's run-time
filter needed slack or braked at ``x_t`` (``None`` for a controller without a filter)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..env import EnvConfig, SwarmEnv
from ..evaluate.episodes import concat_states

__all__ = ["Trajectory", "roll_out"]


@dataclass
class Trajectory:
    """What :func:`roll_out` recorded for ``B`` episodes of ``N`` agents over ``T`` steps (CPU tensors).

    Attributes:
        h: barrier name -> ``(T + 1, B, N)`` float64 values at the states ``x_0 .. x_T``.
        collision: ``(T + 1, B, N)`` bool, the agent is in collision at ``x_t`` (agent or obstacle).
        filter_bad: ``(T, B, N)`` bool, the filter's QP needed slack or failed at ``x_t``; ``None``: no filter.
        dt: the control period (s).
    """

    h: dict[str, Tensor]
    collision: Tensor
    filter_bad: Tensor | None
    dt: float


def roll_out(
    controller: Callable,
    barriers: Mapping[str, object],
    config: EnvConfig,
    seeds: Sequence[int],
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    progress: tqdm | None = None,
) -> Trajectory:
    """Simulate ``len(seeds)`` episodes of ``controller`` (the evaluation signature ``(state, config) -> (u,
    info)``) and record ``barriers`` (name -> an object with ``values(state, config) -> (B, N)``) along them."""
    if not seeds:
        raise ValueError("roll_out needs at least one episode seed")
    env1 = SwarmEnv(dataclasses.replace(config, num_envs=1), device=device, dtype=dtype)
    state = concat_states([env1.reset(s) for s in seeds])
    env = SwarmEnv(dataclasses.replace(config, num_envs=len(seeds)), device=device, dtype=dtype)
    shape = tuple(state.x.shape[:2])
    h = {name: [b.values(state, env.config)] for name, b in barriers.items()}
    collision = [torch.zeros(shape, dtype=torch.bool)]
    bad: list[Tensor] = []
    filtered = None
    for _ in range(config.max_steps):
        u, info = controller(state, env.config)
        has = "slack_mask" in info
        if filtered is None:
            filtered = has
        elif filtered != has:
            raise RuntimeError("the controller reported its filter's per-agent QP status at some steps only")
        if has:
            mask = np.asarray(info["slack_mask"]) | np.asarray(info["failed_mask"])
            bad.append(torch.from_numpy(mask.reshape(shape)))
        state, step = env.step(state, u)
        collision.append(step.collision.detach().cpu())
        for name, b in barriers.items():
            h[name].append(b.values(state, env.config))
        if progress is not None:
            progress.update(len(seeds))
    return Trajectory(
        h={k: torch.stack(v) for k, v in h.items()},
        collision=torch.stack(collision),
        filter_bad=torch.stack(bad) if filtered else None,
        dt=float(env.config.dt),
    )
